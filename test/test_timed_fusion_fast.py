"""The fast time-aware compensation of ModelFusion against the straightforward one it replaces.

``reference_fuse`` below is the compensation as it was written before it was made fast (kept here, verbatim
in what it computes): every pass predicts the readings twice with :meth:`SensorModel.predict` -- the whole
model along the local cubics through the estimate (each solved by LAPACK), and the linear part -- and
subtracts.  The fast path (:meth:`SensorModel.predict_nonlinear`: one difference, the timing stage as a
polynomial in each reading's delay; the local cubics solved all at once and shared by the passes; the delays
computed once) must give the same fused samples to rounding: about 1e-12 of each quantity's size, the
rounding of the local cubics' normal equations themselves (their condition number times machine epsilon).
"""

from __future__ import annotations

import numpy as np
import pytest

from imu_array_ros.fusion.ml_fusion import MLFusion
from imu_array_ros.fusion.model_fusion import ModelFusion
from imu_array_ros.model.layouts import grid_array32
from imu_array_ros.model.linear import LinearArrayModel
from imu_array_ros.model.samples import ImuSamples
from imu_array_ros.model.sensor_model import SensorModel, motion_context
from imu_array_ros.model.terms import REGISTRY, term_names
from imu_array_ros.model.terms.sample_clock import SampleClock
from imu_array_ros.model.terms.stamp_clock import StampClock
from imu_array_ros.model.terms.timing import TimingStage, TimingTerm
from imu_array_ros.model.trajectory import MotionTrajectory, fit_weights, shared_fits, solve_spd, timing_context
from imu_array_ros.simulation.simulator import simulate_twist

#: 1-sigma sizes of every term (test_model_fusion's, with the clocks)
SIZES = {
    "position": 1e-3, "axis_offsets": 5e-4, "time_offset": 1e-3,
    "accelerometer_misalignment": 5e-3, "accelerometer_nonorthogonality": 2e-3, "accelerometer_nonlinearity": 5e-4,
    "accelerometer_gain": 0.01, "accelerometer_bias": 0.2, "bias_drift": 2e-3,
    "gyroscope_misalignment": 5e-3, "gyroscope_nonorthogonality": 2e-3, "gyroscope_gain": 0.01,
    "gyroscope_g_sensitivity": 5e-4, "gyroscope_bias": 0.02,
}
REL = 1e-11  # of each fused quantity's largest magnitude (measured: ~1e-14 .. 1e-12)


# ----------------------------------------------------------------------------------------- the reference


def reference_correction(model: SensorModel, fused, t0_ns, stamp_delays=None):
    """h(x_hat) - h_linear(x_hat) as two predictions (the compensation before it was made fast)."""
    ctx = dict(stamps=fused.stamps, omega=fused.omega, omega_dot=fused.omega_dot,
               specific_force=fused.specific_force, rotations=model.rotations, t0_ns=t0_ns)
    if model.timed or stamp_delays is not None:
        motion = np.concatenate([fused.omega, fused.omega_dot, fused.specific_force], axis=1)
        tc = timing_context(fused.stamps, motion)  # the local cubics, one LAPACK solve per sample
        slope = tc["trajectory"].derivative()[:, 0:3]
        tc["omega_rate"] = slope + np.median(motion[:, 3:6] - slope, axis=0)
        full = model.predict(motion_context(**ctx, stamp_delays=stamp_delays, **tc))
    else:
        full = model.predict(motion_context(**ctx, derivatives=True))
    lin = model.linear_part().predict(motion_context(**ctx))
    return full[0] - lin[0], full[1] - lin[1]


def reference_fuse(model: SensorModel, samples: ImuSamples, passes: int = 2):
    fusion = MLFusion(LinearArrayModel.from_sensor_model(model))
    stamps, accel, gyro = samples.stamps, samples.accel, samples.gyro
    t0 = int(stamps[0])
    fused, stats = fusion.fuse(samples)
    delays = samples.stamp_delays
    valid = samples.valid(model)
    for _ in range(passes):
        idx = np.searchsorted(stamps, fused.stamps)
        da, dg = reference_correction(model, fused, t0, None if delays is None else delays[idx])
        acc, gyr = accel.copy(), gyro.copy()
        acc[idx] -= np.where(valid[idx, :, :3], da, 0.0)
        gyr[idx] -= np.where(valid[idx, :, 3:], dg, 0.0)
        fused, stats = fusion.fuse(ImuSamples(stamps, acc, gyr, samples.names, samples.own_stamps))
    return fused, stats


def assert_close(fast, ref, rel=REL):
    np.testing.assert_array_equal(fast.stamps, ref.stamps)
    for name in ("omega", "omega_dot", "specific_force", "covariance"):
        a, b = getattr(fast, name), getattr(ref, name)
        err = np.abs(a - b).max() / np.abs(b).max()
        assert err <= rel, (name, err)


# ----------------------------------------------------------------------------------------- cases


def every_term(rng: np.random.Generator, k: int = 32) -> SensorModel:
    """A random model with every registered term away from identity: sample clocks (of both sensors, or of one)
    and stamp clocks included."""
    nominal = SensorModel.from_description(grid_array32())
    values = {}
    for name in term_names():
        cls = REGISTRY[name]
        if issubclass(cls, SampleClock):  # period ~1 ms, rate within +-3000 ppm, a random phase
            values[name] = np.column_stack([rng.uniform(0.5e-3, 1.5e-3, k), rng.normal(0, 2000.0, k),
                                            rng.uniform(0, 0.5e-3, k)])
        elif issubclass(cls, StampClock):
            values[name] = np.column_stack([rng.normal(0, 5e-4, k), rng.normal(0, 50.0, k)])
        else:
            values[name] = cls.default_values(k) + rng.normal(0, SIZES[name], (k, cls.dim()))
    values["position"] = nominal.positions + rng.normal(0, SIZES["position"], (k, 3))
    return nominal.with_terms(**values)


@pytest.fixture(scope="module")
def recording():
    rng = np.random.default_rng(20261126)
    model = every_term(rng)
    assert not any(model.terms[n].is_identity for n in term_names())
    samples, _ = simulate_twist(model, 1.5, 200.0, rng, rms_rate=np.deg2rad(600))
    return model, samples, rng


def test_every_term_matches_the_reference(recording):
    model, samples, _ = recording
    fast, stats = ModelFusion(model).fuse(samples)
    ref, ref_stats = reference_fuse(model, samples)
    assert stats.fused == ref_stats.fused == len(samples)
    assert_close(fast, ref)


def test_correction_matches_two_predictions(recording):
    """One pass's correction itself, every term (a sample clock, offsets, stamp clocks, nonlinearity,
    g-sensitivity, drift after the linear maps), against full minus linear prediction: to the rounding of the
    full prediction (its size times ~1e-15) and of the local cubics."""
    model, samples, rng = recording
    fusion = ModelFusion(model, t0_ns=int(samples.stamps[0]))
    fused, _ = fusion.fusion.fuse(samples)
    own = rng.normal(0, 1e-3, (len(fused), model.n_imus))
    for sd in (None, own):
        da, dg = fusion.correction(fused, sd)
        ra, rg = reference_correction(model, fused, fusion.t0_ns, sd)
        for fast, ref, size in ((da, ra, np.abs(samples.accel).max()), (dg, rg, np.abs(samples.gyro).max())):
            assert np.abs(fast - ref).max() <= 1e-12 * size, np.abs(fast - ref).max() / size


def test_first_order_and_other_trajectories_match_the_stage():
    """Without a trajectory (first order) and along a trajectory that is not local polynomials (evaluated
    by the stage itself), the stage's shift mapped by the following linear maps equals apply's."""
    rng = np.random.default_rng(3)
    model = every_term(rng)
    n = 50
    stamps = (np.arange(n) * 5e6).astype(np.int64)
    motion = rng.normal(0, 2.0, (n, 9))
    traj = MotionTrajectory(stamps, motion)

    def truth(when):  # a trajectory given as a function (like the simulator's)
        return traj(when)

    for trajectory in (None, truth, traj):
        ctx = motion_context(stamps, motion[:, :3], motion[:, 3:6], motion[:, 6:], model.rotations,
                             omega_ddot=rng.normal(size=(n, 3)), specific_force_dot=rng.normal(size=(n, 3)),
                             omega_rate=rng.normal(size=(n, 3)), stamp_delays=rng.normal(0, 1e-3, (n, 32)),
                             trajectory=trajectory)
        ctx.positions = model.positions
        maps = rng.normal(size=(32, 3, 3))
        for sensor in ("accelerometer", "gyroscope"):
            stage = next(t for t in model.chain(sensor, ctx=ctx) if isinstance(t, TimingStage))
            ref = np.einsum("kij,nkj->nki", maps, stage.apply(np.zeros((n, 32, 3)), ctx, sensor))
            fast = stage.shift(ctx, sensor, maps=maps, chunk=16)
            assert np.abs(fast - ref).max() <= 1e-14 * np.abs(ref).max(), (sensor, trajectory)
            delays = stage.delays(ctx)
            np.testing.assert_allclose(delays[sensor], stage.delay(ctx, sensor), rtol=0, atol=1e-18)


def test_predict_nonlinear_along_any_trajectory_and_in_chunks():
    """predict_nonlinear equals full minus linear prediction along the local cubics (in chunks of samples, and
    with the readings compensated) and along a trajectory given as a function (the simulator's truth, in
    one piece); an empty batch gives empty arrays."""
    rng = np.random.default_rng(8)
    model = every_term(rng)
    n = 70
    stamps = np.cumsum(rng.integers(4_900_000, 5_100_000, n)).astype(np.int64)
    m = rng.normal(0, 2.0, (n, 9))
    local = MotionTrajectory(stamps, m)
    truth = lambda when: local(when)  # noqa: E731  (a callable without rows)
    for trajectory, chunk in ((local, 16), (truth, 16), (None, 7)):
        def ctx():
            return motion_context(stamps, m[:, :3], m[:, 3:6], m[:, 6:], model.rotations, t0_ns=int(stamps[0]) - 10**9,
                                  omega_ddot=local.derivative()[:, 3:6], specific_force_dot=local.derivative()[:, 6:],
                                  omega_rate=local.derivative()[:, :3], trajectory=trajectory,
                                  stamp_delays=rng.normal(0, 1e-3, (n, 32)) if trajectory is None else None)
        c = ctx()
        full_a, full_g = model.predict(c)
        lin_a, lin_g = model.linear_part().predict(motion_context(stamps, m[:, :3], m[:, 3:6], m[:, 6:],
                                                                  model.rotations, t0_ns=int(stamps[0]) - 10**9))
        fa, fg = model.predict_nonlinear(c, chunk=chunk)
        assert np.abs(fa - (full_a - lin_a)).max() <= 1e-13 * np.abs(full_a).max()
        assert np.abs(fg - (full_g - lin_g)).max() <= 1e-13 * np.abs(full_g).max()
        ya, yg = rng.normal(size=(n, 32, 3)), rng.normal(size=(n, 32, 3))
        ca, cg = model.predict_nonlinear(c, chunk=chunk, subtract_from=(ya, yg))
        np.testing.assert_allclose(ca, ya - fa, rtol=0, atol=1e-15 * np.abs(full_a).max())
        np.testing.assert_allclose(cg, yg - fg, rtol=0, atol=1e-15 * np.abs(full_g).max())
    empty = motion_context(stamps[:0], m[:0, :3], m[:0, 3:6], m[:0, 6:], model.rotations, t0_ns=0)
    assert [a.shape for a in model.predict_nonlinear(empty)] == [(0, 32, 3), (0, 32, 3)]


def test_predict_nonlinear_without_timing_terms():
    """A model whose only non-linear terms are not timing terms: the difference of two predictions."""
    rng = np.random.default_rng(5)
    full = every_term(rng)
    model = full.with_terms(**{n: REGISTRY[n].default_values(32) for n in term_names()
                               if issubclass(REGISTRY[n], TimingTerm)})
    assert not model.timed and model.nonlinear_terms
    n = 40
    m = rng.normal(0, 3.0, (n, 9))
    def ctx():
        return motion_context(np.arange(n) * 5_000_000, m[:, :3], m[:, 3:6], m[:, 6:], model.rotations, t0_ns=-10**9)

    fa, fg = model.predict_nonlinear(ctx())
    full_a, full_g = model.predict(ctx())
    lin_a, lin_g = model.linear_part().predict(ctx())
    assert np.abs(fa - (full_a - lin_a)).max() <= 1e-14 * np.abs(full_a).max()
    assert np.abs(fg - (full_g - lin_g)).max() <= 1e-14 * np.abs(full_g).max()


def test_saturated_and_missing_readings_and_own_stamps_match_the_reference():
    """Saturated gyroscopes (kept as read), a missing IMU (NaN) and own stamps: the same as the reference."""
    rng = np.random.default_rng(31)
    model = every_term(rng).with_terms(stamp_clock=np.zeros((32, 2)))  # own stamps instead
    samples, _ = simulate_twist(model, 1.0, 200.0, rng, rms_rate=np.deg2rad(1800.0))
    assert (~model.gyro_unsaturated(samples.gyro)).any()
    accel, gyro = samples.accel.copy(), samples.gyro.copy()
    accel[10:20, 3] = np.nan
    gyro[10:20, 3] = np.nan
    own = samples.stamps[:, None] + rng.integers(-500_000, 500_000, (len(samples), 32))
    for s in (ImuSamples(samples.stamps, accel, gyro, samples.names),
              ImuSamples(samples.stamps, accel, gyro, samples.names, own)):
        fast, _ = ModelFusion(model).fuse(s)
        ref, _ = reference_fuse(model, s)
        assert_close(fast, ref)


def test_local_cubics_solved_at_once_match_lapack():
    """The local cubics' coefficients solved all at once equal LAPACK's per-sample solves to their rounding
    (both are ~1e-12 of each coefficient's size from the exact fit), with gaps, jitter and short segments;
    within shared_fits the weights are reused for the same stamps and refitted for others."""
    rng = np.random.default_rng(9)
    stamps = np.cumsum(rng.integers(4_900_000, 5_100_000, 600)).astype(np.int64)
    stamps[300:] += 10**8  # a gap
    stamps[597:] += 10**8  # a segment of three samples
    t = (stamps - stamps[0]) * 1e-9
    motion = np.stack([np.sin(3 * t + i) * 10 for i in range(9)], axis=1) + rng.normal(0, 0.01, (len(t), 9))
    a = MotionTrajectory(stamps, motion).coef
    b = MotionTrajectory(stamps, motion, solver="cholesky").coef
    scale = np.abs(a[:597]).max(axis=(0, 2))  # per degree
    assert np.all(np.abs(a - b)[:597].max(axis=(0, 2)) <= 1e-10 * scale)
    # three samples hold a cubic only through the ridge: a condition number of ~1e9 for either solver
    assert np.all(np.abs(a - b)[597:].max(axis=(0, 2)) <= 1e-5 * np.abs(a[597:]).max(axis=(0, 2)))
    with shared_fits():
        c = MotionTrajectory(stamps, motion, solver="cholesky").coef
        d = MotionTrajectory(stamps, 2.0 * motion, solver="cholesky").coef
        e = MotionTrajectory(stamps[:-1], motion[:-1], solver="cholesky").coef
    np.testing.assert_array_equal(c, b)
    np.testing.assert_allclose(d, 2.0 * b, rtol=1e-13, atol=1e-13 * np.abs(b).max())
    np.testing.assert_array_equal(e.shape, (599,) + b.shape[1:])
    idx, w = fit_weights(stamps)
    assert idx.shape[0] == w.shape[0] == len(stamps)


def test_solve_spd():
    rng = np.random.default_rng(2)
    x = rng.normal(size=(100, 4, 4))
    a = x @ x.transpose(0, 2, 1) + 0.1 * np.eye(4)
    b = rng.normal(size=(100, 4, 7))
    np.testing.assert_allclose(solve_spd(a, b), np.linalg.solve(a, b), rtol=1e-10, atol=1e-12)
