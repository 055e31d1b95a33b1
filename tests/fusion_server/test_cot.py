"""Cursor-on-Target: the events' XML (uids, types, times, points, course), a real server sending them to a
UDP socket and to a TCP listener on loopback, a TAK server that is down, and bad URLs."""

from __future__ import annotations

import socket
import threading
import time
import xml.etree.ElementTree as ET
from datetime import datetime

import pytest
from hypothesis import given
from hypothesis import strategies as st

from fusion_server.config import FusionSettings
from fusion_server.cot import MAX_OBJECTS, CotSender, CotTarget, object_event, parse_cot_url, track_event, uav_event
from fusion_server.peaks import Peak
from tests.fusion_server.fake_agent import LAT, LON, blob
from tests.netutil import free_port, udp_listener, wait_until

NOW = 1_790_000_000.0


def _time(text: str) -> float:
    assert text.endswith("Z")
    return datetime.fromisoformat(text.replace("Z", "+00:00")).timestamp()


def _track(gid=7, cls="person", status="tracked", vel=(1.0, 1.0)) -> dict:
    return {"type": "Feature", "id": gid, "geometry": {"type": "Point", "coordinates": [LON, LAT]},
            "properties": {"gid": gid, "cls": cls, "score": 0.8, "vel_en": list(vel), "status": status,
                           "members": [["uav1", 3], ["uav2", 5]], "active_members": [["uav2", 5]]}}


def test_track_event_is_valid_cot():
    event = ET.fromstring(track_event(_track(), NOW, 10.0))
    assert event.tag == "event" and event.get("version") == "2.0"
    assert event.get("uid") == "uavmm.track.7" and event.get("type") == "a-u-G" and event.get("how") == "m-f"
    assert _time(event.get("time")) == pytest.approx(NOW, abs=0.001)
    assert _time(event.get("stale")) == pytest.approx(NOW + 10.0, abs=0.001)
    point = event.find("point")
    assert float(point.get("lat")) == pytest.approx(LAT) and float(point.get("lon")) == pytest.approx(LON)
    assert point.get("hae") == "9999999.0"
    track = event.find("detail/track")
    assert float(track.get("course")) == pytest.approx(45.0) and float(track.get("speed")) == pytest.approx(2**0.5,
                                                                                                           abs=0.01)
    assert event.find("detail/contact").get("callsign") == "person 7"
    assert "seen by uav2" in event.find("detail/remarks").text
    ended = ET.fromstring(track_event(_track(status="ended"), NOW, 10.0))
    assert ended.get("stale") == ended.get("time")  # TAK removes it
    assert ET.fromstring(track_event(_track(cls="boat"), NOW, 10.0)).get("type") == "a-u-S"


@given(st.text(min_size=1, max_size=20).filter(lambda s: "\x00" not in s and s.isprintable()))
def test_class_names_are_escaped(cls):
    event = ET.fromstring(track_event(_track(cls=cls), NOW, 5.0))
    assert event.find("detail/contact").get("callsign") == f"{cls} 7"


def _peak(cls="swimmer", dlat=0.0, score=0.9, gx=140_000.5, gy=90_000.5) -> Peak:
    return Peak(cls=cls, lat=LAT + dlat, lon=LON, score=score, gx=gx, gy=gy)


def test_object_event_is_valid_cot_named_after_its_cell():
    event = ET.fromstring(object_event(_peak(), NOW, 3.0))
    assert event.get("uid") == "uavmm.object.swimmer.140000.90000" and event.get("type") == "a-u-S"
    assert _time(event.get("stale")) == pytest.approx(NOW + 3.0, abs=0.001)
    point = event.find("point")
    assert float(point.get("lat")) == pytest.approx(LAT) and float(point.get("lon")) == pytest.approx(LON)
    assert event.find("detail/contact").get("callsign") == "swimmer 0.90"
    assert "not a global track" in event.find("detail/remarks").text


def test_fused_objects_a_track_explains_are_not_sent_twice():
    features = [_track(gid=1, cls="swimmer")]
    objects = [_peak(dlat=2e-5),  # 2 m from the swimmer's track: that track
               _peak(cls="person", dlat=2e-5, gx=1.5),  # as close, another class: its own object
               _peak(dlat=2e-4, gx=2.5)]  # 22 m away: an untracked swimmer
    sender = CotSender(CotTarget("udp", "127.0.0.1", 9), lambda: features, lambda: [], clock=lambda: NOW,
                       objects=lambda: objects, interval_s=0.5)
    events = [ET.fromstring(e) for e in sender.events()]
    assert [e.get("uid") for e in events] == ["uavmm.track.1", "uavmm.object.person.1.90000",
                                              "uavmm.object.swimmer.2.90000"]
    assert _time(events[1].get("stale")) == pytest.approx(NOW + 1.5, abs=0.001)  # three intervals
    many = [_peak(dlat=1e-3 * (i + 1), gx=float(i)) for i in range(MAX_OBJECTS + 20)]
    sender = CotSender(CotTarget("udp", "127.0.0.1", 9), lambda: [], lambda: [], clock=lambda: NOW,
                       objects=lambda: many)
    assert len(sender.events()) == MAX_OBJECTS  # the strongest first, never a flood
    assert CotSender(CotTarget("udp", "127.0.0.1", 9), lambda: [], lambda: []).events() == []


def test_uav_event_has_a_sensor_and_none_without_a_position():
    row = {"id": "uav1", "online": True, "state": {
        "lat": LAT, "lon": LON, "height_m": 40.0, "pitch_deg": 30.0, "heading_deg": 370.0, "t": NOW,
        "camera": {"width": 1920, "height": 1080, "fx": 960.0, "fy": 960.0, "cx": 960.0, "cy": 540.0}}}
    event = ET.fromstring(uav_event(row, NOW, 10.0))
    assert event.get("uid") == "uavmm.uav.uav1" and event.get("type").startswith("a-f-A")
    sensor = event.find("detail/sensor")
    assert float(sensor.get("azimuth")) == pytest.approx(10.0) and float(sensor.get("elevation")) == -30.0
    assert float(sensor.get("fov")) == pytest.approx(90.0) and float(sensor.get("range")) == pytest.approx(80.0)
    assert uav_event({"id": "uav2", "online": True, "state": None}, NOW, 10.0) is None


@pytest.mark.parametrize("url", ["http://x:1", "udp://host", "udp://:6969", "tcp://host:0", "udp://h:99999",
                                 "udp://h:1/path", "239.2.3.1:6969"])
def test_bad_urls_are_refused(url):
    with pytest.raises(ValueError, match="--cot-url"):
        parse_cot_url(url)
    with pytest.raises(ValueError, match="--cot-url"):
        FusionSettings(db_path=None, cot_url=url)


@pytest.mark.parametrize("score", [0.0, -0.5, 1.5])
def test_a_bad_object_score_is_refused(score):
    with pytest.raises(ValueError, match="cot_objects_min_score must be in"):
        FusionSettings(db_path=None, cot_url="udp://127.0.0.1:6969", cot_objects_min_score=score)


def test_good_urls():
    assert parse_cot_url("udp://239.2.3.1:6969") == CotTarget("udp", "239.2.3.1", 6969)
    assert parse_cot_url("tcp://tak.local:8087") == CotTarget("tcp", "tak.local", 8087)


def _received(sock: socket.socket, until_s: float) -> list[ET.Element]:
    events, deadline = [], time.monotonic() + until_s
    while time.monotonic() < deadline:
        try:
            events.append(ET.fromstring(sock.recvfrom(65536)[0]))
        except TimeoutError:
            continue
    return events


def test_a_server_sends_uavs_and_tracks_over_udp(server_factory, agent_factory):
    listener, port = udp_listener(0.2)
    try:
        server = server_factory(cot_url=f"udp://127.0.0.1:{port}", cot_interval_s=0.2)
        agent = agent_factory("uav1")
        agent.state()
        agent.tracks([(1, "person", LAT, LON), (2, "boat", LAT + 1e-4, LON)])
        events = _received(listener, 1.5)
        uids = {e.get("uid") for e in events}
        gids = {f"uavmm.track.{r.gid}" for r in server.tracker.records(include_ended=False)}
        assert len(gids) == 2 and uids == {"uavmm.uav.uav1", *gids}
        tracks = [e for e in events if e.get("uid") in gids]
        assert {e.get("type") for e in tracks} == {"a-u-G", "a-u-S"}
        for event in events:
            assert _time(event.get("stale")) > _time(event.get("time")) >= time.time() - 5
        assert events
        wait_until(lambda: server.cot.sent >= len(events), 5.0)  # counted once its round is sent
        metrics = server.prometheus()
        assert "uavmm_fusion_cot_events_total" in metrics
    finally:
        listener.close()


@pytest.mark.parametrize("min_score", [0.5, None])
def test_a_server_sends_untracked_fused_objects_unless_told_not_to(server_factory, agent_factory, min_score):
    listener, port = udp_listener(0.2)
    try:
        server = server_factory(cot_url=f"udp://127.0.0.1:{port}", cot_interval_s=0.2,
                                cot_objects_min_score=min_score)
        agent = agent_factory("uav1")
        agent.state()
        agent.tile(blob(128, 128, value=0.9))  # a strong spot in the map, no track
        wait_until(lambda: server.joint.tiles("person"), 5.0)
        events = _received(listener, 1.0)
        objects = [e for e in events if e.get("uid").startswith("uavmm.object.person.")]
        if min_score is None:
            assert not objects and any(e.get("uid") == "uavmm.uav.uav1" for e in events)
            return
        assert objects and {e.get("type") for e in objects} == {"a-u-G"}
        peak = server._object_peaks()[0]
        assert float(objects[-1].find("point").get("lat")) == pytest.approx(peak.lat, abs=1e-7)
    finally:
        listener.close()


def test_tcp_to_a_tak_server_that_comes_up_later(server_factory, agent_factory):
    port = free_port()  # nothing listens yet
    server = server_factory(cot_url=f"tcp://127.0.0.1:{port}", cot_interval_s=0.2)
    agent = agent_factory("uav1")
    agent.state()
    wait_until(lambda: server.cot.failed >= 2, 5.0)  # counted, retried, the server goes on
    assert server.zenoh_open()
    received = bytearray()
    with socket.create_server(("127.0.0.1", port)) as tak:
        tak.settimeout(5.0)
        conn, _ = tak.accept()
        with conn:
            conn.settimeout(0.5)
            deadline = time.monotonic() + 2.0
            while time.monotonic() < deadline:
                try:
                    received += conn.recv(65536)
                except TimeoutError:
                    continue
    events = [e for e in received.split(b"<?xml") if e]
    assert events and all(ET.fromstring(b"<?xml" + e).get("uid") == "uavmm.uav.uav1" for e in events)


def test_each_ended_track_is_sent_once():
    features = [_track(gid=1), _track(gid=2, status="ended")]
    sender = CotSender(CotTarget("udp", "127.0.0.1", 9), lambda: features, lambda: [], clock=lambda: NOW)
    first = [ET.fromstring(e).get("uid") for e in sender.events()]
    second = [ET.fromstring(e).get("uid") for e in sender.events()]
    assert first == ["uavmm.track.1", "uavmm.track.2"] and second == ["uavmm.track.1"]


def test_a_failing_round_does_not_stop_the_thread():
    calls = []

    def tracks():
        calls.append(1)
        if len(calls) == 1:
            raise RuntimeError("a bug in a snapshot")
        return []

    sender = CotSender(CotTarget("udp", "127.0.0.1", 9), tracks, lambda: [], interval_s=0.05)
    sender.start()
    try:
        wait_until(lambda: len(calls) >= 3, 5.0)
    finally:
        sender.close()
    assert sender.failed == 1 and not threading.current_thread().name == "uavmm-cot"


def test_a_track_across_the_antimeridian_explains_its_object():
    """A peak at 179.99999 E and its track 1.1 m east of it, at 179.99999 W: one object, sent as the track only
    (the longitude difference was taken the long way round, 360 degrees, and the object was sent as well)."""
    track = {"type": "Feature", "id": 1, "geometry": {"type": "Point", "coordinates": [-179.99999, -17.0]},
             "properties": {"gid": 1, "cls": "swimmer", "score": 0.8, "vel_en": [0.0, 0.0], "status": "tracked",
                            "members": [["uav1", 3]], "active_members": [["uav1", 3]]}}
    peaks = [Peak(cls="swimmer", lat=-17.0, lon=179.99999, score=0.9, gx=0.5, gy=0.5),
             Peak(cls="swimmer", lat=-17.0, lon=179.9, score=0.9, gx=1.5, gy=0.5)]  # 10 km west: its own
    sender = CotSender(CotTarget("udp", "127.0.0.1", 9), lambda: [track], lambda: [], clock=lambda: NOW,
                       objects=lambda: peaks, interval_s=0.5)
    assert [ET.fromstring(e).get("uid") for e in sender.events()] == ["uavmm.track.1", "uavmm.object.swimmer.1.0"]
