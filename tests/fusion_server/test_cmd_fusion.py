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
