"""`uavmm agent --detections-out` and `--config PARAMS.json` as a real process on a dataset: the live
agent's detections score like `uavmm boost` on the same video, and the parameters file is applied."""

from __future__ import annotations

import json
import subprocess

import pytest

from agent.coco_metrics import coco_detection_metrics
from sim.dataset import write_dataset
from tests.e2e.conftest import ENV, REPO, agent_cmd, finish, start_agent, uavmm

pytestmark = pytest.mark.e2e


@pytest.fixture(scope="module")
def sea(tmp_path_factory):
    data = tmp_path_factory.mktemp("sea")
    write_dataset("sea", data, seed=3, frames=60, progress=False)
    return data


def _video_images(data, video_id: int) -> list[int]:
    coco = json.loads((data / "images.json").read_text())
    return [im["id"] for im in coco["images"] if im["video_id"] == video_id]


def test_agent_detections_score_like_boost_on_the_same_video(server, port, sea, tmp_path):
    out = tmp_path / "agent.json"
    proc = start_agent(agent_cmd(port, "--dataset", str(sea), "--video-id", "2", "--speed", "0",
                                 "--detections-out", str(out)))
    code, summary, err = finish(proc)
    assert code == 0, err[-2000:]
    detections = json.loads(out.read_text())
    ids = _video_images(sea, 2)
    assert detections and {d["image_id"] for d in detections} <= set(ids)
    assert len(detections) == summary["detections"]
    boosted = tmp_path / "boost.json"
    subprocess.run(uavmm("boost", "--frames", str(sea / "images.json"), "--candidates", str(sea / "pre_nms.json"),
                         "--camera", str(sea / "camera.json"), "--out", str(boosted), "--no-clock-offset"),
                   cwd=REPO, env=ENV,
                   check=True, capture_output=True, timeout=120)
    ap_agent = coco_detection_metrics(sea / "images.json", detections, image_ids=ids)["AP50"]
    ap_boost = coco_detection_metrics(sea / "images.json", boosted, image_ids=ids)["AP50"]
    assert ap_agent > 0.3 and abs(ap_agent - ap_boost) < 0.02, (ap_agent, ap_boost)


def test_agent_reads_a_params_file_given_as_config(server, port, sea, tmp_path):
    params = tmp_path / "params.json"
    params.write_text(json.dumps({"format": "uavmm-params", "version": 1, "size_filter": None,
                                  "pipeline": {"max_detections": 2, "memory": {"half_life_s": 0.5}}}))
    out = tmp_path / "agent.json"
    proc = start_agent(agent_cmd(port, "--dataset", str(sea), "--video-id", "1", "--speed", "0",
                                 "--config", str(params), "--detections-out", str(out)))
    code, _, err = finish(proc)
    assert code == 0, err[-2000:]
    per_image: dict[int, int] = {}
    for d in json.loads(out.read_text()):
        per_image[d["image_id"]] = per_image.get(d["image_id"], 0) + 1
    assert per_image and max(per_image.values()) <= 2


def test_agent_refuses_a_missing_output_directory_before_flying(port, sea, tmp_path):
    proc = subprocess.run(agent_cmd(port, "--dataset", str(sea), "--detections-out", str(tmp_path / "no" / "d.json")),
                          cwd=REPO, env=ENV, capture_output=True, text=True, timeout=60)
    assert proc.returncode == 2
    assert "--detections-out: output directory" in proc.stderr and "Traceback" not in proc.stderr
