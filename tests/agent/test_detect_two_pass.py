"""`uavmm detect` reads a recording as a file (agent.offline.two_pass): the detector over the whole video, then the
clock offset, the view cuts and the adaptive stages on all of it, then memory map and tracker. End to end on a
real video (MJPG), a 1 Hz telemetry log and a real ONNX model run by onnxruntime (tests.agent.jump_flight)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from agent.offline.two_pass import CandidateSpool
from agent.sources import pose_from_meta
from uavmm.cli import main

pytest.importorskip("onnx")

from tests.agent.jump_flight import JumpFlight, write_jump_flight  # noqa: E402  (needs onnx)


@pytest.fixture(scope="module")
def flight(tmp_path_factory) -> JumpFlight:
    # seed 0: five objects a view; the views 90 deg apart, jumps at 2.5, 5.5 and 8.5 s, logged at whole seconds
    return write_jump_flight(tmp_path_factory.mktemp("jump-flight"), seed=0)


def _detect(flight: JumpFlight, out: Path, *extra: str) -> dict:
    assert main(["detect", str(flight.video), "--telemetry", str(flight.telemetry), "--model", str(flight.model),
                 "--camera", str(flight.camera), "--out", str(out), "--quiet", *extra]) == 0
    return json.loads((out / "summary.json").read_text())


def _heading_errors(flight: JumpFlight, out: Path) -> np.ndarray:
    """Per frame of images.json: |pose heading - true heading|, degrees (NaN without pose)."""
    errors = []
    for image in json.loads((out / "images.json").read_text())["images"]:
        pose, _, _ = pose_from_meta(image["meta"])
        truth = flight.headings[image["frame_index"]]
        errors.append(np.nan if pose is None else abs((pose.heading_deg - truth + 180.0) % 360.0 - 180.0))
    return np.array(errors)


def _track_ids(out: Path) -> set[int]:
    return {int(line.split(",")[1]) for line in (out / "tracks.txt").read_text().splitlines()}


def test_two_passes_put_the_view_jumps_a_one_hertz_log_smears_where_the_video_jumps(flight, tmp_path, capsys):
    two = _detect(flight, tmp_path / "two")
    printed = capsys.readouterr().out
    one = _detect(flight, tmp_path / "one", "--one-pass")
    assert two["two_pass"] is True and "one_pass_because" not in two
    assert one["two_pass"] is False and one["one_pass_because"] == "--one-pass"
    assert two["frames"] == one["frames"] == len(flight.headings)
    # one pass: the frames between a jump and the next sample get an interpolated heading up to 45 deg off
    one_err = _heading_errors(flight, tmp_path / "one")
    assert (one_err > 2.0).sum() >= 20
    # two passes: every frame's heading is the view it shows; the stage says it acted, the CLI prints it
    two_err = _heading_errors(flight, tmp_path / "two")
    assert not np.isnan(two_err).any() and two_err.max() <= 2.0
    assert two["stages"]["view cuts"]["acted"] == 1
    assert "view cuts: acted 1" in printed
    assert "clock offset" in two["stages"]
    # ten objects: the tracks keep to them; one pass splits them at every jump
    assert len(_track_ids(tmp_path / "two")) <= 12 < len(_track_ids(tmp_path / "one"))
    # the candidates' temporary file is gone: --out holds the outputs and nothing else
    written = {Path(f).name for f in two["files"].values()} | {"summary.json"}
    assert {p.name for p in (tmp_path / "two").iterdir()} == written


def test_max_frames_stops_both_passes(flight, tmp_path):
    summary = _detect(flight, tmp_path / "out", "--max-frames", "17")
    assert summary["frames"] == 17 and summary["two_pass"] is True
    images = json.loads((tmp_path / "out" / "images.json").read_text())["images"]
    assert [im["frame_index"] for im in images] == list(range(17))


def test_the_annotated_video_has_every_frame_decoded_again(flight, tmp_path):
    import cv2

    summary = _detect(flight, tmp_path / "out", "--render-video", "--max-frames", "30")
    capture = cv2.VideoCapture(summary["files"]["video"])
    try:
        frames = 0
        while capture.read()[0]:
            frames += 1
    finally:
        capture.release()
    assert frames == 30


boxes_st = st.integers(0, 12).flatmap(lambda n: st.tuples(
    st.lists(st.lists(st.floats(-1e4, 1e4, width=32), min_size=4, max_size=4), min_size=n, max_size=n),
    st.lists(st.floats(0.0, 1.0, width=32), min_size=n, max_size=n),
    st.lists(st.integers(-(2 ** 40), 2 ** 40), min_size=n, max_size=n)))


@settings(max_examples=40, deadline=None)
@given(st.lists(boxes_st, max_size=8))
def test_the_spool_gives_back_each_frames_candidates_exactly(tmp_path_factory, frames):
    spool = CandidateSpool(tmp_path_factory.mktemp("spool"))
    try:
        for boxes, scores, cids in frames:
            spool.add(np.array(boxes, np.float32).reshape(-1, 4), np.array(scores, np.float32), np.array(cids))
        assert len(spool) == len(frames)
        for i in reversed(range(len(frames))):  # any order
            boxes, scores, cids = spool.get(i)
            want_boxes, want_scores, want_cids = frames[i]
            assert boxes.dtype == np.float32 and scores.dtype == np.float32 and cids.dtype == np.int64
            np.testing.assert_array_equal(boxes, np.array(want_boxes, np.float32).reshape(-1, 4))
            np.testing.assert_array_equal(scores, np.array(want_scores, np.float32))
            np.testing.assert_array_equal(cids, np.array(want_cids, np.int64))
            boxes[:] = 0  # fresh arrays: writable, and the spool keeps its copy
        assert spool.nbytes == 28 * sum(len(f[1]) for f in frames)
    finally:
        spool.close()


def test_the_spool_refuses_candidates_that_disagree_in_length(tmp_path):
    spool = CandidateSpool(tmp_path)
    try:
        with pytest.raises(ValueError, match="3 boxes, 2 scores, 3 class ids"):
            spool.add(np.zeros((3, 4)), np.zeros(2), np.zeros(3))
        assert len(spool) == 0 and spool.nbytes == 0
        spool.add(np.zeros((1, 4)), np.ones(1), np.zeros(1))
        assert spool.get(0)[1].tolist() == [1.0]
    finally:
        spool.close()
    assert list(tmp_path.iterdir()) == []  # unnamed: nothing left behind
