"""Geometry calibration (carlsson2017): estimator vs its Cramér-Rao bound, BCD vs joint,
identifiability, sample selection, and the write rules (atomic, backup, never worse)."""

from __future__ import annotations

import os

import numpy as np
import pytest

from imu_array_ros.calibration.geometry import calibrate_geometry
from imu_array_ros.calibration.result import backup_path
from imu_array_ros.errors import CalibrationError, OutputError
from imu_array_ros.fusion.model_fusion import ModelFusion
from imu_array_ros.model.description import load_description, save_description
from imu_array_ros.model.sensor_model import SensorModel
from imu_array_ros.model.layouts import grid_array32, tetrahedron4
from imu_array_ros.model.samples import ImuSamples, MotionTruth
from imu_array_ros.simulation.perturb import perturb
from imu_array_ros.simulation.simulator import simulate_measurements, simulate_random, simulate_twist
from imu_array_ros.workflows import calibrate

W = np.deg2rad(2000.0)  # carlsson2017 Fig. 4: |omega| = 2000 deg/s, |omega_dot| = 2000 deg/s^2


@pytest.fixture(scope="module")
def nominal32():
    return SensorModel.from_description(grid_array32())


def _truth_and_start(nominal, rng, sigma=1e-3):
    """True positions (nominal + N(0, sigma)) and the start: nominal, shifted so the reference
    (imu_00, held) sits at its true position -- only relative positions are observable."""
    true = perturb(nominal, rng, {"position": sigma})
    start = nominal.with_terms(position=nominal.positions + (true.positions[0] - nominal.positions[0]))
    return true, start


def _rmse_and_crb(results_and_truths):
    err = np.concatenate([(r.positions - t.positions)[1:].ravel() for r, t in results_and_truths])
    var = np.concatenate([(r.position_std ** 2)[1:].ravel() for r, _ in results_and_truths])
    return float(np.sqrt(np.mean(err ** 2))), float(np.sqrt(np.mean(var)))


def test_fig4_setting_rmse_within_20_percent_of_crb_and_falls_as_inverse_sqrt_n(nominal32):
    """carlsson2017 Fig. 4 setting, Monte Carlo: RMSE / sqrt(CRB) in [0.8, 1.2] at each N, and the
    log-log slope of RMSE against N is -1/2 within 0.1."""
    rmse = {}
    for n, runs in ((30, 12), (300, 6)):
        out = []
        for seed in range(runs):
            rng = np.random.default_rng(1000 * n + seed)
            true, start = _truth_and_start(nominal32, rng)
            s, _ = simulate_random(true, n, W, W, rng)
            out.append((calibrate_geometry(s, start), true))
        rmse[n], crb = _rmse_and_crb(out)
        assert 0.8 < rmse[n] / crb < 1.2, (n, rmse[n], crb)
        assert all(r.converged and r.samples_used == n for r, _ in out)
    slope = np.log(rmse[300] / rmse[30]) / np.log(10.0)
    assert abs(slope + 0.5) < 0.1, slope


def test_two_samples_are_refused_as_not_identifiable(nominal32):
    rng = np.random.default_rng(2)
    true, start = _truth_and_start(nominal32, rng)
    s, _ = simulate_random(true, 2, W, W, rng)
    with pytest.raises(CalibrationError, match="too few samples with rotation: 2 of 2 usable"):
        calibrate_geometry(s, start)


def test_bcd_and_joint_reach_the_same_maximum(nominal32):
    rng = np.random.default_rng(3)
    true, start = _truth_and_start(nominal32, rng)
    s, _ = simulate_random(true, 50, W, W, rng)
    joint = calibrate_geometry(s, start, method="joint")
    bcd = calibrate_geometry(s, start, method="bcd", tolerance=1e-4)
    assert joint.converged and bcd.converged and bcd.iterations > joint.iterations
    assert abs(joint.loglik_after - bcd.loglik_after) < 1e-3 * max(1.0, joint.samples_used / 100)
    assert joint.loglik_after > joint.loglik_before
    np.testing.assert_allclose(bcd.positions, joint.positions, atol=0.01 * joint.position_std[1:].min())
    np.testing.assert_allclose(bcd.position_std, joint.position_std, rtol=1e-3)
    # BCD's likelihood never falls from one iteration to the next
    ll = np.array([h[1] for h in bcd.history])
    assert np.all(np.diff(ll) > -1e-6 * np.abs(ll[1:])), ll


def test_literal_alg1_converges_slower_to_the_same_point(nominal32):
    """Alg. 1 with the reference held (recenter=False): the common shift converges by (K-1)/K per iteration."""
    rng = np.random.default_rng(4)
    true, start = _truth_and_start(nominal32, rng)
    s, _ = simulate_random(true, 30, W, W, rng)
    fast = calibrate_geometry(s, start, method="bcd")
    slow = calibrate_geometry(s, start, method="bcd", recenter=False, max_iterations=2000)
    assert slow.converged and slow.iterations > 2 * fast.iterations
    np.testing.assert_allclose(slow.positions, fast.positions, atol=0.05 * fast.position_std[1:].min())


def test_twist_recording_within_3_sigma_and_calibrated_fusion_is_better(nominal32):
    """A continuous hand-twist (the simulator's twist motion, 1200 deg/s RMS): every position within
    its reported 3 sigma (one miss allowed in 93), z-scores of unit spread; on a second, held-out
    twist, omega fused with the calibrated positions is closer to the truth than with the nominal
    ones (most of the way to what the true positions give: at these rates the gyroscopes carry most
    of omega) and omega_dot, which the positions set directly, several times closer."""
    rng = np.random.default_rng(5)
    rate = np.deg2rad(1200.0)
    true, start = _truth_and_start(nominal32, rng, sigma=1e-3)
    s, _ = simulate_twist(true, 5.0, 200.0, rng, rms_rate=rate)
    res = calibrate_geometry(s, start)
    z = ((res.positions - true.positions) / np.where(res.position_std > 0, res.position_std, np.nan))[1:].ravel()
    assert np.sum(np.abs(z) > 3) <= 1 and 0.7 < np.sqrt(np.mean(z ** 2)) < 1.3, z
    held, truth = simulate_twist(true, 2.0, 200.0, np.random.default_rng(6), rms_rate=rate)

    def rmse(model):
        fused, _ = ModelFusion(model).fuse(held)
        idx = np.searchsorted(truth.stamps, fused.stamps)
        return [float(np.sqrt(np.mean((a - b[idx]) ** 2)))
                for a, b in ((fused.omega, truth.omega), (fused.omega_dot, truth.omega_dot))]

    (w_nom, wd_nom), (w_cal, wd_cal), (w_true, _) = rmse(start), rmse(res.model), rmse(true)
    assert w_cal < w_nom and w_cal - w_true < 0.2 * (w_nom - w_true), (w_nom, w_cal, w_true)
    assert wd_cal < 0.2 * wd_nom, (wd_nom, wd_cal)
    assert res.nis_after < res.nis_before and 0.9 < res.nis_after < 1.1


def _fixed_axis_truth(n, axis, rng):
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    t = np.arange(n) / 200.0
    rate = 8.0 * np.sin(2 * np.pi * 1.3 * t)
    return MotionTruth(stamps=(t * 1e9).astype(np.int64), omega=rate[:, None] * axis,
                       omega_dot=(8.0 * 2 * np.pi * 1.3 * np.cos(2 * np.pi * 1.3 * t))[:, None] * axis,
                       specific_force=np.tile([0.0, 0.0, 9.81], (n, 1)) + rng.normal(0, 1.0, (n, 3)))


def test_rotation_about_one_axis_is_refused_naming_the_axis(nominal32):
    rng = np.random.default_rng(7)
    s = simulate_measurements(nominal32, _fixed_axis_truth(400, [0, 0, 1], rng), rng)
    with pytest.raises(CalibrationError, match=r"one axis only \(\[0\.00 0\.00 1\.00\].*rotate about at least two "
                                               r"axes"):
        calibrate_geometry(s, nominal32)


def test_parallel_omega_and_omega_dot_identify_only_when_the_axis_changes(nominal32):
    """carlsson2017 Lemma 1: with omega parallel to omega_dot a sample's C_n has rank 2 (its axis is
    in the null space).  Samples turning about two different axes in turn still determine every
    position (sum C_n^T C_n has full rank): calibrated, with its larger std reported; the same
    samples all about one axis: refused (test above).  In a continuous recording omega parallel to
    omega_dot in every sample means a fixed axis, which is what the refusal names."""
    rng = np.random.default_rng(8)
    n = 200
    axes = np.tile([[1.0, 0, 0], [0, 1.0, 0]], (n // 2, 1))
    truth = MotionTruth(stamps=np.arange(n, dtype=np.int64) * 5_000_000, omega=10.0 * axes, omega_dot=50.0 * axes,
                        specific_force=rng.normal(0, 5.0, (n, 3)))
    true, start = _truth_and_start(nominal32, rng, sigma=5e-4)
    s = simulate_measurements(true, truth, rng)
    res = calibrate_geometry(s, start)
    z = ((res.positions - true.positions) / np.where(res.position_std > 0, res.position_std, np.nan))[1:]
    assert np.all(np.abs(z) < 4.5) and np.all(res.position_std[1:] > 0)
    truth_one = MotionTruth(stamps=truth.stamps, omega=10.0 * np.tile([1.0, 0, 0], (n, 1)),
                            omega_dot=50.0 * np.tile([1.0, 0, 0], (n, 1)), specific_force=truth.specific_force)
    s = simulate_measurements(true, truth_one, rng)
    with pytest.raises(CalibrationError, match=r"one axis only \(\[1\.00 0\.0\d -?0\.0\d\]"):
        calibrate_geometry(s, start)


def test_sample_selection_drops_saturated_and_still_samples(nominal32):
    rng = np.random.default_rng(9)
    true, start = _truth_and_start(nominal32, rng, sigma=2e-4)
    s, _ = simulate_twist(true, 3.0, 200.0, rng)
    acc, gyr = s.accel.copy(), s.gyro.copy()
    gyr[10:20, 3, 1] = nominal32.gyro_clip  # clipped
    acc[30:35, 5, 0] = np.nan  # missing
    still = simulate_measurements(true, MotionTruth(stamps=s.stamps[-1] + 5_000_000 * np.arange(1, 101),
                                                    omega=np.zeros((100, 3)), omega_dot=np.zeros((100, 3)),
                                                    specific_force=np.tile([0, 0, 9.81], (100, 1))), rng)
    stamps = np.concatenate([s.stamps, still.stamps])
    res = calibrate_geometry(ImuSamples(stamps, np.concatenate([acc, still.accel]), np.concatenate([gyr, still.gyro]),
                                        s.names), start)
    assert res.dropped["missing_or_saturated"] == 15
    assert res.dropped["little_rotation"] >= 100
    assert res.samples_used == len(stamps) - sum(res.dropped.values())
    assert not res.used[10:20].any() and not res.used[-100:].any()


def test_errors_are_one_line_and_name_the_problem(nominal32):
    rng = np.random.default_rng(10)
    s, _ = simulate_random(nominal32, 20, W, W, rng)
    with pytest.raises(CalibrationError, match="unknown IMU 'nope'"):
        calibrate_geometry(s, nominal32, reference="nope")
    with pytest.raises(CalibrationError, match="method must be one of joint, bcd"):
        calibrate_geometry(s, nominal32, method="magic")
    with pytest.raises(CalibrationError, match="stamps must increase strictly"):
        calibrate_geometry(ImuSamples(s.stamps[::-1], s.accel, s.gyro, s.names), nominal32)
    with pytest.raises(CalibrationError, match=r"the samples are of IMUs x0, x1, x2, x3\.\.\., the model of imu_"):
        calibrate_geometry(ImuSamples(s.stamps, s.accel, s.gyro, tuple(f"x{i}" for i in range(32))), nominal32)


def test_reference_is_configurable_and_held(nominal32):
    rng = np.random.default_rng(12)
    s, _ = simulate_random(perturb(nominal32, rng, {"position": 5e-4}), 40, W, W, rng)
    res = calibrate_geometry(s, nominal32, reference="imu_07")
    assert res.reference == "imu_07"
    np.testing.assert_array_equal(res.positions[7], nominal32.positions[7])
    assert np.all(res.position_std[7] == 0) and np.all(np.delete(res.position_std, 7, axis=0) > 0)


# --------------------------------------------------------------------------- writing


def calibrate_and_write(desc, samples, out, **options):
    """What the node's service and ``imu-array calibrate geometry`` run: calibrate, then the one install path."""
    cal = calibrate("geometry", samples, desc, **options)
    return cal.details, cal.install(desc, out)


@pytest.fixture
def window():
    """A 4-IMU tetrahedron twisting for 4 s with 1 mm position errors (fast to calibrate)."""
    desc = tetrahedron4()
    model = SensorModel.from_description(desc)
    rng = np.random.default_rng(13)
    true = perturb(model, rng, {"position": 1e-3})
    true = true.with_terms(position=true.positions - true.positions[0] + model.positions[0])
    s, _ = simulate_twist(true, 4.0, 200.0, rng)
    return desc, s


def test_write_then_refuse_a_worse_calibration_leaving_the_file_untouched(window, tmp_path):
    desc, s = window
    out = tmp_path / "cal.yaml"
    res, installed = calibrate_and_write(desc, s, out)
    assert installed.backup is None and out.is_file()
    cal = load_description(out)
    assert cal.calibration["samples_used"] == res.samples_used and cal.calibration["reference"] == "imu_00"
    np.testing.assert_allclose(cal.positions, res.positions)
    assert all("position" in imu.stds for imu in cal.imus)
    before = (out.read_bytes(), os.stat(out).st_mtime_ns)
    # one BCD iteration from the nominal positions: refused as not converged (calibration.guards); with the
    # checks off, the install path alone refuses it: it is worse on this window than the file
    with pytest.raises(CalibrationError, match=r"refused: not converged \(1 iterations\)"):
        calibrate_and_write(desc, s, out, method="bcd", max_iterations=1)
    with pytest.raises(CalibrationError, match="not replaced: the calibration on file fits this window better"):
        calibrate_and_write(desc, s, out, method="bcd", max_iterations=1, checks=False)
    assert (out.read_bytes(), os.stat(out).st_mtime_ns) == before and not backup_path(out).exists()
    # the converged one (equal or better) replaces it, keeping the old one as the backup
    _, installed = calibrate_and_write(desc, s, out, method="bcd")
    assert installed.backup == backup_path(out) and installed.backup.read_bytes() == before[0]


def test_failed_calibration_touches_nothing_and_foreign_files_are_refused(window, tmp_path):
    desc, s = window
    out = tmp_path / "cal.yaml"
    out.write_text("not: [a description\n")
    with pytest.raises(CalibrationError):
        calibrate_and_write(desc, s.select(slice(None, 2)), out)
    assert out.read_text() == "not: [a description\n" and not backup_path(out).exists()
    # an unreadable file is not a good calibration: replaced, its bytes kept as the backup
    calibrate_and_write(desc, s, out)
    assert backup_path(out).read_text() == "not: [a description\n"
    other = tmp_path / "other.yaml"
    save_description(grid_array32(), other)
    with pytest.raises(OutputError, match="description of other IMUs"):
        calibrate_and_write(desc, s, other)
    (tmp_path / "dir.yaml").mkdir()
    with pytest.raises(OutputError, match="not a regular file"):
        calibrate_and_write(desc, s, tmp_path / "dir.yaml")
