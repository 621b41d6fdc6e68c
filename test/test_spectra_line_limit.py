"""spectra.welch_line_limit: the narrowband line test's per-bin limit holds its level at the Bonferroni tail.

Reference: with L Welch segments the relative PSD of white noise at an inner bin is (1/L) sum_j mu_j E_j (E_j ~
Exp(1), mu_j the segments' correlation eigenvalues), whose tail for a few segments is the hypoexponential sum,
exact in closed form.  Welch's equivalent-dof chi-square (the limit used before) is 1.46x its level at 1e-6 with
3 segments and 1.52x with 4; the test fails with it."""

from __future__ import annotations

import numpy as np
import pytest

from imu_array_ros.discovery.spectra import line_bins, welch_line_limit


def _eigenvalues(segments: int, nper: int = 256) -> np.ndarray:
    w = np.hanning(nper + 1)[:-1]  # scipy's periodic Hann, written independently
    d = nper // 2
    rho = float(w[:-d] @ w[d:] / (w @ w))
    return 1.0 + 2.0 * rho * np.cos(np.arange(1, segments + 1) * np.pi / (segments + 1))


def _exact_sf(x: float, mu: np.ndarray) -> float:
    t = x * len(mu)
    return float(sum(np.prod([mu[j] / (mu[j] - mu[i]) for i in range(len(mu)) if i != j]) * np.exp(-t / mu[j])
                     for j in range(len(mu))))


@pytest.mark.parametrize("segments", [2, 3, 4, 5])
@pytest.mark.parametrize("alpha", [1e-4, 1e-6, 1e-8])
def test_the_limit_has_the_exact_tail_probability(segments, alpha):
    x = welch_line_limit(alpha, segments, 256)
    assert _exact_sf(x, _eigenvalues(segments)) == pytest.approx(alpha, rel=0.05)


def test_one_segment_is_exponential():
    assert welch_line_limit(1e-6, 1, 256) == pytest.approx(-np.log(1e-6), rel=1e-12)


def test_white_noise_fires_at_the_bins_level():
    """Per-bin rate at 1e-3 (the same code path as the Bonferroni level, checkable with few draws): 150 draws of
    8 IMUs x 6 channels x 1,792 samples, 13 segments, 18,288 bins each; Poisson 3-sigma band."""
    from imu_array_ros.discovery.spectra import relative_psd
    import imu_array_ros.discovery.spectra as spectra

    rng = np.random.default_rng(20261129)
    hits = total = 0
    lim = welch_line_limit(1e-3, 13, 256)
    for _ in range(150):
        _, p = relative_psd(rng.normal(size=(1792, 48)), 100.0)
        hits += int((p[:, 1:-1] > lim).sum())
        total += p[:, 1:-1].size
    expected = 1e-3 * total
    assert abs(hits - expected) < 3 * np.sqrt(expected)
    assert spectra.LINE_ALPHA == 0.01


def test_line_bins_uses_the_limit():
    """A bin exactly at the Bonferroni limit (times 1 +- 1e-6) is / is not flagged."""
    n, k = 1792, 2
    psd = np.ones((k, 6, 129))
    floor = np.ones((k, 6))
    lim = welch_line_limit(0.01 / (k * 6 * 127), 13, 256)
    psd[0, 0, 40] = lim * (1 + 1e-6)
    psd[1, 2, 41] = lim * (1 - 1e-6)
    b = line_bins(psd, floor, n)
    assert b[0, 0, 40] and not b[1, 2, 41] and b.sum() == 1
