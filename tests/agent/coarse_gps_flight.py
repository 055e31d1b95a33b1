"""A recorded flight for `uavmm detect` with an old DJI SRT: a UAV flying north-east at a steady speed, its camera
looking ahead, a video of white squares (the objects) seen from the true poses, and the Mavic Pro's subtitle file (a
block a second, `GPS(lon, lat, satellites)` with 4 decimals: the position holds for seconds, then steps by 11 m north
or 7 m east; no gimbal angles, so --pitch-deg and --heading-deg give them). The detector is the real ONNX blob model
of tests.agent.jump_flight."""

from __future__ import annotations

import json
import time
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from shared.geo import Camera, Pose, latlon_to_pixel, local_to_latlon
from tests.agent.jump_flight import FPS, FX, HEIGHT, LAT, LON, SQUARE_PX, WIDTH, make_blob_model

HEIGHT_M, PITCH_DEG, HEADING_DEG = 40.0, 60.0, 45.0
SPEED_MPS = 6.0
#: 2017-07-29 13:18:56 UTC, the Mavic Pro sample's first date
T0 = 1501334336.0


@dataclass(frozen=True)
class CoarseGpsFlight:
    video: Path
    srt: Path
    camera: Path
    model: Path
    #: the UAV's true (lat, lon) at each frame
    positions: np.ndarray
    #: objects' (lat, lon)
    objects: np.ndarray


def uav_en(t: float | np.ndarray, stop_s: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The UAV's true east, north (m) from its start at time t (s); from stop_s on it hovers."""
    t = np.asarray(t, dtype=np.float64)
    d = SPEED_MPS * (t if stop_s is None else np.minimum(t, stop_s))
    return d * np.sin(np.radians(HEADING_DEG)), d * np.cos(np.radians(HEADING_DEG))


def _srt_time(s: float) -> str:
    ms = round(s * 1000)
    return f"{ms // 3600000:02d}:{ms // 60000 % 60:02d}:{ms // 1000 % 60:02d},{ms % 1000:03d}"


def write_coarse_gps_flight(folder: Path, *, seconds: float = 12.0, seed: int = 0,
                            stop_s: float | None = None) -> CoarseGpsFlight:
    """The flight in folder: flight.avi (MJPG), flight.srt (1 Hz, GPS with 4 decimals), camera.json, blobs.onnx.
    stop_s: the UAV stops there and hovers to the end."""
    folder.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    camera = Camera(width=WIDTH, height=HEIGHT, fx=FX, fy=FX, cx=WIDTH / 2, cy=HEIGHT / 2)
    # ten objects along the route, 15-105 m ahead of the start, within 10 m of its line
    along = np.sort(rng.uniform(15.0, 105.0, 10))
    across = rng.uniform(-10.0, 10.0, len(along))
    h = np.radians(HEADING_DEG)
    east, north = along * np.sin(h) + across * np.cos(h), along * np.cos(h) - across * np.sin(h)
    lat, lon = local_to_latlon(east, north, LAT, LON)
    n_frames = int(round(seconds * FPS))
    times = np.arange(n_frames) / FPS
    ue, un = uav_en(times, stop_s)
    ulat, ulon = local_to_latlon(ue, un, LAT, LON)
    writer = cv2.VideoWriter(str(folder / "flight.avi"), cv2.VideoWriter.fourcc(*"MJPG"), FPS, (WIDTH, HEIGHT))
    assert writer.isOpened()
    half = SQUARE_PX // 2
    for la, lo in zip(ulat, ulon, strict=True):
        image = np.full((HEIGHT, WIDTH, 3), 30, np.uint8)
        uv, valid = latlon_to_pixel(lat, lon, camera, Pose(float(la), float(lo), HEIGHT_M, PITCH_DEG, HEADING_DEG))
        for (u, v), ok in zip(uv, valid, strict=True):
            if ok and 0 <= u < WIDTH and 0 <= v < HEIGHT:
                cv2.rectangle(image, (int(u) - half, int(v) - half), (int(u) + half, int(v) + half),
                              (255, 255, 255), -1)
        writer.write(image)
    writer.release()
    blocks = []
    for k in range(int(seconds) + 1):
        e, n = uav_en(float(k), stop_s)
        la, lo = local_to_latlon(e, n, LAT, LON)
        date = time.strftime("%Y.%m.%d %H:%M:%S", time.gmtime(T0 + k))
        blocks.append(f"{k + 1}\n{_srt_time(k)} --> {_srt_time(k + 1)}\n"
                      f"HOME({LON:.4f},{LAT:.4f}) {date}\n"
                      f"GPS({float(lo):.4f},{float(la):.4f},14) BAROMETER:{HEIGHT_M:.1f}\n"
                      "ISO:100 Shutter:60 EV: Fnum:2.2 \n")
    (folder / "flight.srt").write_text("\n".join(blocks))
    (folder / "camera.json").write_text(json.dumps({"width": WIDTH, "height": HEIGHT, "fx": FX}))
    return CoarseGpsFlight(folder / "flight.avi", folder / "flight.srt", folder / "camera.json",
                           make_blob_model(folder / "blobs.onnx"), np.stack([ulat, ulon], axis=1),
                           np.stack([lat, lon], axis=1))


def write_held_gps_srt(flight: CoarseGpsFlight, path: Path, *, seconds: float = 12.0, gps_hz: float = 1.0,
                       phase_s: float = 0.35, stop_s: float | None = None, gps_noise_m: float = 0.2,
                       seed: int = 0) -> Path:
    """A subtitle file for the flight's video as later DJI models write it (Mini 3 / Matrice 30: a block a frame,
    ``[latitude: ..] [longitude: ..]`` with 6 decimals, ``rel_alt`` every frame), whose GPS updates gps_hz times a
    second (at phase_s + k / gps_hz), each fix off the truth by gps_noise_m (std per axis), and holds its value on
    the frames between: the real Matrice 30 sample of tests/shared/test_telemetry.py repeats its position on
    consecutive frames while rel_alt moves on."""
    rng = np.random.default_rng(seed)
    first = int(np.floor(-phase_s * gps_hz))  # the update held at t = 0
    fixes = np.arange(first, int(np.ceil(seconds * gps_hz)) + 1)
    noise = {int(k): rng.normal(0.0, gps_noise_m, 2) for k in fixes}
    blocks = []
    for k in range(int(round(seconds * FPS))):
        t = k / FPS
        fix = int(np.floor((t - phase_s) * gps_hz))
        e, n = uav_en(phase_s + fix / gps_hz, stop_s)
        la, lo = local_to_latlon(e + noise[fix][0], n + noise[fix][1], LAT, LON)
        stamp = T0 + t
        date = time.strftime("%Y-%m-%d %H:%M:%S", time.gmtime(stamp)) + f".{round((stamp % 1) * 1000) % 1000:03d}"
        blocks.append(f"{k + 1}\n{_srt_time(t)} --> {_srt_time(t + 1 / FPS)}\n"
                      f'<font size="28">FrameCnt: {k + 1}, DiffTime: {round(1000 / FPS)}ms\n{date}\n'
                      f"[iso: 100] [shutter: 1/500.0] [fnum: 2.8] [ev: 0] [focal_len: 24.00] "
                      f"[latitude: {float(la):.6f}] [longitude: {float(lo):.6f}] "
                      f"[rel_alt: {HEIGHT_M + 0.001 * (k % 7):.3f} abs_alt: {HEIGHT_M + 400.0:.3f}] </font>\n")
    path.write_text("\n".join(blocks))
    return path
