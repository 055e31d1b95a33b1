"""`uavmm demo` as a real process: a fusion server and three simulated agents come up over Zenoh on
loopback, the REST API sees three UAVs online, and every child process is gone afterwards, whether
the demo stops after --duration or is killed with SIGKILL (its reaper cleans up)."""

from __future__ import annotations

import json
import re
import signal
import subprocess
import urllib.request
from pathlib import Path

import pytest

from tests.e2e.conftest import ENV, REPO, uavmm
from tests.netutil import wait_until
from uavmm.cmd_demo import DemoOptions, flying_uavs

pytestmark = pytest.mark.e2e


def processes_with(text: str) -> list[int]:
    """PIDs of the live processes whose command line contains `text` (zombies have none)."""
    pids = []
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            cmdline = (entry / "cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")
        except OSError:
            continue
        if text in cmdline:
            pids.append(int(entry.name))
    return pids


def start_demo(out: Path, *args: str) -> subprocess.Popen:
    with open(out, "wb") as sink:
        return subprocess.Popen(uavmm("demo", "--http", "127.0.0.1:0", *args),
                                cwd=REPO, env=ENV, stdout=sink, stderr=subprocess.STDOUT)


def wait_flying(proc: subprocess.Popen, out: Path) -> tuple[str, str]:
    """Wait for the demo's "N UAVs flying" (or "1 UAV flying") line; returns (map URL, Zenoh endpoint)."""
    flying = re.compile(r"\d+ UAVs? flying")
    text = wait_until(lambda: (out.read_text() if flying.search(out.read_text()) or proc.poll() is not None
                             else None), 90.0, "the demo's agents")
    assert flying.search(text), text
    url = re.search(r"map: (http://\S+)", text).group(1)
    endpoint = re.search(r"zenoh (tcp/\S+),", text).group(1)
    return url, endpoint


def uavs_online(url: str) -> list[str]:
    try:
        with urllib.request.urlopen(url + "v1/uavs", timeout=5) as response:
            return sorted(u["id"] for u in json.loads(response.read()) if u["online"])
    except OSError:
        return []


def test_demo_flies_three_uavs_and_leaves_nothing_behind_after_its_duration(tmp_path):
    out = tmp_path / "demo.out"
    proc = start_demo(out, "--duration", "8", "--status-every", "2")
    try:
        url, endpoint = wait_flying(proc, out)
        assert re.fullmatch(r"http://127\.0\.0\.1:\d+/", url)
        assert len(processes_with(endpoint)) == 4  # the fusion server and three agents
        wait_until(lambda: uavs_online(url) == ["uav1", "uav2", "uav3"], 20.0, "three UAVs online")
        code = proc.wait(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
    text = out.read_text()
    assert code == 0, text
    assert "uavmm demo: 3 UAVs flying (uav1, uav2, uav3; scenario trio, seed 0)" in text
    assert re.search(r"3 UAVs online, \d+ joint tiles, \d+ global tracks", text), text
    assert processes_with(endpoint) == []
    logs = re.search(r"logs in (\S+);", text).group(1)
    assert not Path(logs).exists()  # the temporary work folder (db and logs) is removed after a clean run


def test_one_uav_is_one_uav_in_every_line(tmp_path):
    """Probe: `uavmm demo --uavs 1` said "1 UAVs flying" and, every status, "1 UAVs online"."""
    out = tmp_path / "demo.out"
    proc = start_demo(out, "--uavs", "1", "--duration", "6", "--status-every", "1")
    try:
        url, _ = wait_flying(proc, out)
        wait_until(lambda: uavs_online(url) == ["uav1"], 20.0, "one UAV online")
        code = proc.wait(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
    text = out.read_text()
    assert code == 0, text
    assert "uavmm demo: 1 UAV flying (uav1; scenario trio, seed 0)" in text
    assert re.search(r"uavmm demo: 1 UAV online, \d+ joint tiles?, \d+ global tracks?", text), text
    assert "1 UAVs" not in text and not re.search(r"\b1 (joint tiles|global tracks)\b", text), text


def test_sharded_demo_serves_the_map_through_a_gateway(tmp_path):
    out = tmp_path / "demo.out"
    proc = start_demo(out, "--shards", "2", "--duration", "10", "--status-every", "0")
    try:
        url, endpoint = wait_flying(proc, out)
        assert len(processes_with(endpoint)) == 6  # two shards, the gateway, three agents
        wait_until(lambda: uavs_online(url) == ["uav1", "uav2", "uav3"], 20.0, "three UAVs online at the gateway")
        with urllib.request.urlopen(url + "healthz", timeout=5) as response:
            health = json.loads(response.read())
        assert health["status"] == "ok" and sorted(health["shards"]) == ["0", "1"]
        assert all(shard["status"] == "up" for shard in health["shards"].values())
        code = proc.wait(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
    text = out.read_text()
    assert code == 0, text
    assert "2 fusion shards up (regions of zoom 16)" in text
    assert processes_with(endpoint) == []


def test_demo_killed_with_sigkill_leaves_no_orphans(tmp_path):
    out = tmp_path / "demo.out"
    proc = start_demo(out, "--stop-timeout", "3", "--status-every", "0")
    try:
        _, endpoint = wait_flying(proc, out)
        children = processes_with(endpoint)
        assert len(children) == 4
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.wait(timeout=10)
    # the reaper saw its pipe close: SIGTERM to every process group, SIGKILL after 3 s, then it removes
    # the demo's temporary folder
    wait_until(lambda: processes_with(endpoint) == [], 20.0, "the children to be reaped")
    workdir = Path(re.search(r"logs in (\S+);", out.read_text()).group(1))
    wait_until(lambda: not workdir.exists(), 10.0, "the temporary folder to be removed")


def test_demo_stops_cleanly_on_sigint_while_starting(tmp_path):
    out = tmp_path / "demo.out"
    proc = start_demo(out, "--status-every", "0")
    try:
        wait_until(lambda: "map: http://" in out.read_text() or proc.poll() is not None, 60.0, "the fusion server")
        endpoint = re.search(r"zenoh (tcp/\S+),", out.read_text()).group(1)
        proc.send_signal(signal.SIGINT)
        code = proc.wait(timeout=40)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert code == 0, out.read_text()
    assert processes_with(endpoint) == []


def test_demo_refuses_a_scenario_whose_uavs_fly_one_after_another():
    result = subprocess.run(uavmm("demo", "--scenario", "grass"), cwd=REPO, env=ENV,
                            capture_output=True, text=True, timeout=60)
    assert result.returncode == 2
    assert "scenario 'grass' flies its UAVs one after another" in result.stderr
    assert "coop, coop-slope, trio" in result.stderr and "Traceback" not in result.stderr


def test_flying_uavs_and_options_validate_their_input():
    assert flying_uavs("trio", None) == ["uav1", "uav2", "uav3"]
    assert flying_uavs("trio", 2) == ["uav1", "uav2"]
    assert flying_uavs("coop", None) == ["uav1", "uav2"]
    with pytest.raises(ValueError, match="has 3 UAVs, --uavs 4"):
        flying_uavs("trio", 4)
    with pytest.raises(ValueError, match="unknown scenario 'moon'"):
        flying_uavs("moon", None)
    with pytest.raises(ValueError, match="--speed must be > 0"):
        DemoOptions(speed=0)
    with pytest.raises(ValueError, match="--port must be in 0..65535"):
        DemoOptions(zenoh_port=70000)
    with pytest.raises(ValueError, match="--http must be HOST:PORT, got 'nonsense'"):
        DemoOptions(http="nonsense")
    with pytest.raises(ValueError, match="--http: the port must be in 0..65535, got 99999"):
        DemoOptions(http="127.0.0.1:99999")
    with pytest.raises(ValueError, match="--status-every must be >= 0"):
        DemoOptions(status_interval_s=-1)


def test_trio_scenario_keeps_three_uavs_over_one_scene_for_its_whole_flight():
    """The demo's scenario: three simultaneous UAVs whose flights stay over the scene (the demo loops
    them for as long as it runs) and whose footprints overlap at the scene centre."""
    import math

    import numpy as np

    from shared.geo import Pose, footprint_local
    from sim.scenarios import get_scenario
    from sim.simulator import Simulation

    scenario = get_scenario("trio")
    assert scenario.simultaneous and [f.uav for f in scenario.flights] == ["uav1", "uav2", "uav3"]
    assert scenario.default_frames / scenario.fps >= 600  # ten minutes before the first loop
    sim = Simulation(scenario, seed=0)
    flights = list(sim.flights().values())
    covering = []
    for t in np.arange(0.0, scenario.default_frames / scenario.fps, 5.0):
        n_covering = 0
        for flight in flights:
            s = flight.state(float(t))
            assert math.hypot(s.east_m, s.north_m) < 70.0, f"a UAV left the scene at t={t}"
            pose = Pose(scenario.world.origin_lat, scenario.world.origin_lon, s.height_m, s.pitch_deg, s.heading_deg)
            polygon = footprint_local(sim.camera, pose, max_range_m=150.0) + np.array([s.east_m, s.north_m])
            n_covering += _inside(polygon, 0.0, 0.0)
        covering.append(n_covering)
    assert min(covering) >= 2 and np.mean(np.array(covering) == 3) > 0.7  # measured: always 2, 93 % 3


def _inside(polygon, x: float, y: float) -> bool:
    """Whether (x, y) lies inside the polygon (even-odd rule)."""
    inside = False
    for (x0, y0), (x1, y1) in zip(polygon, list(polygon[1:]) + [polygon[0]], strict=True):
        if (y0 > y) != (y1 > y) and x < x0 + (y - y0) * (x1 - x0) / (y1 - y0):
            inside = not inside
    return inside


def demo_in(tmp_path: Path, *args: str) -> subprocess.CompletedProcess:
    """`uavmm demo ARGS` with its temporary folders under tmp_path/tmp (checked for leftovers)."""
    (tmp_path / "tmp").mkdir()
    return subprocess.run(uavmm("demo", "--duration", "5", "--status-every", "0", *args), cwd=REPO,
                          env={**ENV, "TMPDIR": str(tmp_path / "tmp")}, capture_output=True, text=True, timeout=90)


@pytest.mark.parametrize("http", ["nonsense", ":8000", "127.0.0.1:abc", "127.0.0.1:99999"])
def test_demo_refuses_a_bad_http_address_before_starting_anything(tmp_path, http):
    """A user error like the other flags': one line, exit code 2, no process started, no folder kept (the fusion
    server used to be started to find out, and the demo exited 1 keeping its temporary folder)."""
    result = demo_in(tmp_path, "--http", http)
    assert result.returncode == 2, result.stdout + result.stderr
    assert result.stderr.splitlines() == [result.stderr.strip()] and "uavmm demo: error: --http" in result.stderr
    assert result.stdout == "" and list((tmp_path / "tmp").iterdir()) == []


@pytest.mark.parametrize("flag", ["--http", "--port"])
def test_demo_on_a_taken_port_says_so_in_one_line_and_leaves_nothing(tmp_path, flag):
    """Port 8000 held by another demo (a socket listening here): one line naming the port and the way out, exit
    code 2, before any process starts and with no temporary folder kept (it used to take the fusion server's
    start-up to find out, print its log's tail and keep the folder)."""
    import socket

    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        value = f"127.0.0.1:{port}" if flag == "--http" else str(port)
        result = demo_in(tmp_path, *([] if flag == "--http" else ["--http", "127.0.0.1:0"]), flag, value)
    assert result.returncode == 2, result.stdout + result.stderr
    assert result.stderr.splitlines() == [result.stderr.strip()], result.stderr
    assert f"uavmm demo: error: {flag} {value}" in result.stderr and "in use" in result.stderr
    if flag == "--http":
        assert "--http 127.0.0.1:0 picks a free port" in result.stderr
    assert result.stdout == "" and list((tmp_path / "tmp").iterdir()) == []
