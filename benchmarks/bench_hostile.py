"""Benchmark of the fusion server under a flood: 100,000 malformed or oversized messages at full speed.

A real `uavmm fusion` subprocess; in this process one Zenoh session plays a UAV (``mallory``) that
publishes under its own keys as fast as Zenoh takes them (``CongestionControl.BLOCK``): garbage
bytes, tiles with bad fields, tiles from the future, forged tiles of another UAV, oversized tiles,
10,000-track messages. Two honest UAVs keep publishing valid tiles at 5 Hz. Measured: the server's
resident memory (``/proc/PID/status`` VmRSS) before and after the flood, and its peak over the flood (the kernel's
high-water mark VmHWM, reset to the current RSS as the flood starts, so a spike between two polls counts); whether every
message was counted (``/metrics``: accepted + dropped by reason == sent); whether the honest UAVs'
joint tiles kept arriving. Run three times: with the default per-UAV rate limits, with them off (so
every message reaches validation), and on the files of `uavmm secure init` (mutual TLS and the fleet's
ACL: mallory is an authenticated UAV misbehaving on its own keys). The baseline is the RSS of the same
server before the flood.
"""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import msgpack
import numpy as np

from benchmarks.fusion_load import NO_SHM, free_port, zenoh_config

DESCRIPTION = "fusion server RSS and drop counts under 100,000 malformed/oversized messages from one UAV"

_REPO = Path(__file__).resolve().parents[1]
_X, _Y = 137_700, 91_400


def _rss_mb(pid: int, field: str = "VmRSS") -> float:
    """A /proc/PID/status memory field in MB (VmRSS: resident now; VmHWM: the peak since the last reset)."""
    text = Path(f"/proc/{pid}/status").read_text()
    match = re.search(rf"{field}:\s+(\d+) kB", text)
    return int(match.group(1)) / 1024.0 if match else float("nan")


def _reset_peak_rss(pid: int) -> bool:
    """Set pid's VmHWM to its current RSS (Linux >= 4.0: "5" to /proc/PID/clear_refs); False where it cannot."""
    try:
        Path(f"/proc/{pid}/clear_refs").write_text("5")
    except OSError:
        return False
    return True


def _session_config(endpoint: str, fleet: Path | None, identity: str):
    """A client config: plain, or the identity's own from the fleet folder (TLS with its certificate)."""
    if fleet is None:
        return zenoh_config("client", connect=endpoint)
    import zenoh

    conf = zenoh.Config.from_file(str(fleet / "uavs" / identity / "zenoh.json5"))
    conf.insert_json5("transport/shared_memory/enabled", "false")
    conf.insert_json5("connect/timeout_ms", "5000")
    conf.insert_json5("connect/exit_on_failure", "true")
    return conf


def _start_fusion(port: int, http_port: int, db_dir: str, extra: list[str], fleet: Path | None = None
                  ) -> subprocess.Popen:
    scheme = "tcp" if fleet is None else "tls"
    secure = [] if fleet is None else ["--config", str(fleet / "fusion" / "zenoh.json5")]
    cmd = [sys.executable, "-m", "uavmm", "fusion", *secure, "--listen", f"{scheme}/127.0.0.1:{port}",
           "--http", f"127.0.0.1:{http_port}", "--db", os.path.join(db_dir, "hostile.sqlite"),
           "--no-multicast-scouting", "--cfg", NO_SHM, *extra]
    env = {**os.environ, "PYTHONPATH": str(_REPO) + os.pathsep + os.environ.get("PYTHONPATH", "")}
    proc = subprocess.Popen(cmd, cwd=_REPO, env=env, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
    assert proc.stdout is not None
    line = proc.stdout.readline()
    if "uavmm fusion" not in line:
        proc.kill()
        raise RuntimeError(f"uavmm fusion did not start: {line!r}")
    return proc


def _counters(http_port: int) -> tuple[int, int, dict[str, int]]:
    """(accepted tracks messages, dropped messages, dropped by reason) from /metrics; the honest
    UAVs send only tiles, so hostile messages = accepted tracks messages + dropped ones."""
    import httpx

    text = httpx.get(f"http://127.0.0.1:{http_port}/metrics", timeout=10.0).text
    accepted = sum(int(v) for k, v in re.findall(r'uavmm_fusion_messages_total\{kind="(\w+)"\} (\d+)', text)
                   if k == "tracks")
    reasons: dict[str, int] = {}
    for kind, reason, value in re.findall(r'uavmm_fusion_rejected_total\{kind="(\w+)",reason="(\w+)"\} (\d+)', text):
        if kind != "publisher":
            reasons[reason] = reasons.get(reason, 0) + int(value)
    return accepted, sum(reasons.values()), reasons


def hostile_payloads(rng: np.random.Generator) -> list[tuple[str, bytes]]:
    """One round of the flood: (key, payload) pairs, all under mallory's own keys."""
    from shared.keys import KeySpace
    from shared.messages import TrackItem, TracksMessage, encode_tracks
    from shared.tilecodec import TileMessage, encode_tile

    keys = KeySpace()
    tile_key = keys.uav_tile("mallory", "person", 18, _X + 5, _Y)
    good = TileMessage(uav="mallory", cls="person", z=18, x=_X + 5, y=_Y, n=256, t=time.time(), seq=1,
                       values=np.zeros((256, 256), np.float32))
    base = msgpack.unpackb(encode_tile(good))
    tracks = TracksMessage(uav="mallory", t=time.time(), tracks=tuple(
        TrackItem(id=i, cls="person", lat=47.7 + i * 1e-6, lon=9.3, score=0.5, vel_en=(0.0, 0.0))
        for i in range(10_000)))
    return [
        (tile_key, rng.bytes(64)),  # not msgpack
        (tile_key, msgpack.packb({**base, "v": 9})),
        (tile_key, msgpack.packb({**base, "t": 1e300})),
        (tile_key, msgpack.packb({**base, "seq": 2**64 - 1})),
        (tile_key, msgpack.packb({**base, "uav": "uav1"})),  # forged: another UAV's data on its key
        (tile_key, msgpack.packb({**base, "idx": b"\x01", "val": b""})),
        (tile_key, msgpack.packb({**base, "x": _X + 6})),
        (keys.uav_state("mallory"), msgpack.packb({"v": 1, "uav": "mallory", "t": "now"})),
        (keys.uav_tracks("mallory"), encode_tracks(tracks)),  # ~850 kB: too large
        (tile_key, rng.bytes(300 * 1024)),  # oversized tile
    ]


def _flood(endpoint: str, n_messages: int, fleet: Path | None = None) -> tuple[int, float]:
    import zenoh

    rng = np.random.default_rng(0)
    payloads = hostile_payloads(rng)
    # oversized ones are 1 in 50 (they cost the loopback, not the server); the rest round-robin
    small = [p for p in payloads if len(p[1]) < 64 * 1024]
    large = [p for p in payloads if len(p[1]) >= 64 * 1024]
    with zenoh.open(_session_config(endpoint, fleet, "mallory")) as session:
        publishers = {key: session.declare_publisher(key, congestion_control=zenoh.CongestionControl.BLOCK)
                      for key, _ in payloads}
        token = session.liveliness().declare_token("uavmm/v1/uav/mallory/alive")
        t0 = time.monotonic()
        for i in range(n_messages):
            key, payload = large[i // 50 % len(large)] if i % 50 == 49 else small[i % len(small)]
            publishers[key].put(payload)
        elapsed = time.monotonic() - t0
        del token
    return n_messages, elapsed


class _Honest:
    """Two UAVs publishing valid tiles at 5 Hz; counts the joint tiles of their tiles."""

    def __init__(self, endpoint: str, fleet: Path | None = None) -> None:
        import zenoh

        # with a fleet, both honest UAVs share honest1's session: its ACL lets it put only as honest1
        self.uavs = ("honest1", "honest2") if fleet is None else ("honest1",)
        self.session = zenoh.open(_session_config(endpoint, fleet, "honest1"))
        self.stop = threading.Event()
        self.joint = 0
        self.lock = threading.Lock()
        self.sub = self.session.declare_subscriber("uavmm/v1/joint/tiles/person/18/**", self._on_joint)
        self.thread = threading.Thread(target=self._run, daemon=True)

    def _on_joint(self, sample) -> None:
        with self.lock:
            self.joint += 1

    def joint_count(self) -> int:
        with self.lock:
            return self.joint

    def _run(self) -> None:
        from shared.keys import KeySpace
        from shared.tilecodec import TileMessage, encode_tile

        keys = KeySpace()
        values = np.zeros((256, 256), np.float32)
        values[100:110, 100:110] = 0.8
        seq = 0
        while not self.stop.wait(0.2):
            seq += 1
            for k, uav in enumerate(self.uavs):
                msg = TileMessage(uav=uav, cls="person", z=18, x=_X + k, y=_Y, n=256, t=time.time(), seq=seq,
                                  values=values)
                self.session.put(keys.uav_tile(uav, "person", 18, _X + k, _Y), encode_tile(msg))

    def close(self) -> None:
        self.stop.set()
        self.thread.join(timeout=5)
        self.session.close()


def _one_run(n_messages: int, extra: list[str], label: str, secure: bool = False) -> list[dict[str, Any]]:
    port, http_port = free_port(), free_port()
    endpoint = f"{'tls' if secure else 'tcp'}/{'localhost' if secure else '127.0.0.1'}:{port}"
    with tempfile.TemporaryDirectory() as db_dir:
        fleet = None
        if secure:
            from fusion_server.provision import FleetPlan, provision

            fleet = Path(db_dir) / "fleet"
            provision(fleet, FleetPlan(uavs=("mallory", "honest1"), operators=(), server_hosts=("localhost",),
                                       port=port))
        fusion = _start_fusion(port, http_port, db_dir, extra, fleet)
        try:
            honest = _Honest(endpoint, fleet)
            honest.thread.start()
            time.sleep(3.0)  # warm up: imports, first fusions, allocator
            rss_before = _rss_mb(fusion.pid)
            accepted0, dropped0, _ = _counters(http_port)
            joint0 = honest.joint_count()
            peak = [rss_before]
            done = threading.Event()

            def watch() -> None:
                while not done.wait(0.1):
                    peak.append(_rss_mb(fusion.pid))

            watcher = threading.Thread(target=watch, daemon=True)
            hwm = _reset_peak_rss(fusion.pid)  # polling every 0.1 s alone misses a spike between two polls
            watcher.start()
            flood_start = time.monotonic()
            sent, elapsed = _flood(endpoint, n_messages, fleet)
            deadline = time.monotonic() + 120.0
            while time.monotonic() < deadline:  # until every hostile message is counted
                accepted, dropped, reasons = _counters(http_port)
                if dropped - dropped0 + accepted - accepted0 >= sent:
                    break
                time.sleep(0.5)
            flood_end = time.monotonic()
            joint_during = honest.joint_count() - joint0
            if hwm:
                peak.append(_rss_mb(fusion.pid, "VmHWM"))
            time.sleep(3.0)
            done.set()
            watcher.join()
            rss_after = _rss_mb(fusion.pid)
            accepted, dropped, reasons = _counters(http_port)
            honest.close()
            alive = fusion.poll() is None
        finally:
            fusion.terminate()
            try:
                fusion.wait(timeout=15)
            except subprocess.TimeoutExpired:
                fusion.kill()
    counted = dropped - dropped0 + accepted - accepted0
    seconds = flood_end - flood_start
    return [
        {"case": f"{label}: peak RSS ({'VmHWM' if hwm else 'VmRSS every 0.1 s'}) during {sent:,} hostile msgs "
                 f"({sent / elapsed:,.0f} msg/s sent)",
         "value": max(peak), "unit": "MB", "baseline_name": f"before {rss_before:.0f} MB",
         "ratio": max(peak) / rss_before},
        {"case": f"{label}: RSS 3 s after the flood", "value": rss_after, "unit": "MB",
         "baseline_name": f"before {rss_before:.0f} MB", "ratio": rss_after / rss_before},
        {"case": f"{label}: hostile msgs counted: {accepted - accepted0} 10,000-track msgs truncated and used, "
                 f"dropped by reason {json.dumps(reasons, sort_keys=True)}",
         "value": counted, "unit": "msgs", "baseline_name": f"sent {sent}", "ratio": counted / sent},
        {"case": f"{label}: honest joint tiles received during {seconds:.1f} s of flood (server up: {alive})",
         "value": joint_during, "unit": "tiles", "baseline_name": f"{len(honest.uavs)} tiles refreshed 1/s",
         "ratio": joint_during / (len(honest.uavs) * seconds)},
    ]


def run(quick: bool = False) -> list[dict[str, Any]]:
    n = 5_000 if quick else 100_000
    rows = _one_run(n, [], "default limits")
    rows += _one_run(n, ["--uav-max-msgs-per-s", "1e9", "--uav-max-bytes-per-s", "1e12"], "limits off")
    rows += _one_run(n, [], "secure init files (mTLS + ACL), default limits", secure=True)
    return rows
