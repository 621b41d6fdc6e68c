"""explain.block_tests under the null when a candidate's information sits in a few time blocks (a recording of
icosahedron rests then twisting: the rests tell a lever-arm or gain term next to nothing).

The score test (chi-square) holds its level there; the block-robust test (Hotelling's F with the nominal block
count) does not: benchmarks/results/discovery_score_null.md measured it on the randomised suite's nulls (robust
p < alpha / m on most rests+twist recordings).  The second test is marked xfail(strict): it fails (XPASS) once the
robust test is calibrated, and the marker should then go."""

from __future__ import annotations

import numpy as np
import pytest

from imu_array_ros.discovery.explain import block_tests


def _draws(q: int, b: int, hot: int, reps: int, seed: int):
    """(lrt_p, robust_p) of ``reps`` null draws: block scores g_b ~ N(0, S_b), the first ``hot`` blocks 100x
    the information of the others."""
    rng = np.random.default_rng(seed)
    folds = np.arange(b) % 4
    fold_ids = np.unique(folds)
    out = []
    for _ in range(reps):
        a = rng.normal(size=(b, q, q)) / np.sqrt(q)
        w = np.where(np.arange(b) < hot, 10.0, 0.1)
        sb = np.einsum("bij,bkj->bik", a, a) * w[:, None, None] + 1e-3 * np.eye(q)
        gb = np.einsum("bij,bj->bi", np.linalg.cholesky(sb), rng.normal(size=(b, q)))
        r = block_tests(gb, sb, folds, fold_ids)
        out.append((r[2], r[4]))
    return np.array(out)


def test_the_score_test_holds_its_level_when_the_information_is_in_a_few_blocks():
    """400 draws, 9 dof, 12 of 40 blocks informative: rate below 5 % within 2-8 %."""
    p = _draws(9, 40, 12, 400, 20261129)
    assert 0.02 <= np.mean(p[:, 0] < 0.05) <= 0.08


@pytest.mark.xfail(strict=True, reason="Hotelling's F(q, B - q) with the nominal block count B: anti-conservative "
                                       "when a few blocks hold the information (46 % below 0.01 here, ad hoc)")
def test_the_block_robust_test_holds_its_level_when_the_information_is_in_a_few_blocks():
    """Same draws: the robust p-value below 1 % at most 3 % of the time (calibrated: 1 %)."""
    p = _draws(9, 40, 12, 400, 20261129)
    assert np.mean(p[:, 1] < 0.01) <= 0.03
