"""The `uavmm` entry point: --version, and the global flags accepted after the subcommand as well."""

from __future__ import annotations

import argparse
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

from uavmm.cli import build_parser, main

REPO = Path(__file__).resolve().parents[1]


def _subparsers(parser: argparse.ArgumentParser, path: tuple[str, ...] = ()):
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, sub in action.choices.items():
                yield (*path, name), sub
                yield from _subparsers(sub, (*path, name))


def test_version_is_the_packages():
    declared = re.search(r'^version = "([^"]+)"', (REPO / "pyproject.toml").read_text(), re.M).group(1)
    proc = subprocess.run([sys.executable, "-m", "uavmm", "--version"], cwd=REPO, capture_output=True, text=True,
                          timeout=60)
    assert proc.returncode == 0 and proc.stdout.strip() == f"uavmm {declared}"


def test_version_after_a_subcommand_too(capsys):
    with pytest.raises(SystemExit) as stop:
        build_parser().parse_args(["secure", "init", "--version"])  # before the required arguments are missed
    assert stop.value.code == 0
    assert capsys.readouterr().out.strip().startswith("uavmm ")


def test_every_subcommand_takes_log_level_and_version():
    names = []
    for path, sub in _subparsers(build_parser()):
        assert any("--log-level" in a.option_strings for a in sub._actions), path
        assert any("--version" in a.option_strings for a in sub._actions), path
        names.append(" ".join(path))
    assert {"fusion", "agent", "demo", "secure init", "boost", "track"} <= set(names)


@pytest.mark.parametrize(("argv", "level"), [
    (["fusion"], "WARNING"),
    (["--log-level", "DEBUG", "fusion"], "DEBUG"),
    (["fusion", "--log-level", "INFO"], "INFO"),
    (["--log-level", "DEBUG", "fusion", "--log-level", "ERROR"], "ERROR"),  # the later one wins
])
def test_log_level_before_or_after_the_subcommand(argv, level):
    assert build_parser().parse_args(argv).log_level == level


def test_log_level_after_the_subcommand_configures_logging():
    code = ("import logging, sys; from uavmm.cli import main; "
            "sys.exit(main(['sim', '--list', '--log-level', 'DEBUG']) or logging.getLogger().level)")
    proc = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True, timeout=60)
    assert proc.returncode == 10, proc.stderr  # logging.DEBUG


def test_a_bad_log_level_after_the_subcommand_is_refused():
    proc = subprocess.run([sys.executable, "-m", "uavmm", "sim", "--list", "--log-level", "LOUD"], cwd=REPO,
                          capture_output=True, text=True, timeout=60)
    assert proc.returncode == 2 and "invalid choice: 'LOUD'" in proc.stderr


def test_eval_without_its_baselines_says_how_to_install_them():
    code = ("import sys; sys.modules['norfair'] = None; sys.modules['trackeval'] = None; "
            "from uavmm.cli import main; "
            "sys.exit(main(['eval', '--tasks', 'tracking', '--scenarios', 'grass', '--seeds', '0', '--frames', '20']))")
    proc = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 2
    (line,) = [ln for ln in proc.stderr.splitlines() if "error" in ln]
    assert "needs the norfair package" in line and "pip install --no-deps trackeval==1.3.0 norfair==2.3.0" in line
    assert "Traceback" not in proc.stderr
    # the same for the metrics alone
    code = ("import sys; sys.modules['trackeval'] = None; from sim.track_eval import _metrics; _metrics()")
    proc = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True, timeout=60)
    assert "ImportError: tracking metrics (HOTA, MOTA, IDF1 by TrackEval) needs the trackeval package" in proc.stderr


def test_the_pinned_baselines_match_the_message():
    from sim.track_eval import NODEPS_INSTALL

    pinned = [ln.split("#")[0].strip() for ln in (REPO / "requirements-nodeps.txt").read_text().splitlines()]
    for requirement in ("trackeval==1.3.0", "norfair==2.3.0"):
        assert requirement in pinned and requirement in NODEPS_INSTALL


@pytest.mark.parametrize("argv", [
    ["fit-size-filter", "--frames", "{tmp}/images.json", "--camera", "dji-mavic2-pro", "--out", "{tmp}/no/such/f.json"],
    ["bench", "geo", "--quick", "--json", "{tmp}/no/such/bench.json"],
    ["anomaly", "--frames", "{tmp}/images.json", "--camera", "dji-mavic2-pro", "--out", "{tmp}/no/such/rois.json"],
    ["boost", "--frames", "{tmp}/images.json", "--candidates", "{tmp}/p.json", "--camera", "dji-mavic2-pro",
     "--out", "{tmp}/no/such/results.json"],
    ["tune", "--frames", "{tmp}/images.json", "--candidates", "{tmp}/p.json", "--camera", "dji-mavic2-pro",
     "--out", "{tmp}/no/such/params.json"],
])
def test_a_missing_output_folder_is_named_before_any_work(argv, tmp_path, capsys):
    from uavmm.cli import main

    # the input does not exist either: the output folder is checked first, so no work is done and lost
    assert main([a.format(tmp=tmp_path) for a in argv]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [f"uavmm {argv[0]}: error: output directory {tmp_path / 'no' / 'such'} does not exist "
                   f"(for {tmp_path / 'no' / 'such' / argv[-1].rsplit('/', 1)[1]})"]


def test_eval_coop_takes_the_scenarios_whose_uavs_fly_at_once(tmp_path, capsys):
    import json

    from uavmm.cli import main

    assert main(["eval", "--tasks", "coop", "--scenarios", "grass,sea", "--out", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert "none of --scenarios flies its UAVs at once" in err and "coop-slope" in err
    # a real (short) run: grass flies one UAV at a time and is left out; coop's noise defaults to x1
    (tmp_path / "anchored.json").write_text(json.dumps({"correction_anchor_s": 7.5}))
    assert main(["eval", "--config", str(tmp_path / "anchored.json"), "--out", str(tmp_path)]) == 2
    assert "--config goes with --real or --tasks coop" in capsys.readouterr().err
    assert main(["eval", "--tasks", "coop", "--scenarios", "grass,coop-slope", "--seeds", "0", "--frames", "20",
                 "--config", str(tmp_path / "anchored.json"), "--out", str(tmp_path / "eval")]) == 0
    report = json.loads((tmp_path / "eval" / "coop" / "report.json").read_text())
    assert report["scenarios"] == ["coop-slope"] and report["noise_scales"] == [1.0]
    assert report["config_overrides"] == {"correction_anchor_s": 7.5}  # --config reaches every variant
    assert {s["variant"] for s in report["summary"]} >= {"own memory map", "own memory map + DEM"}
    assert "## Terrain: flat earth vs --dem" in capsys.readouterr().out


def test_an_unknown_flag_gets_the_subcommands_usage_and_one_error_line(capsys):
    """`uavmm detect ... --bogus` printed the top level's usage (`uavmm [-h] ... COMMAND`), not detect's."""
    with pytest.raises(SystemExit) as exit_info:
        main(["detect", "x.mp4", "--telemetry", "t.srt", "--model", "m.onnx", "--camera", "c.json", "--out", "o",
              "--bogus", "1"])
    assert exit_info.value.code == 2
    err = capsys.readouterr().err
    assert err.startswith("usage: uavmm detect ") and err.rstrip().endswith(
        "uavmm detect: error: unrecognized arguments: --bogus 1")
    with pytest.raises(SystemExit):
        main(["--bogus"])
    assert capsys.readouterr().err.rstrip().endswith("uavmm: error: unrecognized arguments: --bogus")
    with pytest.raises(SystemExit):
        main(["secure", "init", "fleet", "--uavs", "u1", "--bogus"])
    err = capsys.readouterr().err
    assert err.startswith("usage: uavmm secure init ") and "uavmm secure init: error: unrecognized" in err


def test_a_reader_that_leaves_the_pipe_ends_the_command_quietly(monkeypatch, capsys):
    """`uavmm eval --list-domains | head -2` ended with 'uavmm eval: error: [Errno 32] Broken pipe'."""
    import os

    read_fd, write_fd = os.pipe()
    os.close(read_fd)  # the reader has left
    stdout = os.fdopen(write_fd, "w", buffering=1)
    monkeypatch.setattr(sys, "stdout", stdout)
    try:
        assert main(["eval", "--list-domains"]) == 1
        stdout.write("after: goes to the null device\n")  # the interpreter's last flush does not fail either
        stdout.flush()
    finally:
        monkeypatch.undo()
        stdout.close()
    assert "Broken pipe" not in capsys.readouterr().err


def test_a_broken_pipe_other_than_stdout_is_an_error_not_silence(monkeypatch, capsys):
    """The quiet ending is for a reader that left stdout; a child process's pipe breaking is said."""
    import uavmm.cli

    def handler(args):
        raise BrokenPipeError(32, "Broken pipe")

    parser = uavmm.cli.build_parser()
    args = parser.parse_args(["eval", "--list-domains"])
    monkeypatch.setattr(argparse.ArgumentParser, "parse_known_args", lambda self, argv=None: (args, []))
    monkeypatch.setattr(args, "handler", handler)
    with open(os.devnull, "w") as healthy:  # stdout itself is fine
        monkeypatch.setattr(sys, "stdout", healthy)
        assert main(["eval", "--list-domains"]) == 2
    assert "uavmm eval: error: [Errno 32] Broken pipe" in capsys.readouterr().err


@pytest.mark.parametrize(("source", "flags", "said"), [
    (["--sim", "coop"], ["--video-fps", "30"], "--video-fps goes with --video, not --sim"),
    (["--dataset", "d"], ["--pitch-deg", "45", "--height-m", "30"],
     "--pitch-deg, --height-m go with --video, not --dataset"),
])
def test_agent_refuses_video_flags_beside_another_source(capsys, source, flags, said):
    """They did nothing, silently: a user who gave --pitch-deg with --dataset thought the pitch was applied."""
    assert main(["agent", "--uav-id", "u1", "--connect", "tcp/127.0.0.1:1", *source, *flags]) == 2
    assert f"uavmm agent: error: {said}" in capsys.readouterr().err


@pytest.mark.parametrize("module", ["uavmm", "uavmm.cli"])
def test_a_command_modules_refusal_is_one_line_and_exit_2_however_the_cli_is_started(tmp_path, module):
    """`python -m uavmm.cli` runs cli.py as __main__: the CliError a cmd_* module raises is uavmm.cli's, which that
    module's own main did not catch (a traceback and exit 1)."""
    frames = tmp_path / "frames.json"
    frames.write_text("{}")
    (tmp_path / "camera.json").write_text("{}")
    proc = subprocess.run([sys.executable, "-m", module, "tune", "--frames", str(frames), "--candidates", str(frames),
                           "--camera", str(tmp_path / "camera.json"), "--out", str(frames)],
                          cwd=REPO, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 2 and "Traceback" not in proc.stderr, proc.stderr
    assert proc.stderr.strip().splitlines() == [proc.stderr.strip()] and "give another output path" in proc.stderr
    assert frames.read_text() == "{}"
