"""The time-aware simulator: every reading is the motion at its sensor's true sample time.

MIMU-like host-read chip clocks (``sample_clock`` + ``time_offset``) and IMUs that stamp their own
messages on their own clocks (``stamp_clock``): readings against the motion evaluated at each
reading's true time, the first-order expansion against them, the attitude integration's accuracy.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from imu_array_ros.model.description import load_description
from imu_array_ros.model.sensor_model import SensorModel, motion_context
from imu_array_ros.simulation.clocks import (mimu_like_clocks, new_session, pair_to_reference,
                                             simulate_own_clocks)
from imu_array_ros.simulation.motion import TwistTrajectory
from imu_array_ros.simulation.simulator import simulate_measurements, simulate_trajectory, simulate_twist

ROOT = Path(__file__).resolve().parents[1]
START = 1_700_000_000_123_456_789


@pytest.fixture(scope="module")
def nominal() -> SensorModel:
    return SensorModel.from_description(load_description(ROOT / "config/array32.yaml"))


def ideal_readings(model: SensorModel, omega, omega_dot, s):
    """Noise-free (N, K, 3) gyroscope and accelerometer readings of the nominal geometry from the array-frame
    motion at each reading's own time, each (N, K, 3)."""
    p = model.positions[None]
    f = s + np.cross(omega, np.cross(omega, p)) + np.cross(omega_dot, p)
    rot = lambda v: np.einsum("kji,nkj->nki", model.rotations, v)  # noqa: E731
    return rot(omega), rot(f)


def stamps_at(rate_hz: float, seconds: float) -> np.ndarray:
    return START + np.round(np.arange(int(round(seconds * rate_hz))) * (1e9 / rate_hz)).astype(np.int64)


# --------------------------------------------------------------------------- the trajectory


def test_motion_at_equals_sample_and_is_a_function_of_time(rng):
    traj = TwistTrajectory.random(rng)
    stamps = stamps_at(62.5, 4.0)
    truth = traj.sample(stamps)
    omega, omega_dot, s, q = traj.motion_at(stamps, stamps[0])
    for a, b in ((truth.omega, omega), (truth.omega_dot, omega_dot), (truth.specific_force, s), (truth.attitude, q)):
        assert np.array_equal(a, b)
    # any shape, unsorted, before the origin; with knots each time's value is the same whatever else is asked
    when = stamps[5:45, None] + rng.integers(-3_000_000, 1, (40, 7))
    when[0, 0] = stamps[0] - 4_000_000
    fn = traj.function(stamps[0])
    full = fn(when)
    assert full[2].shape == (40, 7, 3)
    part = fn(when[3:9, 2:4][::-1])
    np.testing.assert_array_equal(part[2], full[2][3:9, 2:4][::-1])
    np.testing.assert_array_equal(fn.truth(stamps[:10]).specific_force, fn.truth(stamps[:40]).specific_force[:10])


def test_attitude_integration_at_dense_times_is_accurate(rng):
    """The knots (1 ms, 8 substeps) against a 10x finer, denser integration: specific force within 1e-4 m/s^2
    (measured ~5e-6 over 5 s); the stamps-only grid of ``sample`` at 62.5 Hz is ~100x worse."""
    traj = TwistTrajectory.random(rng)
    t = np.sort(rng.uniform(-0.004, 5.0, 3000))
    fine = np.concatenate([t, np.arange(-0.005, 5.0, 2e-4)])
    ref = traj.motion(fine, step=None, substeps=8)[2][:len(t)]
    err = np.abs(traj.motion(t, step=1e-3)[2] - ref).max()
    assert err < 1e-4, err
    grid = np.arange(0.0, 5.0, 1 / 62.5)
    coarse = np.abs(traj.motion(grid)[2] - traj.motion(grid, step=1e-3)[2]).max()
    assert coarse > 10 * err


# --------------------------------------------------------------------------- MIMU-like chip clocks


def mimu_recording(nominal, rng, seconds=3.0):
    model = mimu_like_clocks(nominal, rng)
    traj = TwistTrajectory.random(rng)
    stamps = stamps_at(62.5, seconds)
    samples, truth = simulate_trajectory(model, traj, stamps, rng, noise=False, saturate=False)
    return model, traj, samples, truth


def test_mimu_like_readings_are_the_motion_at_their_true_times(nominal, rng):
    model, traj, samples, truth = mimu_recording(nominal, rng)
    ctx = motion_context(truth.stamps, truth.omega, truth.omega_dot, truth.specific_force, model.rotations)
    delays = model.sample_delays(ctx)  # (N, K, 2) [accelerometer, gyroscope]
    big_t = 1e-3 / (1 + model.terms["sample_clock"].values[:, 1] * 1e-6)
    assert np.all(delays[..., 1] <= 0) and np.all(delays[..., 1] > -big_t)
    np.testing.assert_allclose(delays[..., 0] - delays[..., 1], -1.6e-3, atol=1e-15)
    when = truth.stamps[:, None, None] + np.round(delays * 1e9).astype(np.int64)
    fn = traj.function(truth.stamps[0])
    w_gyro = traj.omega(((when[..., 1] - truth.stamps[0]) * 1e-9).ravel()).reshape(when.shape[:2] + (3,))  # analytic
    gyro, _ = ideal_readings(model, w_gyro, 0 * w_gyro, 0 * w_gyro)
    _, acc = ideal_readings(model, *fn(when[..., 0]))
    assert np.abs(samples.gyro - gyro).max() < 1e-9
    assert np.abs(samples.accel - acc).max() < 1e-9
    np.testing.assert_array_equal(truth.specific_force, fn.truth(truth.stamps).specific_force)


def test_first_order_differs_by_the_second_order_term(nominal, rng):
    """What the fit's first-order shift x + d x' misses: d^2/2 x'' (gyroscope: ~1e-3 rad/s, the noise's size)."""
    model, traj, exact, truth = mimu_recording(nominal, rng)
    first = simulate_measurements(model, truth, rng, noise=False, saturate=False)
    ctx = motion_context(truth.stamps, truth.omega, truth.omega_dot, truth.specific_force, model.rotations)
    d = model.sample_delays(ctx)[..., 1]
    t = (truth.stamps - truth.stamps[0]) * 1e-9
    h = 1e-5
    w_ddot = (traj.omega_dot(t + h) - traj.omega_dot(t - h)) / (2 * h)
    expected = -0.5 * d[..., None] ** 2 * np.einsum("kji,nj->nki", model.rotations, w_ddot)
    diff = first.gyro - exact.gyro
    assert 1e-4 < np.abs(diff).max() < 1e-2
    assert np.abs(diff - expected).max() < 0.05 * np.abs(expected).max()
    acc = np.abs(first.accel - exact.accel).max()  # d up to 2.6 ms; s' from differences over the stamps
    assert 1e-4 < acc < 0.1


def test_untimed_model_or_first_order_keeps_the_earlier_readings(nominal):
    """A model without timing terms reads the stamps' motion, and ``exact_timing=False`` the first-order shift
    of the truth of ``sample``, as before sample times were modelled."""
    timed = mimu_like_clocks(nominal, np.random.default_rng(3))
    for model, exact in ((nominal, True), (timed, False)):
        a, ta = simulate_twist(model, 0.5, 62.5, np.random.default_rng(4), exact_timing=exact)
        rng = np.random.default_rng(4)
        truth = TwistTrajectory.random(rng).sample(ta.stamps)
        b = simulate_measurements(model, truth, rng)
        np.testing.assert_array_equal(a.gyro, b.gyro)
        np.testing.assert_array_equal(a.accel, b.accel)
        np.testing.assert_array_equal(ta.specific_force, truth.specific_force)


def test_new_session_draws_new_phases_only(nominal, rng):
    model = mimu_like_clocks(nominal, rng)
    clock = model.terms["sample_clock"].values
    assert np.all(clock[:, 0] == 1e-3) and np.all(np.abs(clock[:, 1]) <= 3000)
    np.testing.assert_array_equal(model.terms["time_offset"].values, np.tile([-1.6e-3, 0.0], (32, 1)))
    again = new_session(model, rng).terms["sample_clock"].values
    np.testing.assert_array_equal(again[:, :2], clock[:, :2])
    big_t = clock[:, 0] / (1 + clock[:, 1] * 1e-6)
    assert np.all((again[:, 2] >= 0) & (again[:, 2] < big_t))
    assert np.all(again[:, 2] != clock[:, 2])


@pytest.mark.parametrize("call, words", [
    (lambda m, r: mimu_like_clocks(m, r, period=-1e-3), "period must be > 0"),
    (lambda m, r: mimu_like_clocks(m, r, rate_ppm=-1.0), "rate_ppm"),
    (lambda m, r: new_session(m, r), "no sample clock"),
    (lambda m, r: simulate_own_clocks(m, r, 1.0, rate_hz=-200.0), "rate_hz must be > 0"),
    (lambda m, r: simulate_own_clocks(m, r, 1.0, jitter_s=-1e-6), "jitter_s"),
    (lambda m, r: TwistTrajectory.random(r).function(0, step=0.0), "step must be > 0"),
])
def test_bad_inputs_are_one_line(nominal, rng, call, words):
    with pytest.raises(ValueError, match=words) as err:
        call(nominal, rng)
    assert "\n" not in str(err.value)


# --------------------------------------------------------------------------- own clocks


def test_own_clock_readings_are_the_motion_at_their_true_times(nominal, rng):
    streams = simulate_own_clocks(nominal, rng, 2.0, noise=False, saturate=False, start_ns=START)
    assert np.all(np.abs(streams.rates) <= 200e-6) and np.all(np.abs(streams.offsets) <= 2e-3)
    jitter = []
    for k in range(32):
        t = streams.sample_times[k]
        omega, omega_dot, s, _ = streams.truth.seconds((t - START) * 1e-9)
        w = streams.truth.trajectory.omega((t - START) * 1e-9)  # analytic
        gyro, _ = ideal_readings(nominal, w[:, None], omega_dot[:, None], s[:, None])
        _, acc = ideal_readings(nominal, omega[:, None], omega_dot[:, None], s[:, None])
        assert np.abs(streams.gyro[k] - gyro[:, k]).max() < 1e-9
        assert np.abs(streams.accel[k] - acc[:, k]).max() < 1e-9
        clock = (1 + streams.rates[k]) * (t - START) * 1e-9 + streams.offsets[k]
        jitter.append((streams.stamps[k] - START) * 1e-9 - clock)
        assert np.all(np.diff(t) > 0) and abs(t[0] - START) < 5e-3 * 1e9
    assert 40e-6 < np.std(jitter) < 60e-6


def own_clock_samples(nominal, rng, jitter_s=0.0, **kw):
    streams = simulate_own_clocks(nominal, rng, 3.0, jitter_s=jitter_s, noise=False, saturate=False, start_ns=START,
                                  **kw)
    samples = pair_to_reference(streams)
    r = (1 + streams.rates[0]) / (1 + streams.rates) - 1
    b = streams.offsets[0] - (1 + r) * streams.offsets
    period = 5_000_000  # 200 Hz: every clock ticks on START + j 5 ms of its own time
    tick = START + np.round((samples.own_stamps - START) / period).astype(np.int64) * period
    jitter = (samples.own_stamps - tick) * 1e-9
    # true time of each paired message on IMU 0's clock: its clock's tick mapped to IMU 0's clock
    true_delays = (1 + r) * (tick - START) * 1e-9 + b - (samples.stamps[:, None] - START) * 1e-9
    traj = streams.reference_trajectory()
    ctx = lambda delays: motion_context(samples.stamps, *traj(samples.stamps), nominal.rotations,  # noqa: E731
                                        stamp_delays=delays, trajectory=traj)
    model = nominal.with_terms(stamp_clock=streams.stamp_clock_values(samples.stamps[0]))
    return streams, samples, r, jitter, true_delays, ctx, model


def test_true_clock_delays_reproduce_the_own_clock_readings(nominal, rng):
    streams, samples, r, jitter, true_delays, ctx, _ = own_clock_samples(nominal, rng)
    assert len(samples) > 0.95 * 3.0 * 200 and samples.own_stamps.shape == (len(samples), 32)
    assert np.abs(streams.reference_times()[0] - streams.stamps[0]).max() <= 1  # no jitter: IMU 0's tick
    acc, gyro = nominal.predict(ctx(true_delays))
    # times rounded to ns on two clocks: |omega_dot| x 1 ns ~ 2e-7
    assert np.abs(gyro - samples.gyro).max() < 2e-6
    assert np.abs(acc - samples.accel).max() < 2e-6


def test_stamp_clock_with_the_true_offsets_and_skews_reproduces_the_readings(nominal, rng):
    """Without jitter every own stamp is its clock's tick, on IMU 0's grid of stamps; the stamp clock with the
    true offsets and skews relative to IMU 0's clock (which drifts too) gives every reading's true time."""
    streams, samples, r, jitter, true_delays, ctx, model = own_clock_samples(nominal, rng)
    assert streams.rates[0] != 0 and streams.offsets[0] != 0 and np.all(samples.stamp_delays == 0)
    c = ctx(samples.stamp_delays)
    np.testing.assert_allclose(model.sample_delays(c)[..., 1], true_delays, rtol=0, atol=2e-9)
    acc, gyro = model.predict(c)
    assert np.abs(gyro - samples.gyro).max() < 2e-6 and np.abs(acc - samples.accel).max() < 2e-6


def test_stamp_clock_misses_the_stamping_jitter(nominal, rng):
    """With jitter the term's delay misses -(1 + r_k) jitter_k + r_k (own stamp - array stamp): the jitter
    the stamps cannot tell, and the skew counted over the array stamp instead of the IMU's own."""
    streams, samples, r, jitter, true_delays, ctx, model = own_clock_samples(nominal, rng, jitter_s=50e-6)
    assert 30e-6 < np.std(jitter) < 70e-6
    c = ctx(samples.stamp_delays)
    missed = true_delays - model.sample_delays(c)[..., 1]
    np.testing.assert_allclose(missed, r * samples.stamp_delays - (1 + r) * jitter, rtol=0, atol=2e-9)
    acc, gyro = model.predict(c)
    rate = np.abs(streams.truth.trajectory.omega_dot(np.linspace(0, 3, 3000))).max()
    err = np.abs(gyro - samples.gyro).max()
    assert 0.1 * np.abs(missed).max() * rate < err < 1.5 * np.abs(missed).max() * rate + 2e-6
