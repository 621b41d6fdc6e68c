"""Empirical (sparse-regression) models of residual structure: feature library, selection, held-out scoring."""

from __future__ import annotations

import json

import numpy as np
import pytest
from scipy.signal import lfilter

from imu_array_ros.discovery.empirical import block_folds, fit_empirical, motion_features, stlsq

N, FS = 4000, 100.0
STAMPS = np.arange(N, dtype=np.int64) * 10_000_000 + 1_700_000_000 * 10**9


def smooth_motion(rng, n=N):
    """Band-limited random motion (N, 9): omega, its derivative, and s around gravity."""
    w = lfilter([0.05], [1.0, -0.95], rng.normal(0, 20, (n, 3)), axis=0)
    s = lfilter([0.05], [1.0, -0.95], rng.normal(0, 30, (n, 3)), axis=0) + [0.0, 0.0, 9.81]
    return np.column_stack([w, np.gradient(w, 1 / FS, axis=0), s])


def test_feature_library():
    rng = np.random.default_rng(1)
    m = smooth_motion(rng, 200)
    m[50] = np.nan
    x, names = motion_features(m, STAMPS[:200])
    assert x.shape == (200, len(names)) and len(set(names)) == len(names) == 43
    col = {n: x[:, i] for i, n in enumerate(names)}
    ok = np.arange(200) != 50
    assert np.all(col["1"][ok] == 1.0)
    assert np.allclose(col["omega_x*s_y"][ok], (m[:, 0] * m[:, 7])[ok])
    assert np.allclose(col["omega_y*omega_z"][ok], (m[:, 1] * m[:, 2])[ok])
    assert np.allclose(col["s_z*s_z"][ok], (m[:, 8] ** 2)[ok])
    assert np.allclose(col["s_x[n-1]"][52:], m[51:-1, 6]) and np.isnan(col["s_x[n-1]"][0])
    assert np.allclose(col["omega_z[n-1]"][52:], m[51:-1, 2])
    ds = np.gradient(m[:, 8], 1 / FS)
    assert np.allclose(col["d/dt s_z"][60:], ds[60:])
    assert "d/dt omega_dot_y" in col and "omega_dot_x" in col and "omega_x*omega_x" in col
    assert np.all(np.isnan(x[50]))


def test_product_term_is_found():
    rng = np.random.default_rng(42)
    k, cell = 3, (1, 4)
    m = smooth_motion(rng)
    x, names = motion_features(m, STAMPS)
    f = x[:, names.index("omega_x*s_y")]
    scale = np.nanstd(f)
    r = rng.normal(size=(N, k, 6))
    r[:, cell[0], cell[1]] += 0.5 * f / scale
    r[::13, cell[0], cell[1]] = np.nan                 # masked readings
    std = np.full((k, 6), 0.02)
    folds = block_folds(N, 5)
    (model, other) = fit_empirical(r, x, names, [cell, (0, 0)], folds, std=std)
    assert "omega_x*s_y" in model.features and len(model.features) <= 3
    assert model.axis == "gyr_y" and model.k == 1
    assert model.improves and model.heldout_delta_loglik > 100.0
    assert model.delta_loglik >= model.heldout_delta_loglik > 0
    coef = model.coefficients[model.features.index("omega_x*s_y")]
    assert coef == pytest.approx(0.5 / scale * 0.02, rel=0.1)     # SI: rad/s per (rad/s * m/s^2)
    assert 0.7 < model.share_explained < 1.3
    # the model reproduces the structure it found (in SI)
    pred = model.predict(np.nan_to_num(x))
    assert np.corrcoef(pred[1:], (0.5 * 0.02 * f / scale)[1:])[0, 1] > 0.99
    assert not other.improves
    d = model.to_dict()
    json.dumps(d, allow_nan=False)
    assert set(d) >= {"k", "axis", "features", "coefficients", "delta_loglik", "heldout_delta_loglik",
                      "share_explained", "improves"}


@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_white_noise_rarely_improves(seed):
    rng = np.random.default_rng(seed)
    m = smooth_motion(rng)
    x, names = motion_features(m, STAMPS)
    r = rng.normal(size=(N, 4, 6))
    cells = [(k, a) for k in range(4) for a in range(6)][:20]
    models = fit_empirical(r, x, names, cells, block_folds(N, 5))
    assert len(models) == 20
    assert sum(mo.improves for mo in models) <= 1
    for mo in models:
        json.dumps(mo.to_dict(), allow_nan=False)


def test_fixed_threshold_unused_folds_and_stlsq():
    rng = np.random.default_rng(5)
    m = smooth_motion(rng)
    x, names = motion_features(m, STAMPS)
    r = rng.normal(size=(N, 1, 6))
    r[:, 0, 2] += 0.3 + 0.4 * (m[:, 8] - 9.81) / np.std(m[:, 8])    # bias + s_z dependence
    folds = block_folds(N, 4)
    folds[:500] = -1                                                # unused samples
    (mo,) = fit_empirical(r, x, names, [(0, 2)], folds, threshold=0.1, max_terms=2)
    assert mo.threshold == 0.1 and mo.n_samples == N - 500
    assert set(mo.features) == {"1", "s_z"} and mo.improves
    assert mo.coefficients[1] == pytest.approx(0.4 / np.std(m[:, 8]), rel=0.1)
    # one fold only: nothing can be validated
    (mo,) = fit_empirical(r, x, names, [(0, 2)], np.zeros(N, int))
    assert mo.features == [] and not mo.improves
    # stlsq itself: recovers a sparse vector from its Gram matrix
    z = rng.normal(size=(1000, 6))
    y = 2.0 * z[:, 1] - 0.5 * z[:, 4] + 0.1 * rng.normal(size=1000)
    beta = stlsq(z.T @ z, z.T @ y, 1000, 0.2)
    assert np.flatnonzero(beta).tolist() == [1, 4]
    assert beta[1] == pytest.approx(2.0, abs=0.02)
