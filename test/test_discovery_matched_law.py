"""The matched-resonance test's joint family-wise law over its widths (discovery/matched.py, helper-68): on fresh
white draws its realised rate of p < nominal is within the binomial interval of the nominal; the law before it
(a Gumbel per width, Bonferroni over the 4 widths) is below that interval (benchmarks/results/
matched_null_calibration.md: ~5x conservative), so the check can fail."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import stats

from imu_array_ros.model.sensor_model import SensorModel
from imu_array_ros.simulation.suites import array_description

FS, N, DRAWS = 62.5, 1024, 200
NOMINAL = (0.1, 0.2)


@pytest.fixture(scope="module")
def smallest_p():
    """{law: (2 DRAWS,) smallest p over widths and centres} on white residuals of the 4- and 8-IMU arrays (the
    same draws for both laws; seed 731167, drawn at random for this test, not the law's)."""
    from imu_array_ros.discovery.coherent import field_basis
    from imu_array_ros.discovery.matched import matched_scan

    out = {"joint": [], "bonferroni": []}
    for i, array in enumerate(("planar4", "corners8")):
        model = SensorModel.from_description(array_description(array))
        basis = field_basis(model.positions, model.rotations, min_scale=0.25)
        rng = np.random.default_rng([731167, i])
        for _ in range(DRAWS):
            acc = rng.normal(size=(N, basis.shape[0]))
            for law in out:
                scan = matched_scan(acc, basis, FS, 1.0, bonferroni=law == "bonferroni")
                out[law].append(min(float(np.min(w["p"])) for w in scan["widths"].values()))
    return {law: np.array(p) for law, p in out.items()}


def _interval(nominal: float, n: int) -> tuple[float, float]:
    """Central 99.9 % binomial interval of the rate of n draws at the nominal rate."""
    return stats.binom.ppf(0.0005, n, nominal) / n, stats.binom.isf(0.0005, n, nominal) / n


def test_joint_law_is_calibrated_on_fresh_white_draws(smallest_p):
    """400 white recordings (4 and 8 IMUs, 1024 samples): at nominal 0.1 and 0.2 the realised family-wise rate is
    within the 99.9 % binomial interval of the nominal (when written: 0.09 and 0.20; at 0.01: 0.013)."""
    p = smallest_p["joint"]
    for a in NOMINAL:
        lo, hi = _interval(a, len(p))
        assert lo <= np.mean(p < a) <= hi, f"nominal {a}: realised {np.mean(p < a):.3f}, interval {lo:.3f}-{hi:.3f}"


def test_bonferroni_law_before_fails_the_same_check(smallest_p):
    """The same draws under the law before (``bonferroni=True``): below the interval at both levels (ad hoc when
    written: 0.05 and 0.11; at 0.01: 0.005), and less often below 0.2 than the joint law (it spends less of alpha)."""
    p = smallest_p["bonferroni"]
    for a in NOMINAL:
        assert np.mean(p < a) < _interval(a, len(p))[0]
    assert np.mean(p < 0.2) < np.mean(smallest_p["joint"] < 0.2)
