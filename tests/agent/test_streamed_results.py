"""`agent.boost.StreamedResults`: the agent's --detections-out written as the results come, one valid JSON array at
the end, never a truncated file in its place."""

from __future__ import annotations

import json
import os

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
    writing = spool.spool_path
    assert writing is not None and writing.parent == tmp_path and writing.name.startswith(".dets.json.")
    assert not out.exists() and writing.exists()  # a run that dies here leaves no results file
    spool.close()
    spool.close()  # idempotent
    assert json.loads(out.read_text()) == [_result(0), _result(1), _result(2)] and spool.count == 3
    assert sorted(p.name for p in tmp_path.iterdir()) == ["dets.json"]


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
    assert not out.exists() and not list(tmp_path.iterdir())


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


def test_a_link_planted_at_the_old_spool_name_is_not_written_through(tmp_path):
    """The spool was ``OUT.tmp``, opened with a plain open(): a link left at that name took the results (the file it
    pointed to was overwritten) and the rename made ``OUT`` that link. The spool is now a new file of its own."""
    outside = tmp_path / "outside.txt"
    outside.write_text("precious\n")
    out = tmp_path / "dets.json"
    for name in ("dets.json.tmp", ".dets.json.tmp", f".dets.json.{os.getpid()}.tmp"):
        (tmp_path / name).symlink_to(outside)
    spool = StreamedResults(out)
    spool.extend([_result(0)])
    spool.close()
    assert outside.read_text() == "precious\n"
    assert not out.is_symlink() and json.loads(out.read_text()) == [_result(0)]


def test_two_writers_of_one_output_each_put_a_whole_file_in_place(tmp_path):
    """Two runs writing one output shared the fixed spool: the second truncated the first's, the first's close put
    the second's results in place and the second's close failed (FileNotFoundError)."""
    out = tmp_path / "dets.json"
    first, second = StreamedResults(out), StreamedResults(out)
    first.extend([_result(0)])
    second.extend([_result(1), _result(2)])
    first.extend([_result(3)])
    first.close()
    assert json.loads(out.read_text()) == [_result(0), _result(3)]
    second.close()
    assert json.loads(out.read_text()) == [_result(1), _result(2)]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["dets.json"]


def test_the_results_are_on_disk_before_the_rename(tmp_path, monkeypatch):
    """`close` renamed the spool into place without fsync (a crash could leave an empty results file)."""
    import shared.files

    synced: list[int] = []
    real = os.fsync
    monkeypatch.setattr(shared.files.os, "fsync", lambda fd: (synced.append(fd), real(fd))[1])
    spool = StreamedResults(tmp_path / "dets.json")
    spool.extend([_result(0)])
    spool.close()
    assert len(synced) == 1
