"""The agent over real Zenoh sessions on loopback: the test plays the fusion server with a plain router
session (subscribes to what the agent publishes, publishes/answers joint tiles and tracks).

Covers: published tiles/state/tracks decode with the shared codecs and include empty tiles; liveliness;
joint tiles boost an object the agent never saw (through the real pipeline); a late joiner gets the
joint map from the queryable before its first frame; tiles flow again after the server restarts;
global id adoption; malformed joint messages are counted, never fatal.
"""

from __future__ import annotations

import json
import math
import threading
import time
from collections import Counter, defaultdict
from collections.abc import Callable, Iterator

import msgpack
import numpy as np
import pytest
import zenoh

from agent.node import AgentNode, AgentSettings, state_message
from agent.pipeline_config import PipelineConfig
from agent.sources import SourceFrame
from agent.zenoh_config import ZenohOptions
from shared.geo import Camera, Pose, pixel_to_latlon
from shared.keys import KeySpace
from shared.messages import (
    JointTrackItem,
    JointTracksMessage,
    decode_state,
    decode_tracks,
    encode_joint_tracks,
    encode_state,
)
from shared.tilecodec import TileMessage, decode_tile, encode_tile
from shared.tiles import TileGrid
from sim.source import SimSource
from tests.netutil import wait_until

KEYS = KeySpace()
GRID = TileGrid()
LAT, LON = 48.53, 9.06
CAMERA = Camera(width=1920, height=1080, fx=1500.0, fy=1500.0, cx=960.0, cy=540.0)
POSE = Pose(lat=LAT, lon=LON, height_m=30.0, pitch_deg=90.0, heading_deg=0.0)
#: Two plausible person boxes (0.6 x 1.2 m at 30 m): A below the UAV, B 8.8 m east of it.
BOX_A = (945.0, 510.0, 975.0, 570.0)
BOX_B = (1385.0, 510.0, 1415.0, 570.0)
T0 = 1.7e9


# ---- helpers (also used by tests/e2e/test_agent_*.py) --------------------------------------------
def router_config(port: int, *, shared_memory: bool = True) -> zenoh.Config:
    """The test's fusion-server side: a router session listening on loopback."""
    conf = zenoh.Config()
    conf.insert_json5("mode", '"router"')
    conf.insert_json5("listen/endpoints", json.dumps([f"tcp/127.0.0.1:{port}"]))
    conf.insert_json5("scouting/multicast/enabled", "false")
    if not shared_memory:
        conf.insert_json5("transport/shared_memory/enabled", "false")
    return conf


class FakeServer:
    """A router session that records what the agents publish and publishes joint data."""

    def __init__(self, port: int, *, shared_memory: bool = True) -> None:
        self.session = zenoh.open(router_config(port, shared_memory=shared_memory))
        self.samples: dict[str, list[tuple[str, bytes]]] = defaultdict(list)
        self.lock = threading.Lock()
        self.subscriber = self.session.declare_subscriber(KEYS.uav_all(), self._on_sample)

    def _on_sample(self, sample: zenoh.Sample) -> None:
        key = str(sample.key_expr)
        kind = KEYS.parse(key).kind
        with self.lock:
            self.samples[kind].append((key, sample.payload.to_bytes()))

    def count(self, kind: str) -> int:
        with self.lock:
            return len(self.samples[kind])

    def latest(self, kind: str) -> list[tuple[str, bytes]]:
        with self.lock:
            return list(self.samples[kind])

    def put(self, key: str, payload: bytes) -> None:
        self.session.put(key, payload, congestion_control=zenoh.CongestionControl.BLOCK)

    def alive(self) -> list[str]:
        return [str(r.ok.key_expr) for r in self.session.liveliness().get(KEYS.uav_alive("*"), timeout=2.0)
                if r.ok is not None]

    def close(self) -> None:
        if not self.session.is_closed():
            self.session.close()


def agent_settings(port: int, uav: str = "uav1", mode: str | None = None, **kwargs) -> AgentSettings:
    options = ZenohOptions(mode=mode, connect=(f"tcp/127.0.0.1:{port}",), multicast_scouting=False)
    return AgentSettings(uav_id=uav, zenoh=options, open_timeout_s=20.0, **kwargs)


class RunningAgent:
    """An AgentNode running in a thread until the source ends or the test leaves the block."""

    def __init__(self, node: AgentNode) -> None:
        self.node = node
        self.stop = threading.Event()
        self.summary: dict | None = None
        self.error: BaseException | None = None
        self.thread = threading.Thread(target=self._run, daemon=True)

    def _run(self) -> None:
        try:
            self.summary = self.node.run(self.stop)
        except BaseException as exc:  # surfaced by the test
            self.error = exc

    def __enter__(self) -> RunningAgent:
        self.thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop.set()
        self.thread.join(timeout=20.0)
        assert not self.thread.is_alive(), "the agent did not stop within 20 s"
        if self.error is not None:
            raise self.error

    def join(self, timeout_s: float) -> dict:
        self.thread.join(timeout=timeout_s)
        assert not self.thread.is_alive(), f"the agent did not finish within {timeout_s} s"
        if self.error is not None:
            raise self.error
        assert self.summary is not None
        return self.summary


class ScriptedSource:
    """A hovering UAV (POSE) whose candidates per frame come from ``candidates(i)``; ``hold`` maps a
    frame index to an Event the source waits for (bounded) before yielding that frame."""

    name = "scripted"

    def __init__(self, n_frames: int, candidates: Callable[[int], list[tuple[tuple, float]]],
                 hold: dict[int, threading.Event] | None = None) -> None:
        self.n_frames = n_frames
        self.candidates = candidates
        self.hold = hold or {}
        self.camera = CAMERA
        self.class_names = {1: "person", 2: "swimmer"}

    def frames(self) -> Iterator[SourceFrame]:
        for i in range(self.n_frames):
            if i in self.hold:
                assert self.hold[i].wait(20.0), f"frame {i} was never released"
            boxes = self.candidates(i)
            xyxy = np.array([b for b, _ in boxes], np.float32).reshape(-1, 4)
            scores = np.array([s for _, s in boxes], np.float32)
            t = T0 + i / 30.0
            yield SourceFrame(i, t, POSE, t, xyxy, scores, np.ones(len(boxes), np.int64), CAMERA)

    def close(self) -> None:
        pass


def box_ground(box: tuple) -> tuple[float, float]:
    """Ground point (lat, lon) of a box's centre seen from POSE (the nadir anchor is the centre)."""
    uv = np.array([[(box[0] + box[2]) / 2, (box[1] + box[3]) / 2]])
    lat, lon, valid = pixel_to_latlon(uv, CAMERA, POSE)
    assert valid[0]
    return float(lat[0]), float(lon[0])


def boosted(c: float, p: float, scale: float | None = None) -> float:
    """The default pipeline's boost of confidence c by map evidence p (see agent.pipeline); scale: the
    log-odds scale (default the boost's own; joint detections score with PipelineConfig.joint_scale)."""
    cfg = PipelineConfig()
    if cfg.boost_mode == "add":
        return c + cfg.boost_weight * p
    scale = cfg.logodds_scale if scale is None else scale
    return 1.0 / (1.0 + math.exp(-(math.log(c / (1 - c)) + cfg.boost_weight * scale * p)))


def joint_tile_with_blob(lat: float, lon: float, value: float = 0.8, cls: str = "person",
                         seq: int = 1) -> tuple[str, bytes]:
    """A joint tile message (key, payload) holding a Gaussian bump of peak ``value`` at (lat, lon)."""
    gx, gy = GRID.latlon_to_cell_index(lat, lon)
    x, y = int(gx) // GRID.n, int(gy) // GRID.n
    row, col = int(gy) - y * GRID.n, int(gx) - x * GRID.n
    r = np.arange(GRID.n)[:, None] - row
    c = np.arange(GRID.n)[None, :] - col
    values = (value * np.exp(-0.5 * (r**2 + c**2) / 4.0**2)).astype(np.float32)
    values[values < 0.05] = 0.0
    msg = TileMessage(uav="joint", cls=cls, z=GRID.z, x=x, y=y, n=GRID.n, t=time.time(), seq=seq, values=values)
    return KEYS.joint_tile(cls, GRID.z, x, y), encode_tile(msg)


def scores_of(result, box: tuple) -> list[float]:
    return [float(s) for b, s in zip(result.boxes_xyxy, result.scores, strict=True) if np.allclose(b, box)]


# ---- what the agent publishes ------------------------------------------------------------------
def test_agent_publishes_tiles_state_tracks_and_a_liveliness_token(server, server_port):
    source = SimSource("coop", seed=0, uav_index=1, frames=900)
    node = AgentNode(agent_settings(server_port, "uav2", speed=2.0), source)
    with RunningAgent(node):
        wait_until(lambda: server.count("uav_tile") >= 16 and server.count("uav_state") >= 3, 20.0)
        assert server.alive() == [KEYS.uav_alive("uav2")]
        # tracks need a few frames to confirm
        wait_until(lambda: any(decode_tracks(p).tracks for _, p in server.latest("uav_tracks")), 20.0)
    tiles = [(key, decode_tile(p)) for key, p in server.latest("uav_tile")]
    for key, msg in tiles:
        assert KEYS.parse(key) == KEYS.parse(KEYS.uav_tile("uav2", msg.cls, msg.z, msg.x, msg.y))
        assert (msg.uav, msg.z, msg.n) == ("uav2", 18, 256)
    people = [m for _, m in tiles if m.cls == "person"]
    assert any(m.values.max() > 0 for m in people), "tiles with evidence"
    assert any(m.values.max() == 0 for m in people), "empty tiles it covers"
    assert any(m.cls == "swimmer" for _, m in tiles)  # a class it never saw: covered, nothing seen
    seqs = defaultdict(list)
    for _, m in tiles:
        seqs[(m.cls, m.x, m.y)].append(m.seq)
    assert all(s == sorted(s) and len(set(s)) == len(s) for s in seqs.values())
    states = [decode_state(p) for _, p in server.latest("uav_state")]
    assert all(s.uav == "uav2" and len(s.footprint) == 32 and s.camera.width == 3840 for s in states)
    first = next(iter(source.frames())).pose
    assert abs(states[0].lat - first.lat) < 1e-3 and abs(states[0].lon - first.lon) < 1e-3
    tracks = [decode_tracks(p) for _, p in server.latest("uav_tracks")]
    assert all(t.uav == "uav2" for t in tracks)
    items = [i for t in tracks for i in t.tracks]
    assert all(i.cls == "person" and 0 <= i.score <= 1 for i in items)
    assert abs(np.median([i.lat for i in items]) - 48.5312) < 5e-4  # the coop scene
    assert node.summary()["link"]["rejected"] == {}


def test_agent_learns_the_other_uavs_footprints_from_their_state_messages(server, server_port):
    last_t = []
    node = AgentNode(agent_settings(server_port, "uav1", speed=1.0), ScriptedSource(10**6, lambda i: []),
                     on_frame=lambda frame, result, tracks: last_t.append(frame.t))
    other = Pose(lat=LAT, lon=LON + 0.0003, height_m=30.0, pitch_deg=90.0, heading_deg=0.0)  # ~22 m east
    state = state_message("uav2", time.time(), other, CAMERA, range_m=200.0)
    with RunningAgent(node):
        wait_until(lambda: node.counts["frames"] > 3, 20.0)
        server.put(KEYS.uav_state("uav2"), msgpack.packb({**msgpack.unpackb(encode_state(state)), "uav": "uav3"}))
        server.put(KEYS.uav_state("uav2"), b"\xc1junk")
        server.put(KEYS.uav_state("uav2"), encode_state(state))
        wait_until(lambda: node.counts["footprints_applied"] >= 1, 10.0)
    gx, gy = GRID.latlon_to_cell_index(np.array([LAT, LAT]), np.array([LON + 0.0003, LON - 0.0003]))
    cover = node.joint.others_cover(int(gx[1]), int(gy[0]), int(gx[0] - gx[1]) + 1, 1, last_t[-1])
    assert cover is not None and cover[0, -1] == 1 and cover[0, 0] == 0  # under uav2, 44 m west of it
    rejected = node.summary()["link"]["rejected"]
    assert rejected == {"uav_mismatch": 1, "not_msgpack": 1}  # and its own state is not taken for another's
    assert node.summary()["link"]["counts"]["states"] == 1


# ---- the joint map boosts ----------------------------------------------------------------------
def test_joint_tiles_boost_an_object_the_agent_never_saw(server, server_port):
    release = threading.Event()
    last = 15

    def candidates(i: int):
        # nothing until the last frame, then a weak A (where the joint map has evidence) and a weak B
        return [(BOX_A, 0.2), (BOX_B, 0.2)] if i == last else []

    results = {}
    source = ScriptedSource(last + 1, candidates, hold={last: release})
    # boosting alone (the joint detections would promote A further: see the late joiner's test)
    node = AgentNode(agent_settings(server_port, speed=0.0), source, PipelineConfig(joint_detections=False),
                     on_frame=lambda frame, result, tracks: results.__setitem__(frame.index, result))
    with RunningAgent(node) as agent:
        wait_until(lambda: len(results) == last, 20.0)  # the window is placed, the map is empty
        key, payload = joint_tile_with_blob(*box_ground(BOX_A), value=0.8)
        server.put(key, payload)
        wait_until(lambda: node.link.stats()["counts"].get("joint_tiles", 0) >= 1)
        release.set()
        summary = agent.join(20.0)
    assert summary["joint_tiles_applied"] == 1
    assert scores_of(results[last], BOX_A) == [pytest.approx(boosted(0.2, 0.8), abs=0.01)]  # c boosted by p_joint
    assert scores_of(results[last], BOX_B) == [pytest.approx(0.2, abs=1e-6)]  # no evidence there


def test_joint_mode_local_ignores_the_joint_map(server, server_port):
    release = threading.Event()
    results = {}
    source = ScriptedSource(3, lambda i: [(BOX_A, 0.2)] if i == 2 else [], hold={2: release})
    node = AgentNode(agent_settings(server_port, speed=0.0), source, PipelineConfig(joint_mode="local"),
                     on_frame=lambda frame, result, tracks: results.__setitem__(frame.index, result))
    with RunningAgent(node) as agent:
        wait_until(lambda: len(results) == 2, 20.0)
        server.put(*joint_tile_with_blob(*box_ground(BOX_A)))
        wait_until(lambda: node.link.stats()["counts"].get("joint_tiles", 0) >= 1)
        release.set()
        agent.join(20.0)
    assert scores_of(results[2], BOX_A) == [pytest.approx(0.2, abs=1e-6)]


def test_late_joiner_gets_the_joint_map_before_its_first_frame(server, server_port):
    key, payload = joint_tile_with_blob(*box_ground(BOX_A), value=0.6)
    tracks = JointTracksMessage(t=0.0, tracks=(JointTrackItem(7, "person", *box_ground(BOX_A), 0.9, (0.0, 0.0),
                                                              (("uavX", 3),)),))

    def on_query(query: zenoh.Query) -> None:
        query.reply(key, payload)
        query.reply(KEYS.joint_tracks(), encode_joint_tracks(tracks))

    queryable = server.session.declare_queryable(KEYS.joint_all(), on_query)
    results = {}
    source = ScriptedSource(1, lambda i: [(BOX_A, 0.2)])  # the object is in the very first frame
    node = AgentNode(agent_settings(server_port, speed=0.0), source,
                     on_frame=lambda frame, result, tracks: results.__setitem__(frame.index, result))
    summary = RunningAgent(node).__enter__().join(20.0)
    queryable.undeclare()
    assert summary["joint_query_replies"] == 2
    # the weak box sits on the others' peak: boosted by the joint map, then promoted by the joint
    # detections to the score of the others' evidence (2 * 0.6 - own ~0, clipped to 1; docs/agent.md)
    prior, joint_scale = PipelineConfig().joint_prior_score, PipelineConfig().joint_scale
    assert scores_of(results[0], BOX_A) == [pytest.approx(boosted(prior, 1.0, joint_scale), abs=0.01)]
    assert results[0].from_joint is not None and results[0].from_joint.tolist() == [True]
    assert boosted(prior, 1.0, joint_scale) > boosted(0.2, 0.6)
    joint = node.link.joint_tracks()
    assert joint is not None and joint[0].tracks[0].gid == 7


def test_new_local_track_adopts_the_global_id_where_a_global_track_is(server, server_port):
    lat, lon = box_ground(BOX_A)
    joint = JointTracksMessage(t=0.0, tracks=(JointTrackItem(42, "person", lat + 2e-5, lon, 0.9, (0.0, 0.0),
                                                             (("uav1", 9),)),))
    release = threading.Event()
    source = ScriptedSource(90, lambda i: [(BOX_A, 0.9)], hold={0: release})
    node = AgentNode(agent_settings(server_port, "uav2", speed=1.0), source)
    stop_publishing = threading.Event()

    def publish_joint_tracks() -> None:  # the server's 5 Hz joint tracks
        while not stop_publishing.wait(0.2):
            server.put(KEYS.joint_tracks(), encode_joint_tracks(joint))

    publisher = threading.Thread(target=publish_joint_tracks, daemon=True)
    publisher.start()
    try:
        with RunningAgent(node) as agent:
            wait_until(lambda: node.link.joint_tracks() is not None)
            release.set()
            agent.join(20.0)
    finally:
        stop_publishing.set()
        publisher.join()
    raw = [msgpack.unpackb(p) for _, p in server.latest("uav_tracks")]
    reported = [t for m in raw for t in m["tracks"]]
    assert reported and all(t.get("gid") == 42 for t in reported)
    assert node.adopter.n_adopted_by_position == 1


# ---- resilience --------------------------------------------------------------------------------
@pytest.mark.parametrize("mode", ["peer", "client"])
def test_tiles_flow_again_after_the_server_goes_away_and_comes_back(server_port, mode):
    server = FakeServer(server_port)
    node = AgentNode(agent_settings(server_port, mode=mode, speed=1.0, loop=True),
                     SimSource("coop", seed=0, uav_index=0, frames=300))
    try:
        with RunningAgent(node):
            wait_until(lambda: server.count("uav_tile") > 0 and server.count("uav_state") > 0, 20.0)
            server.close()
            time.sleep(1.5)  # the agent keeps running without its server
            server = FakeServer(server_port)  # same port, new session
            wait_until(lambda: server.count("uav_state") > 2 and server.count("uav_tile") > 0, 20.0)
            assert server.alive() == [KEYS.uav_alive("uav1")]
            # the agent queried the joint map again when the server came back
            wait_until(lambda: node.link.stats()["counts"].get("reconnects", 0) >= 1, 10.0)
    finally:
        server.close()


def test_malformed_joint_messages_are_counted_and_never_fatal(server, server_port):
    lat, lon = box_ground(BOX_A)
    # every joint key, so that off-window ones (another grid, a bad key) reach the validation too
    node = AgentNode(agent_settings(server_port, speed=1.0, loop=True, joint_window=False),
                     SimSource("coop", frames=300))
    good_key, good = joint_tile_with_blob(lat, lon)
    x, y = (int(v) for v in GRID.tile_of(lat, lon))
    base = msgpack.unpackb(good)
    bad = {
        "not msgpack": (good_key, b"\xc1garbage"),
        "wrong version": (good_key, msgpack.packb({**base, "v": 2})),
        "uav not joint": (good_key, msgpack.packb({**base, "uav": "uav9"})),
        "tile of another key": (KEYS.joint_tile("person", 18, x + 1, y), good),
        "another grid": (KEYS.joint_tile("person", 17, x // 2, y // 2),
                         msgpack.packb({**base, "z": 17, "x": x // 2, "y": y // 2})),
        "idx and val disagree": (good_key, msgpack.packb({**base, "idx": b"\x01\x00", "val": b"\x01\x02"})),
        "bad key": (f"{KEYS.prefix}/joint/tiles/person/18/{x}", good),
        "huge": (good_key, b"\x00" * (300 * 1024)),
        "tracks not a map": (KEYS.joint_tracks(), msgpack.packb([1, 2, 3])),
        "tracks NaN": (KEYS.joint_tracks(), msgpack.packb({"v": 1, "uav": "joint", "t": float("nan"), "tracks": []})),
    }
    with RunningAgent(node):
        wait_until(lambda: node.counts["frames"] > 5, 20.0)
        for key, payload in bad.values():
            server.put(key, payload)
        server.session.delete(good_key)
        server.put(good_key, good)
        wait_until(lambda: node.link.stats()["counts"].get("joint_tiles", 0) >= 1)
        rejected = wait_until(lambda: (r := node.link.stats()["rejected"]) and sum(r.values()) >= len(bad) + 1 and r)
        frames = node.counts["frames"]
        wait_until(lambda: node.counts["frames"] > frames + 10)  # still running
    assert rejected == {"not_msgpack": 1, "bad_version": 1, "uav_mismatch": 1, "tile_mismatch": 1, "wrong_grid": 1,
                        "bad_length": 1, "bad_key": 1, "too_large": 1, "not_a_map": 1, "non_finite": 1,
                        "unexpected_delete": 1}


def test_the_last_frame_is_published_before_the_agent_exits(server, server_port):
    source = ScriptedSource(20, lambda i: [(BOX_A, 0.9)])
    summary = RunningAgent(AgentNode(agent_settings(server_port, speed=0.0), source)).__enter__().join(20.0)
    last_t = T0 + 19 / 30.0
    wait_until(lambda: server.count("uav_tracks") == summary["link"]["counts"]["sent_tracks"])
    assert decode_tracks(server.latest("uav_tracks")[-1][1]).t == pytest.approx(last_t)
    assert decode_state(server.latest("uav_state")[-1][1]).t == pytest.approx(last_t)
    assert server.count("uav_tile") == summary["link"]["counts"]["sent_tile"]


def test_a_frame_that_fails_is_counted_and_the_agent_goes_on(server, server_port):
    class BrokenFrameSource(ScriptedSource):
        def frames(self):
            for frame in super().frames():
                if frame.index == 3:  # a class id the detector never declared: the pipeline refuses it
                    frame = SourceFrame(frame.index, frame.t, frame.pose, frame.pose_t, frame.boxes_xyxy,
                                        frame.scores, np.full(len(frame.scores), 99, np.int64), frame.camera)
                yield frame

    results = {}
    node = AgentNode(agent_settings(server_port, speed=0.0), BrokenFrameSource(10, lambda i: [(BOX_A, 0.9)]),
                     on_frame=lambda frame, result, tracks: results.__setitem__(frame.index, result))
    summary = RunningAgent(node).__enter__().join(20.0)
    assert summary["frame_errors"] == 1 and summary["frames"] == 9
    assert sorted(results) == [0, 1, 2, 4, 5, 6, 7, 8, 9]


@pytest.fixture(scope="module")
def recording(tmp_path_factory):
    """A 600-frame `sea` dataset: reading its telemetry stages takes the agent most of a second."""
    from sim.dataset import write_dataset

    out = tmp_path_factory.mktemp("recording") / "data"
    write_dataset("sea", out, seed=2, frames=600, progress=False)
    return out


@pytest.mark.parametrize("how", ["stop", "duration"])
def test_a_stop_or_the_duration_holds_while_the_agent_reads_a_recording(server_port, recording, tmp_path, how):
    """Review finding: the recording's stages ran inside the frame loop, after the agent was up on Zenoh, deaf to
    SIGTERM and --duration (a 9,000-frame recording: --duration 2 exited after 6.5 s, SIGTERM took 5.5 s). They now
    run before the agent connects, in a thread the stop and the duration end; the outputs are written, empty."""
    from agent.dataset_source import DatasetSource

    stop = threading.Event()
    if how == "stop":
        stop.set()
    out = tmp_path / "tracks.geojson"
    node = AgentNode(agent_settings(server_port, duration_s=0.01 if how == "duration" else None, tracks_out=out,
                                    detections_out=tmp_path / "detections.json"),
                     DatasetSource(recording, video_id=1, use_images=False))
    summary = node.run(stop)
    assert summary["frames"] == 0 and summary["publish_cycles"] == 0
    assert "time zone" not in summary["stages"] and "view cuts" not in summary["stages"]  # the reading did not end
    assert json.loads(out.read_text())["features"] == []
    assert json.loads((tmp_path / "detections.json").read_text()) == []


def test_the_agent_numbers_a_datasets_frames_and_video_as_uavmm_track_does(server, server_port, recording, tmp_path):
    """Review finding: `--tracks-out` numbered frames from 0 in playing order and wrote video_id 0, where `uavmm
    track` writes the dataset's frame_index and video id (the same on simulated data, not on a real file)."""
    from agent.dataset import Candidates, Dataset
    from agent.dataset_source import DatasetSource
    from agent.tracking_io import geojson_tracks, track_video

    coco = json.loads((recording / "images.json").read_text())
    for im in coco["images"]:  # frame numbers as a real file has them: every 15th frame of a longer video
        im["frame_index"] = 1000 + 15 * im["frame_index"]
    data = tmp_path / "renumbered"
    data.mkdir()
    (data / "images.json").write_text(json.dumps(coco))
    for name in ("pre_nms.json", "camera.json"):
        (data / name).write_bytes((recording / name).read_bytes())
    out = tmp_path / "tracks.geojson"
    node = AgentNode(agent_settings(server_port, tracks_out=out, speed=0.0), DatasetSource(data, video_id=2,
                                                                                            use_images=False))
    node.run()
    agent = json.loads(out.read_text())["features"]
    dataset = Dataset.load(data / "images.json")
    rows = track_video(dataset, Candidates.load(data / "pre_nms.json", dataset), Camera.from_file(data / "camera.json"),
                       2, PipelineConfig())
    track = geojson_tracks({2: rows}, dataset.categories)["features"]
    assert agent and {f["properties"]["video_id"] for f in agent} == {2}
    assert sorted(f["properties"]["frames"] for f in agent) == sorted(f["properties"]["frames"] for f in track)
    assert min(min(f["properties"]["frames"]) for f in agent) >= 1000


def test_the_agent_says_why_frames_of_a_dataset_had_no_pose(server, server_port, recording):
    """The agent counted frames without a pose but never said why (`uavmm track` gives the reasons)."""
    from agent.dataset_source import DatasetSource

    for stamped in (False, True):
        summary = AgentNode(agent_settings(server_port, speed=0.0),
                            DatasetSource(recording, video_id=1, use_images=False,
                                          telemetry_as_stamped=stamped)).run()
        reasons = summary["frames_without_pose_by_reason"]
        assert summary["frames_without_pose"] > 0 and sum(reasons.values()) == summary["frames_without_pose"]
        assert all(isinstance(k, str) and k for k in reasons)


def test_a_looped_recording_writes_each_frame_once(server, server_port, recording, tmp_path, caplog):
    """The contract audit (1 Dec 2026): with --loop, every pass wrote its detections under the same image ids (573
    frames, 20 distinct ids), which a COCO scorer takes as one image each; the MOT rows repeated too."""
    from agent.dataset_source import DatasetSource

    coco = json.loads((recording / "images.json").read_text())
    coco["images"] = [im for im in coco["images"] if im["video_id"] == 1 and im["frame_index"] < 40]
    images = {im["id"] for im in coco["images"]}
    short = tmp_path / "short"
    short.mkdir()
    (short / "images.json").write_text(json.dumps(coco))
    (short / "camera.json").write_bytes((recording / "camera.json").read_bytes())
    candidates = json.loads((recording / "pre_nms.json").read_text())
    (short / "pre_nms.json").write_text(json.dumps([c for c in candidates if c["image_id"] in images]))
    dets, tracks = tmp_path / "detections.json", tmp_path / "tracks.geojson"
    node = AgentNode(agent_settings(server_port, speed=0.0, loop=True, duration_s=4.0, detections_out=dets,
                                    tracks_out=tracks), DatasetSource(short, video_id=1, use_images=False))
    with caplog.at_level("WARNING"):
        summary = node.run()
    written = json.loads(dets.read_text())
    assert summary["frames"] > len(images) and summary["frames_not_written"] == summary["frames"] - len(images)
    assert {d["image_id"] for d in written} <= images
    per_image = Counter(d["image_id"] for d in written)
    assert summary["frames"] >= 2 * len(images)  # looped at least once
    assert max(per_image.values()) < 300  # one pass's detections, not every pass's
    assert caplog.text.count("came again") == 1
    for feature in json.loads(tracks.read_text())["features"]:
        frames = feature["properties"]["frames"]
        assert len(frames) == len(set(frames))
