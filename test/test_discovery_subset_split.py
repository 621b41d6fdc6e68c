"""Narrowing a pooled finding on a scope too large for every subset (:mod:`imu_array_ros.discovery.subset_split`,
:func:`imu_array_ros.discovery.subset.propose`): one value shared by an unknown 12-20 of 32 IMUs, each in its
own orientation, with a common value the fit cannot tell from the motion (an exact gauge the fit holds on its
first IMU, or a near-gauge: a common value only weakly observed), is reported on exactly those IMUs.

Hand-made joint fits (exact numbers, no engine), fixed seeds."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from imu_array_ros.discovery.subset import EIG_RTOL, GAUGE_SEARCH_MAX, propose, shared_sets, shared_statistics
from imu_array_ros.discovery.subset_split import split_sets

TERM = "gyroscope_bias"  # 3 parameters
G, P = 32, 3


def _scenario(seed: int, exact: bool):
    """(fit, carriers): a gyroscope bias v shared by a random 12-20 of 32 randomly oriented IMUs, plus a common
    body-frame bias b (R_k^T b on IMU k) and independent noise (std 0.5-2 per IMU).  exact: b is a gauge of the
    fit (gauge_directions), held at IMU 0's value; else b is weakly observed (std 100, in the covariance)."""
    rng = np.random.default_rng(seed)
    carriers = np.sort(rng.choice(G, size=int(rng.integers(12, 21)), replace=False))
    rot = Rotation.random(G, random_state=rng).as_matrix()
    gauge = np.concatenate([r.T for r in rot])  # (G p, 3): the common body-frame bias in each sensor's frame
    sd = np.repeat(rng.uniform(0.5, 2.0, G), P)
    v = rng.normal(size=P)
    v *= 20.0 / np.linalg.norm(v)  # >= 10 std on every IMU: each carrier is needed
    inside = np.zeros(G, dtype=bool)
    inside[carriers] = True
    b = rng.normal(size=P) * 100.0
    x = (inside[:, None] * v).reshape(-1) + gauge @ b + rng.normal(size=G * P) * sd
    cov = np.diag(sd ** 2)
    if exact:  # the fit's gauge puts IMU 0 at its starting value: d = A x, A = I - D R_0 E_0
        a = np.eye(G * P)
        a[:, :P] -= gauge @ rot[0]
        d, cov = a @ x, a @ cov @ a.T
        d[:P], cov[:P, :], cov[:, :P] = 0.0, 0.0, 0.0
        directions = gauge
    else:
        d, cov, directions = x, cov + 100.0 ** 2 * gauge @ gauge.T, np.zeros((G * P, 0))
    names = tuple(f"imu_{k:02d}" for k in range(G))
    fit = SimpleNamespace(free=(TERM,), imus=names, model=SimpleNamespace(names=names), theta=d, covariance=cov,
                          gauge_directions=directions)
    return fit, tuple(int(k) for k in carriers)


@pytest.mark.parametrize("exact", [True, False], ids=["exact gauge", "near gauge"])
@pytest.mark.parametrize("seed", range(6))
def test_a_value_shared_by_an_unknown_set_of_32_is_found(seed, exact):
    fit, carriers = _scenario(seed, exact)
    prop = propose(fit, TERM, range(G), np.zeros((G, P)), 0.01)
    assert prop is not None and prop.in_gauge
    assert prop.imus == carriers
    assert prop.gauge == exact  # the report says "up to the gauge" only where a gauge freedom moves the term


@pytest.mark.parametrize("exact", [True, False], ids=["exact gauge", "near gauge"])
def test_the_carriers_are_a_split_along_the_whitened_values(exact):
    fit, carriers = _scenario(100, exact)
    basis = np.linalg.svd(fit.gauge_directions, full_matrices=False)[0] if exact else np.zeros((G * P, 0))
    sets = split_sets(fit.theta, fit.covariance, basis, G, P, rtol=EIG_RTOL)
    assert len(sets) == 2 * (G - 1)
    truth = np.zeros(G, dtype=bool)
    truth[list(carriers)] = True
    assert any((s == truth).all() for s in sets) and any((s == ~truth).all() for s in sets)
    stat, dof = shared_statistics(fit.theta, fit.covariance, basis, P, sets)
    assert (sets[np.argmin(stat)] == truth).all() or (exact and (sets[np.argmin(stat)] == ~truth).all())
    assert (dof == G * P - P - basis.shape[1]).all()


def test_small_scopes_still_try_every_subset():
    """shared_sets (G <= GAUGE_SEARCH_MAX): every non-empty proper subset, statistics as shared_statistics."""
    rng = np.random.default_rng(7)
    g = GAUGE_SEARCH_MAX
    d, basis = rng.normal(size=g * P), np.linalg.qr(np.tile(np.eye(P), (g, 1)))[0]
    sets, stat, dof = shared_sets(d, np.eye(g * P), basis, g, P)
    assert len(sets) == 2 ** g - 2 and len({tuple(s) for s in sets}) == len(sets)
    again = shared_statistics(d, np.eye(g * P), basis, P, sets[::-1])
    assert np.array_equal(again[0][::-1], stat) and np.array_equal(again[1][::-1], dof)
