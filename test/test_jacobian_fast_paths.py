"""The model's Jacobians and the Schur blocks computed the short way (issue 23 item 7: discovery's linearisations)
equal the long way they replaced: the lever-arm rows of ``position`` and ``axis_offsets`` and the timing stage's
motion rows in closed form instead of 3x3 products (:func:`~imu_array_ros.model.kinematics.lever_rows_jacobian`),
the timing stage's delays and signal rates computed once per chain (:meth:`TimingStage.memoised`), and the stacked
G_n = L_n^-1 B_n as one product per sample (:func:`~imu_array_ros.fitting.schur.stacked_g`).  The long way is
kept here verbatim (the code before the change) and swapped in; the two must agree to 1e-12 of each array's
largest entry (the predictions bit for bit)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

import imu_array_ros.fitting.problem as problem_module
from imu_array_ros.fitting.problem import Problem, keep_schur
from imu_array_ros.fitting.reading_rates import reading_rates
from imu_array_ros.fitting.schur import g_per_imu
from imu_array_ros.model import trajectory
from imu_array_ros.model.kinematics import skew
from imu_array_ros.model.sensor_model import motion_context
from imu_array_ros.model.terms.axis_offsets import AxisOffsets
from imu_array_ros.model.terms.position import Position
from imu_array_ros.model.terms import REGISTRY
from imu_array_ros.model.terms.timing import TimingStage, signal_rate
from imu_array_ros.model.terms.triad import nonorthogonality_matrix

from conftest import clocked_twist_case

ROOT = Path(__file__).resolve().parents[1]
STAMPS = (np.arange(150) * 16_000_000).astype(np.int64)  # 150 reads at 62.5 Hz
SEED = 574522  # drawn with secrets for this test
RTOL = 1e-12


# ---- the long way, as the code was before the short one (verbatim but for the names)

def _old_axis_offsets_d_motion(self, x, ctx, sensor):
    o = self.values.reshape(-1, 3, 3)
    r = np.einsum("kij,kaj->kai", ctx.rotations, o)
    out = np.zeros(x.shape + (9,))
    for a in range(3):
        j = ctx.force_jacobian(r[:, a])
        j[..., 6:] = 0.0
        out[..., a, :] = np.einsum("kj,nkjl->nkl", ctx.rotations[:, :, a], j)
    return out


def _old_position_d_motion(self, x, ctx, sensor):
    j = ctx.force_jacobian(self.values)
    j[..., 6:] = 0.0
    return np.matmul(ctx.rot_t[None], j)


def _old_timing_d_motion(self, x, ctx, sensor):
    out = np.zeros(x.shape + (9,))
    d = self.delay(ctx, sensor)
    rt = ctx.rot_t
    if sensor == "gyroscope":
        if ctx.omega_rate is None:
            out[..., 3:6] = d[..., None, None] * rt[None]
        return out
    p = ctx.positions
    sw, swd, sp = skew(ctx.omega)[:, None], skew(ctx.omega_dot)[:, None], skew(p)[None]
    d_w = -swd @ sp - skew(np.cross(ctx.omega_dot[:, None], p[None]))
    d_wd = -skew(np.cross(ctx.omega[:, None], p[None])) - sw @ sp
    out[..., 0:3] = d[..., None, None] * (rt[None] @ d_w)
    out[..., 3:6] = d[..., None, None] * (rt[None] @ d_wd)
    return out


def _old_stacked_g(jx, linv, jt, out=None):
    n, kf, _, p = jt.shape
    d = jx.shape[-1]
    gk = g_per_imu(jx, linv, jt)[1]
    gmat = gk.transpose(0, 2, 1, 3).reshape(d * n, kf * p)
    if out is not None:  # the linearisation copied it into the G it keeps
        out[...] = gmat.reshape(n, d, kf * p)
    return gmat


def _long_way(monkeypatch):
    monkeypatch.setattr(AxisOffsets, "d_motion", _old_axis_offsets_d_motion)
    monkeypatch.setattr(Position, "d_motion", _old_position_d_motion)
    monkeypatch.setattr(TimingStage, "d_motion", _old_timing_d_motion)
    monkeypatch.setattr(TimingStage, "memoised", lambda self: self)  # every quantity computed where it is read
    monkeypatch.setattr(problem_module, "stacked_g", _old_stacked_g)


def _close(new, old, what):
    new, old = np.asarray(new), np.asarray(old)
    assert new.shape == old.shape, what
    scale = np.max(np.abs(old))
    err = np.max(np.abs(new - old))
    assert err <= RTOL * scale, f"{what}: differs by {err:.3g} of {scale:.3g}"


@pytest.fixture(scope="module")
def case():
    """Sample clocks, time offsets and axis offsets on 8 corner IMUs, hand-like twisting."""
    clocked, samples, motion = clocked_twist_case(SEED, STAMPS)
    rng = np.random.default_rng(SEED + 1)
    k = clocked.n_imus
    model = clocked.with_terms(axis_offsets=rng.normal(0.0, 3e-3, (k, 9)),
                               time_offset=rng.normal(0.0, 2e-3, (k, 2)))
    return model, samples, motion


FREE = ("position", "axis_offsets", "time_offset", "gyroscope_gain",
        "accelerometer_misalignment", "gyroscope_nonorthogonality")


@pytest.mark.parametrize("with_trajectory", [True, False])
def test_the_model_jacobians_equal_the_long_way(case, monkeypatch, with_trajectory):
    model, samples, motion = case
    tc = trajectory.timing_context(samples.stamps, motion[:, :9], degree=trajectory.ENGINE_DEGREE,
                                   window_s=trajectory.ENGINE_WINDOW_S)
    delays = np.random.default_rng(SEED + 2).normal(0.0, 1e-4, (len(samples.stamps), model.n_imus))

    def ctx():  # a fresh context each time (contexts cache derived quantities)
        return motion_context(samples.stamps, motion[:, 0:3], motion[:, 3:6], motion[:, 6:9], model.rotations,
                              omega_ddot=tc["omega_ddot"], specific_force_dot=tc["specific_force_dot"],
                              trajectory=tc["trajectory"] if with_trajectory else None, stamp_delays=delays)
    free = [t for t in FREE if t in model.terms]
    new = model.jacobians(ctx(), free)
    again = model.jacobians(ctx(), free)
    _long_way(monkeypatch)
    old = model.jacobians(ctx(), free)
    assert np.array_equal(new.predicted, old.predicted)
    _close(new.motion, old.motion, "motion")
    assert np.any(new.motion[..., 0:6, 0:6] != 0)
    for name in free:
        assert np.any(old.params[name] != 0), name  # each term's columns are exercised
        _close(new.params[name], old.params[name], name)
    # the memo is per call: a second call gives the same arrays bit for bit
    assert np.array_equal(again.motion, new.motion)
    assert all(np.array_equal(again.params[t], new.params[t]) for t in free)


def test_the_memoised_stage_recomputes_for_another_context(case):
    model, samples, motion = case
    stage = model.chain("accelerometer")
    stage = next(t for t in stage if isinstance(t, TimingStage)).memoised()
    a = motion_context(samples.stamps, motion[:, 0:3], motion[:, 3:6], motion[:, 6:9], model.rotations)
    b = motion_context(samples.stamps, 2 * motion[:, 0:3], motion[:, 3:6], motion[:, 6:9], model.rotations)
    for c, p in ((a, model.positions), (b, model.positions), (a, 1.5 * model.positions)):
        c.positions = p
        x = np.zeros((c.n, c.k, 3))
        plain = TimingStage(stage.terms)
        assert np.array_equal(stage.apply(x, c, "accelerometer"), plain.apply(x, c, "accelerometer"))
        assert np.array_equal(stage.d_motion(x, c, "accelerometer"), plain.d_motion(x, c, "accelerometer"))


def test_the_linearisation_equals_the_long_way(case, monkeypatch):
    """The whole Schur-complemented system with reading rates (discovery's 15 motion coordinates)."""
    model, samples, motion = case
    with reading_rates(), keep_schur():
        prob = Problem(samples, model, ("time_offset", "axis_offsets", "gyroscope_gain"), np.arange(model.n_imus))
        prob.chunk = 64  # several chunks
        z = prob.check_motion(motion[:, :9])
        new = prob.linearize(model, z)
        _long_way(monkeypatch)
        old = prob.linearize(model, z)
    assert new.S.shape == (prob.m, prob.m) and prob.dm == 15
    assert new.G is not None and old.G is not None
    for name in ("S", "g", "linv", "h", "r", "cdiag", "G"):
        _close(getattr(new, name), getattr(old, name), name)
    assert abs(new.cost - old.cost) <= RTOL * old.cost
    assert np.array_equal(new.ok, old.ok) and np.array_equal(new.exact, old.exact)


def test_the_weighted_parameter_jacobian_is_the_concatenated_one_bit_for_bit(case):
    model, samples, motion = case
    fit = np.array([0, 2, 5])
    prob = Problem(samples, model, ("time_offset", "axis_offsets", "gyroscope_gain"), fit)
    ctx = prob.context(model, motion[:, :9], prob.derivatives(motion[:, :9]), 0, prob.n)
    jac = model.jacobians(ctx, prob.free)
    long = np.concatenate([jac.params[t] for t in prob.free], axis=3)[:, fit] * prob.w[:, fit, :, None]
    short = prob.parameter_jacobian(jac, prob.w)
    assert short.shape == long.shape and np.array_equal(short, long)


def test_the_written_out_products_equal_the_einsums(case):
    """Non-orthogonality's L x and the accelerometers' signal rate ds/dt + dC/dt p_k as the einsums they replaced."""
    model, samples, motion = case
    rng = np.random.default_rng(SEED + 3)
    k = model.n_imus
    for name in ("accelerometer_nonorthogonality", "gyroscope_nonorthogonality"):
        values = rng.normal(0.0, 0.02, (k, 3))
        x = rng.normal(0.0, 10.0, (len(samples.stamps), k, 3))
        new = REGISTRY[name](values).apply(x, None, REGISTRY[name].sensors[0])
        _close(new, np.einsum("kij,nkj->nki", nonorthogonality_matrix(values), x), name)
        assert np.array_equal(new[..., 0], x[..., 0])
    ctx = motion_context(samples.stamps, motion[:, 0:3], motion[:, 3:6], motion[:, 6:9], model.rotations,
                         derivatives=True)
    ctx.positions = model.positions
    sd = ctx.specific_force_dot[:, None, :] + np.einsum("nij,kj->nki", ctx.lever_dot, ctx.positions)
    old = np.matmul(sd.transpose(1, 0, 2), ctx.rotations).transpose(1, 0, 2)
    _close(signal_rate(ctx, "accelerometer"), old, "accelerometer signal rate")
