"""The timing remainders the fitting engine keeps on a frozen trajectory (issue 23 item 7: discovery's speed) give
the answers of the long way bit for bit: the remainder (the exact shift along the trajectory minus its own first
order) does not depend on the samples' motion, so a problem keeps each chunk's until the next freeze
(:meth:`~imu_array_ros.fitting.problem.Problem.context_at`, ``MotionContext.remainders``) and the step halving's
subsets read their rows (:meth:`~imu_array_ros.fitting.problem.Problem.remainder_rows`); the stage recomputes one
whose delays, positions or rotations changed (:meth:`~imu_array_ros.model.terms.timing.TimingStage.remainder`)."""

from __future__ import annotations

import numpy as np
import pytest

from imu_array_ros.fitting.engine import fit_motion, fit_terms
from imu_array_ros.fitting.problem import Problem
from imu_array_ros.fitting.reading_rates import reading_rates
from imu_array_ros.model.terms.timing import TimingStage

from conftest import clocked_twist_case

STAMPS = (np.arange(150) * 16_000_000).astype(np.int64)  # 150 reads at 62.5 Hz


@pytest.fixture(scope="module")
def case():
    """Sample clocks on 8 corner IMUs, hand-like twisting (test_fitting_fast_paths.py's recording, another seed)."""
    return clocked_twist_case(617093, STAMPS)


def _counted(monkeypatch, long_way: bool) -> list:
    """[remainders computed]; long_way: every remainder computed afresh (nothing kept), as before the cache."""
    count = [0]
    compute = TimingStage._remainder

    def counted(self, *args, **kwargs):
        count[0] += 1
        return compute(self, *args, **kwargs)
    monkeypatch.setattr(TimingStage, "_remainder", counted)
    if long_way:
        monkeypatch.setattr(TimingStage, "remainder", lambda self, ctx, sensor, delta: self._remainder(ctx, sensor,
                                                                                                      delta))
    return count


def _both(monkeypatch, run):
    out = []
    for long_way in (True, False):
        count = _counted(monkeypatch, long_way)
        out.append((run(), count[0]))
        monkeypatch.undo()
    return out


@pytest.mark.parametrize("chunk", [None, 40])  # one chunk; four, so that the step halving's subsets span chunks
def test_motion_fit_keeps_the_remainders_and_the_answer(case, monkeypatch, chunk):
    clocked, samples, motion = case
    if chunk is not None:
        init = Problem.__init__

        def small(self, *args, **kwargs):
            init(self, *args, **kwargs)
            self.chunk = chunk
        monkeypatch.setattr(Problem, "__init__", small)

    def run():
        with reading_rates():  # from a perturbed start: several rounds, steps halved on some samples
            return fit_motion(samples, clocked, motion * (1 + 0.02 * np.cos(np.arange(len(motion))))[:, None])
    (long, n_long), (short, n_short) = _both(monkeypatch, run)
    # the kept remainders were read (one Gauss-Newton step per round since rounds.MOTION_ROUND_STEPS: fewer passes
    # per held trajectory to read them, 12 computed against 20 in one chunk; without the cache the counts are equal)
    assert n_short < n_long
    assert np.array_equal(short.motion, long.motion, equal_nan=True)  # bit for bit
    assert np.array_equal(short.residuals, long.residuals, equal_nan=True)
    assert short.loglik == long.loglik and short.rounds == long.rounds and short.converged == long.converged


def test_joint_fit_with_changing_delays_gives_the_same_answer(case, monkeypatch):
    """time_offset free: the delays change at every step (the kept remainder must not be returned); the gains
    held to theirs (it must)."""
    clocked, samples, motion = case

    def run():
        with reading_rates():
            return fit_terms(samples, clocked, ["time_offset", "gyroscope_gain"], motion0=motion, max_iterations=20,
                             sandwich=False, cost_tolerance=0.1)
    (long, n_long), (short, n_short) = _both(monkeypatch, run)
    assert n_short < n_long
    assert np.array_equal(short.theta, long.theta)
    assert np.array_equal(short.motion, long.motion, equal_nan=True)
    assert short.loglik_after == long.loglik_after and short.iterations == long.iterations
    assert np.array_equal(short.covariance, long.covariance)


def test_a_remainder_is_kept_only_for_its_own_delays_positions_and_rotations(case):
    clocked, samples, motion = case
    with reading_rates():
        prob = Problem(samples, clocked, ("position",), np.arange(clocked.n_imus))
        z = prob.check_motion(motion)
    prob.freeze(z)
    derivs = prob.derivatives(z)
    ctx = clocked._prepare(prob.context_at(clocked, z, derivs, slice(0, prob.n)))
    assert ctx.remainders is not None
    stage = [t for t in clocked.chain("accelerometer", ctx=ctx) if isinstance(t, TimingStage)][0]
    delta = stage.delay(ctx, "accelerometer")
    first = stage.remainder(ctx, "accelerometer", delta)
    assert stage.remainder(ctx, "accelerometer", delta.copy()) is first  # kept
    other = stage.remainder(ctx, "accelerometer", delta * 1.5)
    assert other is not first and not np.array_equal(other, first)
    assert np.array_equal(other, stage._remainder(ctx, "accelerometer", delta * 1.5))
    ctx.positions = ctx.positions + 1e-3
    moved = stage.remainder(ctx, "accelerometer", delta * 1.5)
    assert moved is not other and np.array_equal(moved, stage._remainder(ctx, "accelerometer", delta * 1.5))
    # a context on another trajectory than the frozen one keeps nothing
    prob.freeze(None)
    assert prob.context_at(clocked, z, prob.derivatives(z), slice(0, prob.n)).remainders is None


def test_rows_of_the_kept_chunks_are_the_subsets_own_remainders(case):
    clocked, samples, motion = case
    with reading_rates():
        prob = Problem(samples, clocked, ("position",), np.arange(clocked.n_imus))
        z = prob.check_motion(motion)
    prob.chunk = 37
    prob.freeze(z)
    derivs = prob.derivatives(z)
    prob.residuals(clocked, z, derivs)  # every chunk's remainders kept
    idx = np.array([1, 5, 36, 37, 80, 111, 112, 149])
    held = prob.remainder_rows(idx)
    assert set(held) == {"accelerometer", "gyroscope"}
    plain = clocked._prepare(prob.context_at(clocked, z, derivs, idx))
    plain.remainders = None
    for sensor, (delta, _, _, value) in held.items():
        stage = [t for t in clocked.chain(sensor, ctx=plain) if isinstance(t, TimingStage)][0]
        own = stage.delay(plain, sensor)
        assert np.array_equal(delta, own)
        assert np.array_equal(value, stage._remainder(plain, sensor, own))
    prob.freeze(z)  # a new freeze keeps nothing
    assert prob.remainder_rows(idx) == {}
