"""Fusion of samples with IMU dropouts, missing axes and saturation, sample by sample (issue 6 §5).

A batch mixes many patterns of valid axes.  Whatever the batch code does
with them (shared geometry for the common pattern, per-sample geometry for the
rest), every sample must come out as if it had been fused on its own:

* IMU dropouts: equal to fusing the sample alone with the sub-array of the
  IMUs present (``LinearArrayModel.select``), i.e. the full-pattern path of a
  smaller model;
* any mix of missing axes, saturated accelerometer and gyroscope axes and
  unidentifiable samples: equal to fusing the sample alone (a batch of one has
  a single pattern), with the same samples skipped and the same counts.

No numbers are stored: both sides are computed here.
"""

from __future__ import annotations

import numpy as np
import pytest

from imu_array_ros.fusion.ml_fusion import FusionStats, MLFusion
from imu_array_ros.model.linear import LinearArrayModel
from imu_array_ros.simulation.motion import random_motion
from imu_array_ros.simulation.simulator import simulate_measurements, simulate_twist
from imu_array_ros.model.samples import ImuSamples


def _assert_same(batch, ref, where):
    np.testing.assert_allclose(batch.omega, ref.omega, rtol=1e-9, atol=1e-12, err_msg=where)
    np.testing.assert_allclose(batch.omega_dot, ref.omega_dot, rtol=1e-9, atol=1e-9, err_msg=where)
    np.testing.assert_allclose(batch.specific_force, ref.specific_force, rtol=1e-9, atol=1e-11, err_msg=where)
    # covariance entries relative to the sample's own standard deviations (correlations to 1e-9)
    sd = np.sqrt(np.einsum("nii->ni", ref.covariance))
    np.testing.assert_allclose(np.sqrt(np.einsum("nii->ni", batch.covariance)), sd, rtol=1e-9, err_msg=where)
    np.testing.assert_allclose(batch.covariance / (sd[:, :, None] * sd[:, None, :]),
                               ref.covariance / (sd[:, :, None] * sd[:, None, :]), rtol=0, atol=1e-9, err_msg=where)
    assert np.array_equal(batch.converged, ref.converged), where


def _concat(parts):
    return {k: np.concatenate([getattr(p, k) for p in parts]) for k in
            ("stamps", "omega", "omega_dot", "specific_force", "covariance", "iterations", "converged")}


class _Rows:
    def __init__(self, d):
        self.__dict__.update(d)


def test_random_imu_dropouts_equal_reduced_arrays(array32, rng):
    """10 % random IMU dropouts (hundreds of patterns): each sample = its sub-array fused alone."""
    model = LinearArrayModel.from_description(array32)
    samples, _ = simulate_twist(array32, duration=0.4, rate_hz=1000.0, rng=rng, rms_rate=np.deg2rad(1500))
    n = len(samples)
    drop = rng.random((n, 32)) < 0.10
    drop[:20] = False  # some complete samples too
    samples.accel[drop] = np.nan
    samples.gyro[drop] = np.nan
    fused, stats = MLFusion(model).fuse(samples)
    assert stats.fused == n and stats.incomplete_samples == np.count_nonzero(drop.any(1))
    assert stats.patterns > 300  # the case of issue 6 §5: (nearly) one pattern per sample
    assert stats.saturated_gyro_samples > 0  # fast enough that some gyros clip, too
    parts = []
    for i in range(n):
        keep = np.flatnonzero(~drop[i])
        sub = model.select(keep)
        one, st = MLFusion(sub).fuse(ImuSamples(samples.stamps[i:i + 1], samples.accel[i:i + 1, keep],
                                                samples.gyro[i:i + 1, keep], sub.names))
        assert st.fused == 1 and st.incomplete_samples == 0 and st.patterns == 1
        parts.append(one)
    _assert_same(fused, _Rows(_concat(parts)), "IMU dropouts vs sub-array")


def _mixed_batch(desc, rng):
    """Samples at 1000-4000 deg/s with every kind of invalid axis, and the unidentifiable ones' indices."""
    k = len(desc.imus)
    model = LinearArrayModel.from_description(desc)
    speeds = np.deg2rad([1000.0, 2300.0, 2600.0, 4000.0])
    truth_parts = [random_motion(120, w, np.deg2rad(2000.0), rng) for w in speeds]
    samples = simulate_measurements(desc, truth_parts[0], rng)
    for t in truth_parts[1:]:
        s = simulate_measurements(desc, t, rng)
        samples.accel = np.concatenate([samples.accel, s.accel])
        samples.gyro = np.concatenate([samples.gyro, s.gyro])
    n = len(samples.accel)
    samples.stamps = np.arange(n, dtype=np.int64) * 1000
    acc, gyr = samples.accel, samples.gyro
    acc[rng.random((n, k)) < 0.05] = np.nan  # IMU dropouts (accelerometer and gyroscope alike)
    gyr[np.isnan(acc[:, :, 0])] = np.nan
    acc[rng.random((n, k, 3)) < 0.01] = np.nan  # single missing axes
    gyr[rng.random((n, k, 3)) < 0.01] = np.nan
    acc[rng.random((n, k, 3)) < 0.002] = np.inf  # bad values
    clip = rng.random((n, k, 3)) < 0.01  # accelerometer axes at the clip level
    acc[clip] = np.sign(rng.normal(size=np.count_nonzero(clip))) * model.acc_clip
    # unidentifiable: no gyroscope; gyro axes spanning only a plane (no starting point);
    # only 2 accelerometer triads; 3 collinear ones (one grid row)
    bad = [7, 20, 130, 250]
    gyr[7] = np.nan
    gyr[20, :, 2] = np.nan
    acc[130, 2:] = np.nan
    row = np.flatnonzero(np.isclose(model.positions[:, 1], model.positions[0, 1])
                         & np.isclose(model.positions[:, 2], model.positions[0, 2]))
    assert len(row) == 4
    acc[250, np.setdiff1d(np.arange(k), row[:3])] = np.nan
    # still identifiable: a single gyro triad; 3 non-collinear accelerometer triads
    gyr[300, np.arange(k) != 5] = np.nan
    gyr[300, 5] = 0.1
    acc[310, np.setdiff1d(np.arange(k), [row[0], row[1], row[0] + 4])] = np.nan
    return samples, bad


def test_mixed_invalid_axes_equal_one_sample_at_a_time(array32, rng):
    """Missing/bad/saturated axes of both sensors and unidentifiable samples: batch = one by one."""
    model = LinearArrayModel.from_description(array32)
    samples, bad = _mixed_batch(array32, rng)
    n = len(samples.stamps)
    fz = MLFusion(model)
    fused, stats = fz.fuse(samples)
    assert stats.patterns > 200
    assert stats.saturated_gyro_samples > 100 and stats.saturated_accel_samples > 50
    parts, total = [], FusionStats()
    for i in range(n):
        one, st = MLFusion(model).fuse(samples.select(slice(i, i + 1)))
        parts.append(one)
        total.merge(st)
    skipped = [i for i in range(n) if samples.stamps[i] not in set(fused.stamps.tolist())]
    assert skipped == bad
    assert stats.fused == n - len(bad) == total.fused
    for name in ("skipped_unidentifiable", "incomplete_samples", "saturated_gyro_samples", "saturated_accel_samples",
                 "not_converged"):
        assert getattr(stats, name) == getattr(total, name), name
    assert stats.skipped_stamps == samples.stamps[bad].tolist()
    ref = _Rows(_concat(parts))
    assert np.array_equal(fused.stamps, ref.stamps)
    _assert_same(fused, ref, "batch vs one at a time")
    assert np.all(np.isfinite(fused.omega)) and np.all(np.isfinite(fused.covariance))


@pytest.mark.parametrize("dead", ["imu", "axis", "three_imus"])
def test_shared_pattern_need_not_be_complete(array32, rng, dead):
    """Part of the array dead for a whole recording plus random dropouts: the same numbers as one by one.

    The most common pattern is then an IMU missing (in the table), a single accelerometer axis
    missing, or three IMUs missing (both built per pattern).
    """
    model = LinearArrayModel.from_description(array32)
    samples, _ = simulate_twist(array32, duration=0.1, rate_hz=1000.0, rng=rng, rms_rate=np.deg2rad(900))
    if dead == "axis":
        samples.accel[:, 11, 2] = np.nan
    else:
        imus = [11] if dead == "imu" else [3, 11, 20]
        samples.accel[:, imus] = np.nan
        samples.gyro[:, imus] = np.nan
    drop = rng.random((len(samples), 32)) < 0.03
    samples.accel[drop] = np.nan
    samples.gyro[drop] = np.nan
    fused, stats = MLFusion(model).fuse(samples)
    assert stats.fused == len(samples) and stats.incomplete_samples == len(samples)
    parts = [MLFusion(model).fuse(samples.select(slice(i, i + 1)))[0]
             for i in range(len(samples))]
    _assert_same(fused, _Rows(_concat(parts)), "dead IMU")


def test_planar_array_dropouts_and_unidentifiable_patterns(planar4, rng):
    """4 coplanar IMUs (z = 0), 0-2 of them missing per sample, plus a missing z axis in some.

    Out of the plane, omega_dot_x, omega_dot_y and s_z need three z readings: with fewer a sample is
    not identifiable, whether its geometry comes from the table (2 IMUs missing) or is built (an IMU
    and a z axis missing).  Counts and numbers as one by one.
    """
    model = LinearArrayModel.from_description(planar4)
    truth = random_motion(600, np.deg2rad(2500), np.deg2rad(2000), rng)  # some gyros saturate too
    samples = simulate_measurements(planar4, truth, rng)
    n_drop = rng.integers(0, 3, size=600)
    drop = np.argsort(rng.random((600, 4)), axis=1) < n_drop[:, None]
    samples.accel[drop] = np.nan
    samples.gyro[drop] = np.nan
    samples.accel[::7, 0, 2] = np.nan  # a single missing accelerometer axis (the per-sample build)
    fused, stats = MLFusion(model).fuse(samples)
    parts, total = [], FusionStats()
    for i in range(600):
        one, st = MLFusion(model).fuse(samples.select(slice(i, i + 1)))
        parts.append(one)
        total.merge(st)
    too_few = np.isfinite(samples.accel[:, :, 2]).sum(axis=1) < 3
    assert np.count_nonzero(too_few & (n_drop == 2)) > 100 and np.count_nonzero(too_few & (n_drop == 1)) > 10
    assert stats.skipped_unidentifiable == total.skipped_unidentifiable == np.count_nonzero(too_few)
    assert set(fused.stamps.tolist()) == set(samples.stamps[~too_few].tolist())
    assert stats.saturated_gyro_samples == total.saturated_gyro_samples > 0
    _assert_same(fused, _Rows(_concat(parts)), "planar array")
