"""`uavmm bench hostile` builds its plain client sessions' config (it imported a helper that had moved)."""

from __future__ import annotations

import json

from benchmarks.bench_hostile import _session_config


def test_the_plain_client_config_connects_to_the_endpoint_without_shared_memory():
    conf = _session_config("tcp/127.0.0.1:7447", None, "mallory")
    assert json.loads(conf.get_json("mode")) == "client"
    assert json.loads(conf.get_json("connect/endpoints")) == ["tcp/127.0.0.1:7447"]
    assert json.loads(conf.get_json("transport/shared_memory/enabled")) is False
