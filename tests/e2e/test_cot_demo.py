"""A TAK client's view of a running demo: `uavmm demo --cot-url udp://...` and a plain UDP socket on loopback
receive valid Cursor-on-Target events for the three UAVs and for global tracks."""

from __future__ import annotations

import signal
import subprocess
import time
import xml.etree.ElementTree as ET

import pytest

from tests.e2e.conftest import ENV, REPO, uavmm
from tests.netutil import udp_listener

pytestmark = pytest.mark.e2e


def test_demo_sends_cot_events_of_its_uavs_and_tracks(tmp_path):
    listener, port = udp_listener(0.5)
    demo = subprocess.Popen(
        uavmm("demo", "--http", "127.0.0.1:0", "--duration", "60", "--status-every", "0", "--log-dir",
              str(tmp_path / "logs"), "--cot-url", f"udp://127.0.0.1:{port}"),
        cwd=REPO, env=ENV, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    events: dict[str, ET.Element] = {}
    try:
        deadline = time.monotonic() + 90.0
        while time.monotonic() < deadline:
            try:
                event = ET.fromstring(listener.recvfrom(65536)[0])
            except TimeoutError:
                continue
            events[event.get("uid")] = event
            uavs = {u for u in events if u.startswith("uavmm.uav.")}
            tracks = {u for u in events if u.startswith("uavmm.track.")}
            if len(uavs) == 3 and len(tracks) >= 2:
                break
    finally:
        demo.send_signal(signal.SIGINT)
        try:
            demo.wait(timeout=40)
        except subprocess.TimeoutExpired:
            demo.kill()
        listener.close()
    assert {u for u in events if u.startswith("uavmm.uav.")} == {"uavmm.uav.uav1", "uavmm.uav.uav2", "uavmm.uav.uav3"}
    tracks = [e for u, e in events.items() if u.startswith("uavmm.track.")]
    assert len(tracks) >= 2
    for event in events.values():
        point = event.find("point")
        # the trio scenario's scene (docs/demo.md): 48.53 N, 9.06 E
        assert abs(float(point.get("lat")) - 48.5335) < 0.02 and abs(float(point.get("lon")) - 9.0555) < 0.02
        assert event.get("stale") > event.get("time") or event.get("uid").startswith("uavmm.track.")
    assert all(e.get("type") == "a-u-G" for e in tracks)  # people
