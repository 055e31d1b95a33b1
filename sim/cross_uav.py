"""Cross-UAV identities: does the fusion server give one object one global id over all the UAVs that track it?

Each UAV's tracker numbers its own tracks; the fusion server (`fusion_server.global_tracks.GlobalTracker`, with
`uavmm fusion`'s defaults) joins them into global tracks from the tracks messages the agents publish (5 Hz).
`CrossUavRecorder` is that server on the frame clock of an in-process cooperative run (`sim.coop_eval.run_coop`'s
`on_tracks`): it takes each UAV's tracks message, feeds the tracker at the agents' publish rate and records which
global id each local track has in each frame.

`cross_uav_metrics` scores the identities over all UAVs at once, the way multi-camera tracking is scored
(MTMC: every camera's frames in one sequence, one identity per object over all of them): the UAVs' sequences are
laid end to end, ground-truth ids are the simulator's world object ids (one per object over all UAVs), and
TrackEval's HOTA, IDF1 and ID switches are computed (a) with each local track carrying its global id and (b) with
the local ids kept apart per UAV, the figure of UAVs that do not share their tracks. An object two UAVs see under
one global id counts as one identity; under two (or under each UAV's local id) it loses the frames of all but one.
`same_id` is the plain share: of the objects more than one UAV tracks, those whose most frequent id is the same
in every UAV that tracks them. Each figure also comes for the first-look association (a second tracker on the
same messages without re-association, `fusion_server.reassociation`): `*_first_look`.

A local track's frames before its first global id (until the agent's first tracks message with it reaches the
server, at most one publish period) carry that first id: the figure measures the association, not the latency.
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Callable
from typing import Any

import numpy as np

from fusion_server.config import FusionSettings
from fusion_server.global_tracks import GlobalTracker
from shared.messages import TracksMessage
from sim.track_eval import (
    SequenceTracks,
    SequenceTruth,
    frame_matches,
    mot_metrics,
    trackeval_data,
)

__all__ = ["CROSS_METRICS", "CrossUavRecorder", "cross_uav_metrics", "frame_clock_tracker"]

PUBLISH_PERIOD_S = 0.2  # the agent's default 5 Hz
#: The figures of `cross_uav_metrics`, in report order.
CROSS_METRICS = ("IDF1", "IDF1_first_look", "IDF1_separate", "HOTA", "HOTA_first_look", "HOTA_separate", "AssA",
                 "AssA_first_look", "AssA_separate", "IDs", "IDs_first_look", "IDs_separate", "shared_objects",
                 "same_id", "same_id_first_look")
#: Local ids of different UAVs kept apart: video index x this + local id (local ids of a sequence stay below it).
_ID_SPAN = 1 << 32


def frame_clock_tracker(clock: Callable[[], float], settings: FusionSettings | None = None, *,
                        reassociate_m: float | None = None) -> GlobalTracker:
    """The fusion server's global tracker with its settings' tracker options (default `uavmm fusion`'s) on an
    in-process run's frame clock (`clock`, also its wall clock); reassociate_m: None for the settings' own."""
    s = settings or FusionSettings(db_path=None)
    return GlobalTracker(gate_m=s.track_gate_m, hold_s=s.track_hold_s, member_ttl_s=s.ttl_s,
                         history_len=s.track_history_len, history_interval_s=s.track_history_interval_s,
                         reassociate_m=s.track_reassociate_m if reassociate_m is None else reassociate_m,
                         keep_changes=False, clock=clock, wall=clock)


class CrossUavRecorder:
    """The fusion server's global tracker fed with every UAV's tracks messages on the frame clock.

    settings: the fusion server's settings whose tracker options apply (default `uavmm fusion`'s); period_s: the
    agents' publish period. Call it with (video id, frame index, tracks message) in time order; `gids` then holds,
    per video id and frame index, local id -> global id of the tracks that had one in that frame, and
    `first_look_gids` the same from a second tracker fed the same messages without re-association (the first
    association kept for good, `--track-reassociate-m 0`): the baseline of the same run.
    """

    def __init__(self, settings: FusionSettings | None = None, *, period_s: float = PUBLISH_PERIOD_S) -> None:
        s = settings or FusionSettings(db_path=None)
        self.now = float("-inf")
        self.period_s = period_s
        self.tracker, self.first_look = (frame_clock_tracker(lambda: self.now, s, reassociate_m=reassociate_m)
                                         for reassociate_m in (s.track_reassociate_m, 0.0))
        self.gids: dict[int, dict[int, dict[int, int]]] = {}
        self.first_look_gids: dict[int, dict[int, dict[int, int]]] = {}
        self._next: dict[int, float] = {}

    def __call__(self, video_id: int, frame_index: int, msg: TracksMessage) -> None:
        self.now = max(self.now, msg.t)
        due = msg.t >= self._next.get(video_id, float("-inf"))
        if due:
            self._next[video_id] = msg.t + self.period_s
        for tracker, gids in ((self.tracker, self.gids), (self.first_look, self.first_look_gids)):
            if due:
                tracker.expire(self.now)
                tracker.update(msg, self.now)
            frame = {}
            for item in msg.tracks:
                gid = tracker.gid_of(msg.uav, item.id)
                if gid is not None:
                    frame[item.id] = gid
            gids.setdefault(video_id, {})[frame_index] = frame


def _relabelled(seq: SequenceTracks, index: int, gids: dict[int, dict[int, int]] | None) -> SequenceTracks:
    """seq with each track's id replaced by its global id in that frame (else the first it gets later, else its
    local id kept apart per video); gids None: every local id kept apart (no sharing). Global ids are >= 1,
    local ones negative. A global id a frame gives two tracks goes to the first; the other keeps its local id."""
    first_later: dict[int, int] = {}
    if gids is not None:
        for f in sorted(gids, reverse=True):  # a frame's ids -> the first global id each gets from then on
            first_later.update(gids[f])
    out = SequenceTracks(seconds=seq.seconds, reidentified=seq.reidentified, latlon=dict(seq.latlon))
    seen: dict[int, int] = {}  # local id -> the global id it had last (a frame without one carries it on)
    for f in sorted(seq.frames):
        ids, boxes, scores = seq.frames[f]
        frame = gids.get(f, {}) if gids is not None else {}
        new = np.empty(len(ids), dtype=np.int64)
        used: set[int] = set()
        for k, local in enumerate(ids.tolist()):
            gid = frame.get(local, seen.get(local, first_later.get(local))) if gids is not None else None
            if gid is not None:
                seen[local] = gid
            if gid in used:  # two of a UAV's tracks on one global id in a frame: one id a frame is one box
                gid = None
            new[k] = gid if gid is not None else -(index * _ID_SPAN + int(local) + 1)
            used.add(int(new[k]))
        out.frames[f] = (new, boxes, scores)
    return out


def _end_to_end(truths: list[SequenceTruth], seqs: list[SequenceTracks]) -> tuple[SequenceTruth, SequenceTracks]:
    """The sequences of several UAVs as one, each after the previous one's last frame."""
    frames: dict[int, tuple[np.ndarray, np.ndarray]] = {}
    tracks = SequenceTracks()
    offset = 0
    for truth, seq in zip(truths, seqs, strict=True):
        for f, gt in truth.frames.items():
            frames[offset + f] = gt
        for f, rows in seq.frames.items():
            if f in truth.frames:
                tracks.frames[offset + f] = rows
        offset += max(truth.frames, default=-1) + 1
    return SequenceTruth(frames, truths[0].fps if truths else 30.0), tracks


def _same_id(truths: list[SequenceTruth], seqs: list[SequenceTracks]) -> tuple[int, int]:
    """(objects more than one UAV tracks, those of them whose most frequent tracker id is the same in every UAV)."""
    dominant: dict[int, list[int]] = {}
    for truth, seq in zip(truths, seqs, strict=True):
        counts: dict[int, Counter[int]] = {}
        for matches in frame_matches(truth, seq).values():
            for gt, tr in matches.items():
                counts.setdefault(gt, Counter())[tr] += 1
        for gt, c in counts.items():
            dominant.setdefault(gt, []).append(c.most_common(1)[0][0])
    shared = [ids for ids in dominant.values() if len(ids) > 1]
    return len(shared), sum(len(set(ids)) == 1 for ids in shared)


def cross_uav_metrics(truths: dict[int, SequenceTruth], seqs: dict[int, SequenceTracks],
                      gids: dict[int, dict[int, dict[int, int]]],
                      first_look_gids: dict[int, dict[int, dict[int, int]]] | None = None) -> dict[str, Any]:
    """Identity figures over all UAVs (module doc): per video id its truth (hidden objects as ignore regions
    already dropped from seqs), its tracker output and `CrossUavRecorder.gids` (and `first_look_gids`).

    Returns HOTA, AssA, IDF1 (percent) and IDs with global ids, the same as `*_first_look` with the first-look
    global ids (NaN without them) and as `*_separate` with each UAV's ids kept apart, `shared_objects` (objects
    more than one UAV tracks) and `same_id` / `same_id_first_look` (percent of them with one id everywhere; NaN
    without shared objects).
    """
    videos = sorted(truths)
    t_list = [truths[v] for v in videos]
    out: dict[str, Any] = {}
    for suffix, given in (("", gids), ("_first_look", first_look_gids), ("_separate", None)):
        if suffix == "_first_look" and given is None:
            out.update({f"{m}_first_look": float("nan") for m in ("HOTA", "AssA", "IDF1", "IDs", "same_id")})
            continue
        relabelled = [_relabelled(seqs[v], i, given.get(v, {}) if given is not None else None)
                      for i, v in enumerate(videos)]
        truth, seq = _end_to_end(t_list, relabelled)
        m = mot_metrics([trackeval_data(truth, seq)])
        out.update({f"HOTA{suffix}": m["HOTA"], f"AssA{suffix}": m["AssA"], f"IDF1{suffix}": m["IDF1"],
                    f"IDs{suffix}": m["IDs"]})
        if given is not None:
            shared, same = _same_id(t_list, relabelled)
            out["shared_objects"] = shared
            out[f"same_id{suffix}"] = 100.0 * same / shared if shared else float("nan")
    return out
