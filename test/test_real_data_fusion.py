"""Reality check on the real MIMU4444BT captures: fusion beyond the gyro range (skog2016 Fig. 3)."""

from __future__ import annotations

import numpy as np
import pytest

from imu_array_ros.model.description import load_description
from imu_array_ros.fusion.ml_fusion import MLFusion
from imu_array_ros.io.openshoe.framing import si_saturation_level
from imu_array_ros.io.openshoe.capture import import_capture
from imu_array_ros.model.linear import LinearArrayModel

from conftest import REPO, SHARED_DATA

pytestmark = pytest.mark.skipif(not SHARED_DATA.exists(), reason="shared real data not present")


@pytest.mark.parametrize("capture", ["exp_1.bin", "exp_6.bin"])
def test_range_extension_on_real_twisting(capture):
    """While the gyros clip at 2000 deg/s, the accelerometers carry omega on.

    Even with the nominal (uncalibrated) description: on saturated axes the
    fused component stays beyond the range with the saturated gyros' sign,
    the estimate joins its unsaturated neighbours without a jump, and it
    reaches well past the gyro range.
    """
    desc = load_description(REPO / "config" / "mimu4444bt_corners.yaml")
    model = LinearArrayModel.from_description(desc)
    samples, _ = import_capture(SHARED_DATA / capture, desc)
    fused, stats = MLFusion(model).fuse(samples)
    assert stats.fused >= stats.samples - 5 and stats.saturated_gyro_samples > 500
    idx = np.searchsorted(samples.stamps, fused.stamps)
    gyro = samples.gyro[idx]
    clipped = np.abs(gyro) >= si_saturation_level()[1] * (1 - 1e-9)  # from the raw counts, not the fusion's rule
    sat_sample = clipped.any(axis=(1, 2))
    # imu_1 is mounted with identity orientation: its saturated axes are array axes
    sat_axes = clipped[:, 0, :]
    comp = fused.omega[sat_axes]
    assert np.all(np.sign(comp) == np.sign(gyro[:, 0, :][sat_axes]))
    for sign in (1, -1):  # positive (+32767) and negative (-32768) clipping alike
        c = np.abs(fused.omega[sat_axes & (np.sign(gyro[:, 0, :]) == sign)]) / model.gyro_range
        # measured 1.08-1.10 and 0.83; a fusion that trusts clipped readings is pinned at 1.000 and 0.0
        assert np.median(c) > 1.04 and np.mean(c > 1.01) > 0.6, (sign, np.median(c), np.mean(c > 1.01))
    assert np.linalg.norm(fused.omega[sat_sample], axis=1).max() > 1.4 * model.gyro_range
    # no jump where saturation starts or ends: steps there are like other fast steps
    step = np.linalg.norm(np.diff(fused.omega, axis=0), axis=1)
    edges = np.flatnonzero(np.diff(sat_sample.astype(int)) != 0)
    fast = (np.linalg.norm(fused.omega[1:], axis=1) > 20) & ~sat_sample[1:] & ~sat_sample[:-1]
    assert np.median(step[edges]) < 1.3 * np.median(step[fast])
