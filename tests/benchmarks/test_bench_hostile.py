"""`uavmm bench hostile` builds its plain client sessions' config (it imported a helper that had moved) and reads the
server's peak memory from the kernel's high-water mark."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from benchmarks.bench_hostile import _session_config


def test_the_plain_client_config_connects_to_the_endpoint_without_shared_memory():
    conf = _session_config("tcp/127.0.0.1:7447", None, "mallory")
    assert json.loads(conf.get_json("mode")) == "client"
    assert json.loads(conf.get_json("connect/endpoints")) == ["tcp/127.0.0.1:7447"]
    assert json.loads(conf.get_json("transport/shared_memory/enabled")) is False


@pytest.mark.skipif(not Path("/proc/self/clear_refs").exists(), reason="needs Linux's /proc/PID/clear_refs")
def test_the_peak_rss_counts_a_spike_between_two_polls():
    """The flood's peak RSS was the largest of VmRSS polls 0.1 s apart: a spike between two polls was missed."""
    from benchmarks.bench_hostile import _reset_peak_rss, _rss_mb

    child = subprocess.Popen([sys.executable, "-c", (
        "import sys, numpy as np\n"
        "sys.stdin.readline()\n"
        "a = np.ones(200 * 2**20 // 8); del a\n"  # 200 MB for a moment, then given back
        "print('done', flush=True)\n"
        "sys.stdin.readline()\n")], stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    try:
        assert _reset_peak_rss(child.pid)
        before = _rss_mb(child.pid)
        child.stdin.write("go\n")
        child.stdin.flush()
        assert child.stdout.readline() == "done\n"
        assert _rss_mb(child.pid) < before + 100  # a poll now sees nothing of it
        assert _rss_mb(child.pid, "VmHWM") > before + 150
    finally:
        child.kill()
        child.wait(timeout=10)
