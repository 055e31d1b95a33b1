"""The `uavmm` command line: one entry point, a subcommand per job (DESIGN.md 5).

Argument parsing lives here; each handler imports its module lazily and calls a typed main().
"""

from __future__ import annotations

import argparse
import logging
import sys
from collections.abc import Callable, Sequence
from pathlib import Path

log = logging.getLogger("uavmm")

Handler = Callable[[argparse.Namespace], int]


class CliError(Exception):
    """A user error: printed as one line on stderr, exit code 2."""


# --------------------------------------------------------------------------------------------- sim

def _add_sim(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "sim", help="write a simulated dataset (SeaDronesSee layout)",
        description="Simulate UAV flights over people/swimmers and write images.json, camera.json, "
                    "pre_nms.json and truth.json to --out. `uavmm sim --list` lists the scenarios.",
    )
    p.add_argument("scenario", nargs="?", help="scenario name (see --list)")
    p.add_argument("--list", action="store_true", help="list the scenarios and exit")
    p.add_argument("--out", type=Path, help="output directory")
    p.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    p.add_argument("--frames", type=int, default=None, help="frames per video (default: the scenario's)")
    p.add_argument("--noise-scale", type=float, default=1.0,
                   help="multiply the scenario's telemetry noise levels (default 1.0)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(handler=_run_sim)


def _run_sim(args: argparse.Namespace) -> int:
    from sim.scenarios import SCENARIOS

    if args.list:
        for name, scenario in SCENARIOS.items():
            print(f"{name:10s} {scenario.description}")
        return 0
    if not args.scenario:
        raise CliError("sim: give a SCENARIO (or --list)")
    if args.out is None:
        raise CliError("sim: --out DIR is required")
    if args.seed < 0:
        raise CliError(f"sim: --seed must be >= 0, got {args.seed}")
    if args.frames is not None and args.frames < 1:
        raise CliError(f"sim: --frames must be >= 1, got {args.frames}")
    from sim.dataset import write_dataset

    summary = write_dataset(args.scenario, args.out, seed=args.seed, frames=args.frames,
                            noise_scale=args.noise_scale, progress=not args.quiet)
    print(f"wrote {args.out}: " + ", ".join(f"{k}={v}" for k, v in summary.items()))
    return 0


# --------------------------------------------------------------------------------------------- bench

def _add_bench(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "bench", help="run the performance benchmarks",
        description="Run benchmarks/ and print each figure beside a baseline measured in the same run.",
    )
    p.add_argument("names", nargs="*", help="benchmarks to run (default: all); see --list")
    p.add_argument("--list", action="store_true", help="list the benchmarks and exit")
    p.add_argument("--quick", action="store_true", help="smaller sizes, for a smoke run")
    p.add_argument("--json", type=Path, default=None, help="also write the results as JSON")
    p.set_defaults(handler=_run_bench)


def _run_bench(args: argparse.Namespace) -> int:
    from benchmarks import BENCHMARK_MODULES, load_benchmark, run_benchmarks

    if args.list:
        for name in BENCHMARK_MODULES:
            print(f"{name:14s} {load_benchmark(name).DESCRIPTION}")
        return 0
    try:
        rows = run_benchmarks(args.names or None, quick=args.quick, json_path=args.json)
    except ValueError as exc:
        raise CliError(str(exc)) from None
    from benchmarks import format_table

    print(format_table(rows))
    return 0


# --------------------------------------------------------------------------------------------- main

COMMANDS: tuple[Callable[[argparse._SubParsersAction], None], ...] = (_add_sim, _add_bench)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="uavmm",
        description="uav-memory-maps: metadata-aware detection, tracking and cooperative mapping on drones.",
    )
    parser.add_argument("--log-level", default="WARNING",
                        choices=["DEBUG", "INFO", "WARNING", "ERROR"], help="logging level (stderr)")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for add in COMMANDS:
        add(sub)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    logging.basicConfig(level=args.log_level, format="%(asctime)s %(levelname)s %(name)s: %(message)s",
                        stream=sys.stderr)
    if not getattr(args, "handler", None):
        parser.print_help(sys.stderr)
        return 2
    try:
        return int(args.handler(args) or 0)
    except (CliError, ValueError, OSError) as exc:
        print(f"uavmm {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return 130


if __name__ == "__main__":
    sys.exit(main())
