"""What to draw, read from a simulated dataset directory: true poses, worlds (trees, clutter) and the objects.

The renderer draws exactly what the dataset knows: `truth.json` (true poses, blur flags, trees, clutter,
objects hidden behind trees), `images.json` (the annotated objects' true ``lat``/``lon`` and track ids) and
`camera.json`. An object that leaves the image is annotated only while at least half of its box is inside,
so its position is continued for up to `CONTINUE_S` beyond its first and last known sightings, and such
estimated positions are drawn only where the object is cut by the image border (see `SceneObject.known`).
"""

from __future__ import annotations

import json
import logging
import math
from collections import defaultdict
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from shared.geo import Camera, Pose, latlon_to_local
from shared.telemetry import parse_datetime
from sim.sea_state import SeaState
from sim.world import CLASS_BOX_M, Tree  # Tree: the cylinder the simulator occludes with

logger = logging.getLogger(__name__)

#: Files a simulated dataset directory must hold for rendering.
REQUIRED_FILES = ("images.json", "camera.json", "truth.json")
#: Seconds an object's position is continued beyond its known sightings (objects at the image border).
CONTINUE_S = 1.0
#: Seconds over which an object's heading is estimated from its motion.
_YAW_WINDOW_S = 0.5
#: Motion below this many metres over the window keeps the previous heading (a pause, a resting person).
_YAW_MIN_MOVE_M = 0.05


@dataclass(frozen=True, slots=True)
class SceneObject:
    """One tracked object in one frame.

    Attributes
    ----------
    track_id : int
    cls : str
        "person" or "swimmer" (`sim.world.CLASS_BOX_M`).
    east_m, north_m : float
        World-frame position (metres around the world origin).
    yaw_deg : float
        Heading of the object's depth axis, clockwise from north: a person's from its motion (fixed while it
        rests), a swimmer's fixed per swimmer.
    known : bool
        True when the dataset gives the position at this time (annotated or hidden behind a tree in some
        video of the group); False when continued from a sighting up to `CONTINUE_S` away, which is drawn
        only where the object is cut by the image border.
    """

    track_id: int
    cls: str
    east_m: float
    north_m: float
    yaw_deg: float
    known: bool


@dataclass(frozen=True, slots=True)
class SceneWorld:
    """The static scene of one group of videos (one world): kind, origin, trees and clutter spots.

    kind is "sea" (swimmers) or "meadow" (people); clutter_en is (C, 2) world east/north metres.
    """

    group: int
    kind: str
    origin_lat: float
    origin_lon: float
    trees: tuple[Tree, ...]
    clutter_en: np.ndarray


@dataclass(frozen=True, slots=True)
class SceneVideo:
    """One video of the dataset: id, name (image folder and file stem), uav, group, image ids in frame order."""

    id: int
    name: str
    uav: str
    group: int
    image_ids: tuple[int, ...]


@dataclass(frozen=True, slots=True)
class SceneFrame:
    """Everything needed to draw one image.

    pose is the TRUE pose (truth.json); meta the image's SeaDronesSee meta (the NOISY telemetry, None for a
    dropout), `t` the frame time (UNIX seconds).
    """

    image_id: int
    video_id: int
    frame_index: int
    file_name: str
    t: float
    pose: Pose
    blurred: bool
    heading_rate_deg_s: float
    meta: dict[str, Any] | None
    objects: tuple[SceneObject, ...]


def _load_json(path: Path) -> Any:
    try:
        return json.loads(path.read_text())
    except json.JSONDecodeError as exc:
        raise ValueError(f"{path} is not valid JSON: {exc}") from None


class SimulatedDataset:
    """A dataset directory written by `uavmm sim`, opened for rendering.

    Parameters
    ----------
    directory : path
        Holds images.json, camera.json and truth.json.

    Raises
    ------
    ValueError
        One line: the directory does not exist, a file is missing or unreadable, or the dataset is not a
        simulated one (no true poses, annotations without ``lat``/``lon``).

    Attributes
    ----------
    directory : Path
    camera : shared.geo.Camera
    fps : float
    seed : int
    scenario : str
    sea_state : SeaState
        How rough the sea is drawn (truth.json ``scenario.sea_state``; absent: the calm sea).
    videos : list of SceneVideo
    worlds : dict of int to SceneWorld
        By group.
    """

    def __init__(self, directory: str | Path) -> None:
        self.directory = Path(directory)
        if not self.directory.is_dir():
            raise ValueError(f"dataset directory {self.directory} does not exist")
        missing = [n for n in REQUIRED_FILES if not (self.directory / n).is_file()]
        if "images.json" in missing:
            raise ValueError(f"{self.directory} is not a dataset directory: images.json is missing")
        if missing:
            raise ValueError(f"{self.directory} is not a simulated dataset: {', '.join(missing)} missing "
                             "(rendering needs the true poses that `uavmm sim` writes)")
        self.camera = Camera.from_file(self.directory / "camera.json")
        coco = _load_json(self.directory / "images.json")
        truth = _load_json(self.directory / "truth.json")
        if not isinstance(coco, dict) or not isinstance(coco.get("images"), list):
            raise ValueError(f"{self.directory / 'images.json'} is not COCO (no 'images' list)")
        if not isinstance(truth, dict) or not isinstance(truth.get("poses"), list) or "scenario" not in truth:
            raise ValueError(f"{self.directory / 'truth.json'} is not a simulator truth file (no 'poses'/'scenario')")
        if "terrain" in truth:  # the renderer draws flat ground: its frames would not show the annotated boxes
            raise ValueError(f"{self.directory} was simulated over a terrain ({truth['terrain'].get('kind')}); the "
                             "renderer draws flat ground only (the dataset itself needs no frames)")
        try:
            self._parse(coco, truth)
        except (KeyError, TypeError, IndexError) as exc:
            raise ValueError(f"{self.directory} is not a simulated dataset: missing or malformed field {exc}") from None

    # ------------------------------------------------------------------ parsing

    def _parse(self, coco: dict[str, Any], truth: dict[str, Any]) -> None:
        sc = truth["scenario"]
        self.scenario = str(sc["name"])
        self.sea_state = SeaState.from_dict(sc.get("sea_state"))
        self.fps = float(sc["fps"])
        self.seed = int(truth["seed"])
        self.blur_heading_rate_deg_s = float(sc.get("emulator", {}).get("blur_heading_rate_deg_s", 30.0))
        world = sc["world"]
        cls = str(world["cls"])
        if cls not in CLASS_BOX_M:
            raise ValueError(f"{self.directory / 'truth.json'}: unknown object class {cls!r}")
        self.cls = cls
        origin = (float(world["origin_lat"]), float(world["origin_lon"]))
        self.images = {int(im["id"]): im for im in coco["images"]}
        if not self.images:
            raise ValueError(f"{self.directory / 'images.json'} has no images")
        poses = {int(p["image_id"]): p for p in truth["poses"]}
        no_pose = [i for i in self.images if i not in poses]
        if no_pose:
            raise ValueError(f"{self.directory / 'truth.json'} has no true pose for {len(no_pose)} image(s) "
                             f"(first: image id {no_pose[0]})")
        self._poses = poses
        video_meta = {int(v["id"]): v for v in truth["videos"]}
        names = {int(v["id"]): str(v["name"]) for v in coco.get("videos", [])}
        by_video: dict[int, list[tuple[int, int]]] = defaultdict(list)
        for im in coco["images"]:
            by_video[int(im["video_id"])].append((int(im["frame_index"]), int(im["id"])))
        self.videos: list[SceneVideo] = []
        for vid in sorted(by_video):
            if vid not in video_meta:
                raise ValueError(f"{self.directory / 'truth.json'} does not describe video {vid}")
            vm = video_meta[vid]
            frames = sorted(by_video[vid])
            self.videos.append(SceneVideo(vid, names.get(vid, str(vm["name"])), str(vm["uav"]), int(vm["group"]),
                                          tuple(i for _, i in frames)))
        groups = sorted({v.group for v in self.videos})
        self.worlds: dict[int, SceneWorld] = {}
        for g in groups:
            trees = tuple(Tree(float(t["east_m"]), float(t["north_m"]), float(t["radius_m"]), float(t["height_m"]))
                          for t in truth.get("trees", []) if int(t["group"]) == g)
            clutter = [(float(c["lat"]), float(c["lon"])) for c in truth.get("clutter", []) if int(c["group"]) == g]
            if clutter:
                ce, cn = latlon_to_local(np.array([c[0] for c in clutter]), np.array([c[1] for c in clutter]), *origin)
                clutter_en = np.column_stack([np.atleast_1d(ce), np.atleast_1d(cn)])
            else:
                clutter_en = np.zeros((0, 2))
            self.worlds[g] = SceneWorld(g, "sea" if cls == "swimmer" else "meadow", origin[0], origin[1], trees,
                                        clutter_en)
        self._origin = origin
        self._tracks = self._track_tables(coco, truth)

    def _track_tables(self, coco: dict[str, Any], truth: dict[str, Any]) -> dict[int, dict[int, np.ndarray]]:
        """Per group and track: an (F, 3) array of (frame_index, east_m, north_m) of the known positions."""
        group_of_image = {}
        for v in self.videos:
            for image_id in v.image_ids:
                group_of_image[image_id] = v.group
        seen: dict[int, dict[int, dict[int, tuple[float, float]]]] = defaultdict(lambda: defaultdict(dict))
        missing = 0
        sightings = list(coco.get("annotations", [])) + list(truth.get("occluded_boxes", []))
        for a in sightings:
            if "lat" not in a or "lon" not in a:
                missing += 1
                continue
            image_id = int(a["image_id"])
            if image_id not in group_of_image:
                continue
            f = int(self.images[image_id]["frame_index"])
            seen[group_of_image[image_id]][int(a["track_id"])][f] = (float(a["lat"]), float(a["lon"]))
        if missing:
            raise ValueError(f"{self.directory} is not a simulated dataset: {missing} annotation(s) have no true "
                             "'lat'/'lon'")
        tables: dict[int, dict[int, np.ndarray]] = {}
        for g, tracks in seen.items():
            tables[g] = {}
            for tid, by_frame in tracks.items():
                frames = np.array(sorted(by_frame), dtype=np.float64)
                lat = np.array([by_frame[int(f)][0] for f in frames])
                lon = np.array([by_frame[int(f)][1] for f in frames])
                east, north = latlon_to_local(lat, lon, *self._origin)
                tables[g][tid] = np.column_stack([frames, np.atleast_1d(east), np.atleast_1d(north)])
        return tables

    # ------------------------------------------------------------------ per frame

    def pose(self, image_id: int) -> Pose:
        """The TRUE pose of an image."""
        p = self._poses[image_id]
        return Pose(float(p["lat"]), float(p["lon"]), float(p["height_m"]), float(p["pitch_deg"]),
                    float(p["heading_deg"]))

    def time_of(self, image_id: int) -> float:
        """UNIX seconds of an image (its true pose's time, else its date_time)."""
        p = self._poses[image_id]
        return float(p["t"]) if "t" in p else parse_datetime(str(self.images[image_id]["date_time"]))

    def objects_at(self, group: int, frame_index: int) -> tuple[SceneObject, ...]:
        """The objects of a group's world at one time step (known or continued positions; see the module doc)."""
        out = []
        continue_frames = CONTINUE_S * self.fps
        half = max(1.0, _YAW_WINDOW_S * self.fps / 2.0)
        for tid, table in sorted(self._tracks.get(group, {}).items()):
            frames = table[:, 0]
            lo, hi = frames[0], frames[-1]
            if not lo - continue_frames <= frame_index <= hi + continue_frames:
                continue
            k = int(np.searchsorted(frames, frame_index))
            known = k < len(frames) and frames[k] == frame_index
            if known:
                east, north = float(table[k, 1]), float(table[k, 2])
            else:
                east, north, ok = _continued(table, frame_index, continue_frames, half)
                if not ok:
                    continue
            # people face where they walk; swimmers drift with the current facing any way (fixed per swimmer)
            yaw = _yaw_from_motion(table, frame_index, half, tid) if self.cls == "person" else _rest_yaw(tid)
            out.append(SceneObject(tid, self.cls, east, north, yaw, bool(known)))
        return tuple(out)

    def frames(self, video: SceneVideo) -> Iterator[SceneFrame]:
        """The frames of one video in frame order."""
        rates = self._heading_rates(video)
        for image_id, rate in zip(video.image_ids, rates, strict=True):
            im = self.images[image_id]
            p = self._poses[image_id]
            yield SceneFrame(image_id=image_id, video_id=video.id, frame_index=int(im["frame_index"]),
                             file_name=str(im.get("file_name") or ""), t=self.time_of(image_id),
                             pose=self.pose(image_id),
                             blurred=bool(p.get("blurred", False)), heading_rate_deg_s=float(rate),
                             meta=im.get("meta"), objects=self.objects_at(video.group, int(im["frame_index"])))

    def _heading_rates(self, video: SceneVideo) -> np.ndarray:
        """(F,) gimbal yaw rate (deg/s) per frame from the true headings (central differences)."""
        heads = np.array([float(self._poses[i]["heading_deg"]) for i in video.image_ids])
        if len(heads) < 2:
            return np.zeros(len(heads))
        unwrapped = np.degrees(np.unwrap(np.radians(heads)))
        return np.gradient(unwrapped) * self.fps


def _continued(table: np.ndarray, frame_index: int, continue_frames: float,
               half: float) -> tuple[float, float, bool]:
    """Position at an unknown frame: linear between the bracketing sightings when they are at most
    2 * `continue_frames` apart, else extrapolated from the nearer sighting (within `continue_frames`) with
    its recent velocity; ok False beyond."""
    frames = table[:, 0]
    k = int(np.searchsorted(frames, frame_index))
    before = k - 1 if k > 0 else None
    after = k if k < len(frames) else None
    if before is not None and after is not None:
        f0, f1 = frames[before], frames[after]
        if f1 - f0 <= 2.0 * continue_frames:
            w = (frame_index - f0) / (f1 - f0)
            pos = (1.0 - w) * table[before, 1:] + w * table[after, 1:]
            return float(pos[0]), float(pos[1]), True
        j: int | None = before if frame_index - f0 <= f1 - frame_index else after
    else:
        j = before if before is not None else after
    assert j is not None
    if abs(frame_index - frames[j]) > continue_frames:
        return math.nan, math.nan, False
    vel = _velocity(table, j, half)
    pos = table[j, 1:] + vel * (frame_index - frames[j])
    return float(pos[0]), float(pos[1]), True


def _velocity(table: np.ndarray, j: int, half: float) -> np.ndarray:
    """(2,) metres per frame around sighting j, from the sightings within `2 * half` frames."""
    frames = table[:, 0]
    near = np.flatnonzero(np.abs(frames - frames[j]) <= 2.0 * half)
    if len(near) < 2:
        return np.zeros(2)
    a, b = near[0], near[-1]
    return (table[b, 1:] - table[a, 1:]) / (frames[b] - frames[a])


def _yaw_from_motion(table: np.ndarray, frame_index: int, half: float, track_id: int) -> float:
    """Direction of motion around frame_index (deg from north); a fixed per-track heading while resting."""
    frames = table[:, 0]
    lo = int(np.searchsorted(frames, frame_index - half))
    hi = int(np.searchsorted(frames, frame_index + half, side="right")) - 1
    for _ in range(4):  # widen the window a few times for slow objects
        if 0 <= lo < hi < len(frames):
            d = table[hi, 1:] - table[lo, 1:]
            if float(np.hypot(d[0], d[1])) >= _YAW_MIN_MOVE_M:
                return float(math.degrees(math.atan2(d[0], d[1])) % 360.0)
        lo, hi = max(lo - int(half), 0), min(hi + int(half), len(frames) - 1)
    return _rest_yaw(track_id)


def _rest_yaw(track_id: int) -> float:
    """A fixed heading per object, spread by the golden angle (objects at rest face different ways)."""
    return float((track_id * 137.508) % 360.0)
