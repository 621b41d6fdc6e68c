"""PCA calibration (rupniewski Algorithm 2, its biased extension, and the array resolution of pca_array)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

import imu_array_ros.calibration.pca as pca_mod
from imu_array_ros.calibration.pca import ARRAY_TERMS, calibration_error, pca_array, pca_calibrate
from imu_array_ros.errors import CalibrationError
from imu_array_ros.model.constants import STANDARD_GRAVITY
from imu_array_ros.model.sensor_model import SensorModel, motion_context
from imu_array_ros.model.layouts import ROT_180_ABOUT_Y_EQ_X, grid_array32, tetrahedron4
from imu_array_ros.simulation.perturb import perturb

SCALES = {"accelerometer_gain": 0.02, "accelerometer_nonorthogonality": 0.01, "accelerometer_misalignment": 0.01,
          "accelerometer_bias": 0.3}


def directions(rng: np.random.Generator, n: int, d: int = 3) -> np.ndarray:
    u = rng.normal(size=(n, d))
    return u / np.linalg.norm(u, axis=-1, keepdims=True)


def random_rotation(rng: np.random.Generator) -> np.ndarray:
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q = q * np.sign(np.diag(r))
    return q * np.linalg.det(q)


def frame_between(x: np.ndarray, x_hat: np.ndarray) -> np.ndarray:
    """Least-squares Omega with x_hat ~ Omega x (both (d, n))."""
    return np.linalg.lstsq(x.T, x_hat.T, rcond=None)[0].T


# --------------------------------------------------------------------------- pca_calibrate


def test_unbiased_noiseless_exact(rng):
    a = rng.normal(size=(3, 12))
    v = 2.5 * directions(rng, 6).T                      # the minimum n = d(d+1)/2
    res = pca_calibrate(v.T @ a, 2.5)
    omega = frame_between(v, res.v)
    np.testing.assert_allclose(omega @ omega.T, np.eye(3), atol=1e-12)
    np.testing.assert_allclose(res.a, omega @ a, atol=1e-12)
    np.testing.assert_allclose(res.v, omega @ v, atol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(res.v, axis=0), 2.5, rtol=1e-13)
    assert calibration_error(a, res.a) < 1e-12
    assert res.residual_rms < 1e-13 and np.all(res.bias == 0) and not res.biased
    assert res.a.shape == (3, 12) and res.v.shape == (3, 6) and res.singular_values.shape == (6,)


@pytest.mark.parametrize("m, n, with_bias", [(12, 9, True), (12, 40, True), (12, 40, False), (3, 20, True)])
def test_biased_noiseless_exact(rng, m, n, with_bias):
    """Affine extension: 9 poses suffice for d = 3; zero bias and a single triad (m = d) work too."""
    a = np.eye(3, m) + 0.3 * rng.normal(size=(3, m))
    beta = rng.normal(size=m) if with_bias else np.zeros(m)
    v = 9.8 * directions(rng, n).T
    res = pca_calibrate(v.T @ a + beta, 9.8, biased=True)
    omega = frame_between(v, res.v)
    np.testing.assert_allclose(omega @ omega.T, np.eye(3), atol=1e-11)
    np.testing.assert_allclose(res.a, omega @ a, atol=1e-11)
    np.testing.assert_allclose(res.bias, beta, atol=1e-11)
    np.testing.assert_allclose(res.predict(), v.T @ a + beta, atol=1e-11)
    assert calibration_error(a, res.a) < 1e-11


def test_batched_equals_one_by_one(rng):
    a = np.eye(3, 12) + 0.1 * rng.normal(size=(2, 3, 3, 12))
    v = directions(rng, 2 * 3 * 15).reshape(2, 3, 15, 3)
    readings = v @ a + 1e-3 * rng.normal(size=(2, 3, 15, 12))
    for biased in (False, True):
        batch = pca_calibrate(readings, 1.0, biased=biased)
        assert batch.a.shape == (2, 3, 3, 12) and batch.residual_rms.shape == (2, 3)
        one = pca_calibrate(readings[1, 2], 1.0, biased=biased)
        np.testing.assert_allclose(batch.predict()[1, 2], one.predict(), atol=1e-12)
        np.testing.assert_allclose(calibration_error(one.a, batch.a[1, 2]), 0.0, atol=1e-12)
        assert batch.residual_rms[1, 2] == pytest.approx(one.residual_rms, rel=1e-12)


def test_refuses_too_few_poses(rng):
    a = rng.normal(size=(3, 12))
    with pytest.raises(CalibrationError, match=r"^5 poses < d\(d\+1\)/2 = 6 needed"):
        pca_calibrate(directions(rng, 5) @ a, 1.0)
    with pytest.raises(CalibrationError, match=r"^2 poses < d\(d\+1\)/2 = 3 needed for d = 2"):
        pca_calibrate(directions(rng, 2, 2) @ a[:2], 1.0, dim=2)
    with pytest.raises(CalibrationError, match=r"^8 poses < d\(d\+3\)/2 = 9 needed for a biased"):
        pca_calibrate(directions(rng, 8) @ a + 1.0, 1.0, biased=True)


def test_refuses_coplanar_poses(rng):
    a = rng.normal(size=(3, 12))
    circle = np.column_stack([directions(rng, 20, 2), np.zeros(20)])     # rotation about one axis only
    with pytest.raises(CalibrationError, match=r"span fewer than 3 dimensions \(singular values .*\): the poses are "
                       "coplanar") as err:
        pca_calibrate(circle @ a, 1.0)
    assert "\n" not in str(err.value)
    with pytest.raises(CalibrationError, match="span fewer than 3 dimensions"):
        pca_calibrate(circle @ a + 0.5, 1.0, biased=True)


def test_refuses_indefinite_g():
    """b_1 = (1, 0), b_2 = (0, 1), b_3 = (0.4, 0.4) with c = 1: g_12 = 2.125, g indefinite (a hyperbola)."""
    with pytest.raises(CalibrationError, match="g of rupniewski eq. 7 is not positive definite"):
        pca_calibrate(np.array([[1.0, 0.0], [0.0, 1.0], [0.4, 0.4]]), 1.0, dim=2)


def test_refuses_non_finite_readings(rng):
    readings = directions(rng, 10) @ rng.normal(size=(3, 6))
    readings[3, 2] = np.nan
    with pytest.raises(CalibrationError, match="^1 readings are not finite$"):
        pca_calibrate(readings, 1.0)


def test_fig34_scaling():
    """Reduced rupniewski Fig. 3-4 (benchmarks/rupniewski_fig34.py has 1000 repetitions): the median
    calibration error grows as sigma and falls as n^-0.5."""
    rng = np.random.default_rng(34)
    a_model = np.array([[1, 0, 0, 0, 1, 0, 0, -1, 0, 1, 0, 0], [0, 1, 0, -1, 0, 0, 1, 0, 0, 0, 0, -1],
                        [0, 0, 1, 0, 0, 1, 0, 0, 1, 0, 1, 0]], dtype=float)
    reps = 300

    def median_eps(n: int, sigma: float) -> float:
        a = a_model + rng.normal(0.0, 0.01, (reps, 3, 12))
        v = directions(rng, reps * n).reshape(reps, n, 3)             # c = 1 rad/s
        res = pca_calibrate(v @ a + rng.normal(0.0, sigma, (reps, n, 12)), 1.0)
        return float(np.median(calibration_error(a, res.a)))

    sigmas, ns = np.array([1e-4, 1e-3, 1e-2]), np.array([10, 100, 1000])
    slope_sigma = np.polyfit(np.log(sigmas), np.log([median_eps(100, s) for s in sigmas]), 1)[0]
    slope_n = np.polyfit(np.log(ns), np.log([median_eps(int(n), 1e-3) for n in ns]), 1)[0]
    assert 0.85 <= slope_sigma <= 1.15
    assert -0.65 <= slope_n <= -0.35


# --------------------------------------------------------------------------- pca_array


def static_readings(model: SensorModel, s: np.ndarray) -> np.ndarray:
    zero = np.zeros_like(s)
    acc, _ = model.predict(motion_context(np.arange(len(s)), zero, zero, s, model.rotations))
    return acc


def true_array(rng, desc, reference: int | None = None) -> tuple[SensorModel, SensorModel]:
    """(nominal model, perturbed truth); the truth's reference misalignment set to 0 unless ``reference`` is None."""
    nominal = SensorModel.from_description(desc)
    truth = perturb(nominal, rng, SCALES)
    if reference is not None:
        xi = truth.terms["accelerometer_misalignment"].values.copy()
        xi[reference] = 0.0
        truth = truth.with_terms(accelerometer_misalignment=xi)
    return nominal, truth


def assert_recovers(res, truth: SensorModel, rtol: float = 1e-8, atol: float = 1e-10) -> None:
    for name in ARRAY_TERMS:
        np.testing.assert_allclose(res.values[name], truth.terms[name].values, rtol=rtol, atol=atol, err_msg=name)


@pytest.mark.parametrize("reference", [0, 21])   # imu_21 sits underneath, rotated 180 deg about y = x
def test_pca_array_noiseless_exact(rng, reference):
    nominal, truth = true_array(rng, grid_array32(), reference)
    s = -STANDARD_GRAVITY * directions(rng, 30)
    res = pca_array(static_readings(truth, s), nominal, reference=reference)
    assert_recovers(res, truth)
    np.testing.assert_allclose(res.specific_force, s, rtol=0, atol=1e-8 * STANDARD_GRAVITY)
    assert res.reference == nominal.names[reference] and res.skipped == () and res.poses.all()
    assert np.all(res.values["accelerometer_misalignment"][reference] == 0.0)
    assert np.ptp(res.values["accelerometer_gain"]) > 0.02   # the test data are far from identity
    assert res.pca.residual_rms < 1e-12 and res.seconds > 0


def test_pca_array_minimum_poses_and_unbiased(rng):
    nominal, truth = true_array(rng, tetrahedron4(), 0)
    s = -STANDARD_GRAVITY * directions(rng, 9)
    assert_recovers(pca_array(static_readings(truth, s), nominal, reference="imu_00"), truth)
    unbiased = truth.with_terms(accelerometer_bias=np.zeros((4, 3)))
    assert_recovers(pca_array(static_readings(unbiased, s[:6]), nominal, biased=False), unbiased)
    with pytest.raises(CalibrationError, match=r"^8 poses < 9 needed for the biased PCA calibration"):
        pca_array(static_readings(truth, s[:8]), nominal)
    with pytest.raises(CalibrationError, match=r"^5 poses < 6 needed for the unbiased"):
        pca_array(static_readings(unbiased, s[:5]), nominal, biased=False)


def test_pca_array_reproduces_readings_with_reference_misalignment(rng):
    """Truth with xi_ref != 0: another gauge, but the estimated model must predict the same readings."""
    nominal, truth = true_array(rng, grid_array32(), None)
    s = -STANDARD_GRAVITY * directions(rng, 25)
    acc = static_readings(truth, s)
    res = pca_array(acc, nominal, reference=3)
    np.testing.assert_allclose(static_readings(res.calibrated(nominal), res.specific_force), acc,
                               rtol=0, atol=1e-9 * STANDARD_GRAVITY)
    np.testing.assert_allclose(np.linalg.norm(res.specific_force, axis=-1), STANDARD_GRAVITY, rtol=1e-10)


def test_pca_array_noisy(rng):
    """sigma = 0.01 m/s^2, 40 poses.  RMS errors over 20 seeds (measured): gain 3.0e-4 (max 3.4e-4),
    non-orthogonality 4.3e-4 (4.8e-4), misalignment 4.1e-4 (6.2e-4), bias 1.7e-3 (2.2e-3) m/s^2, specific
    force 2.9e-3 (4.3e-3) m/s^2; the bounds are ~2x the largest and >= 15x below the perturbation sizes
    (SCALES).  The errors are linear in the noise: the same noise / 10 gives errors / 10 (no bias floor)."""
    nominal, truth = true_array(rng, grid_array32(), 0)
    s = -STANDARD_GRAVITY * directions(rng, 40)
    sigma = 0.01
    clean, noise = static_readings(truth, s), rng.normal(0.0, 1.0, (40, 32, 3))

    def rms_errors(scale: float) -> np.ndarray:
        res = pca_array(clean + scale * noise, nominal)
        assert res.pca.residual_rms == pytest.approx(scale, rel=0.2)
        err = [res.values[name] - truth.terms[name].values for name in ARRAY_TERMS] + [res.specific_force - s]
        return np.array([np.sqrt(np.mean(e ** 2)) for e in err])

    err = rms_errors(sigma)
    assert np.all(err < [6e-4, 1e-3, 1.2e-3, 4.5e-3, 9e-3]), err
    np.testing.assert_allclose(err / rms_errors(sigma / 10), 10.0, rtol=0.01)


def test_pca_array_skips_dead_imu_and_drops_incomplete_poses(rng):
    nominal, truth = true_array(rng, grid_array32(), 0)
    s = -STANDARD_GRAVITY * directions(rng, 20)
    acc = static_readings(truth, s)
    acc[:, 5] = np.nan                      # dead IMU
    acc[:, 9, 1] = np.nan                   # dead axis: the whole triad is skipped
    acc[7, 12, 2] = np.nan                  # one missing reading: pose 7 is not used
    res = pca_array(acc, nominal)
    assert res.skipped == ("imu_05", "imu_09")
    assert np.flatnonzero(~res.poses).tolist() == [7]
    assert np.isnan(res.specific_force[7]).all()
    np.testing.assert_allclose(np.delete(res.specific_force, 7, 0), np.delete(s, 7, 0), atol=1e-8 * STANDARD_GRAVITY)
    kept = np.setdiff1d(np.arange(32), [5, 9])
    for name in ARRAY_TERMS:
        np.testing.assert_allclose(res.values[name][kept], truth.terms[name].values[kept], rtol=1e-8, atol=1e-10)
        identity = nominal.terms[name].values[[5, 9]]
        np.testing.assert_array_equal(res.values[name][[5, 9]], identity)
    assert res.pca.a.shape == (3, 90)
    with pytest.raises(CalibrationError, match="reference IMU imu_05 has an axis without readings"):
        pca_array(acc, nominal, reference="imu_05")
    acc[:12, 20, 0] = np.nan
    with pytest.raises(CalibrationError, match=r"^8 poses \(12 of 20 with a missing reading\) < 9 needed"):
        pca_array(acc, nominal)


def test_pca_array_invariant_to_rotated_poses(rng):
    nominal, truth = true_array(rng, grid_array32(), 2)
    s = -STANDARD_GRAVITY * directions(rng, 20)
    q = random_rotation(rng)
    res = pca_array(static_readings(truth, s), nominal, reference=2)
    rotated = pca_array(static_readings(truth, s @ q.T), nominal, reference=2)
    for name in ARRAY_TERMS:
        np.testing.assert_allclose(rotated.values[name], res.values[name], rtol=1e-9, atol=1e-11)
    np.testing.assert_allclose(rotated.specific_force, res.specific_force @ q.T, atol=1e-8 * STANDARD_GRAVITY)


@pytest.mark.parametrize("reflect", [False, True])
def test_pca_array_invariant_to_pca_frame(rng, monkeypatch, reflect):
    """Remark 1: the PCA's arbitrary orthogonal frame (reflections included) does not reach the result, with noise."""
    nominal, truth = true_array(rng, grid_array32(), 0)
    s = -STANDARD_GRAVITY * directions(rng, 15)
    acc = static_readings(truth, s) + rng.normal(0.0, 0.02, (15, 32, 3))
    res = pca_array(acc, nominal)
    omega = random_rotation(rng) @ (np.diag([1.0, 1.0, -1.0]) if reflect else np.eye(3))
    original = pca_mod.pca_calibrate

    def turned(*args, **kwargs):
        r = original(*args, **kwargs)
        return dataclasses.replace(r, a=omega @ r.a, v=omega @ r.v)

    monkeypatch.setattr(pca_mod, "pca_calibrate", turned)
    other = pca_array(acc, nominal)
    assert not np.allclose(other.pca.a, res.pca.a, atol=1e-3)
    for name in ARRAY_TERMS:
        np.testing.assert_allclose(other.values[name], res.values[name], rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(other.specific_force, res.specific_force, atol=1e-10)


def test_pca_array_wrong_nominal_orientation(rng):
    desc = grid_array32()
    nominal, truth = true_array(rng, desc, 0)
    rotations = nominal.rotations.copy()
    rotations[17] = np.eye(3)               # imu_17 is mounted underneath (ROT_180_ABOUT_Y_EQ_X)
    assert np.allclose(nominal.rotations[17], ROT_180_ABOUT_Y_EQ_X)
    wrong = dataclasses.replace(nominal, rotations=rotations)
    s = -STANDARD_GRAVITY * directions(rng, 20)
    with pytest.raises(CalibrationError, match="IMU imu_17: estimated accelerometer gains .* are not all > 0"):
        pca_array(static_readings(truth, s), wrong)


def test_pca_array_refuses_bad_shapes(rng):
    nominal = SensorModel.from_description(tetrahedron4())
    with pytest.raises(CalibrationError, match=r"must be \(poses, 4, 3\) for this array, got \(10, 3, 3\)"):
        pca_array(np.zeros((10, 3, 3)), nominal)
    with pytest.raises(CalibrationError, match="reference: unknown IMU 'imu_99'"):
        pca_array(np.zeros((10, 4, 3)), nominal, reference="imu_99")
