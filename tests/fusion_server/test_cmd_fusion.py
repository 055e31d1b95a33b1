"""`uavmm fusion` flags -> FusionSettings, and settings validation."""

import json
from pathlib import Path

import pytest

from fusion_server.config import FusionSettings, ZenohOptions, default_db_path, zenoh_config
from uavmm.cli import build_parser
from uavmm.cmd_fusion import DEFAULT_LISTEN, settings_from_args


def parse(*argv: str) -> FusionSettings:
    return settings_from_args(build_parser().parse_args(["fusion", *argv]))


def test_defaults_listen_on_7447_as_router_with_rest_on_localhost():
    settings = parse()
    assert settings.zenoh.listen == (DEFAULT_LISTEN,) and settings.zenoh.mode == "router"
    assert (settings.http_host, settings.http_port) == ("127.0.0.1", 8000)
    assert settings.db_path == default_db_path() and settings.fusion_rule == "mean" and settings.ttl_s == 2.0


def test_flags_reach_the_settings(tmp_path: Path):
    settings = parse("--mode", "peer", "--connect", "tcp/10.0.0.1:7447", "--listen", "tcp/127.0.0.1:7500",
                     "--http", "0.0.0.0:9000", "--db", str(tmp_path / "x.sqlite"), "--ttl-s", "3.5",
                     "--prefix", "fleet/v1", "--fusion-rule", "noisy-or", "--no-multicast-scouting",
                     "--cfg", "transport/link/tx/lease:2000")
    assert settings.zenoh == ZenohOptions(mode="peer", connect=("tcp/10.0.0.1:7447",), listen=("tcp/127.0.0.1:7500",),
                                          multicast_scouting=False, cfg=("transport/link/tx/lease:2000",))
    assert (settings.http_host, settings.http_port, settings.ttl_s) == ("0.0.0.0", 9000, 3.5)
    assert settings.prefix == "fleet/v1" and settings.fusion_rule == "noisy-or"
    conf = zenoh_config(settings.zenoh)
    assert json.loads(conf.get_json("transport/link/tx/lease")) == 2000
    assert parse("--no-db").db_path is None


def test_a_config_file_with_listen_endpoints_is_not_overridden(tmp_path: Path):
    config = tmp_path / "z.json5"
    config.write_text('{ listen: { endpoints: ["tcp/127.0.0.1:7777"] } }')
    settings = parse("--config", str(config))
    assert settings.zenoh.listen is None
    assert json.loads(zenoh_config(settings.zenoh).get_json("listen/endpoints")) == ["tcp/127.0.0.1:7777"]


@pytest.mark.parametrize(("name", "text"), [
    ("z.json5", '{ mode: "router", scouting: { multicast: { enabled: false } } }'),
    ("z.json5", '{ listen: { timeout_ms: 2000 } }'),  # listen, but not its endpoints
    ("z.json", '{ "connect": { "endpoints": ["tcp/10.0.0.1:7447"] } }'),
    ("z.yaml", "mode: router\nscouting:\n  multicast:\n    enabled: false\n"),
    ("z.json5", "// the fleet's ground station\n{ /* nothing about listening */ }\n"),
])
def test_a_config_file_without_listen_endpoints_gets_the_documented_default(tmp_path: Path, name, text):
    """--listen's help: "default tcp/0.0.0.0:7447 unless --config sets listen/endpoints". Zenoh's own default
    for listen/endpoints is a per-mode table that is never empty: it used to count as set, so any --config
    file dropped the default (issue 17)."""
    config = tmp_path / name
    config.write_text(text)
    settings = parse("--config", str(config))
    assert settings.zenoh.listen == (DEFAULT_LISTEN,)
    assert json.loads(zenoh_config(settings.zenoh).get_json("listen/endpoints")) == [DEFAULT_LISTEN]


@pytest.mark.parametrize(("name", "text"), [
    ("z.json5", '// JSON5: comments, quoted and bare keys, trailing commas\n'
                '{ "listen": { endpoints: ["tcp/127.0.0.1:7777",], }, }'),
    ("z.json5", '{ listen: { endpoints: { router: ["tcp/127.0.0.1:7777"], peer: ["tcp/127.0.0.1:7777"] } } }'),
    ("z.yaml", "listen:\n  endpoints: [tcp/127.0.0.1:7777]\n"),
])
def test_a_config_file_that_sets_listen_endpoints_keeps_them(tmp_path: Path, name, text):
    config = tmp_path / name
    config.write_text(text)
    settings = parse("--config", str(config))
    assert settings.zenoh.listen is None
    assert "tcp/127.0.0.1:7777" in zenoh_config(settings.zenoh).get_json("listen/endpoints")
    assert parse("--config", str(config), "--listen", "tcp/127.0.0.1:7001").zenoh.listen == ("tcp/127.0.0.1:7001",)


def test_the_help_promises_the_default_unless_the_config_file_sets_listen_endpoints(capsys):
    with pytest.raises(SystemExit):
        build_parser().parse_args(["fusion", "--help"])
    help_text = " ".join(capsys.readouterr().out.split())
    assert "default tcp/0.0.0.0:7447 unless --config sets listen/endpoints" in help_text
    assert "Zenoh session mode (default: router unless --config sets mode)" in help_text


def test_a_config_file_zenoh_reads_but_that_is_not_a_map_or_json5_is_refused_naming_it(tmp_path: Path):
    from transport.options import config_file_value

    config = tmp_path / "z.json5"
    config.write_text("[1, 2]")
    with pytest.raises(ValueError, match=f"zenoh config {config}: the top level is not a map"):
        config_file_value(config, "listen/endpoints")
    config.write_text("{ listen: ")
    with pytest.raises(ValueError, match=f"cannot parse zenoh config {config}"):
        config_file_value(config, "listen/endpoints")


def test_the_config_files_own_mode_beats_the_default_mode_and_a_client_file_gets_no_listener(tmp_path: Path):
    """`uavmm secure init` writes fusion/zenoh-client.json5 for "uavmm fusion --config zenoh-client.json5: the
    fusion server as a client of a zenohd router"; the --mode default (router) used to override the file's
    mode, so that server ran as a router listening on 7447 instead."""
    client = tmp_path / "zenoh-client.json5"
    client.write_text('{ mode: "client", connect: { endpoints: ["tcp/127.0.0.1:7999"] } }')
    settings = parse("--config", str(client))
    assert settings.zenoh.mode is None and settings.zenoh.listen is None
    conf = zenoh_config(settings.zenoh)
    assert json.loads(conf.get_json("mode")) == "client"
    assert json.loads(conf.get_json("connect/endpoints")) == ["tcp/127.0.0.1:7999"]
    # an explicit --mode still wins over the file, and then the default listener applies
    forced = parse("--config", str(client), "--mode", "router")
    assert forced.zenoh.mode == "router" and forced.zenoh.listen == (DEFAULT_LISTEN,)
    peer = tmp_path / "peer.json5"
    peer.write_text('{ mode: "peer" }')
    settings = parse("--config", str(peer))
    assert settings.zenoh.mode is None and settings.zenoh.listen == (DEFAULT_LISTEN,)
    assert json.loads(zenoh_config(settings.zenoh).get_json("mode")) == "peer"


def test_a_client_gets_no_default_listener_whatever_its_config_file(tmp_path: Path):
    config = tmp_path / "z.json5"
    config.write_text("{}")
    assert parse("--config", str(config), "--mode", "client").zenoh.listen is None


def test_an_unreadable_config_file_raises_value_error_naming_it(tmp_path: Path):
    missing = tmp_path / "missing.json5"
    with pytest.raises(ValueError, match=f"cannot read zenoh config {missing}"):
        parse("--config", str(missing))


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["--fusion-rule", "median"], "fusion_rule"),
        (["--ttl-s", "0"], "ttl_s"),
        (["--http", "8000"], "HOST:PORT"),
        (["--prefix", "a/*"], "prefix"),
        (["--grid-n", "300"], "n must be"),
    ],
)
def test_bad_flags_raise_value_error_naming_the_field(argv, message):
    with pytest.raises(ValueError, match=message):
        parse(*argv)


def test_cli_reports_bad_values_as_exit_code_2(capsys):
    from uavmm.cli import main

    assert main(["fusion", "--fusion-rule", "median", "--no-db"]) == 2
    assert "fusion_rule must be one of mean, max, noisy-or" in capsys.readouterr().err


def test_map_max_cells_flag_reaches_the_settings_of_fusion_and_gateway():
    from uavmm.cmd_gateway import settings_from_args as gateway_settings_from_args

    assert parse().map_max_cells == FusionSettings().map_max_cells == 2**23
    assert parse("--map-max-cells", "65536").map_max_cells == 65536
    gateway = gateway_settings_from_args(build_parser().parse_args(
        ["gateway", "--shards", "2", "--connect", "tcp/127.0.0.1:7447", "--map-max-cells", "20000000"]))
    assert gateway.map_max_cells == 20_000_000
    with pytest.raises(ValueError, match="map_max_cells must be an int >= 1, got 0"):
        parse("--map-max-cells", "0")


def test_map_max_cells_flag_caps_the_served_map_window():
    """`uavmm fusion --map-max-cells N` through to HTTP: N cells get 200, one column more the 400 naming the flag."""
    import httpx

    from fusion_server.server import FusionServer
    from tests.fusion_server.fake_agent import GRID, TILE_X, TILE_Y
    from tests.netutil import free_port

    settings = parse("--map-max-cells", str(256 * 256), "--http", "127.0.0.1:0", "--no-db",
                     "--listen", f"tcp/127.0.0.1:{free_port()}", "--no-multicast-scouting")
    west, south, east, north = GRID.tile_bounds(TILE_X, TILE_Y)
    one_tile = f"{west + 1e-7},{south + 1e-7},{east - 1e-7},{north - 1e-7}"
    one_more_column = f"{west + 1e-7},{south + 1e-7},{east + 180.0 / GRID.world_cells},{north - 1e-7}"
    with FusionServer(settings) as server:
        server.start()
        with httpx.Client(base_url=server.url.rstrip("/"), timeout=10.0) as http:
            assert http.get("/v1/map", params={"cls": "person", "bbox": one_tile}).status_code == 200
            over = http.get("/v1/map", params={"cls": "person", "bbox": one_more_column})
    assert over.status_code == 400 and "65792 cells, at most 65536 allowed (the server's --map-max-cells)" in \
        over.json()["detail"]
