"""The Zenoh options shared by every process: validation, the zenoh.Config they build, the old import
paths, and that an agent runs without the fusion server package."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from transport.options import ZENOH_MODES, ZenohOptions, zenoh_config

REPO = Path(__file__).resolve().parents[2]


def test_options_become_config_entries_with_cfg_applied_last():
    options = ZenohOptions(mode="client", connect=("tcp/10.0.0.1:7447",), listen=("tcp/127.0.0.1:7500",),
                           multicast_scouting=False, cfg=("connect/endpoints:[\"tcp/10.0.0.9:7447\"]",
                                                          "transport/link/tx/lease:2000"))
    conf = zenoh_config(options)
    assert json.loads(conf.get_json("mode")) == "client"
    assert json.loads(conf.get_json("listen/endpoints")) == ["tcp/127.0.0.1:7500"]
    assert json.loads(conf.get_json("scouting/multicast/enabled")) is False
    assert json.loads(conf.get_json("connect/endpoints")) == ["tcp/10.0.0.9:7447"]  # --cfg wins
    assert json.loads(conf.get_json("transport/link/tx/lease")) == 2000


def test_a_config_file_is_read_and_the_flags_override_it(tmp_path):
    path = tmp_path / "zenoh.json5"
    path.write_text('{mode: "router", listen: {endpoints: ["tcp/127.0.0.1:7600"]}}')
    conf = zenoh_config(ZenohOptions(config_file=path, mode="peer"))
    assert json.loads(conf.get_json("mode")) == "peer"
    assert json.loads(conf.get_json("listen/endpoints")) == ["tcp/127.0.0.1:7600"]


@pytest.mark.parametrize(("kwargs", "message"), [
    ({"mode": "server"}, "zenoh mode must be one of peer, router, client"),
    ({"cfg": ("no-colon",)}, "KEY:VALUE"),
])
def test_bad_options_fail_fast(kwargs, message):
    with pytest.raises(ValueError, match=message):
        ZenohOptions(**kwargs)


def test_bad_files_and_cfg_values_are_value_errors(tmp_path):
    with pytest.raises(ValueError, match="cannot read zenoh config"):
        zenoh_config(ZenohOptions(config_file=tmp_path / "missing.json5"))
    with pytest.raises(ValueError, match="--cfg"):
        zenoh_config(ZenohOptions(cfg=("mode:{not json5",)))
    # the contract audit (1 Dec 2026): a JSON list was taken silently (an empty config); a pipeline config given as
    # the Zenoh config was called an invalid Zenoh config, without saying what it is
    (tmp_path / "list.json").write_text("[1, 2]")
    with pytest.raises(ValueError, match=r"list\.json: a Zenoh config is a JSON5 object, got a list"):
        zenoh_config(ZenohOptions(config_file=tmp_path / "list.json"))
    (tmp_path / "pipeline.json").write_text(json.dumps({"memory": {"half_life_s": 0.5}, "nms_iou": 0.5}))
    with pytest.raises(ValueError, match="pipeline settings .*--pipeline-config"):
        zenoh_config(ZenohOptions(config_file=tmp_path / "pipeline.json"))
    (tmp_path / "ok.json5").write_text('{mode: "peer", // a comment\n}')
    assert zenoh_config(ZenohOptions(config_file=tmp_path / "ok.json5")) is not None  # JSON5: Zenoh reads it


@pytest.mark.parametrize(("kwargs", "message"), [
    ({"connect": ("notanendpoint",)}, r"--connect 'notanendpoint' is not a Zenoh endpoint: <protocol>/<address>"),
    ({"listen": ("tcp/127.0.0.1:7447", "bad")}, r"--listen 'bad' is not a Zenoh endpoint"),
    ({"connect": ("/no-protocol",)}, r"--connect '/no-protocol' is not a Zenoh endpoint"),
])
def test_a_malformed_endpoint_is_named_in_one_line(kwargs, message):
    """`uavmm agent --connect notanendpoint` ended in zenoh's traceback (fusion and gateway printed its message)."""
    with pytest.raises(ValueError, match=message):
        zenoh_config(ZenohOptions(**kwargs))


def test_the_agent_refuses_a_malformed_endpoint_in_one_line(capsys):
    from uavmm.cli import main

    assert main(["agent", "--uav-id", "uav1", "--sim", "coop", "--connect", "notanendpoint", "--duration", "1"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == ["uavmm agent: error: --connect 'notanendpoint' is not a Zenoh endpoint: <protocol>/<address>, "
                   "e.g. tcp/192.168.1.10:7447"]


def test_the_old_import_paths_are_the_same_objects():
    import agent.zenoh_config
    import fusion_server.config
    import uavmm._zenoh_args
    import uavmm.cmd_fusion

    for module in (agent.zenoh_config, fusion_server.config):
        assert (module.ZenohOptions, module.ZENOH_MODES) == (ZenohOptions, ZENOH_MODES)
    assert fusion_server.config.zenoh_config is zenoh_config
    assert uavmm.cmd_fusion.add_zenoh_arguments is uavmm._zenoh_args.add_zenoh_arguments


AGENT_WITHOUT_SERVER = """
import sys
sys.modules["fusion_server"] = None  # any import of it raises ImportError
import agent.node
import agent.zenoh_config
from uavmm.cli import build_parser
from uavmm.cmd_agent import settings_from_args

args = build_parser().parse_args(["agent", "--uav-id", "uav1", "--sim", "coop", "--connect", "tcp/10.0.0.2:7447",
                                  "--mode", "client", "--cfg", "transport/link/tx/lease:2000"])
settings = settings_from_args(args)
conf = agent.zenoh_config.agent_zenoh_config(settings.zenoh)
print(conf.get_json("mode"), conf.get_json("connect/endpoints"))
"""


def test_the_agent_imports_and_configures_without_the_fusion_server_package():
    proc = subprocess.run([sys.executable, "-c", AGENT_WITHOUT_SERVER], cwd=REPO, capture_output=True, text=True,
                          timeout=120)
    assert proc.returncode == 0, proc.stderr[-3000:]
    mode, endpoints = proc.stdout.split(maxsplit=1)
    assert json.loads(mode) == "client" and json.loads(endpoints) == ["tcp/10.0.0.2:7447"]


def test_blocking_the_package_does_fail_an_import_of_it():
    # the check above is only meaningful if the block works
    code = 'import sys; sys.modules["fusion_server"] = None; import fusion_server.config'
    proc = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True, timeout=60)
    assert proc.returncode != 0 and "ModuleNotFoundError" in proc.stderr
