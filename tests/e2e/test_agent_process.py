"""`uavmm agent` as a real process against a plain Zenoh router session playing the server: it prints a
ready line and a JSON summary, publishes, exits at the end of its source, on --duration and cleanly on
SIGINT/SIGTERM (its liveliness token disappears), and fails with one clear line on bad arguments."""

from __future__ import annotations

import json
import signal
import subprocess
import time

import pytest

from shared.messages import decode_state, decode_tracks
from shared.tilecodec import decode_tile
from sim.dataset import write_dataset
from tests.agent.test_node_zenoh import KEYS
from tests.e2e.conftest import ENV, REPO, agent_cmd, finish, start_agent
from tests.netutil import wait_until

pytestmark = pytest.mark.e2e


def test_agent_process_publishes_and_exits_at_the_end_of_its_source(server, port):
    proc = start_agent(agent_cmd(port, "--sim", "coop", "--uav-index", "1", "--frames", "90", "--speed", "2"))
    wait_until(lambda: server.alive() == [KEYS.uav_alive("uav1")], 10.0, "the agent's liveliness token")
    code, summary, err = finish(proc)
    assert code == 0, err[-2000:]
    assert summary["frames"] == 90 and summary["publish_cycles"] >= 5
    assert summary["link"]["counts"]["sent_tile"] == server.count("uav_tile") > 0
    assert all(decode_tile(p).uav == "uav1" for _, p in server.latest("uav_tile"))
    assert all(len(decode_state(p).footprint) == 32 for _, p in server.latest("uav_state"))
    assert server.count("uav_tracks") == summary["link"]["counts"]["sent_tracks"]
    assert all(decode_tracks(p).uav == "uav1" for _, p in server.latest("uav_tracks"))
    wait_until(lambda: server.alive() == [], 5.0, "the token gone")  # the token went with the process


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT])
def test_agent_process_stops_cleanly_on_a_signal(server, port, sig):
    proc = start_agent(agent_cmd(port, "--sim", "coop", "--frames", "60", "--loop"))
    wait_until(lambda: server.count("uav_tile") > 0, 20.0, "tiles")
    proc.send_signal(sig)
    code, summary, err = finish(proc, 15.0)
    assert code == 0, err[-2000:]
    assert summary["frames"] > 0
    wait_until(lambda: server.alive() == [], 5.0, "the token gone")


def test_agent_process_stops_after_its_duration(server, port):
    started = time.monotonic()
    proc = start_agent(agent_cmd(port, "--sim", "coop", "--loop", "--duration", "2"))
    code, summary, _ = finish(proc)
    assert code == 0
    assert 1.5 <= summary["elapsed_s"] <= 4.0 and time.monotonic() - started < 30.0


def test_agent_process_plays_a_dataset_and_writes_tracks_with_global_ids(server, port, tmp_path):
    data = tmp_path / "coop"
    write_dataset("coop", data, seed=0, frames=120, progress=False)
    out = tmp_path / "tracks.geojson"
    proc = start_agent(agent_cmd(port, "--dataset", str(data), "--video-id", "2", "--speed", "0",
                                 "--tracks-out", str(out)))
    code, summary, err = finish(proc)
    assert code == 0, err[-2000:]
    assert summary["frames"] == 120 and server.count("uav_state") > 0
    collection = json.loads(out.read_text())
    assert collection["type"] == "FeatureCollection" and collection["features"]
    props = collection["features"][0]["properties"]
    assert props["uav"] == "uav1" and "gid" in props and props["cls_name"] == "person"


@pytest.mark.parametrize(("args", "message"), [
    (["--sim", "nosuch"], "unknown scenario 'nosuch'; valid scenarios: coop, coop-slope, grass, hills, reid, sea"),
    (["--dataset", "/nonexistent/dir"], "dataset directory /nonexistent/dir does not exist"),
    (["--video", "v.mp4"], "--video needs --telemetry FILE (.srt, .csv, .json, .tlog, .ulg, KLV, udp:HOST:PORT); "
                           "--model M.onnx (a YOLO ONNX export with raw, pre-NMS output: docs/detect.md, Inputs); "
                           "--camera C.json or a preset (dji-air2s, "),
    (["--sim", "coop", "--uav-index", "5"], "uav_index must be in 0..1"),
    (["--sim", "coop", "--publish-hz", "0"], "publish_hz must be a finite number > 0"),
])
def test_agent_process_fails_with_one_clear_line(port, args, message):
    proc = subprocess.run(agent_cmd(port, *args), cwd=REPO, env=ENV, capture_output=True, text=True, timeout=60)
    assert proc.returncode == 2
    assert message in proc.stderr and "Traceback" not in proc.stderr


def test_bad_uav_id_is_refused(port):
    proc = subprocess.run(agent_cmd(port, "--sim", "coop", uav="a/b"), cwd=REPO, env=ENV, capture_output=True,
                          text=True, timeout=60)
    assert proc.returncode == 2 and "uav_id must not contain '/'" in proc.stderr
