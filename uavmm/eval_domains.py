"""`uavmm eval --domains ...`: the evaluation domains (`sim.domains`) and, with `--tasks coop`, the cooperative
domains (`sim.coop_domains`); the parser is `uavmm.cli`'s eval command. Bad values raise ValueError, which
`uavmm.cli.main` prints as the command's error (exit 2)."""

from __future__ import annotations

import argparse
import math
from pathlib import Path
from typing import TYPE_CHECKING

from uavmm.csv_args import csv_list

if TYPE_CHECKING:
    from agent.pipeline_config import PipelineConfig
    from agent.size_filter import SizeFilter

__all__ = ["coop_noise_scale", "coop_params", "noise_scales", "require_out_dir", "run_domain_eval_command"]


def coop_params(path: Path | None) -> tuple[PipelineConfig | None, SizeFilter | None]:
    """`--config` of `uavmm eval --tasks coop` (scenarios or domains): (its pipeline settings, the fitted size
    filter a `uavmm tune` parameters file carries); (None, None) without one. Until 28 Nov 2026 the size
    filter was dropped here (and the whole file ignored with --domains)."""
    if path is None:
        return None, None
    from agent.boost import load_params

    return load_params(path)


def run_domain_eval_command(args: argparse.Namespace) -> int:
    """`uavmm eval --domains ...` (and `--list-domains`): issue 15's domains, or with `--tasks coop` the
    cooperative ones."""
    from sim.domain_eval import run_domain_eval
    from sim.domains import domain_table, resolve_domains
    from sim.evaluate import stderr_progress

    tasks = tuple(csv_list(args.tasks or "detection,tracking", str, "--tasks"))
    if "coop" in tasks:
        if tasks != ("coop",):
            raise ValueError(f"--tasks: with --domains coop runs alone (the cooperative domains); "
                             f"got {', '.join(tasks)}")
        return _run_coop_domain_eval(args)
    if args.list_domains:
        print(domain_table())
        return 0
    given = {"--frames": args.frames is not None, "--scenarios": args.scenarios is not None,
             "--ablations": args.ablations}
    ignored = [flag for flag, was_given in given.items() if was_given]
    if ignored:  # silently dropped until 30 Nov 2026: `--frames 30` ran the domain's full clip
        raise ValueError(f"{', '.join(ignored)}: not used with --domains (each domain has its clip length; --full "
                         "makes them 5x longer)")
    try:
        domains = resolve_domains(csv_list(args.domains, str, "--domains"))
    except ValueError as exc:
        raise ValueError(f"--domains: {exc}") from None
    seeds = _seeds(args.seeds if args.seeds is not None else "0,1,2")
    unknown = sorted(set(tasks) - {"detection", "tracking"})
    if unknown:
        raise ValueError(f"--tasks: with --domains valid tasks are detection, tracking; got {', '.join(unknown)}")
    noise = tuple(noise_scales(args.noise_scales or "1,2"))
    if "tracking" in tasks and 1.0 not in noise:  # until 30 Nov 2026: exit 0 and a report without tracking
        raise ValueError(f"--noise-scales {args.noise_scales}: tracking runs at noise x1 only; add 1 or give "
                         "--tasks detection")
    out = args.out if args.out != Path("out/eval") else Path("out/eval-domains")
    require_out_dir(out)
    report = run_domain_eval(domains, seeds, noise_scales=noise, tasks=tasks, full=args.full, out_dir=out,
                             progress=stderr_progress)
    print((out / "report.md").read_text())
    print(f"reports: {out / 'report.md'}, {out / 'report.json'} ({report['seconds']} s)")
    return 0


def _run_coop_domain_eval(args: argparse.Namespace) -> int:
    from sim.coop_domain_eval import run_coop_domain_eval
    from sim.coop_domains import coop_domain_table, resolve_coop_domains
    from sim.evaluate import stderr_progress

    if args.list_domains:
        print(coop_domain_table())
        return 0
    if args.full:
        raise ValueError("--full: the cooperative domains have one clip length")
    try:
        domains = resolve_coop_domains(csv_list(args.domains, str, "--domains"))
    except ValueError as exc:
        raise ValueError(f"--domains: {exc}") from None
    seeds = _seeds(args.seeds if args.seeds is not None else "0,1,2")
    noise = coop_noise_scale(args.noise_scales)
    out = args.out if args.out != Path("out/eval") else Path("out/eval-coop-domains")
    require_out_dir(out)
    config, size_filter = coop_params(args.pipeline_config)  # every variant's settings
    report = run_coop_domain_eval(domains, seeds, noise_scale=noise, out_dir=out, progress=stderr_progress,
                                  config=config, size_filter=size_filter)
    print((out / "report.md").read_text())
    print(f"reports: {out / 'report.md'}, {out / 'report.json'} ({report['seconds']} s)")
    return 0


def coop_noise_scale(text: str | None) -> float:
    """The one telemetry noise multiplier of `--tasks coop --domains` (`--noise-scales`, default 1)."""
    noise = csv_list(text or "1", float, "--noise-scales")
    if len(noise) != 1:
        raise ValueError(f"--noise-scales: the cooperative domains run at one noise scale, got {text}")
    if not (math.isfinite(noise[0]) and noise[0] >= 0):
        raise ValueError("--noise-scales must be a finite number >= 0")
    return noise[0]


def noise_scales(text: str) -> list[float]:
    """`--noise-scales`: telemetry noise multipliers, each a finite number >= 0 (0: exact telemetry); checked before
    any work (a bad one after the first failed only when its turn came, with the good ones' work lost)."""
    noise = csv_list(text, float, "--noise-scales")
    bad = [v for v in noise if not (math.isfinite(v) and v >= 0)]
    if bad:
        raise ValueError(f"--noise-scales: each must be a finite number >= 0, got {bad[0]:g}")
    return noise


def require_out_dir(out: Path) -> None:
    """ValueError naming `--out` when it, or a folder above it, is a file, and naming the folder when it holds files
    that are not an earlier eval's (`sim.evaluate.require_eval_folder`): found before the work, not by the report's
    write after it."""
    from sim.evaluate import require_eval_folder

    for path in (out, *out.parents):
        if path.exists():
            if not path.is_dir():
                what = "" if path == out else f" ({path} is a file)"
                raise ValueError(f"--out {out}: not a folder{what}: give a folder for the reports")
            require_eval_folder(out)
            return


def _seeds(text: str) -> list[int]:
    seeds = csv_list(text, int, "--seeds")
    if any(s < 0 for s in seeds):
        raise ValueError("--seeds must be >= 0")
    return seeds
