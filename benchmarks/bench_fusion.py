"""Benchmark of the fusion server: how many UAVs one `uavmm fusion` process sustains, two shards against
one, and UAV bandwidth.

A real `uavmm fusion` subprocess is fed by a load-generator process (N simulated UAVs, each putting
9 tiles of 1 class at 5 Hz, values changing every cycle); this process subscribes to the joint tiles
and measures agent put -> joint tile received (benchmarks.fusion_load). A load is sustained when p99
<= 50 ms and >= 95 % of the expected joint tiles arrive. Baseline in the same run: the raw Zenoh put ->
receive rate of the same payloads. Then the same search behind a Zenoh router, for one process and
for two `--shard K/2` processes (benchmarks.fusion_shards).
Bandwidth: bytes per second one agent publishes with 20 objects in view (agent.memory_map tiles,
state and tracks at 5 Hz), against the 100 kB/s budget. Loopback, shared memory off.
"""

from __future__ import annotations

import gc
import logging
import multiprocessing as mp
import os
import tempfile
import time
from typing import Any

import numpy as np

from benchmarks.fusion_load import (
    BASE_X,
    BASE_Y,
    P99_BUDGET_S,
    P99_LIMITED_BUDGET_S,
    RATE_HZ,
    TILES_PER_UAV,
    JointLatency,
    blob_cells,
    blocks_of,
    free_port,
    latency_case,
    run_load,
    search,
    start_fusion,
    stop_process,
    zenoh_config,
)
from benchmarks.fusion_shards import run_sharded

DESCRIPTION = ("UAVs one fusion process holds at p99 put->joint <= 50 ms vs raw zenoh; two shards vs one; "
               "CPU/message; up/downlink per UAV")

log = logging.getLogger(__name__)


BYTES_BUDGET = 100_000.0


def _raw_zenoh_rate(ctx, duration_s: float) -> float:
    """Messages per second from a publisher process to a subscriber here, same payloads, BLOCK."""
    import zenoh

    port = free_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    count = [0]
    first: list[float] = []
    last = [0.0]

    def on_sample(_sample) -> None:
        now = time.perf_counter()
        if not first:
            first.append(now)
        count[0] += 1
        last[0] = now

    with zenoh.open(zenoh_config("peer", listen=endpoint)) as session:
        sub = session.declare_subscriber("bench/raw/**", on_sample)
        proc = ctx.Process(target=_raw_publisher, args=(endpoint, duration_s))
        proc.start()
        proc.join(timeout=duration_s + 60)
        time.sleep(0.2)
        sub.undeclare()
    if count[0] < 2:
        return 0.0
    return (count[0] - 1) / (last[0] - first[0])


def _raw_publisher(endpoint: str, duration_s: float) -> None:
    import zenoh

    from shared.tilecodec import encode_tile_sparse

    idx = blob_cells()
    payloads = [encode_tile_sparse("u", "person", 18, BASE_X, BASE_Y, 256, time.time(), k + 1, idx,
                                   (np.arange(idx.size) + k) % 225 + 30) for k in range(16)]
    with zenoh.open(zenoh_config("peer", connect=endpoint)) as session:
        pub = session.declare_publisher("bench/raw/tile", congestion_control=zenoh.CongestionControl.BLOCK)
        time.sleep(0.5)
        end = time.perf_counter() + duration_s
        k = 0
        while time.perf_counter() < end:
            pub.put(payloads[k & 15])
            k += 1
        time.sleep(0.3)


def _synthetic_map(objects: int, seconds: float, rng: np.random.Generator):
    """Yield (t, MemoryMap) at 30 fps with ``objects`` in view, ~10 candidate boxes each per frame."""
    from agent.memory_map import MemoryMap
    from shared.tiles import TileGrid

    grid = TileGrid()
    lat0, lon0 = 47.67, 9.27
    m_per_deg = 111_320.0
    obj_n = rng.uniform(-100, 100, objects)
    obj_e = rng.uniform(-100, 100, objects)
    mm = MemoryMap(grid=grid)
    fps = 30.0
    for f in range(int(seconds * fps)):
        mm.advance(f / fps, lat0, lon0)
        jitter_n = obj_n[:, None] + rng.normal(0, 0.5, (objects, 10))
        jitter_e = obj_e[:, None] + rng.normal(0, 0.5, (objects, 10))
        lat = lat0 + jitter_n / m_per_deg
        lon = lon0 + jitter_e / (m_per_deg * np.cos(np.radians(lat0)))
        gx, gy = grid.latlon_to_cell(lat.ravel(), lon.ravel())
        mm.add("person", gx, gy, rng.uniform(0.05, 0.6, gx.size))
        yield f / fps, mm


def uav_bytes_per_s(objects: int = 20, seconds: float = 4.0, fleet: int = 200) -> dict[str, float]:
    """Bytes/s one agent publishes and receives at 5 Hz with ``objects`` in view, at the agent's
    default settings (agent.tile_updates.TileChangeTracker with AgentSettings' min value, refresh
    and tile byte budget), over a synthetic memory map (agent.memory_map, 30 fps of ~10 candidate
    boxes per object); the first second (map filling up) is not counted. Uplink: its tiles, state
    and tracks. Downlink: the joint tiles of its window (the fusion server re-publishes a tile when
    its fused content changes: here, as often as this UAV's own tiles change), the joint tracks of
    its objects, and the other UAVs' state messages, for a fleet of 1 and of ``fleet`` UAVs laid out
    as the load above (one UAV per 4 x 4 tiles, objects within 100 m of each) and the agent's
    subscriptions: the joint tiles of its window (agent.joint_window; before it, every joint tile of
    the fleet), the joint tracks and the other UAVs' states of the regions its window touches (before:
    every global track and every state; the most any UAV of the layout receives).
    """
    from agent.node import AgentSettings
    from agent.tile_updates import TileChangeTracker
    from fusion_server.zenoh_node import REGION_TRACKS_HZ
    from shared.messages import (
        CameraInfo,
        JointTrackItem,
        JointTracksMessage,
        StateMessage,
        TrackItem,
        TracksMessage,
        encode_joint_tracks,
        encode_state,
        encode_tracks,
    )
    from shared.tiles import TileGrid

    defaults = AgentSettings(uav_id="u1")
    rng = np.random.default_rng(0)
    clock = [0.0]
    tracker = TileChangeTracker("uav-1", ["person"], TileGrid(), refresh_s=defaults.refresh_s,
                                min_value=defaults.tile_min_value,
                                budget_bytes_per_s=defaults.tile_budget_bytes_per_s, clock=lambda: clock[0])
    unlimited = TileChangeTracker("uav-1", ["person"], TileGrid(), refresh_s=defaults.refresh_s,
                                  min_value=defaults.tile_min_value, clock=lambda: clock[0])
    period_frames = int(round(30.0 / defaults.publish_hz))
    tile_bytes = raw_bytes = 0
    counted_s = seconds - 1.0
    for f, (t, mm) in enumerate(_synthetic_map(objects, seconds, rng)):
        clock[0] = t
        if f % period_frames:
            continue
        sent = sum(len(m[3]) for m in tracker.messages(mm, t))
        raw = sum(len(m[3]) for m in unlimited.messages(mm, t))
        if t >= 1.0:
            tile_bytes += sent
            raw_bytes += raw
    lat0, lon0 = 47.67, 9.27
    camera = CameraInfo(width=3840, height=2160, fx=2900.0, fy=2900.0, cx=1920.0, cy=1080.0)
    state = len(encode_state(StateMessage("uav-1", 1.0, lat0, lon0, 40.0, 45.0, 140.0,
                                          tuple((lat0 + i * 1e-4, lon0) for i in range(4)), camera)))
    tracks = len(encode_tracks(TracksMessage("uav-1", 1.0, tuple(
        TrackItem(i, "person", lat0 + i * 1e-4, lon0, 0.8, (0.1, 0.2)) for i in range(objects)))))

    def joint_tracks(n_tracks: int) -> int:
        return len(encode_joint_tracks(JointTracksMessage(1.0, tuple(
            JointTrackItem(i, "person", lat0 + i * 1e-6, lon0, 0.8, (0.1, 0.2), ((f"uav-{i // objects}", i),))
            for i in range(n_tracks)))))

    hz = defaults.publish_hz
    tiles_per_s = tile_bytes / counted_s
    up = tiles_per_s + (state + tracks) * hz
    down_1 = tiles_per_s + joint_tracks(objects) * hz  # alone: its joint tiles and its tracks
    n_tracks, n_states = _window_regions_load(fleet, objects)
    fleet_tracks = joint_tracks(n_tracks) * REGION_TRACKS_HZ
    all_tracks = joint_tracks(objects * fleet) * hz
    fleet_states = n_states * state * hz
    all_states = (fleet - 1) * state * hz
    return {"uplink": up, "uplink_unlimited": raw_bytes / counted_s + (state + tracks) * hz,
            "tiles": tiles_per_s, "state_tracks": (state + tracks) * hz,
            "downlink_alone": down_1, "downlink_fleet": tiles_per_s + fleet_tracks + fleet_states,
            "downlink_fleet_all_tiles": fleet * tiles_per_s + all_tracks + all_states,
            "fleet_tracks": fleet_tracks, "fleet_states": fleet_states, "fleet": fleet}


def _window_regions_load(fleet: int, objects: int) -> tuple[int, int]:
    """Most global tracks and most other UAVs' states any UAV of the bench layout receives through
    the regions its window touches (agent.joint_window, shared.keys.track_region): objects uniform
    within 100 m of each UAV, a UAV's state forwarded to its own region (small footprints); the
    layout as in the load above and shifted by 2 tiles (windows across region corners), the worse."""
    from shared.tiles import TileGrid

    grid = TileGrid()
    rng = np.random.default_rng(1)
    cell_m = float(grid.cell_size_m(47.67))
    found = [_most_in_regions(grid, rng, cell_m, fleet, objects, shift) for shift in (1.5, 3.5)]
    return max(tracks for tracks, _ in found), max(states for _, states in found)


def _most_in_regions(grid, rng: np.random.Generator, cell_m: float, fleet: int, objects: int,
                     shift: float) -> tuple[int, int]:
    from agent.joint_window import window_tiles
    from shared.keys import track_region

    n = grid.n
    centres = [((BASE_X + 4 * (b % 50) + shift) * n, (BASE_Y + 4 * (b // 50) + shift) * n) for b in range(fleet)]
    cells = np.vstack([np.column_stack([cx + rng.uniform(-100, 100, objects) / cell_m,
                                        cy + rng.uniform(-100, 100, objects) / cell_m]) for cx, cy in centres])
    track_regions = [track_region(grid.z, int(x), int(y)) for x, y in (cells // n).astype(np.int64)]
    uav_regions = [track_region(grid.z, int(cx // n), int(cy // n)) for cx, cy in centres]
    size = int(np.ceil(300.0 / cell_m))
    most_tracks = most_states = 0
    for cx, cy in centres:
        mine = {track_region(grid.z, x, y) for x, y in window_tiles((int(cx - size / 2), int(cy - size / 2)), size, n,
                                                                     margin=0)}
        most_tracks = max(most_tracks, sum(region in mine for region in track_regions))
        most_states = max(most_states, sum(region in mine for region in uav_regions) - 1)
    return most_tracks, most_states


def run(quick: bool = False) -> list[dict[str, Any]]:
    ctx = mp.get_context("spawn")  # never fork after zenoh.open
    steps = [2, 10] if quick else [50, 100, 150, 200, 250]
    pair_n = 4 if quick else 200
    duration_s = 2.5 if quick else 5.0
    raw_rate = _raw_zenoh_rate(ctx, 1.0 if quick else 3.0)
    raw_uavs = raw_rate / (RATE_HZ * TILES_PER_UAV)
    rows: list[dict[str, Any]] = [
        {"case": "raw zenoh put->receive, sparse tile payloads, BLOCK", "value": raw_rate, "unit": "msg/s"},
    ]
    import zenoh

    endpoint = f"tcp/127.0.0.1:{free_port()}"
    with tempfile.TemporaryDirectory() as db_dir:
        fusion = start_fusion(os.path.join(db_dir, "bench.sqlite"), listen=endpoint)
        try:
            with zenoh.open(zenoh_config("peer", connect=endpoint)) as session:
                receiver = JointLatency()
                sub = session.declare_subscriber("uavmm/v1/joint/tiles/**", receiver)
                gc.freeze()  # as uavmm fusion does: no full-collection pauses over start-up objects here
                sustained, results = search(ctx, endpoint, receiver, steps, duration_s, "s",
                                            watch={"fusion": fusion.pid})
                rows += [{"case": latency_case(r, f"{r.n} UAVs x 9 tiles @5 Hz, no overlap"),
                          "value": r.p99 * 1e3, "unit": "ms", "baseline_name": "budget 50 ms",
                          "ratio": r.p99 / P99_BUDGET_S} for r in results]
                cpu_per_msg = results[-1].cpu_per_msg("fusion") if results else None  # of the largest load run
                pairs = run_load(ctx, endpoint, receiver, blocks_of(pair_n, shared_pairs=True), duration_s, "sp",
                                 shared_pairs=True, n_procs=2 if pair_n >= 100 else 1)
                log.info("fusion bench, pairs: %s", pairs)
                rows.append({
                    "case": latency_case(pairs, f"{pair_n} UAVs, 2 per tile (rate limit 5 Hz/tile)"),
                    "value": pairs.p99 * 1e3, "unit": "ms", "baseline_name": "budget 250 ms",
                    "ratio": pairs.p99 / P99_LIMITED_BUDGET_S,
                })
                sub.undeclare()
        finally:
            stop_process(fusion)
    capped = sustained == steps[-1]
    rows.append({
        "case": "UAVs sustained, no overlap, p99 <= 50 ms" + (" (largest load tried)" if capped else ""),
        "value": float(sustained), "unit": "UAVs",
        "baseline_name": f"raw zenoh = {raw_uavs:.0f} UAV-equivalents",
        "ratio": sustained / raw_uavs if raw_uavs else None,
    })
    if cpu_per_msg:
        rows.append({
            "case": f"fusion process CPU per UAV message (largest load; UAVs one core holds: "
                    f"{1.0 / (cpu_per_msg * RATE_HZ * TILES_PER_UAV):.0f})",
            "value": cpu_per_msg * 1e6, "unit": "us",
        })
    rows += run_sharded(ctx, quick, duration_s, sustained)
    bw = uav_bytes_per_s(seconds=2.5 if quick else 4.0)
    rows += [
        {"case": f"uplink per UAV, 20 objects, defaults (tiles {bw['tiles'] / 1e3:.0f}, state+tracks "
                 f"{bw['state_tracks'] / 1e3:.0f} kB/s)",
         "value": bw["uplink"] / 1e3, "unit": "kB/s", "baseline_name": "budget 100 kB/s",
         "ratio": bw["uplink"] / BYTES_BUDGET},
        {"case": "uplink per UAV, same without the tile byte budget (every changed tile @5 Hz)",
         "value": bw["uplink_unlimited"] / 1e3, "unit": "kB/s", "baseline_name": "budget 100 kB/s",
         "ratio": bw["uplink_unlimited"] / BYTES_BUDGET},
        {"case": "downlink per UAV, alone (its joint tiles, joint tracks)",
         "value": bw["downlink_alone"] / 1e3, "unit": "kB/s", "baseline_name": "budget 100 kB/s",
         "ratio": bw["downlink_alone"] / BYTES_BUDGET},
        {"case": f"downlink per UAV in a fleet of {bw['fleet']}: window's joint tiles, its regions' tracks "
                 f"({bw['fleet_tracks'] / 1e3:.0f}) and states ({bw['fleet_states'] / 1e3:.1f})",
         "value": bw["downlink_fleet"] / 1e3, "unit": "kB/s", "baseline_name": "budget 100 kB/s",
         "ratio": bw["downlink_fleet"] / BYTES_BUDGET},
        {"case": f"downlink per UAV in a fleet of {bw['fleet']}, every joint tile, track, state (joint_window off)",
         "value": bw["downlink_fleet_all_tiles"] / 1e3, "unit": "kB/s", "baseline_name": "budget 100 kB/s",
         "ratio": bw["downlink_fleet_all_tiles"] / BYTES_BUDGET},
    ]
    return rows
