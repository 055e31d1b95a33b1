"""A MAVLink stream (pymavlink's encoder, the flight's telemetry) replayed on loopback UDP drives `uavmm agent
--video FILE --telemetry udp:127.0.0.1:PORT` end to end, and `uavmm detect` the same way (issue 18, acceptance)."""

from __future__ import annotations

import json
import threading

import pytest

from shared.messages import decode_state
from shared.telemetry import read_csv
from tests.agent.test_node_zenoh import KEYS, FakeServer
from tests.e2e.conftest import agent_cmd, finish, start_agent
from tests.netutil import free_port, free_udp_port, wait_until
from tests.shared.mavlink_writer import flight_packets, replay_udp
from uavmm.cli import main

pytestmark = pytest.mark.e2e
FRAMES = 20


@pytest.fixture(scope="module")
def flight(tmp_path_factory: pytest.TempPathFactory) -> dict:
    """The coop scenario's second UAV rendered to MP4 + CSV; its telemetry as MAVLink packets; an ONNX model."""
    pytest.importorskip("pymavlink")
    pytest.importorskip("onnx")
    from tests.agent.test_sources import _write_model

    root = tmp_path_factory.mktemp("mavlink")
    out = root / "coop"
    assert main(["sim", "coop", "--out", str(out), "--frames", str(FRAMES), "--image-size", "640x360", "--video",
                 "--no-images", "--max-texture-px", "1024", "--quiet"]) == 0
    name = json.loads((out / "images.json").read_text())["videos"][1]["name"]
    records = read_csv(out / f"{name}.csv")
    return {"video": out / f"{name}.mp4", "camera": out / "camera.json", "records": records,
            "packets": flight_packets(records), "model": _write_model(root / "model.onnx")}


def _replayer(packets, port: int) -> tuple[threading.Thread, dict]:
    sent: dict = {}

    def run() -> None:
        sent["datagrams"] = replay_udp(packets, port)

    thread = threading.Thread(target=run, daemon=True)
    thread.start()
    return thread, sent


def test_live_mavlink_drives_the_agent_end_to_end(flight, tmp_path):
    zenoh_port, udp_port = free_port(), free_udp_port()
    server = FakeServer(zenoh_port)
    try:
        replay, sent = _replayer(flight["packets"], udp_port)
        proc = start_agent(agent_cmd(zenoh_port, "--video", str(flight["video"]), "--telemetry",
                                     f"udp:127.0.0.1:{udp_port}", "--telemetry-offset-s", str(flight["records"][0].t),
                                     "--model", str(flight["model"]), "--camera", str(flight["camera"]),
                                     "--speed", "0", "--no-size-filter"))
        wait_until(lambda: server.count("uav_state") > 0 or proc.poll() is not None, 30.0, "the agent's state")
        code, summary, err = finish(proc, 60.0)
        replay.join(timeout=30.0)
        assert code == 0, err[-2000:]
        assert sent["datagrams"] == 2 * len(flight["packets"])
        assert summary["frames"] == FRAMES
        assert summary["frames_without_pose"] == 0  # every frame georeferenced from the MAVLink stream
        assert summary["detections"] >= FRAMES
        # the state the agent published is the MAVLink position and gimbal, on the telemetry's UNIX clock
        state = decode_state(server.latest("uav_state")[-1][1])
        by_time = min(flight["records"], key=lambda r: abs(r.t - state.t))
        assert abs(by_time.t - state.t) < 0.05
        assert (state.lat, state.lon) == pytest.approx((by_time.lat, by_time.lon), abs=2e-6)
        assert state.height_m == pytest.approx(by_time.height_m, abs=0.01)
        assert state.pitch_deg == pytest.approx(by_time.pitch_deg, abs=0.05)
    finally:
        server.close()
    assert KEYS.uav_alive("uav1")  # the key space the agent used


def test_live_mavlink_drives_detect(flight, tmp_path):
    udp_port = free_udp_port()
    replay, _ = _replayer(flight["packets"], udp_port)
    out = tmp_path / "out"
    assert main(["detect", str(flight["video"]), "--telemetry", f"udp:127.0.0.1:{udp_port}",
                 "--telemetry-offset-s", str(flight["records"][0].t), "--model", str(flight["model"]),
                 "--camera", str(flight["camera"]), "--out", str(out), "--no-size-filter", "--quiet"]) == 0
    replay.join(timeout=30.0)
    summary = json.loads((out / "summary.json").read_text())
    assert summary["frames"] == FRAMES and summary["frames_without_pose"] == 0
    # a live stream cannot be looked ahead in: one pass, as the live agent runs, and the summary says why
    assert summary["two_pass"] is False and summary["one_pass_because"] == "live telemetry stream: no look ahead"
    images = json.loads((out / "images.json").read_text())["images"]
    for image, rec in zip(images, flight["records"], strict=True):  # the CSV has a record per frame
        assert image["meta"]["gps_latitude"] == pytest.approx(rec.lat, abs=2e-7)
        assert image["meta"]["gimbal_heading"] == pytest.approx(rec.heading_deg, abs=0.05)


def test_no_mavlink_on_the_port_is_one_clear_line(flight, tmp_path, capsys):
    port = free_udp_port()
    assert main(["detect", str(flight["video"]), "--telemetry", f"udp:127.0.0.1:{port}", "--telemetry-timeout-s",
                 "0.5", "--model", str(flight["model"]), "--camera", str(flight["camera"]),
                 "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and f"no MAVLink position (GLOBAL_POSITION_INT) on udp:127.0.0.1:{port}" in err[0]
    assert main(["detect", str(flight["video"]), "--telemetry", "udp:nonsense", "--model", str(flight["model"]),
                 "--camera", str(flight["camera"]), "--out", str(tmp_path / "o")]) == 2
    assert "a live MAVLink stream is udp:HOST:PORT" in capsys.readouterr().err
