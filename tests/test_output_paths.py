"""The output-writing commands refuse an output that is one of their own inputs (by any spelling, a symbolic or a
hard link, or a file a folder output would get) or another of their outputs: one line naming both flags, exit 2,
before the work, and nothing written (`uavmm.cli.require_outputs_apart`)."""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from tests.agent.test_boost_cli import make_dataset
from uavmm.cli import main
from uavmm.dataset_inputs import DatasetImages


def _snapshot(folder: Path) -> dict[str, bytes | str]:
    """Every entry of a folder tree (hidden ones too): file bytes, or the target of a link."""
    return {str(p.relative_to(folder)): (os.readlink(p) if p.is_symlink() else p.read_bytes() if p.is_file() else "/")
            for p in sorted(folder.rglob("*"))}


def _refused(capsys, command: str, *flags: str) -> str:
    err = capsys.readouterr().err
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"uavmm {command}: error: "), err
    assert all(flag in lines[0] for flag in flags), (flags, lines[0])
    return lines[0]


# ------------------------------------------------------------------------------------------------------------ track

def _track_args(d: Path) -> list[str]:
    return ["track", "--frames", str(d / "images.json"), "--candidates", str(d / "pre_nms.json"), "--camera",
            str(d / "camera.json"), "--no-images"]


@pytest.mark.parametrize("case", ["out spelled ./", "out spelled sub/..", "geojson symlink", "offsets hard link",
                                  "out folder file", "two outputs"])
def test_track_refuses_an_output_naming_one_of_its_inputs(tmp_path, capsys, monkeypatch, case):
    """Probe: each of these exited 0 with the input replaced by MOT rows (or, through a link, the link by them)."""
    d = tmp_path / "d"
    (d / "sub").mkdir(parents=True)
    make_dataset(d, frames=3)
    args = _track_args(d)
    if case == "out spelled ./":
        monkeypatch.chdir(d)
        extra, flags = ["--out", "./pre_nms.json"], ("--out", "--candidates")
    elif case == "out spelled sub/..":
        extra, flags = ["--out", str(d / "sub" / ".." / "camera.json")], ("--out", "--camera")
    elif case == "geojson symlink":
        (d / "link.geojson").symlink_to(d / "images.json")
        extra, flags = ["--out", str(tmp_path / "t.txt"), "--geojson", str(d / "link.geojson")], ("--geojson",
                                                                                                   "--frames")
    elif case == "offsets hard link":
        os.link(d / "camera.json", d / "offsets.csv")
        extra, flags = ["--out", str(tmp_path / "t.txt"), "--clock-offsets-out", str(d / "offsets.csv")], (
            "--clock-offsets-out", "--camera")
    elif case == "out folder file":  # --out DIR/ writes DIR/<video name>.txt: here the candidates are that file
        (d / "sub" / "v1.txt").write_bytes((d / "pre_nms.json").read_bytes())
        args[args.index("--candidates") + 1] = str(d / "sub" / "v1.txt")
        extra, flags = ["--out", f"{d / 'sub'}/"], ("--out (video 1)", "--candidates")
    else:
        extra, flags = ["--out", str(tmp_path / "t.txt"), "--geojson", str(d / "x.csv"), "--registrations-out",
                        str(d / "sub" / ".." / "x.csv")], ("--geojson", "--registrations-out")
    before = _snapshot(tmp_path)
    assert main([*args, *extra]) == 2
    _refused(capsys, "track", *flags)
    assert _snapshot(tmp_path) == before  # the inputs as they were, nothing written


def test_track_still_writes_into_a_folder_beside_its_inputs(tmp_path, capsys):
    d = make_dataset(tmp_path, frames=3)
    assert main([*_track_args(d), "--out", f"{d}/"]) == 0
    assert (d / "v1.txt").is_file() and json.loads((d / "pre_nms.json").read_text())


@pytest.mark.parametrize("case", ["out over a frame beside --frames", "geojson through a link into --image-dir",
                                  "offsets a hard link to a frame", "out folder file a frame"])
def test_track_refuses_an_output_naming_one_of_its_images(tmp_path, capsys, case):
    """Probe (left open): `track --out FRAME.jpg`, or an output reaching --image-dir's files through a link, exited 0
    with the image replaced by MOT rows / GeoJSON."""
    (tmp_path / "d").mkdir()
    d = make_dataset(tmp_path / "d", frames=3)
    args = [a for a in _track_args(d) if a != "--no-images"]
    images = d
    if case == "geojson through a link into --image-dir":
        images = tmp_path / "imgs"
        images.mkdir()
        (tmp_path / "link").symlink_to(images)
        args += ["--image-dir", str(images)]
    for k in range(3):
        (images / f"{k:05d}.jpg").write_bytes(b"\xff\xd8 not decoded: refused before any image is read")
    if case == "out over a frame beside --frames":
        extra, flags = ["--out", str(d / "00001.jpg")], ("--out", "--frames image")
    elif case == "geojson through a link into --image-dir":
        extra, flags = ["--out", str(tmp_path / "t.txt"), "--geojson", str(tmp_path / "link" / "00002.jpg")], (
            "--geojson", "--image-dir image")
    elif case == "offsets a hard link to a frame":
        os.link(d / "00000.jpg", tmp_path / "offsets.csv")
        extra, flags = ["--out", str(tmp_path / "t.txt"), "--clock-offsets-out", str(tmp_path / "offsets.csv")], (
            "--clock-offsets-out", "--frames image")
    else:  # --out DIR/ writes DIR/v1.txt, here a hard link to a frame
        (tmp_path / "out").mkdir()
        os.link(d / "00002.jpg", tmp_path / "out" / "v1.txt")
        extra, flags = ["--out", f"{tmp_path / 'out'}/"], ("--out (video 1)", "--frames image")
    before = _snapshot(tmp_path)
    assert main([*args, *extra]) == 2
    _refused(capsys, "track", *flags)
    assert _snapshot(tmp_path) == before


_NAMES = st.one_of(st.none(), st.integers(), st.just(""), st.just("/abs/x.jpg"),
                   st.text("ab/._-", min_size=1, max_size=12))


@settings(max_examples=80, deadline=None)
@given(entries=st.lists(st.one_of(st.fixed_dictionaries({}, optional={"file_name": _NAMES}), st.integers(),
                                  st.none()), max_size=6),
       top=st.sampled_from(["images", "list", "junk"]), image_dir=st.booleans())
def test_dataset_images_are_the_file_names_images_json_gives(tmp_path_factory, entries, top, image_dir):
    """`DatasetImages` parses images.json as `agent.dataset.image_file` resolves it: each non-empty string
    file_name, absolute as is, else under the image folder (default: beside images.json); any other shape gives
    none, never an error (the command itself says what is wrong)."""
    folder = tmp_path_factory.mktemp("ds")
    body = {"images": entries} if top == "images" else entries if top == "list" else None
    (folder / "images.json").write_text(json.dumps(body) if body is not None else "{not json")
    base = folder / "imgs" if image_dir else folder
    found = list(DatasetImages("--frames image", folder / "images.json", base if image_dir else None))
    names = [e["file_name"] for e in entries if isinstance(e, dict) and isinstance(e.get("file_name"), str)
             and e["file_name"]] if top == "images" else []
    assert found == [("--frames image", base / n) for n in names]
    assert all(p == Path(n) for (_, p), n in zip(found, names, strict=True) if n.startswith("/"))


# ---------------------------------------------------------------------------------------------------------- anomaly

@pytest.fixture(scope="module")
def rendered(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Two small rendered frames per video: `uavmm anomaly` runs through them (and wrote over an input, before)."""
    out = tmp_path_factory.mktemp("rendered") / "r"
    assert main(["sim", "sea", "--out", str(out), "--frames", "2", "--render", "--image-size", "160x90",
                 "--quiet"]) == 0
    return out


@pytest.mark.parametrize("case", ["hard link to the camera", "frames spelled ../"])
def test_anomaly_refuses_an_output_naming_one_of_its_inputs(tmp_path, capsys, monkeypatch, rendered, case):
    """Probe: `--out ../r/images.json` put the regions over the frames they came from (exit 0)."""
    d = tmp_path / "r"
    shutil.copytree(rendered, d)
    (d / "sub").mkdir()
    if case == "hard link to the camera":
        os.link(d / "camera.json", d / "rois.json")
        out, flags = str(d / "rois.json"), ("--out", "--camera")
    else:
        monkeypatch.chdir(d / "sub")
        out, flags = "../images.json", ("--out", "--frames")
    before = _snapshot(tmp_path)
    assert main(["anomaly", "--frames", str(d / "images.json"), "--camera", str(d / "camera.json"), "--method", "mean",
                 "--out", out, "--quiet"]) == 2
    _refused(capsys, "anomaly", *flags)
    assert _snapshot(tmp_path) == before


@pytest.mark.parametrize("case", ["out over a frame", "out a link into the frames' folder"])
def test_anomaly_refuses_an_output_naming_one_of_its_frames(tmp_path, capsys, rendered, case):
    """Probe (left open): `anomaly --frames images.json --out FRAME.jpg` exited 0 with the frame replaced by JSON."""
    d = tmp_path / "r"
    shutil.copytree(rendered, d)
    frame = d / json.loads((d / "images.json").read_text())["images"][1]["file_name"]
    if case == "out over a frame":
        out = frame
    else:
        (tmp_path / "link").symlink_to(frame.parent)
        out = tmp_path / "link" / frame.name
    before = _snapshot(tmp_path)
    assert main(["anomaly", "--frames", str(d / "images.json"), "--camera", str(d / "camera.json"), "--method", "mean",
                 "--out", str(out), "--quiet"]) == 2
    _refused(capsys, "anomaly", "--out", "--frames image", frame.name)
    assert _snapshot(tmp_path) == before


# ----------------------------------------------------------------------------------------------------------- detect

@pytest.mark.parametrize("name, flag", [("annotated.mp4", "VIDEO"), ("tracks.txt", "--telemetry"),
                                        ("summary.json", "--camera")])
def test_detect_refuses_an_out_folder_whose_fixed_names_are_its_inputs(tmp_path, capsys, name, flag):
    """Probe: `uavmm detect run/annotated.mp4 --out run --render-video` wrote the annotated video over the video it
    read (exit 0). Refused before the model or the video is opened: the files here are stand-ins."""
    run = tmp_path / "run"
    run.mkdir()
    files = {"VIDEO": run / "flight.mp4", "--telemetry": run / "flight.csv", "--camera": run / "camera.json"}
    files[flag] = run / name
    for path in files.values():
        path.write_bytes(b"input")
    (tmp_path / "m.onnx").write_bytes(b"model")
    before = _snapshot(tmp_path)
    assert main(["detect", str(files["VIDEO"]), "--telemetry", str(files["--telemetry"]), "--model",
                 str(tmp_path / "m.onnx"), "--camera", str(files["--camera"]), "--out", str(run),
                 "--render-video", "--quiet"]) == 2
    line = _refused(capsys, "detect", "--out", flag)
    assert str(run / name) in line
    assert _snapshot(tmp_path) == before


# ------------------------------------------------------------------------------------------------------------ agent

@pytest.mark.parametrize("case", ["detections over the candidates", "tracks through a link to the frames",
                                  "one file twice"])
def test_agent_refuses_an_output_naming_one_of_its_inputs(tmp_path, capsys, case):
    """Probe: `uavmm agent --dataset DS --detections-out DS/pre_nms.json` flew and put its detections over the
    candidates it played (exit 0); `--tracks-out` over images.json the same. Refused before Zenoh is opened."""
    d = tmp_path / "ds"
    d.mkdir()
    make_dataset(d, frames=3)
    if case == "detections over the candidates":
        extra, flags = ["--detections-out", str(d / "pre_nms.json")], ("--detections-out", "--dataset")
    elif case == "tracks through a link to the frames":
        (tmp_path / "tracks.geojson").symlink_to(d / "images.json")
        extra, flags = ["--tracks-out", str(tmp_path / "tracks.geojson")], ("--tracks-out", "--dataset")
    else:
        extra, flags = ["--tracks-out", str(tmp_path / "o.json"), "--detections-out",
                        str(d / ".." / "o.json")], ("--tracks-out", "--detections-out")
    before = _snapshot(tmp_path)
    assert main(["agent", "--uav-id", "uav1", "--dataset", str(d), "--speed", "0", *extra]) == 2
    _refused(capsys, "agent", *flags)
    assert _snapshot(tmp_path) == before


# ------------------------------------------------------------------------------------------------------------ boost

def test_boost_refuses_results_and_corrections_in_one_file(tmp_path, capsys):
    """Probe: `--out X --corrections-out X` wrote the results, then the corrections CSV over them (exit 0)."""
    d = make_dataset(tmp_path, frames=3)
    before = _snapshot(tmp_path)
    assert main(["boost", "--frames", str(d / "images.json"), "--candidates", str(d / "pre_nms.json"), "--camera",
                 str(d / "camera.json"), "--out", str(d / "r.json"), "--corrections-out", f"{d}/./r.json"]) == 2
    _refused(capsys, "boost", "--out", "--corrections-out")
    assert _snapshot(tmp_path) == before
