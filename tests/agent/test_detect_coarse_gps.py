"""`uavmm detect` in two passes makes an old DJI SRT's 4-decimal GPS continuous again (agent.telemetry_dequantize, as
the dataset path does), end to end on a real MJPG video, a Mavic Pro style SRT and a real ONNX model
(tests.agent.coarse_gps_flight)."""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pytest

from agent.sources import pose_from_meta
from shared.geo import latlon_to_local, local_to_latlon
from uavmm.cli import main

pytest.importorskip("onnx")

from tests.agent.coarse_gps_flight import (  # noqa: E402
    HEADING_DEG,
    LAT,
    LON,
    PITCH_DEG,
    CoarseGpsFlight,
    uav_en,
    write_coarse_gps_flight,
)


@pytest.fixture(scope="module")
def flight(tmp_path_factory) -> CoarseGpsFlight:
    return write_coarse_gps_flight(tmp_path_factory.mktemp("coarse-gps"), seed=0)


def _detect(flight: CoarseGpsFlight, out: Path, *extra: str, srt: Path | None = None) -> dict:
    assert main(["detect", str(flight.video), "--telemetry", str(srt or flight.srt), "--model", str(flight.model),
                 "--camera", str(flight.camera), "--pitch-deg", str(PITCH_DEG), "--heading-deg", str(HEADING_DEG),
                 "--out", str(out), "--quiet", *extra]) == 0
    return json.loads((out / "summary.json").read_text())


def _position_errors(flight: CoarseGpsFlight, out: Path) -> np.ndarray:
    """Per frame of images.json: metres between its pose's position and the UAV's true one."""
    errors = []
    for image in json.loads((out / "images.json").read_text())["images"]:
        pose, _, _ = pose_from_meta(image["meta"])
        assert pose is not None
        lat, lon = flight.positions[image["frame_index"]]
        east, north = latlon_to_local(np.array([pose.lat]), np.array([pose.lon]), lat, lon)
        errors.append(float(np.hypot(east[0], north[0])))
    return np.array(errors)


def _object_errors(flight: CoarseGpsFlight, out: Path) -> np.ndarray:
    """Per object of objects.geojson: metres to the nearest true object."""
    errors = []
    for feature in json.loads((out / "objects.geojson").read_text())["features"]:
        lon, lat = feature["geometry"]["coordinates"]
        east, north = latlon_to_local(flight.objects[:, 0], flight.objects[:, 1], lat, lon)
        errors.append(float(np.hypot(east, north).min()))
    return np.array(errors)


def test_two_passes_make_four_decimal_gps_continuous_and_the_frames_land_nearer_the_truth(flight, tmp_path, capsys):
    two = _detect(flight, tmp_path / "two")
    printed = capsys.readouterr().out
    one = _detect(flight, tmp_path / "one", "--one-pass")
    assert two["stages"]["dequantize"] == {"acted": 1, "stood_down": 0, "why": {"lat 0.0001, lon 0.0001": 1}}
    assert "dequantize: acted 1" in printed
    assert "dequantize" not in one["stages"]  # a live feed cannot look ahead at the next step
    one_err, two_err = _position_errors(flight, tmp_path / "one"), _position_errors(flight, tmp_path / "two")
    # one pass holds each written level: up to half a step (5.6 m north) off; two passes interpolate through the steps
    # (seed 0 on this VM: mean 2.41 -> 1.22 m, max 5.71 -> 3.34 m)
    assert one_err.mean() > 2.0 and one_err.max() > 5.0
    assert two_err.mean() < 1.5 and two_err.max() < 4.0
    # the objects found: as many, and where they are no further off than a metre and a half
    one_obj, two_obj = _object_errors(flight, tmp_path / "one"), _object_errors(flight, tmp_path / "two")
    assert len(two_obj) == len(one_obj) == 10
    assert two_obj.max() < 2.0 < one_obj.max()


def test_six_decimal_gps_is_left_as_written(flight, tmp_path):
    # the same flight written with 6 decimals (later DJI models: 0.11 m): nothing to make continuous, the stage stands
    # down and the poses are what one pass interpolates
    text = flight.srt.read_text()
    fine = tmp_path / "fine.srt"
    def six(match: re.Match) -> str:
        k = int(match.group(1)) - 1
        lat, lon = local_to_latlon(*uav_en(float(k)), LAT, LON)
        return f"{match.group(0).split('GPS(')[0]}GPS({float(lon):.6f},{float(lat):.6f},14)"

    fine.write_text(re.sub(r"(?m)^(\d+)\n[^\n]*\n[^\n]*\nGPS\([^)]*\)", six, text))
    assert fine.read_text() != text
    two = _detect(flight, tmp_path / "two", srt=fine)
    _detect(flight, tmp_path / "one", "--one-pass", srt=fine)
    assert two["stages"]["dequantize"] == {"acted": 0, "stood_down": 1, "why": {"no quantised coordinate": 1}}
    np.testing.assert_allclose(_position_errors(flight, tmp_path / "two"), _position_errors(flight, tmp_path / "one"),
                               atol=0.05)


def test_no_dequantize_in_the_params_keeps_the_written_levels(flight, tmp_path):
    params = tmp_path / "params.json"
    params.write_text(json.dumps({"dequantize_telemetry": False}))
    two = _detect(flight, tmp_path / "two", "--config", str(params))
    assert "dequantize" not in two["stages"]
    assert _position_errors(flight, tmp_path / "two").max() > 5.0
