"""`uavmm demo`: a fusion server and simulated agents on this machine, over Zenoh on loopback, with the map page.

Each part runs as its own process (`python -m uavmm fusion|agent`) in its own process group. The demo
stops them in order (agents, then the server: SIGTERM, then SIGKILL after a timeout), and a small reaper
process kills them all should the demo itself die without cleaning up (even by SIGKILL).
"""

from __future__ import annotations

import argparse
import errno
import json
import logging
import os
import re
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
import urllib.request
from dataclasses import dataclass
from pathlib import Path

from uavmm._signals import stop_on_signals
from uavmm.cmd_fusion import http_address

log = logging.getLogger("uavmm.demo")

DEFAULT_SCENARIO = "trio"
#: Region zoom of a sharded demo: regions of 4 x 4 tiles (~400 m), so one scene spans several shards.
DEMO_REGION_ZOOM = 16

# The reaper: reads process-group ids from stdin, one a line. "done" means the demo cleaned up itself;
# end of input without it means the demo died: SIGTERM every group, SIGKILL what is left after the grace,
# then remove the demo's temporary folder.
_REAPER_SOURCE = r"""
import os, shutil, signal, sys, time
grace_s, workdir = float(sys.argv[1]), sys.argv[2]
groups, done = [], False
for line in sys.stdin:
    line = line.strip()
    if line == "done":
        done = True
        break
    if line.isdigit():
        groups.append(int(line))
if not done:
    def alive(group):
        try:
            os.killpg(group, 0)
            return True
        except OSError:
            return False
    for group in groups:
        try:
            os.killpg(group, signal.SIGTERM)
        except OSError:
            pass
    deadline = time.monotonic() + grace_s
    while time.monotonic() < deadline and any(alive(g) for g in groups):
        time.sleep(0.1)
    for group in groups:
        try:
            os.killpg(group, signal.SIGKILL)
        except OSError:
            pass
    time.sleep(0.5)  # let the killed processes close their files
    shutil.rmtree(workdir, ignore_errors=True)
"""


@dataclass(frozen=True, slots=True)
class DemoOptions:
    """What `uavmm demo` is told; times in seconds.

    http: the fusion server's REST address ``HOST:PORT`` (port 0 picks a free one).
    zenoh_port: TCP port of the server's Zenoh endpoint on 127.0.0.1 (0 picks a free one).
    db: SQLite file of the server, or None for one in the work folder (deleted at exit).
    log_dir: folder of the children's logs, or None for the work folder.
    scenario, seed, speed: the simulated flights (a scenario whose UAVs fly at the same time).
    uavs: how many of the scenario's UAVs fly (None: all of them).
    duration_s: stop this long after the agents are up (None: run until a signal).
    cot_url: the fusion server's Cursor-on-Target output (``udp://HOST:PORT``), or None.
    shards: 1 (one fusion server), or that many fusion shards (regions of zoom DEMO_REGION_ZOOM, so the
    scenario's few hundred metres spread over them) behind a `uavmm gateway` serving the map.
    """

    http: str = "127.0.0.1:8000"
    zenoh_port: int = 0
    db: Path | None = None
    log_dir: Path | None = None
    scenario: str = DEFAULT_SCENARIO
    seed: int = 0
    speed: float = 1.0
    uavs: int | None = None
    duration_s: float | None = None
    startup_timeout_s: float = 60.0
    stop_timeout_s: float = 10.0
    status_interval_s: float = 10.0
    log_level: str = "WARNING"
    cot_url: str | None = None
    shards: int = 1

    def __post_init__(self) -> None:
        if not 1 <= self.shards <= 8:
            raise ValueError(f"--shards must be in 1..8, got {self.shards}")
        if self.shards > 1 and self.cot_url is not None:
            raise ValueError("--cot-url works with one fusion server, not with --shards")
        if not 0 <= self.zenoh_port <= 65535:
            raise ValueError(f"--port must be in 0..65535, got {self.zenoh_port}")
        http_address(self.http)  # raises ValueError naming --http
        if self.seed < 0:
            raise ValueError(f"--seed must be >= 0, got {self.seed}")
        if not self.speed > 0:
            raise ValueError(f"--speed must be > 0, got {self.speed}")
        if self.uavs is not None and self.uavs < 1:
            raise ValueError(f"--uavs must be >= 1, got {self.uavs}")
        if self.duration_s is not None and not self.duration_s > 0:
            raise ValueError(f"--duration must be > 0, got {self.duration_s}")
        if self.cot_url is not None:
            from fusion_server.cot import parse_cot_url

            parse_cot_url(self.cot_url)
        if not self.status_interval_s >= 0:
            raise ValueError(f"--status-every must be >= 0 (0 = never), got {self.status_interval_s}")
        for name in ("startup_timeout_s", "stop_timeout_s"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be > 0, got {getattr(self, name)}")


def free_tcp_port(host: str = "127.0.0.1") -> int:
    """A TCP port that was free on ``host`` a moment ago (the OS picks it)."""
    with socket.socket() as sock:
        sock.bind((host, 0))
        return int(sock.getsockname()[1])


def check_can_listen(host: str, port: int, flag: str) -> None:
    """Raise OSError (one line naming ``flag``) when a TCP server could not listen on ``host:port`` now.

    The same bind the servers make (SO_REUSEADDR, as uvicorn), so a port in TIME_WAIT passes and one with a
    listener (another demo) does not; port 0 checks only that the host is an address of this machine.
    """
    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    with socket.socket(family, socket.SOCK_STREAM) as sock:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            sock.bind((host, port))
        except OSError as exc:
            value = f"{host}:{port}" if flag == "--http" else str(port)
            if exc.errno != errno.EADDRINUSE:
                raise OSError(f"{flag} {value}: cannot listen there ({exc.strerror or exc})") from None
            hint = "--http 127.0.0.1:0 picks a free port" if flag == "--http" else "leave --port out for a free one"
            raise OSError(f"{flag} {value}: in use (another demo or server?); {hint}") from None


def flying_uavs(scenario_name: str, count: int | None) -> list[str]:
    """The UAV ids of the scenario's first ``count`` flights (all when None).

    ValueError for an unknown scenario, one whose flights are not simultaneous (they would not share
    a world or a clock), or more UAVs than it has.
    """
    from sim.scenarios import SCENARIOS, get_scenario

    scenario = get_scenario(scenario_name)
    if not scenario.simultaneous:
        together = ", ".join(sorted(n for n, s in SCENARIOS.items() if s.simultaneous))
        raise ValueError(f"scenario {scenario_name!r} flies its UAVs one after another; the demo needs one whose "
                         f"UAVs fly at the same time: {together}")
    uavs = [spec.uav for spec in scenario.flights]
    if count is not None and count > len(uavs):
        raise ValueError(f"scenario {scenario_name!r} has {_counted(len(uavs), 'UAV')}, --uavs {count} asked for more")
    return uavs[:count] if count is not None else uavs


class Reaper:
    """A separate process that kills the registered process groups if this process dies first.

    grace_s: time between SIGTERM and SIGKILL; workdir: a temporary folder it then removes.
    """

    def __init__(self, grace_s: float, workdir: Path) -> None:
        self._proc = subprocess.Popen([sys.executable, "-c", _REAPER_SOURCE, str(grace_s), str(workdir)],
                                      stdin=subprocess.PIPE, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                                      start_new_session=True, text=True)

    def watch(self, pgid: int) -> None:
        """Kill process group ``pgid`` should this process die without calling :meth:`release`."""
        assert self._proc.stdin is not None
        self._proc.stdin.write(f"{pgid}\n")
        self._proc.stdin.flush()

    def release(self) -> None:
        """Everything was stopped cleanly: let the reaper exit without killing anything."""
        if self._proc.stdin is not None and not self._proc.stdin.closed:
            try:
                self._proc.stdin.write("done\n")
                self._proc.stdin.close()
            except OSError:
                pass
        try:
            self._proc.wait(timeout=5.0)
        except subprocess.TimeoutExpired:
            self._proc.kill()
            self._proc.wait()


class Child:
    """One `python -m uavmm ...` process in its own process group, stdout and stderr in a log file."""

    def __init__(self, name: str, argv: list[str], log_path: Path, env: dict[str, str]) -> None:
        self.name = name
        self.log_path = log_path
        with open(log_path, "wb") as out:
            self.proc = subprocess.Popen([sys.executable, "-m", "uavmm", *argv], stdin=subprocess.DEVNULL,
                                         stdout=out, stderr=subprocess.STDOUT, env=env, start_new_session=True)

    @property
    def pid(self) -> int:
        """The process id (= its process group id)."""
        return self.proc.pid

    def running(self) -> bool:
        """Whether the process has not exited yet."""
        return self.proc.poll() is None

    def log_text(self) -> str:
        """Everything the process wrote so far."""
        try:
            return self.log_path.read_text(errors="replace")
        except OSError:
            return ""

    def log_tail(self, lines: int = 20) -> str:
        """The last ``lines`` lines of its log, indented, for error messages."""
        return "\n".join("    " + line for line in self.log_text().splitlines()[-lines:])

    def wait_for(self, pattern: str, timeout_s: float, stop: threading.Event) -> re.Match[str] | None:
        """Wait (bounded) until the log matches ``pattern``; None if it exits, times out or ``stop`` is set."""
        regex = re.compile(pattern)
        deadline = time.monotonic() + timeout_s
        while True:
            match = regex.search(self.log_text())
            if match is not None:
                return match
            if not self.running() or time.monotonic() > deadline or stop.wait(0.05):
                return None

    def signal_group(self, signum: int) -> None:
        """Send ``signum`` to the whole process group (ignored when it is gone)."""
        try:
            os.killpg(self.proc.pid, signum)
        except OSError:
            pass


def stop_children(children: list[Child], timeout_s: float) -> None:
    """SIGTERM the children's process groups, wait up to ``timeout_s``, then SIGKILL what is left."""
    for child in children:
        if child.running():
            child.signal_group(signal.SIGTERM)
    deadline = time.monotonic() + timeout_s
    for child in children:
        try:
            child.proc.wait(timeout=max(0.0, deadline - time.monotonic()))
        except subprocess.TimeoutExpired:
            log.warning("%s did not stop within %.0f s of SIGTERM: killing it", child.name, timeout_s)
    for child in children:
        child.signal_group(signal.SIGKILL)  # also anything left in its group
        if child.running():
            child.proc.wait(timeout=5.0)


def _child_env() -> dict[str, str]:
    # The children import the same code as this process, installed or not.
    root = str(Path(__file__).resolve().parents[1])
    path = os.environ.get("PYTHONPATH")
    return {**os.environ, "PYTHONUNBUFFERED": "1", "PYTHONPATH": root if not path else f"{root}{os.pathsep}{path}"}


def _health(url: str) -> dict | None:
    try:
        with urllib.request.urlopen(url + "healthz", timeout=2.0) as response:
            return json.loads(response.read())
    except (OSError, ValueError):
        return None


def _counted(n: int, noun: str) -> str:
    """``n`` and its noun, plural unless one: '1 UAV flying', '3 UAVs', '0 global tracks'."""
    return f"{n} {noun}{'' if n == 1 else 's'}"


def _say(text: str) -> None:
    sys.stdout.write(f"uavmm demo: {text}\n")
    sys.stdout.flush()


def _warn(text: str) -> None:
    sys.stderr.write(f"uavmm demo: {text}\n")
    sys.stderr.flush()


def run_demo(options: DemoOptions, stop: threading.Event) -> int:
    """Start the server and the agents, report the map URL, run until ``stop`` or the duration, stop all.

    Returns the exit code: 0 after a requested stop, 1 when a process failed to start or died. OSError (before
    anything starts) when a port of ``options`` is taken or its host is not an address of this machine.
    """
    uavs = flying_uavs(options.scenario, options.uavs)
    # a taken port is a user error found before anything starts: one line, nothing to clean up
    check_can_listen(*http_address(options.http), "--http")
    if options.zenoh_port:
        check_can_listen("127.0.0.1", options.zenoh_port, "--port")
    workdir = Path(tempfile.mkdtemp(prefix="uavmm-demo-"))
    log_dir = options.log_dir or workdir
    log_dir.mkdir(parents=True, exist_ok=True)
    db = options.db or workdir / "fusion.sqlite"
    zenoh_port = options.zenoh_port or free_tcp_port()
    endpoint = f"tcp/127.0.0.1:{zenoh_port}"
    env = _child_env()
    common = ["--log-level", options.log_level]
    reaper = Reaper(options.stop_timeout_s, workdir)
    servers: list[Child] = []  # the fusion server, or the shards and the gateway
    agents: list[Child] = []
    failed: Child | None = None
    code = 1  # until everything came up
    try:
        for name, label, argv, pattern in _server_commands(options, endpoint, db):
            child = Child(name, [*common, *argv], log_dir / f"{name}.log", env)
            reaper.watch(child.pid)
            servers.append(child)
            match = child.wait_for(pattern, options.startup_timeout_s, stop)
            if match is None:
                if stop.is_set():
                    code = 0
                    return code
                hint = " (--http 127.0.0.1:0 picks a free port)" if "address already in use" in child.log_text() \
                    else ""
                _warn(f"the {label} did not start{hint} (log {child.log_path}):\n{child.log_tail()}")
                return code
        fusion = servers[-1]  # the process that serves the map
        assert match is not None  # its line, the last one waited for, names the map
        url = match.group(1)
        # an --http beyond loopback: the server generated a REST token and printed the page with it
        from fusion_server.http_auth import is_loopback_host

        page = None
        if not is_loopback_host(options.http.rpartition(":")[0].strip("[]")):
            page = fusion.wait_for(r"page: (http://\S+#token=[\w-]+)", 2.0, stop)
        if page is not None:
            url = page.group(1)
        if options.shards > 1:
            _say(f"{options.shards} fusion shards up (regions of zoom {DEMO_REGION_ZOOM}), zenoh {endpoint}, "
                 f"databases {db.with_name(db.stem + '-shard*.sqlite')}; the gateway serves the map")
        else:
            _say(f"fusion server up: zenoh {endpoint}, db {db}")
        _say(f"map: {url}")
        for index, uav in enumerate(uavs):
            child = Child(uav, [*common, "agent", "--uav-id", uav, "--connect", endpoint, "--no-multicast-scouting",
                                "--sim", options.scenario, "--seed", str(options.seed), "--uav-index", str(index),
                                "--speed", f"{options.speed:g}", "--loop"], log_dir / f"agent-{uav}.log", env)
            reaper.watch(child.pid)
            agents.append(child)
        for child in agents:
            if child.wait_for(r" up: ", options.startup_timeout_s, stop) is None:
                if stop.is_set():
                    code = 0
                    return code
                _warn(f"agent {child.name} did not start (log {child.log_path}):\n{child.log_tail()}")
                return code
        _say(f"{_counted(len(agents), 'UAV')} flying ({', '.join(uavs)}; scenario {options.scenario}, "
             f"seed {options.seed}); logs in {log_dir}; Ctrl-C to stop")
        code = 0
        deadline = None if options.duration_s is None else time.monotonic() + options.duration_s
        next_status = time.monotonic() + options.status_interval_s if options.status_interval_s > 0 else None
        while not stop.wait(0.2):
            now = time.monotonic()
            failed = next((c for c in (*servers, *agents) if not c.running()), None)
            if failed is not None:
                _warn(f"{failed.name} exited unexpectedly (code {failed.proc.returncode}; log {failed.log_path}):\n"
                      f"{failed.log_tail()}")
                code = 1
                break
            if deadline is not None and now >= deadline:
                break
            if next_status is not None and now >= next_status:
                next_status = now + options.status_interval_s
                health = _health(url)
                if health is not None:
                    _warn(f"{_counted(health['uavs_online'], 'UAV')} online, "
                          f"{_counted(health['joint_tiles'], 'joint tile')}, "
                          f"{_counted(health['global_tracks'], 'global track')}")
        return code
    finally:
        stop_children(agents, options.stop_timeout_s)  # agents first: their liveliness tokens go cleanly
        stop_children(servers[::-1], options.stop_timeout_s)  # the gateway before the shards
        reaper.release()
        if code == 0:
            shutil.rmtree(workdir, ignore_errors=True)
        else:
            _warn(f"kept {workdir} for inspection")


def _server_commands(options: DemoOptions, endpoint: str, db: Path) -> list[tuple[str, str, list[str], str]]:
    """(name, what it is, uavmm arguments, line that says it is up) of each server process, in start order: the
    fusion server; or the shards (shard 0 the router the others and the agents connect to) and the
    gateway (whose line names the map)."""
    map_line = r"map: (http://\S+)"
    if options.shards == 1:
        cot = ["--cot-url", options.cot_url] if options.cot_url else []
        return [("fusion", "fusion server", ["fusion", "--listen", endpoint, "--http", options.http, "--db", str(db),
                                   "--no-multicast-scouting", *cot], map_line)]
    n, zoom = options.shards, str(DEMO_REGION_ZOOM)
    commands = []
    for k in range(n):
        # shard 0 is the router; the others and the gateway are its clients (everything through it, as
        # with a zenohd router on a ground station: no peer-to-peer links to get wrong)
        where = ["--listen", endpoint] if k == 0 else ["--mode", "client", "--connect", endpoint]
        db_k = str(db.with_name(f"{db.stem}-shard{k}.sqlite"))
        commands.append((f"fusion-shard{k}", f"fusion shard {k}/{n}",
                         ["fusion", "--shard", f"{k}/{n}", "--region-zoom", zoom, *where, "--db", db_k, "--no-http",
                          "--no-multicast-scouting"], r"uavmm fusion: shard "))
    commands.append(("gateway", "gateway", ["gateway", "--shards", str(n), "--region-zoom", zoom, "--mode", "client",
                                            "--connect", endpoint, "--http", options.http, "--no-multicast-scouting"],
                     map_line))
    return commands


def register(sub: argparse._SubParsersAction) -> None:
    """Add the ``demo`` subcommand."""
    p = sub.add_parser(
        "demo", help="fusion server + simulated agents on this machine; prints the live map URL",
        description="Start a fusion server and one agent per UAV of a simulated scenario (three by default) as "
                    "separate processes talking Zenoh over loopback, print the map page's URL and run until "
                    "Ctrl-C or --duration; then stop every process. See docs/demo.md.",
    )
    p.add_argument("--http", default="127.0.0.1:8000", metavar="HOST:PORT",
                   help="address of the REST API and map page (127.0.0.1:8000; port 0 picks a free one)")
    p.add_argument("--port", type=int, default=0,
                   help="Zenoh TCP port of the fusion server on 127.0.0.1 (default 0: a free port)")
    p.add_argument("--db", type=Path, default=None,
                   help="SQLite file of the fusion server (default: a temporary file, deleted at exit)")
    p.add_argument("--log-dir", type=Path, default=None,
                   help="folder for the processes' logs (default: a temporary folder, deleted at exit)")
    p.add_argument("--scenario", default=DEFAULT_SCENARIO,
                   help=f"simulator scenario whose UAVs fly at the same time ({DEFAULT_SCENARIO}; or coop)")
    p.add_argument("--uavs", type=int, default=None, help="how many of the scenario's UAVs fly (default: all)")
    p.add_argument("--seed", type=int, default=0, help="simulation seed, shared by the agents (0)")
    p.add_argument("--speed", type=float, default=1.0, help="playback speed of the flights (1 = real time)")
    p.add_argument("--duration", type=float, default=None, metavar="S",
                   help="stop S seconds after the agents are up (default: run until Ctrl-C)")
    p.add_argument("--startup-timeout", type=float, default=60.0, metavar="S",
                   help="longest wait for each process to come up (60)")
    p.add_argument("--stop-timeout", type=float, default=10.0, metavar="S",
                   help="grace between SIGTERM and SIGKILL when stopping the processes (10)")
    p.add_argument("--status-every", type=float, default=10.0, metavar="S",
                   help="print a status line to stderr this often (10; 0 = never)")
    p.add_argument("--cot-url", default=None, metavar="URL",
                   help="also send Cursor-on-Target events to TAK (udp://HOST:PORT or tcp://HOST:PORT; see "
                        "uavmm fusion --help)")
    p.add_argument("--shards", type=int, default=1, metavar="N",
                   help="run N fusion shards (uavmm fusion --shard K/N) and a uavmm gateway serving the map "
                        "instead of one fusion server (1; docs/fusion.md, 'Sharding')")
    p.set_defaults(handler=_run_demo_command)


def options_from_args(args: argparse.Namespace) -> DemoOptions:
    """DemoOptions from the parsed flags; ValueError on bad values."""
    return DemoOptions(
        http=args.http, zenoh_port=args.port, db=args.db, log_dir=args.log_dir, scenario=args.scenario,
        seed=args.seed, speed=args.speed, uavs=args.uavs, duration_s=args.duration,
        startup_timeout_s=args.startup_timeout, stop_timeout_s=args.stop_timeout,
        status_interval_s=args.status_every, log_level=args.log_level, cot_url=args.cot_url, shards=args.shards,
    )


def _run_demo_command(args: argparse.Namespace) -> int:
    options = options_from_args(args)
    flying_uavs(options.scenario, options.uavs)  # a bad scenario fails before any process starts
    stop = stop_on_signals(log, (signal.SIGINT, signal.SIGTERM, signal.SIGHUP))
    return run_demo(options, stop)
