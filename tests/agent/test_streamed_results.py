"""`agent.boost.StreamedResults`: the agent's --detections-out written as the results come, one valid JSON array at
the end, never a truncated file in its place."""

from __future__ import annotations

import json

import pytest

from agent.boost import StreamedResults


def _result(i: int) -> dict:
    return {"image_id": i, "category_id": 1, "bbox": [1.0, 2.0, 3.0, 4.0], "score": 0.5 + i / 1000}


def test_results_stream_to_a_tmp_file_and_land_whole_at_close(tmp_path):
    out = tmp_path / "dets.json"
    spool = StreamedResults(out)
    spool.extend([_result(0), _result(1)])
    spool.extend([])
    spool.extend([_result(2)])
    assert not out.exists() and (tmp_path / "dets.json.tmp").exists()  # a run that dies here leaves no results file
    spool.close()
    spool.close()  # idempotent
    assert json.loads(out.read_text()) == [_result(0), _result(1), _result(2)] and spool.count == 3
    assert not (tmp_path / "dets.json.tmp").exists()


def test_no_results_give_an_empty_array_and_a_missing_folder_is_named(tmp_path):
    spool = StreamedResults(tmp_path / "none.json")
    spool.close()
    assert json.loads((tmp_path / "none.json").read_text()) == []
    with pytest.raises(FileNotFoundError, match="output directory .*missing does not exist"):
        StreamedResults(tmp_path / "missing" / "d.json")


def test_an_aborted_run_leaves_neither_the_file_nor_its_tmp(tmp_path):
    out = tmp_path / "dets.json"
    spool = StreamedResults(out)
    spool.extend([_result(0)])
    spool.abort()
    spool.close()  # after an abort: nothing to put in place
    assert not out.exists() and not (tmp_path / "dets.json.tmp").exists()


def test_a_folder_as_the_results_file_is_refused_before_the_run(tmp_path):
    """`uavmm boost --out DIR` ran the whole dataset and failed when putting the file in place, leaving the .tmp."""
    (tmp_path / "out").mkdir()
    with pytest.raises(IsADirectoryError, match="is a directory"):
        StreamedResults(tmp_path / "out")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]


def test_a_frame_is_written_whole_or_not_at_all(tmp_path):
    """Second read: a frame's results were written one by one, so an interrupt inside a frame (Ctrl-C in `uavmm
    anomaly`, which then puts the file in place) left part of it. Here the third result of a frame fails to
    serialise: none of that frame is written."""
    out = tmp_path / "dets.json"
    spool = StreamedResults(out)
    spool.extend([_result(0)])
    with pytest.raises(TypeError):
        spool.extend([_result(1), _result(2), {"image_id": 3, "score": object()}])
    spool.close()
    assert json.loads(out.read_text()) == [_result(0)] and spool.count == 1
