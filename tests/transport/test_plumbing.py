"""The shared Zenoh plumbing with real sessions on loopback: publishers, guarded callbacks, retries."""

from __future__ import annotations

import json
import logging
import threading
import time

import pytest
import zenoh

from tests.netutil import free_port, wait_until
from transport.guard import RateLimitedLog, guarded
from transport.publishers import PublisherCache
from transport.session import config_value, open_session, remote_ids


def _config(*, listen: int | None = None, connect: int | None = None) -> zenoh.Config:
    conf = zenoh.Config()
    conf.insert_json5("scouting/multicast/enabled", "false")
    if listen is not None:
        conf.insert_json5("listen/endpoints", json.dumps([f"tcp/127.0.0.1:{listen}"]))
    if connect is not None:
        conf.insert_json5("connect/endpoints", json.dumps([f"tcp/127.0.0.1:{connect}"]))
    return conf


def _until_routed(client: zenoh.Session, key: str, seen: list) -> None:
    """Put on key until the server's subscriber (which appends to seen) got one: declarations travel."""
    wait_until(lambda: client.put(key, b"warm-up") or seen, what=f"the subscriber on {key} to be reachable")
    time.sleep(0.2)  # warm-ups still in flight arrive before the clear
    seen.clear()


@pytest.fixture
def pair():
    port = free_port()
    server = zenoh.open(_config(listen=port))
    client = zenoh.open(_config(connect=port))
    wait_until(lambda: remote_ids(client), what="the client's connection")
    yield server, client
    client.close()
    server.close()


def test_publisher_cache_reuses_bounds_and_delivers(pair):
    server, client = pair
    got: list[tuple[str, bytes, bytes | None]] = []
    sub = server.declare_subscriber("t/**", lambda s: got.append(
        (str(s.key_expr), s.payload.to_bytes(), None if s.attachment is None else s.attachment.to_bytes())))
    _until_routed(client, "t/warm", got)
    cache = PublisherCache(client, max_publishers=2)
    first = cache.get("t/a")
    assert cache.get("t/a") is first and len(cache) == 1
    cache.put("t/a", b"1", attachment=b"zid")
    cache.put("t/b", b"2")
    cache.put("t/c", b"3")  # evicts t/a, the least recently used
    assert len(cache) == 2 and "t/a" not in cache and "t/c" in cache
    cache.put("t/a", b"4")  # declared again on demand
    wait_until(lambda: len(got) == 4, what="four samples")
    assert got == [("t/a", b"1", b"zid"), ("t/b", b"2", None), ("t/c", b"3", None), ("t/a", b"4", None)]
    cache.drop("t/a")
    cache.drop("t/never")  # unknown: no-op
    assert "t/a" not in cache
    cache.clear()
    assert len(cache) == 0
    del sub


def test_publisher_cache_rejects_a_bad_bound(pair):
    with pytest.raises(ValueError, match="max_publishers"):
        PublisherCache(pair[1], max_publishers=0)


def test_a_guarded_subscriber_survives_a_raising_handler_and_counts_it(pair, caplog):
    server, client = pair
    errors: list[int] = []
    seen: list[bytes] = []

    def handler(sample: zenoh.Sample) -> None:
        payload = sample.payload.to_bytes()
        if payload == b"boom":
            raise RuntimeError("bug in the handler")
        seen.append(payload)

    logger = logging.getLogger("tests.transport")
    sub = server.declare_subscriber("g/**", guarded(handler, logger, "a sample", lambda: errors.append(1)))
    _until_routed(client, "g/warm", seen)
    with caplog.at_level(logging.ERROR, logger="tests.transport"):
        for payload in (b"ok1", b"boom", b"ok2"):
            client.put("g/x", payload)
        wait_until(lambda: len(seen) == 2, what="both good samples")
    assert seen == [b"ok1", b"ok2"] and errors == [1]
    assert "internal error handling a sample" in caplog.text and "bug in the handler" in caplog.text
    del sub


def test_guarded_logs_a_failing_error_counter_too(caplog):
    def counter() -> None:
        raise ValueError("counter broke")

    run = guarded(lambda _: 1 / 0, logging.getLogger("tests.transport"), "an item", counter)
    with caplog.at_level(logging.ERROR, logger="tests.transport"):
        run(None)  # neither exception escapes
    assert [r.getMessage() for r in caplog.records] == ["internal error handling an item",
                                                        "internal error counting an internal error"]


def test_rate_limited_log_suppresses_per_reason_and_reports_the_count(caplog):
    limited = RateLimitedLog(logging.getLogger("tests.transport"), interval_s=0.2)
    with caplog.at_level(logging.WARNING, logger="tests.transport"):
        assert limited.warning("a", "first %s", "a")
        assert not limited.warning("a", "second %s", "a")
        assert not limited.warning("a", "third %s", "a")
        assert limited.warning("b", "other reason")  # reasons are independent
        assert limited.suppressed("a") == 2
        time.sleep(0.25)
        assert limited.warning("a", "fourth %s", "a")
    messages = [r.getMessage() for r in caplog.records]
    assert messages == ["first a", "other reason", "fourth a (2 more like it suppressed)"]
    assert limited.suppressed("a") == 0


def test_open_session_retries_until_the_router_is_up():
    port = free_port()
    conf = _config(connect=port)
    conf.insert_json5("mode", '"client"')  # a client cannot open without its router
    opened: list[zenoh.Session | None] = []
    thread = threading.Thread(target=lambda: opened.append(open_session(conf, retry_s=0.2, timeout_s=20.0)))
    thread.start()
    time.sleep(0.5)
    assert not opened  # still retrying
    router = zenoh.open(_config(listen=port))
    try:
        thread.join(timeout=20.0)
        assert opened and opened[0] is not None
        assert wait_until(lambda: remote_ids(opened[0]), what="the router connection")
        opened[0].close()
    finally:
        router.close()


def test_open_session_gives_up_on_stop_or_timeout():
    conf = _config(connect=free_port())
    conf.insert_json5("mode", '"client"')
    assert open_session(conf, retry_s=0.1, timeout_s=0.3) is None
    stop = threading.Event()
    stop.set()
    assert open_session(conf, stop, retry_s=0.1) is None


def test_config_value_reads_json_and_none_when_unset():
    conf = _config(connect=7447)
    assert config_value(conf, "connect/endpoints") == ["tcp/127.0.0.1:7447"]
    assert config_value(conf, "transport/auth/usrpwd/user") is None
    assert config_value(conf, "no/such/key") is None
