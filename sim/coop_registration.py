"""The joint registration (`agent.joint_detections.JointRegistration`) against the truth of a simulated flight.

Every UAV georeferences with its own telemetry errors, so the others' evidence of an object lands beside this
UAV's own view of it; the registration estimates that offset in the image and the joint detections move the
others' peaks by it. Here the offset the telemetry actually makes is computed from the truth, frame by frame:
the true ground point P under a reference pixel (`REF_PIXEL`: the image's centre column, 65 % down) of this
UAV's true pose is where each other UAV sees the object; that UAV's noisy pose puts it at G (its map holds G
moved by its telemetry correction); this UAV, its noisy pose moved by its own correction (as the joint
detections project), sees G at a pixel. That pixel minus the reference pixel is the true offset of that UAV's
evidence; with several other UAVs, their mean (the registration estimates the offset most peaks share).

`registration_errors` gives per UAV the median length of the true offset (what no registration leaves) and of
the registration's estimate minus it (what the registration leaves), in pixels.

A model, not a replay: the other UAV's map holds evidence laid down under its corrections over the last seconds,
and the model takes its latest one. The figure is sensitive to that (on a 3 s `coop-glare` clip, taking the
other UAV's correction as zero moves what is left from 42 / 50 px to 32 / 100 px). Camera roll is not in
truth.json: domains that roll the camera would need it. Flat ground only (datasets with a DEM are refused).
"""

from __future__ import annotations

import json
import math
import statistics
from pathlib import Path

import numpy as np

from agent.dataset import Dataset, iter_video_frames
from shared.geo import Camera, Pose, latlon_to_local, latlon_to_pixel, local_to_latlon, pixel_to_latlon

__all__ = ["REF_PIXEL", "RegistrationRecord", "registration_errors", "true_offsets"]

#: the reference pixel as fractions of the image's width and height (below the horizon at every pitch we fly)
REF_PIXEL = (0.5, 0.65)
#: partner frames farther apart in time than this are not compared (seconds)
_MAX_DT_S = 0.2
#: a frame's own records, truth and noisy pose are the same frame within this (stamps rounded differently)
_SAME_FRAME_S = 0.002

#: (t, offset x px, offset y px, correction east m, correction north m) of one frame of one video
RegistrationRecord = tuple[float, float, float, float, float]


def registration_errors(data_dir: Path, records: dict[int, list[RegistrationRecord]],
                        given: dict[int, dict[float, tuple[Pose, Camera]]] | None = None
                        ) -> dict[str, dict[str, float]]:
    """Per UAV of a simultaneous dataset: frames compared, `offset_px` (median length of the true offset of the
    others' evidence) and `left_px` (median length of the registration's estimate minus it).

    records: per video id, each frame's registration estimate and telemetry correction (`sim.coop_eval.run_coop`'s
    registration_out). given: the poses the pipeline was given (run_coop's poses_out; None: the telemetry as
    stamped). Frames without a true or noisy pose, or whose reference ray meets no ground, are skipped.
    """
    dataset, true, noisy = _load(data_dir)
    if given is not None:
        noisy = given
    truth = _true_offsets(records, true, noisy)
    uav_of = {v["id"]: v.get("uav", str(v["id"])) for v in dataset.coco.get("videos", [])}
    out: dict[str, dict[str, float]] = {}
    for vid, recs in records.items():
        offsets, left = [], []
        for (_, ox, oy, _, _), offset in zip(recs, truth[vid], strict=True):
            if offset is None:
                continue
            offsets.append(float(np.hypot(*offset)))
            left.append(float(np.hypot(ox - offset[0], oy - offset[1])))
        out[uav_of.get(vid, str(vid))] = {
            "frames": len(offsets),
            "offset_px": statistics.median(offsets) if offsets else math.nan,
            "left_px": statistics.median(left) if left else math.nan}
    return out


def true_offsets(data_dir: Path, records: dict[int, list[RegistrationRecord]]
                 ) -> dict[int, list[tuple[float, float] | None]]:
    """Per video id and record (frame): the true image offset (x, y pixels) of the other UAVs' evidence from this
    UAV's view (see the module docstring), None where it cannot be computed (no true or noisy pose, the
    reference ray meets no ground, no other UAV sees the point)."""
    return _true_offsets(records, *_load(data_dir)[1:])


def _load(data_dir: Path) -> tuple[Dataset, dict[int, dict[float, Pose]], dict[int, dict[float, tuple[Pose, Camera]]]]:
    """The dataset and, per video id and frame time, its true poses (truth.json) and the noisy ones with cameras
    (the telemetry as stamped, `iter_video_frames`; registration_errors takes those run_coop gave when it has them)."""
    if (data_dir / "dem.npz").exists():
        raise ValueError(f"registration_errors: {data_dir} is over a terrain (dem.npz); the truth model here puts the "
                         "reference pixel's ground point on flat ground")
    dataset = Dataset.load(data_dir / "images.json")
    camera = Camera.from_file(data_dir / "camera.json")
    truth = json.loads((data_dir / "truth.json").read_text())
    true: dict[int, dict[float, Pose]] = {}
    for p in truth.get("poses", []):
        true.setdefault(p["video_id"], {})[round(p["t"], 4)] = Pose(p["lat"], p["lon"], p["height_m"],
                                                                   p["pitch_deg"], p["heading_deg"])
    noisy: dict[int, dict[float, tuple[Pose, Camera]]] = {
        vid: {round(f.t, 4): (f.pose, f.camera) for f in iter_video_frames(dataset, camera, vid, at_frame_time=False)
              if f.pose is not None}
        for vid in dataset.videos}
    return dataset, true, noisy


def _true_offsets(records: dict[int, list[RegistrationRecord]], true: dict[int, dict[float, Pose]],
                  noisy: dict[int, dict[float, tuple[Pose, Camera]]]) -> dict[int, list[tuple[float, float] | None]]:
    corrections = {vid: {round(r[0], 4): (r[3], r[4]) for r in recs} for vid, recs in records.items()}
    return {vid: [_true_offset(vid, rec, records, true, noisy, corrections) for rec in recs]
            for vid, recs in records.items()}


def _true_offset(vid: int, rec: RegistrationRecord, records: dict[int, list[RegistrationRecord]],
                 true: dict[int, dict[float, Pose]], noisy: dict[int, dict[float, tuple[Pose, Camera]]],
                 corrections: dict[int, dict[float, tuple[float, float]]]) -> tuple[float, float] | None:
    """One frame's true offset (see true_offsets)."""
    t, _, _, ce, cn = rec
    own = _nearest(noisy.get(vid, {}), t, _SAME_FRAME_S)
    own_true = _nearest(true.get(vid, {}), t, _SAME_FRAME_S)
    if own is None or own_true is None:
        return None
    pose, cam = own
    ref = np.array([[cam.width * REF_PIXEL[0], cam.height * REF_PIXEL[1]]])
    lat, lon, ok = pixel_to_latlon(ref, cam, own_true)
    if not ok[0]:
        return None
    seen = []
    for other in records:
        if other == vid:
            continue
        tb = _nearest(true.get(other, {}), t)
        nb = _nearest(noisy.get(other, {}), t)
        if tb is None or nb is None:
            continue
        uv_b, ok_b = latlon_to_pixel(lat, lon, nb[1], tb)
        if not ok_b[0]:
            continue
        lat_g, lon_g, ok_g = pixel_to_latlon(uv_b, nb[1], nb[0])
        if not ok_g[0]:
            continue
        cb = _nearest(corrections.get(other, {}), t) or (0.0, 0.0)
        east, north = latlon_to_local(lat_g, lon_g, pose.lat, pose.lon)
        lat_c, lon_c = local_to_latlon(east + cb[0] - ce, north + cb[1] - cn, pose.lat, pose.lon)
        uv, ok_a = latlon_to_pixel(lat_c, lon_c, cam, pose)
        if ok_a[0]:
            seen.append(uv[0] - ref[0])
    if not seen:
        return None
    offset = np.mean(seen, axis=0)
    return float(offset[0]), float(offset[1])


def _nearest(table: dict, t: float, tolerance_s: float = _MAX_DT_S):
    """The value of table (keys: times) nearest to t within tolerance_s, else None."""
    if not table:
        return None
    key = min(table, key=lambda k: abs(k - t))
    return table[key] if abs(key - t) <= tolerance_s else None
