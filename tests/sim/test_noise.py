"""The noisy meta differs from the truth by the configured amounts (bias, jitter, latency, sample and hold)."""

from __future__ import annotations

import dataclasses
import math
import re
from datetime import datetime

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from shared.geo import latlon_to_local
from shared.telemetry import from_seadronessee_meta, parse_datetime
from sim.flight import KeyframeFlight, OrbitFlight
from sim.noise import (
    CLOCK_FIELDS,
    TelemetryNoise,
    TelemetryStream,
    format_frame_time,
    format_log_time,
    format_time,
    truncate_stamp,
)
from sim.simulator import Simulation

LAT0, LON0, T0 = 48.53, 9.06, 1685613600.0
FPS = 30.0


def _static_flight() -> KeyframeFlight:
    return KeyframeFlight([0.0], [10.0], [-20.0], [40.0], [45.0], [30.0])


def _errors(noise: TelemetryNoise, seed: int, frames: int) -> dict[str, np.ndarray]:
    """meta - truth over a static hover (so latency and hold do not matter)."""
    flight = _static_flight()
    stream = TelemetryStream(noise, flight, np.random.default_rng(seed), LAT0, LON0, T0)
    out: dict[str, list[float]] = {k: [] for k in ("east", "north", "heading", "pitch", "height")}
    for f in range(frames):
        meta, st = stream.meta(f / FPS)
        assert meta is not None
        e, n = latlon_to_local(meta["gps_latitude"], meta["gps_longitude"], LAT0, LON0)
        out["east"].append(float(e) - st.east_m)
        out["north"].append(float(n) - st.north_m)
        out["heading"].append((meta["gimbal_heading"] - st.heading_deg + 180.0) % 360.0 - 180.0)
        out["pitch"].append(meta["gimbal_pitch"] - st.pitch_deg)
        out["height"].append(meta["altitude"] - st.height_m)
    return {k: np.array(v) for k, v in out.items()}


def test_bias_is_constant_per_flight_and_has_the_configured_spread() -> None:
    noise = TelemetryNoise()
    gps, heading, pitch, height = [], [], [], []
    for seed in range(300):
        stream = TelemetryStream(noise, _static_flight(), np.random.default_rng(seed), LAT0, LON0, T0)
        b = stream.bias
        gps.append(math.hypot(b["east_m"], b["north_m"]))
        heading.append(b["heading_deg"])
        pitch.append(b["pitch_deg"])
        height.append(b["height_m"])
    # RMS over 300 flights: ~4 % standard error
    assert math.sqrt(np.mean(np.square(gps))) == pytest.approx(noise.gps_bias_m, rel=0.15)
    assert np.std(heading) == pytest.approx(noise.heading_bias_deg, rel=0.15)
    assert np.std(pitch) == pytest.approx(noise.pitch_bias_deg, rel=0.15)
    assert np.std(height) == pytest.approx(noise.height_bias_m, rel=0.15)
    assert abs(np.mean(heading)) < 0.4


@pytest.mark.parametrize("seed", [0, 1])
def test_jitter_around_the_bias_has_the_configured_std(seed: int) -> None:
    noise = TelemetryNoise()
    err = _errors(noise, seed, frames=9000)  # 300 s, 3000 telemetry samples, ~300 independent
    gps_jitter = np.sqrt(np.var(err["east"]) + np.var(err["north"]))
    assert gps_jitter == pytest.approx(noise.gps_jitter_m, rel=0.2)
    assert np.std(err["heading"]) == pytest.approx(noise.heading_jitter_deg, rel=0.2)
    assert np.std(err["pitch"]) == pytest.approx(noise.pitch_jitter_deg, rel=0.2)
    assert np.std(err["height"]) == pytest.approx(noise.height_jitter_m, rel=0.2)
    stream = TelemetryStream(noise, _static_flight(), np.random.default_rng(seed), LAT0, LON0, T0)
    assert np.mean(err["heading"]) == pytest.approx(stream.bias["heading_deg"], abs=0.1)
    assert np.mean(err["height"]) == pytest.approx(stream.bias["height_m"], abs=0.05)


def test_noise_scale_two_doubles_every_error_exactly_for_the_same_seed() -> None:
    base = TelemetryNoise(time_offset_s=0.0)  # a doubled lag would pick other samples; here every sample matches
    e1 = _errors(base, 7, frames=300)
    e2 = _errors(base.scaled(2.0), 7, frames=300)
    for k in ("east", "north", "heading", "height"):
        np.testing.assert_allclose(e2[k], 2.0 * e1[k], atol=2e-3)  # meta values are rounded to 3 decimals


def test_zero_noise_reproduces_the_truth() -> None:
    err = _errors(TelemetryNoise().scaled(0.0), 3, frames=60)
    for k, v in err.items():
        assert np.abs(v).max() < 2e-3, k


def test_scaled_keeps_rates_and_validates() -> None:
    n = TelemetryNoise(missing_meta_rate=0.01).scaled(2.0)
    assert n.gps_bias_m == 3.0 and n.time_offset_s == pytest.approx(0.1)
    assert n.telemetry_hz == 10.0 and n.missing_meta_rate == 0.01 and n.jitter_corr_s == 0.5
    with pytest.raises(ValueError, match="noise scale"):
        TelemetryNoise().scaled(-1.0)
    with pytest.raises(ValueError, match="gps_bias_m"):
        TelemetryNoise(gps_bias_m=-1.0)


def test_telemetry_is_sampled_at_10_hz_and_held_between_samples() -> None:
    flight = OrbitFlight(0.0, 0.0, 50.0, 40.0, 40.0, 5.0, 0.0)
    stream = TelemetryStream(TelemetryNoise(), flight, np.random.default_rng(0), LAT0, LON0, T0)
    metas = [stream.meta(f / FPS)[0] for f in range(300)]
    stamps = [m["date_time"] for m in metas]
    changes = sum(a != b for a, b in zip(stamps, stamps[1:], strict=False))
    assert 95 <= changes <= 100  # 10 s at 10 Hz
    # held: identical meta for consecutive frames with the same stamp
    for a, b in zip(metas, metas[1:], strict=False):
        if a["date_time"] == b["date_time"]:
            assert a == b


def test_meta_lags_the_frame_by_the_time_offset_plus_hold() -> None:
    flight = OrbitFlight(0.0, 0.0, 50.0, 40.0, 40.0, 5.0, 0.0)
    noise = TelemetryNoise()
    stream = TelemetryStream(noise, flight, np.random.default_rng(1), LAT0, LON0, T0)
    for f in range(30, 200):
        t = f / FPS
        ts = stream.sample_time(t)
        assert t - noise.time_offset_s - 1.0 / noise.telemetry_hz - 1e-9 <= ts <= t - noise.time_offset_s + 1e-9


def test_meta_is_seadronessee_shaped() -> None:
    flight = OrbitFlight(0.0, 0.0, 50.0, 40.0, 40.0, 5.0, 0.0, nose_along_track=True)
    stream = TelemetryStream(TelemetryNoise(), flight, np.random.default_rng(2), -33.9, -70.6, T0)
    meta, st = stream.meta(1.0)
    assert meta["gps_latitude_ref"] == "S" and meta["gps_longitude_ref"] == "W"
    assert meta["gps_latitude"] > 0 and meta["gps_longitude"] > 0
    assert 0.0 <= meta["gimbal_heading"] < 360.0 and 0.0 <= meta["compass_heading"] < 360.0
    # nose along the track, gimbal at the centre: the two headings differ by ~90 deg
    diff = (meta["compass_heading"] - meta["gimbal_heading"]) % 360.0
    assert min(abs(diff - 90.0), abs(diff - 270.0)) < 1e-6
    assert meta["speed"] == pytest.approx(5.0, abs=0.5)
    assert meta["xspeed"] == pytest.approx(st.vel_north_mps, abs=0.5)
    assert meta["yspeed"] == pytest.approx(st.vel_east_mps, abs=0.5)
    assert datetime.fromisoformat(meta["date_time"]).timestamp() == pytest.approx(T0 + 1.0, abs=0.2)


def test_format_time_has_milliseconds() -> None:
    assert format_time(T0) == "2023-06-01T10:00:00.000Z"
    assert format_time(T0 + 1.0 / 30.0) == "2023-06-01T10:00:00.033Z"
    assert format_time(T0 + 59.9996) == "2023-06-01T10:01:00.000Z"


def test_simulation_noise_scale_doubles_the_realised_biases() -> None:
    facts = {}
    for k in (1.0, 2.0):
        sim = Simulation("grass", seed=5, frames=5, noise_scale=k)
        for _ in sim.frames():
            pass
        facts[k] = sim.facts()["videos"]
    for v1, v2 in zip(facts[1.0], facts[2.0], strict=True):
        for name, b in v1["telemetry_bias"].items():
            assert v2["telemetry_bias"][name] == pytest.approx(2.0 * b, abs=1e-12)


def test_simulated_meta_error_grows_with_noise_scale() -> None:
    """Over a whole scenario, position errors of the meta scale with noise_scale (biases dominate)."""
    rms = {}
    for k in (1.0, 2.0):
        errs = []
        for fs in Simulation("sea", seed=2, frames=60, noise_scale=k).frames():
            if fs.meta is None:
                continue
            e, n = latlon_to_local(fs.meta["gps_latitude"], fs.meta["gps_longitude"], fs.true_pose.lat,
                                   fs.true_pose.lon)
            errs.append(math.hypot(float(e), float(n)))
        rms[k] = math.sqrt(np.mean(np.square(errs)))
    assert rms[2.0] > 1.5 * rms[1.0]
    assert rms[1.0] > 0.2


def test_some_sea_frames_have_no_meta() -> None:
    n = missing = 0
    for fs in Simulation("sea", seed=0, frames=600).frames():
        n += 1
        missing += fs.meta is None
    assert 0.003 < missing / n < 0.025  # 1 % configured


# ---------------------------------------------------------------- SeaDronesSee-style clocks and layout

FLIGHT_LOG_FIELDS = {"datetime(utc)", "latitude", "longitude", "height_above_takeoff(meter)", "speed(m/s)",
                     "xspeed(m/s)", "yspeed(m/s)", "zspeed(m/s)", "compass_heading(degrees)",
                     "gimbal_heading(degrees)", "gimbal_pitch(degrees)"}
SDS_CLOCKS = {"meta_layout": "flight_log", "stamp_resolution_s": 1.0, "frame_clock_utc_offset_s": 7200.0}


def _stream_metas(noise: TelemetryNoise, frames: int, seed: int = 4) -> list[dict]:
    flight = OrbitFlight(0.0, 0.0, 30.0, 40.0, 50.0, 4.0, 0.0)
    stream = TelemetryStream(noise, flight, np.random.default_rng(seed), LAT0, LON0, T0 + 0.37)
    return [stream.meta(f / FPS)[0] for f in range(frames)]


def test_flight_log_layout_has_the_log_names_and_whole_second_utc_stamps() -> None:
    agree = _stream_metas(TelemetryNoise(), 90)
    logged = _stream_metas(TelemetryNoise(**SDS_CLOCKS), 90)
    for old, new in zip(agree, logged, strict=True):
        assert set(new) == FLIGHT_LOG_FIELDS
        assert re.fullmatch(r"\d{4}-\d\d-\d\d \d\d:\d\d:\d\d", new["datetime(utc)"])
        # the same sample, its stamp cut down to the whole second (naive text read as UTC)
        t_ms = parse_datetime(old["date_time"])
        assert parse_datetime(new["datetime(utc)"]) == math.floor(t_ms + 1e-6)
        assert new["latitude"] == old["gps_latitude"] and new["longitude"] == old["gps_longitude"]
        assert new["height_above_takeoff(meter)"] == old["altitude"]
        assert new["gimbal_pitch(degrees)"] == old["gimbal_pitch"] > 0  # positive below the horizon
        for name in ("compass_heading", "gimbal_heading"):
            assert new[f"{name}(degrees)"] == old[name]
        for name in ("speed", "xspeed", "yspeed", "zspeed"):
            assert new[f"{name}(m/s)"] == old[name]
        # the project's reader takes both layouts to the same record, bar the stamp
        a, b = from_seadronessee_meta(old), from_seadronessee_meta(new)
        assert a is not None and b is not None
        assert (b.lat, b.lon, b.height_m, b.pitch_deg, b.heading_deg, b.vel_en_mps) == \
            (a.lat, a.lon, a.height_m, a.pitch_deg, a.heading_deg, a.vel_en_mps)
        assert 0.0 <= a.t - b.t < 1.0
    # 10 Hz sample and hold under whole-second stamps: many samples share one stamp
    assert len({m["datetime(utc)"] for m in logged}) <= 4
    assert len({m["gimbal_heading(degrees)"] for m in logged}) >= 25


def test_flight_log_layout_writes_signed_coordinates_south_and_west() -> None:
    flight = OrbitFlight(0.0, 0.0, 50.0, 40.0, 40.0, 5.0, 0.0)
    stream = TelemetryStream(TelemetryNoise(meta_layout="flight_log"), flight, np.random.default_rng(2),
                             -33.9, -70.6, T0)
    meta, _ = stream.meta(1.0)
    assert meta["latitude"] < 0 and meta["longitude"] < 0
    # without a stamp resolution the log's time keeps its milliseconds
    assert parse_datetime(meta["datetime(utc)"]) == pytest.approx(T0 + 1.0, abs=0.2)


@settings(max_examples=200, deadline=None)
@given(t=st.floats(1.0e9, 2.0e9), resolution=st.sampled_from([0.001, 0.1, 0.5, 1.0, 2.0]))
def test_truncate_stamp_cuts_down_to_a_multiple_of_the_resolution(t: float, resolution: float) -> None:
    cut = truncate_stamp(t, resolution)
    assert -5e-4 <= t - cut < resolution + 5e-4  # on the millisecond grid
    assert round(cut * 1000) % round(resolution * 1000) == 0
    assert truncate_stamp(t, 0.0) == t


@settings(max_examples=200, deadline=None)
@given(t=st.floats(1.0e9, 2.0e9), offset=st.sampled_from([-18000.0, -3600.0, 3600.0, 7200.0, 19800.0]))
def test_frame_clock_is_naive_local_time_with_microseconds(t: float, offset: float) -> None:
    text = format_frame_time(t, offset)
    assert re.fullmatch(r"\d{4}-\d\d-\d\dT\d\d:\d\d:\d\d\.\d{6}", text)  # no zone: local time
    assert parse_datetime(text) == pytest.approx(t + offset, abs=1e-6)
    assert parse_datetime(text, utc_offset_s=offset) == pytest.approx(t, abs=1e-6)
    assert format_frame_time(t, 0.0) == format_time(t)  # agreeing clocks: as before


def test_frame_and_log_time_examples() -> None:
    assert format_frame_time(T0 + 1.0 / 30.0, 7200.0) == "2023-06-01T12:00:00.033333"
    assert format_log_time(T0 + 1.0) == "2023-06-01 10:00:01"
    assert format_log_time(T0 + 1.25) == "2023-06-01 10:00:01.250"


def test_clock_fields_change_no_value_and_draw_no_random_numbers() -> None:
    plain = _stream_metas(TelemetryNoise(), 120, seed=9)
    ms = _stream_metas(TelemetryNoise(stamp_resolution_s=1.0), 120, seed=9)
    for a, b in zip(plain, ms, strict=True):
        assert {k: v for k, v in a.items() if k != "date_time"} == {k: v for k, v in b.items() if k != "date_time"}
        assert b["date_time"].endswith(".000Z")
    assert _stream_metas(TelemetryNoise(frame_clock_utc_offset_s=7200.0), 120, seed=9) == plain


@pytest.mark.parametrize(("field", "value"), [
    ("meta_layout", "airdata"), ("meta_layout", 1), ("stamp_resolution_s", -1.0), ("stamp_resolution_s", 1e-4),
    ("stamp_resolution_s", math.nan), ("frame_clock_utc_offset_s", math.inf),
    ("frame_clock_utc_offset_s", 15 * 3600.0), ("frame_clock_utc_offset_s", "7200"),
])
def test_clock_fields_are_validated(field: str, value: object) -> None:
    with pytest.raises(ValueError, match=field):
        TelemetryNoise(**{field: value})


def test_clock_fields_allow_western_zones_and_survive_scaling() -> None:
    noise = TelemetryNoise(meta_layout="flight_log", stamp_resolution_s=1.0, frame_clock_utc_offset_s=-18000.0)
    for k in (0.0, 2.0):
        scaled = noise.scaled(k)
        assert {f: getattr(scaled, f) for f in CLOCK_FIELDS} == {f: getattr(noise, f) for f in CLOCK_FIELDS}
    assert noise.scaled(2.0).gps_bias_m == 3.0
    defaults = {f.name: f.default for f in dataclasses.fields(TelemetryNoise) if f.name in CLOCK_FIELDS}
    assert defaults == {"stamp_resolution_s": 0.0, "meta_layout": "seadronessee", "frame_clock_utc_offset_s": 0.0}


def test_a_gps_slower_than_the_telemetry_is_held_while_the_rest_moves_on() -> None:
    # 30 Hz records (one a frame) whose GPS updates once a second: latitude and longitude repeat for ~30 records,
    # the heading (white jitter) changes on every one; the held position is where the UAV was at the update
    flight = OrbitFlight(0.0, 0.0, 50.0, 40.0, 40.0, 5.0, 0.0)
    noise = TelemetryNoise(telemetry_hz=30.0, gps_hz=1.0, white_heading_deg=0.5)
    stream = TelemetryStream(noise, flight, np.random.default_rng(3), LAT0, LON0, T0)
    metas = [stream.meta(f / FPS)[0] for f in range(300)]
    positions = [(m["gps_latitude"], m["gps_longitude"]) for m in metas]
    updates = sum(a != b for a, b in zip(positions, positions[1:], strict=False))
    headings = sum(a["gimbal_heading"] != b["gimbal_heading"] for a, b in zip(metas, metas[1:], strict=False))
    assert 9 <= updates <= 10 and headings >= 290
    plain_stream = TelemetryStream(dataclasses.replace(noise, gps_hz=0.0), flight, np.random.default_rng(3), LAT0,
                                   LON0, T0)
    plain = [plain_stream.meta(f / FPS)[0] for f in range(300)]
    assert sum(a["gps_latitude"] != b["gps_latitude"] for a, b in zip(plain, plain[1:], strict=False)) >= 290
    # the held position lags: at 5 m/s up to 5 m (plus the GPS errors, 1.5 m bias)
    lags = []
    for f, m in enumerate(metas):
        st = flight.state(f / FPS)
        e, n = latlon_to_local(m["gps_latitude"], m["gps_longitude"], LAT0, LON0)
        lags.append(math.hypot(float(e) - st.east_m, float(n) - st.north_m))
    assert max(lags) > 4.0
    # kept by scaling, at most the telemetry's rate, and no random numbers drawn from the stream's own generator
    assert noise.scaled(2.0).gps_hz == 1.0
    with pytest.raises(ValueError, match="gps_hz"):
        TelemetryNoise(telemetry_hz=10.0, gps_hz=20.0)
    with pytest.raises(ValueError, match="gps_hz"):
        TelemetryNoise(gps_hz=-1.0)
    held = [{k: v for k, v in m.items() if k not in ("gps_latitude", "gps_longitude")} for m in metas]
    assert held == [{k: v for k, v in m.items() if k not in ("gps_latitude", "gps_longitude")} for m in plain]
