"""The noisy meta differs from the truth by the configured amounts (bias, jitter, latency, sample and hold)."""

from __future__ import annotations

import math
from datetime import datetime

import numpy as np
import pytest

from shared.geo import latlon_to_local
from sim.flight import KeyframeFlight, OrbitFlight
from sim.noise import TelemetryNoise, TelemetryStream, format_time
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
