"""A pooled candidate is preferred over a simpler one it holds only when its increment is block-robust
(:mod:`imu_array_ros.discovery.increment`, :func:`imu_array_ros.discovery.explain.increment_test`).

Synthetic block scores of one 3-parameter term on 4 IMUs (cross-IMU informations, 40 blocks): a strong effect on
imu 0, constant over the blocks (the robust carrier), plus on imus 1-3 either a block-coloured effect (its own
value in every block, mean zero: a large score, nothing robust) or a constant one.  The joint ("all own") robust
test passes in both cases, carried by imu 0; only the increment's test tells them apart."""

from __future__ import annotations

import numpy as np
import scipy.stats

from imu_array_ros.discovery.explain import Candidate, block_tests, increment_test
from imu_array_ros.discovery.increment import increment_gate
from imu_array_ros.discovery.scopes import Scope, scoped_blocks
from imu_array_ros.fitting.score import ScoreBlocks

LEVEL = 1e-4
K, P, B = 4, 3, 40
CARRIER = np.array([40.0, -30.0, 35.0])


def _blocks(extra: str, seed: int = 0, strength: float = 1.0) -> ScoreBlocks:
    """ScoreBlocks of gyroscope_bias on K IMUs: g_b = S_b theta_b + N(0, S_b), theta_b: CARRIER on imu 0 and on
    the others nothing (extra "none"), a value drawn anew in every block ("coloured", sd 28 strength) or one
    value in all blocks ("robust", 5 strength)."""
    rng = np.random.default_rng(seed)
    n = K * P
    a = rng.normal(size=(B, n, n)) / np.sqrt(n * B)
    S = a @ np.swapaxes(a, 1, 2)  # (B, KP, KP), sum ~ I
    theta = np.zeros((B, K, P))
    theta[:, 0] = CARRIER
    if extra == "coloured":
        theta[:, 1:] = 28.0 * strength * rng.normal(size=(B, K - 1, P))
    elif extra == "robust":
        theta[:, 1:] = 5.0 * strength * np.array([1.0, -1.0, 0.5])
    g = np.einsum("bij,bj->bi", S, theta.reshape(B, n))
    g += np.einsum("bij,bj->bi", np.linalg.cholesky(S + 1e-12 * np.eye(n)), rng.normal(size=(B, n)))
    cross = S.reshape(B, K, P, K, P).transpose(0, 1, 3, 2, 4)  # (B, K, K, p, p)
    own = np.stack([cross[:, k, k] for k in range(K)], axis=1)
    return ScoreBlocks(terms=("gyroscope_bias",), offsets={"gyroscope_bias": 0}, g=g.reshape(B, K, P), S=own,
                       counts=np.full(B, 100), residuals=None, expected=None, valid_axes=10_000,
                       S_cross={"gyroscope_bias": cross})


def _candidate(sb, scope: Scope) -> Candidate:
    gb, Sb = scoped_blocks(sb, "gyroscope_bias", scope) if scope.kind != "imu" else (
        sb.g[:, scope.imus[0]], sb.S[:, scope.imus[0]])
    folds = np.arange(B) % 4
    stat, q, lrt_p, log_p, robust_p, heldout, theta = block_tests(gb, Sb, folds, np.unique(folds))
    sensors = tuple(f"imu_{k}" for k in scope.imus)
    return Candidate("gyroscope_bias", scope.imus[0], scope.label, stat, q, lrt_p, robust_p, stat / 2,
                     q * np.log(sb.valid_axes) - stat, heldout, theta, log_p, 1, scope=scope.label, imus=scope.imus,
                     sensors=sensors)


def _pair(extra: str, seed: int = 0):
    sb = _blocks(extra, seed)
    return sb, _candidate(sb, Scope("all own", "own", tuple(range(K)))), _candidate(sb, Scope("imu", "imu", (0,)))


def test_a_block_coloured_increment_riding_on_a_robust_carrier_is_left_out():
    """Coloured extras: 'all own' passes every test of its own and beats imu 0 by BIC (what the search took
    before); its increment (9 dof) has a large score but fails the robust test, so the gate leaves it out."""
    sb, pooled, one = _pair("coloured")
    assert pooled.passes(LEVEL) and one.passes(LEVEL) and pooled.delta_bic < one.delta_bic - 10
    gb, Sb = scoped_blocks(sb, "gyroscope_bias", Scope("all own", "own", tuple(range(K))))
    stat, dof, p = increment_test(gb, Sb, P)  # imu 0's columns first: the nuisance
    assert dof == (K - 1) * P and scipy.stats.chi2.sf(stat, dof) < LEVEL and p > 100 * LEVEL
    kept, left = increment_gate(sb, [pooled, one], LEVEL)
    assert kept == [one] and len(left) == 1 and left[0][:2] == (pooled, one)
    np.testing.assert_allclose(left[0][2], (stat, dof, p), rtol=1e-8)


def test_a_robust_increment_keeps_the_pooled_candidate():
    sb, pooled, one = _pair("robust")
    assert pooled.passes(LEVEL) and pooled.delta_bic < one.delta_bic
    kept, left = increment_gate(sb, [pooled, one], LEVEL)
    assert kept == [pooled, one] and left == []


def test_the_increment_statistic_is_the_joint_less_the_simpler_one():
    """statistic = T(all own) - T(imu 0) (the efficient score statistic of the increment)."""
    sb, pooled, one = _pair("robust", seed=3)
    gb, Sb = scoped_blocks(sb, "gyroscope_bias", Scope("all own", "own", tuple(range(K))))
    np.testing.assert_allclose(increment_test(gb, Sb, P)[0], pooled.statistic - one.statistic, rtol=1e-9)


def test_the_increment_test_holds_its_level_with_no_increment():
    """No effect beyond imu 0 (white scores): the increment's robust p is about uniform (ad hoc bounds on 300
    draws: the share below 5 % within 2-10 %, below 20 % within 12-30 %)."""
    p = []
    for seed in range(300):
        sb = _blocks("none", seed)
        gb, Sb = scoped_blocks(sb, "gyroscope_bias", Scope("all own", "own", tuple(range(K))))
        p.append(increment_test(gb, Sb, P)[2])
    p = np.array(p)
    assert np.all(np.isfinite(p))
    assert 0.02 <= np.mean(p < 0.05) <= 0.10 and 0.12 <= np.mean(p < 0.2) <= 0.30
