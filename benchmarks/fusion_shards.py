"""Sharded fusion in `uavmm bench fusion`: how many UAVs two `uavmm fusion --shard K/2` processes hold
behind a Zenoh router, against one process behind the same router, in the same run.

The topology is the deployment's (deploy/docker-compose.sharded.yml): a router, and the fusion
processes, the load generators and the joint-tile subscriber all Zenoh clients of it. The generators
put each tile on its shard's bucket key, as agents do while shards are up (agent.shard_routing), so
Zenoh delivers it to that shard only. Two more loads price the plain DESIGN keys, which reach every
shard: the same load, and one whose tiles all lie in shard 1's regions, so shard 0's CPU per message
is what a dropped sample costs.
"""

from __future__ import annotations

import logging
import os
import subprocess
import tempfile
import time
from collections.abc import Sequence
from typing import Any

from benchmarks.fusion_load import (
    GRID_Z,
    P99_BUDGET_S,
    RATE_HZ,
    TILES_PER_UAV,
    JointLatency,
    LoadResult,
    block_tiles,
    blocks_of,
    free_port,
    latency_case,
    router_process,
    run_load,
    search,
    start_fusion,
    stop_process,
    zenoh_config,
)
from shared.sharding import DEFAULT_REGION_ZOOM, ShardSpec

log = logging.getLogger(__name__)

#: the issue's acceptance: two shards on one machine hold this many times one process
SHARD_TARGET = 1.6


def shard_shares(blocks: Sequence[int], count: int = 2, region_zoom: int = DEFAULT_REGION_ZOOM) -> list[float]:
    """Share of the tile messages of UAVs on ``blocks`` that each of ``count`` shards owns (sums to 1)."""
    spec = ShardSpec(0, count, region_zoom)
    counts = [0] * count
    for block in blocks:
        for x, y in block_tiles(block):
            counts[spec.owner(GRID_Z, x, y)] += 1
    total = sum(counts)
    return [c / total if total else 0.0 for c in counts]


def blocks_owned_by(shard: int, count: int, n: int, region_zoom: int = DEFAULT_REGION_ZOOM) -> list[int]:
    """The first ``n`` blocks whose 9 tiles all lie in regions of shard ``shard`` of ``count``."""
    spec = ShardSpec(shard, count, region_zoom)
    found: list[int] = []
    block = 0
    while len(found) < n:
        if all(spec.owns(GRID_Z, x, y) for x, y in block_tiles(block)):
            found.append(block)
        block += 1
    return found


def balanced_blocks(n: int, count: int = 2, region_zoom: int = DEFAULT_REGION_ZOOM) -> list[int]:
    """Blocks of ``n`` UAVs taken in turn from each shard's regions (blocks_owned_by), so every shard
    owns 1/count of the tiles: the sharded capacity, not the luck of the hash over a few regions."""
    per_shard = [blocks_owned_by(k, count, -(-n // count), region_zoom) for k in range(count)]
    return [per_shard[i % count][i // count] for i in range(n)]


def _regions(blocks: Sequence[int], region_zoom: int = DEFAULT_REGION_ZOOM) -> int:
    spec = ShardSpec(0, 1, region_zoom)
    return len({spec.region(GRID_Z, x, y) for block in blocks for x, y in block_tiles(block)})


def _same_load(one: list[LoadResult], two: list[LoadResult]) -> tuple[LoadResult | None, LoadResult | None]:
    """The runs of both searches at the largest load both sustained (else both ran): CPU per message is
    compared there, since an idle process's fixed costs weigh more at smaller loads."""
    for pick in (lambda r: r.sustained, lambda r: True):
        common = {r.n for r in one if pick(r)} & {r.n for r in two if pick(r)}
        if common:
            n = max(common)
            return next(r for r in one if r.n == n), next(r for r in two if r.n == n)
    return (one[-1] if one else None), (two[-1] if two else None)


def _step_rows(results: list[LoadResult], what: str) -> list[dict[str, Any]]:
    return [{"case": latency_case(r, f"{what}, {r.n} UAVs"), "value": r.p99 * 1e3, "unit": "ms",
             "baseline_name": "budget 50 ms", "ratio": r.p99 / P99_BUDGET_S} for r in results]


def _capped(sustained: int, steps: Sequence[int]) -> str:
    return " (largest load tried)" if sustained == steps[-1] else ""


def _us(value: float | None) -> float:
    return float("nan") if value is None else value * 1e6


def run_sharded(ctx, quick: bool, duration_s: float, direct_sustained: int) -> list[dict[str, Any]]:
    """The rows of the sharded comparison (see the module docstring); ``direct_sustained``: UAVs one
    process held with the generators as its direct peers, earlier in the run."""
    import zenoh

    steps_one = [4] if quick else [50, 100, 125, 150, 175, 200, 225, 250, 275, 300]
    steps_two = [8] if quick else [100, 150, 175, 200, 225, 250, 275, 300, 325, 350, 400, 450]
    drop_n = 100
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    ready, stop = ctx.Event(), ctx.Event()
    router = ctx.Process(target=router_process, args=(endpoint, ready, stop))
    router.start()
    try:
        if not ready.wait(30):
            raise RuntimeError("the zenoh router process did not start")
        with tempfile.TemporaryDirectory() as db_dir, \
                zenoh.open(zenoh_config("client", connect=endpoint)) as session:
            receiver = JointLatency()
            sub = session.declare_subscriber("uavmm/v1/joint/tiles/**", receiver)
            one = start_fusion(os.path.join(db_dir, "one.sqlite"), connect=endpoint)
            try:  # the same UAVs as the shards get: one load, two deployments
                one_n, one_results = search(ctx, endpoint, receiver, steps_one, duration_s, "r1s", mode="client",
                                            watch={"fusion": one.pid, "router": router.pid},
                                            layout=balanced_blocks)
            finally:
                stop_process(one)
            shards: list[subprocess.Popen] = []
            try:
                for k in range(2):  # one by one: a shard that fails to start stops the one before it too
                    shards.append(start_fusion(os.path.join(db_dir, f"shard{k}.sqlite"), connect=endpoint,
                                               shard=f"{k}/2"))
                watch = {"shard0": shards[0].pid, "shard1": shards[1].pid, "router": router.pid}
                # the agents see the shards' tokens and put each tile on its shard's bucket key
                two_n, two_results = search(ctx, endpoint, receiver, steps_two, duration_s, "r2s", mode="client",
                                            watch=watch, layout=balanced_blocks, routed_zoom=DEFAULT_REGION_ZOOM)
                plain_run = drop = None
                if not quick:  # the same load on DESIGN's plain keys (agents that do not route): both get all
                    same = _same_load(one_results, two_results)[1]
                    plain_run = run_load(ctx, endpoint, receiver, balanced_blocks(same.n if same else 100), duration_s,
                                     "r2p", n_procs=2, mode="client", watch=watch)
                    time.sleep(2.5)
                    drop = run_load(ctx, endpoint, receiver, blocks_owned_by(1, 2, drop_n), duration_s, "r2d",
                                    n_procs=2, mode="client", watch=watch)
            finally:
                for proc in shards:
                    stop_process(proc)
            sub.undeclare()
    finally:
        stop.set()
        router.join(timeout=10)
        if router.is_alive():
            router.terminate()
    rows = _step_rows(one_results, "one fusion process behind a zenoh router")
    rows += _step_rows(two_results, "two shards (--shard 0/2, 1/2) behind the router, bucket keys")
    at = max(two_n, steps_two[0])
    shares, row_shares = shard_shares(balanced_blocks(at)), shard_shares(blocks_of(at))
    rows.append({
        "case": f"UAVs sustained, one process behind the router, p99 <= 50 ms{_capped(one_n, steps_one)} "
                f"(as direct peers earlier: {direct_sustained})",
        "value": float(one_n), "unit": "UAVs"})
    rows.append({
        "case": f"UAVs sustained, two shards behind the router, tiles on their shard's bucket keys"
                f"{_capped(two_n, steps_two)} (tile messages per shard "
                f"{shares[0]:.0%} / {shares[1]:.0%}; acceptance >= {SHARD_TARGET} x one process)",
        "value": float(two_n), "unit": "UAVs", "baseline_name": f"one process behind the router = {one_n}",
        "ratio": two_n / one_n if one_n else None})
    rows.append({
        "case": f"busiest shard's share of the tiles of {at} UAVs laid out in rows instead ({_regions(blocks_of(at))} "
                f"regions of zoom {DEFAULT_REGION_ZOOM}: the hash over few regions; the search above uses "
                f"UAVs taken in turn from each shard's regions)",
        "value": max(row_shares) * 100, "unit": "%", "baseline_name": "even = 50 %", "ratio": max(row_shares) / 0.5})
    rows += _cpu_rows(*_same_load(one_results, two_results))
    if plain_run is not None:
        shares = shard_shares(balanced_blocks(plain_run.n))
        per = [plain_run.cpu_per_msg(f"shard{k}", plain_run.puts * shares[k]) for k in range(2)]
        rows.append({
            "case": f"two shards, same load on DESIGN's plain tile keys ({plain_run.n} UAVs: every shard gets every "
                    f"tile, drops the other's; p99 {plain_run.p99 * 1e3:.0f} ms): CPU per message owned, shard 0 / 1 "
                    f"{_us(per[0]):.0f} / {_us(per[1]):.0f} us, all processes",
            "value": _us(_total_per_msg(plain_run, ("shard0", "shard1", "router", "generator"))), "unit": "us"})
    if drop is not None:
        owned, dropped = drop.cpu_per_msg("shard1"), drop.cpu_per_msg("shard0")
        rows.append({
            "case": f"shard 0 CPU per dropped tile sample on the plain keys ({drop.n} UAVs, all in shard 1's "
                    "regions: Zenoh receive + Python callback + key check)",
            "value": _us(dropped), "unit": "us",
            "baseline_name": f"shard 1 per owned message = {_us(owned):.0f} us",
            "ratio": dropped / owned if owned and dropped is not None else None})
    return rows


def _total_per_msg(result: LoadResult, names: Sequence[str]) -> float | None:
    """CPU seconds per UAV message of the named processes together."""
    return sum(result.cpu.get(name, 0.0) for name in names) / result.puts if result.puts else None


def _cpu_rows(one: LoadResult | None, two: LoadResult | None) -> list[dict[str, Any]]:
    """CPU per tile message of every process, one process and two shards at the same load (_same_load),
    and what those costs predict on a dedicated machine (_dedicated_rows)."""
    rows: list[dict[str, Any]] = []
    one_total = None
    if one is not None:
        one_total = _total_per_msg(one, ("fusion", "router", "generator"))
        rows.append({"case": f"one process behind the router, CPU per UAV message ({one.n} UAVs; router "
                             f"{_us(one.cpu_per_msg('router')):.0f} us, load generator "
                             f"{_us(one.cpu_per_msg('generator')):.0f} us; all three {_us(one_total):.0f} us)",
                     "value": _us(one.cpu_per_msg("fusion")), "unit": "us"})
    if two is not None:
        shares = shard_shares(balanced_blocks(two.n))
        for k in range(2):
            owned = two.cpu_per_msg(f"shard{k}", two.puts * shares[k])
            rows.append({"case": f"shard {k} CPU per UAV message it owns ({shares[k]:.0%} of {two.n} UAVs' tiles, "
                                 f"routed to it by bucket key; per message of the fleet: "
                                 f"{_us(two.cpu_per_msg(f'shard{k}')):.0f} us)",
                         "value": _us(owned), "unit": "us"})
        two_total = _total_per_msg(two, ("shard0", "shard1", "router", "generator"))
        rows.append({"case": f"two shards, CPU per UAV message of shards + router "
                             f"({_us(two.cpu_per_msg('router')):.0f} us) + load generator "
                             f"({_us(two.cpu_per_msg('generator')):.0f} us), {two.n} UAVs",
                     "value": _us(two_total), "unit": "us",
                     "baseline_name": f"one process + router + generator = {_us(one_total):.0f} us",
                     "ratio": two_total / one_total if two_total and one_total else None})
        if one is not None and two_total and one_total:
            rows += _dedicated_rows(one, two, one_total, two_total)
    return rows


def _dedicated_rows(one: LoadResult, two: LoadResult, one_total: float, two_total: float) -> list[dict[str, Any]]:
    """What the CPU per message predicts on a machine of this many cores with nothing else on it, which
    this shared machine's latency search cannot show: one process is held to one core (one fusion
    thread, the GIL), each shard to one core, all processes together to the machine's cores."""
    cores = os.cpu_count() or 1
    per_uav = TILES_PER_UAV * RATE_HZ
    one_fusion = one.cpu_per_msg("fusion")
    shard_worst = max(two.cpu_per_msg("shard0") or 0.0, two.cpu_per_msg("shard1") or 0.0)
    if not one_fusion or not shard_worst:
        return []
    one_cap = min(1.0 / one_fusion, cores / one_total) / per_uav
    two_cap = min(1.0 / shard_worst, cores / two_total) / per_uav
    need = SHARD_TARGET * two_total / one_fusion  # cores for 1.6 x one process's one-core capacity
    return [{
        "case": f"predicted on {cores} dedicated cores from CPU per message: one process {one_cap:.0f} UAVs "
                f"(its core), two shards {two_cap:.0f} UAVs (all processes' cores); {SHARD_TARGET} x needs "
                f"{need:.1f} cores",
        "value": two_cap / one_cap, "unit": "x", "baseline_name": f"acceptance {SHARD_TARGET} x",
        "ratio": two_cap / one_cap / SHARD_TARGET}]
