"""`uavmm agent --video` as a real process on a rendered MP4 with its SRT (or CSV) telemetry and an ONNX model:
it plays every frame, georeferences every frame from the telemetry and publishes (issue 16, rendering)."""

from __future__ import annotations

import json

import pytest

from tests.agent.test_node_zenoh import KEYS, FakeServer
from tests.e2e.conftest import agent_cmd, finish, start_agent
from tests.netutil import free_port, wait_until
from uavmm.cli import main

pytestmark = pytest.mark.e2e
FRAMES = 30


@pytest.fixture(scope="module")
def rendered(tmp_path_factory: pytest.TempPathFactory):
    """coop, both UAVs, 640x360, rendered to MP4 + SRT + CSV (no image files)."""
    out = tmp_path_factory.mktemp("rendered") / "coop"
    assert main(["sim", "coop", "--out", str(out), "--frames", str(FRAMES), "--image-size", "640x360", "--video",
                 "--no-images", "--max-texture-px", "1024", "--quiet"]) == 0
    return out


@pytest.fixture
def server():
    port = free_port()
    fake = FakeServer(port)
    yield fake, port
    fake.close()


@pytest.mark.parametrize("telemetry", ["srt", "csv"])
def test_agent_plays_a_rendered_video_with_its_telemetry(rendered, server, tmp_path, telemetry):
    pytest.importorskip("onnx")
    from tests.agent.test_sources import _write_model

    fake, port = server
    name = json.loads((rendered / "images.json").read_text())["videos"][1]["name"]
    proc = start_agent(agent_cmd(port, "--video", str(rendered / f"{name}.mp4"),
                                 "--telemetry", str(rendered / f"{name}.{telemetry}"),
                                 "--model", str(_write_model(tmp_path / "model.onnx")),
                                 "--camera", str(rendered / "camera.json"), "--speed", "0",
                                 "--no-size-filter"))  # the model's one box is far too big for a person
    wait_until(lambda: fake.alive() == [KEYS.uav_alive("uav1")] or proc.poll() is not None, 20.0, "the agent's token")
    code, summary, err = finish(proc, 60.0)
    assert code == 0, err[-2000:]
    assert summary["frames"] == FRAMES
    assert summary["frames_without_pose"] == 0  # the telemetry covers every frame
    assert summary["detections"] >= FRAMES  # the model's box in every frame
    assert fake.count("uav_state") > 0 and fake.count("uav_tile") > 0
