"""Session states from a recording's own readings (imu_array_ros.timing): sawtooth search and phase fit on
synthetic delays; sample-clock phases and the board's common rate of a simulated MIMU-like array (readings
sampled from the exact motion at their true times); fusion with them against the same array sampled
synchronously; too little motion; stamp clocks of IMUs with their own stamps."""

from __future__ import annotations

import numpy as np
import pytest

from imu_array_ros.io.pairing import ImuStream, pair_streams
from imu_array_ros.model.description import load_description
from imu_array_ros.model.samples import ImuSamples
from imu_array_ros.model.sensor_model import SensorModel
from imu_array_ros.simulation.clocks import mimu_like_clocks, new_session, simulate_own_clocks
from imu_array_ros.simulation.motion import TwistTrajectory
from imu_array_ros.simulation.simulator import simulate_trajectory
from imu_array_ros.timing import estimate_session, fit_phases, search_rates
from imu_array_ros.timing.sawtooth import sawtooth_delay
from imu_array_ros.workflows import fuse

from conftest import REPO

CORNERS = REPO / "config" / "mimu4444bt_corners.yaml"


def circular(a, b, period):
    """|a - b| on a circle of ``period``."""
    d = np.mod(a - b, period)
    return np.minimum(d, period - d)


def test_sawtooth_rates_and_phases_from_noisy_delays():
    """Delays of chips at 62.5 Hz reads (an exact multiple of the nominal 1 kHz), 30 us noise: rates to
    0.5 ppm whichever sign the rate has, and the fitted sawtooths within 20 us RMS of the true ones where the
    data are (the phase counts from t = 0, 500 s before them: a rate error moves it there, not here)."""
    rng = np.random.default_rng(3)
    t = np.arange(6000) * 0.016 + 500.0
    period = np.full(5, 1e-3)
    rates = np.array([-2500.0, 800.0, 1500.0, -400.0, 2900.0])
    phases = rng.uniform(0, 1e-3, 5)
    d = sawtooth_delay(t, period, rates, phases) + 2e-4 + rng.normal(0, 3e-5, (len(t), 5))
    w = np.ones_like(d)
    found, amp = search_rates(t, d, w, period)
    assert np.all(np.abs(found - rates) < 0.5), found
    assert np.all(amp > 1e-4)
    ph, _ = fit_phases(t, d, w, period, found)
    err = circular(sawtooth_delay(t, period, found, ph), sawtooth_delay(t, period, rates, phases), 1e-3)
    # a wrap is only seen between two reads: the age moves by 16 ms x rate per read (40 us at 2500 ppm)
    bound = np.maximum(2e-5, 0.8 * 0.016 * np.abs(rates) * 1e-6)
    assert np.all(np.sqrt(np.mean(err ** 2, axis=0)) < bound), np.sqrt(np.mean(err ** 2, axis=0))


@pytest.fixture(scope="module")
def mimu():
    """The 8-corner array with MIMU-like clocks (+-3000 ppm, accelerometers 1.6 ms behind), a new session,
    30 s of hand twisting at 62.5 Hz; and the same motion sampled synchronously (no timing terms)."""
    rng = np.random.default_rng(2026)
    nominal = SensorModel.from_description(load_description(CORNERS))
    device = mimu_like_clocks(nominal, rng)
    session = new_session(device, rng)
    traj = TwistTrajectory.random(rng)
    stamps = 10**9 + np.round(np.arange(int(30 * 62.5)) * 16e6).astype(np.int64)
    timed, truth = simulate_trajectory(session, traj, stamps, np.random.default_rng(1))
    sync, _ = simulate_trajectory(nominal, traj, stamps, np.random.default_rng(1))
    return nominal, device, session, timed, sync, truth


def rms_omega(fused, truth):
    idx = np.searchsorted(truth.stamps, fused.stamps)
    return float(np.sqrt(np.mean((fused.omega - truth.omega[idx]) ** 2)))


def test_session_phases_of_a_simulated_mimu_array(mimu):
    """Starting from other phases (the device constants only), the session's phases come back to ~10 us and
    the common rate to a few ppm; fusing with them is within 1.5x of the synchronous array, while ignoring
    the timing is many times worse."""
    nominal, device, session, timed, sync, truth = mimu
    start = new_session(device, np.random.default_rng(7))  # same device constants, wrong phases
    states = estimate_session(timed, start)
    clock = session.terms["sample_clock"].values
    big_t = clock[:, 0] / (1 + clock[:, 1] * 1e-6)
    assert states.estimated and abs(states.common_rate_ppm["sample_clock"]) < 3.0, states.common_rate_ppm
    t = (timed.stamps - timed.stamps[0]) * 1e-9
    got = states.model.terms["sample_clock"].values
    err = circular(sawtooth_delay(t, got[:, 0], got[:, 1], got[:, 2]),
                   sawtooth_delay(t, clock[:, 0], clock[:, 1], clock[:, 2]), big_t)
    bound = np.maximum(2e-5, 0.8 * 0.016 * np.abs(clock[:, 1]) * 1e-6)  # the age's step per read
    assert np.all(np.sqrt(np.mean(err ** 2, axis=0)) < bound), np.sqrt(np.mean(err ** 2, axis=0))
    e_sync = rms_omega(fuse(sync, nominal)[0], truth)
    e_timed = rms_omega(fuse(timed, start)[0], truth)  # the workflow estimates the session itself
    e_unaware = rms_omega(fuse(timed, nominal)[0], truth)
    assert e_timed < 1.5 * e_sync, (e_timed, e_sync)
    assert e_unaware > 5 * e_sync, (e_unaware, e_sync)


def test_each_chips_rate_is_a_session_state(mimu):
    """Between sessions every chip's clock moved by its own 10-25 ppm besides a common 120 ppm (as the
    MIMU4444BT captures' did): from the device's rates the session's phases still come back (a common shift
    alone leaves the sawtooths drifting by ~0.5 ms over the 30 s)."""
    nominal, device, _, _, _, _ = mimu
    rng = np.random.default_rng(31)
    clock = device.terms["sample_clock"].values.copy()
    clock[:, 1] += 120.0 + rng.choice([-1.0, 1.0], 8) * rng.uniform(10.0, 25.0, 8)
    session = new_session(device.with_terms(sample_clock=clock), rng)
    stamps = 10**9 + np.round(np.arange(int(30 * 62.5)) * 16e6).astype(np.int64)
    timed, _ = simulate_trajectory(session, TwistTrajectory.random(rng), stamps, np.random.default_rng(2))
    states = estimate_session(timed, device)
    truth = session.terms["sample_clock"].values
    got = states.model.terms["sample_clock"].values
    resolution = 0.1 * 1e-3 / 30.0 * 1e6  # ppm moving the sawtooth by a tenth of its period over the 30 s
    assert np.all(np.abs(got[:, 1] - truth[:, 1]) < resolution), got[:, 1] - truth[:, 1]
    t = (timed.stamps - timed.stamps[0]) * 1e-9
    err = circular(sawtooth_delay(t, got[:, 0], got[:, 1], got[:, 2]),
                   sawtooth_delay(t, truth[:, 0], truth[:, 1], truth[:, 2]), truth[:, 0] / (1 + truth[:, 1] * 1e-6))
    bound = np.maximum(2e-5, 0.8 * 0.016 * np.abs(truth[:, 1]) * 1e-6)
    assert np.all(np.sqrt(np.mean(err ** 2, axis=0)) < 2 * bound), np.sqrt(np.mean(err ** 2, axis=0))


def test_too_little_motion_is_said_and_falls_back_to_the_mean_age(mimu):
    nominal, device, session, timed, sync, truth = mimu
    still = timed.select(slice(0, 60))  # one second
    states = estimate_session(still, device)
    assert not states.estimated
    assert any("s of motion" in n for n in states.notes) and any("mean age" in n for n in states.notes)
    assert np.all(states.model.terms["sample_clock"].values[:, 0] == 0)
    half = 0.5e-3 / (1 + device.terms["sample_clock"].values[:, 1:2] * 1e-6)
    np.testing.assert_allclose(states.model.terms["time_offset"].values - device.terms["time_offset"].values,
                               np.broadcast_to(-half, (8, 2)), atol=1e-12)


def test_stamp_clocks_of_imus_with_their_own_stamps():
    """8 IMUs at ~200 Hz on their own clocks (+-200 ppm, offsets up to 2 ms, 50 us jitter), paired onto the
    reference's stamps: the offsets (relative to the reference) come back to ~20 us, and the fusion is within
    1.5x of the synchronous oracle, every grid sample fused."""
    rng = np.random.default_rng(11)
    nominal = SensorModel.from_description(load_description(CORNERS))
    streams = simulate_own_clocks(nominal, rng, 20.0, 200.0, start_ns=10**9)
    samples, stats = pair_streams([ImuStream(s, a, g) for s, a, g in zip(streams.stamps, streams.accel, streams.gyro)],
                                  nominal.names)
    assert samples.own_stamps is not None
    states = estimate_session(samples, nominal)
    true = streams.stamp_clock_values(int(samples.stamps[0]))
    assert np.all(np.abs(states.stamp_offset - true[:, 0]) < 3e-5), (states.stamp_offset, true[:, 0])
    fused, fstats = fuse(samples, nominal)
    assert fstats.fused == len(samples)
    ref = streams.reference_trajectory()
    omega_true = ref(fused.stamps[:, None])[0][:, 0]
    err = np.sqrt(np.mean((fused.omega - omega_true) ** 2))
    # the oracle: every IMU sampled at the reference's true sample times, together
    oracle, truth = simulate_trajectory(nominal, streams.truth.trajectory, streams.sample_times[0],
                                        np.random.default_rng(5))
    e_oracle = rms_omega(fuse(oracle, nominal)[0], truth)
    unaware = ImuSamples(samples.stamps, samples.accel, samples.gyro, samples.names)
    e_unaware = np.sqrt(np.mean((fuse(unaware, nominal)[0].omega - omega_true) ** 2))
    assert err < 1.5 * e_oracle and e_unaware > 3 * e_oracle, (err, e_oracle, e_unaware)
