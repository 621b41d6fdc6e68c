"""The sensor model's terms and the one forward model: analytic Jacobians vs finite
differences, registry, and agreement with the linear model the fusion uses."""

from __future__ import annotations

import numpy as np
import pytest

from imu_array_ros.model.sensor_model import SensorModel, motion_context
from imu_array_ros.model.linear import LinearArrayModel
from imu_array_ros.model.terms import REGISTRY, term_names
from imu_array_ros.simulation.motion import random_motion
from imu_array_ros.model.kinematics import quadratic_monomials

from imu_array_ros.simulation.perturb import TERM_TEST_CENTRES, TERM_TEST_SIZES

from conftest import perturbed

#: realistic 1-sigma sizes, per registry name (each term is exercised away from identity)
SIZES = TERM_TEST_SIZES


def random_rotations(rng, k):
    q, _ = np.linalg.qr(rng.normal(size=(k, 3, 3)))
    return q * np.sign(np.linalg.det(q))[:, None, None]


@pytest.fixture
def setup(rng):
    k, n = 5, 7
    rot = random_rotations(rng, k)
    model = SensorModel(names=tuple(f"imu_{i}" for i in range(k)), frame_id="a", rotations=rot,
                        acc_std=np.full((k, 3), 0.04), gyro_std=np.full((k, 3), 1e-3),
                        terms={name: REGISTRY[name].identity(k) for name in term_names()})
    values = {name: REGISTRY[name].default_values(k) + np.asarray(TERM_TEST_CENTRES.get(name, 0.0))
              + rng.normal(0, SIZES[name], (k, REGISTRY[name].dim())) for name in term_names()}
    model = model.with_terms(**values)
    motion = dict(stamps=np.arange(n) * 5_000_000 + 10**18, omega=rng.normal(0, 5, (n, 3)),
                  omega_dot=rng.normal(0, 50, (n, 3)), specific_force=rng.normal(0, 10, (n, 3)),
                  omega_ddot=rng.normal(0, 500, (n, 3)), specific_force_dot=rng.normal(0, 100, (n, 3)))
    return model, motion, rot


def predict6(model, motion, rot):
    acc, gyr = model.predict(motion_context(rotations=rot, t0_ns=10**18 - 3 * 10**9, **motion))
    return np.concatenate([acc, gyr], axis=2)


def test_registry_holds_the_required_terms():
    assert set(SIZES) == set(REGISTRY)  # every required term, and nothing untested
    for name, cls in REGISTRY.items():
        assert cls.name == name and cls.fields and len(cls.parameter_names()) == cls.dim()


@pytest.mark.parametrize("name", sorted(SIZES))
def test_parameter_jacobian_matches_finite_differences(setup, name):
    model, motion, rot = setup
    jac = model.jacobians(motion_context(rotations=rot, t0_ns=10**18 - 3 * 10**9, **motion), free=[name])
    np.testing.assert_allclose(jac.predicted, predict6(model, motion, rot), rtol=0, atol=1e-12)
    values = model.terms[name].values
    scale = max(SIZES[name], 1e-3)
    for i in range(model.n_imus):
        for p in range(values.shape[1]):
            h = 1e-6 * max(scale, abs(values[i, p]))
            up, dn = values.copy(), values.copy()
            up[i, p] += h
            dn[i, p] -= h
            num = (predict6(model.with_terms(**{name: up}), motion, rot)
                   - predict6(model.with_terms(**{name: dn}), motion, rot)) / (2 * h)
            ref = np.abs(num).max() + 1.0
            np.testing.assert_allclose(jac.params[name][:, :, :, p] * (np.arange(model.n_imus) == i)[None, :, None],
                                       num, rtol=0, atol=1e-6 * ref, err_msg=f"{name} IMU {i} parameter {p}")
            # block structure: IMU i's parameters move only IMU i's readings
            assert np.all(num[:, np.arange(model.n_imus) != i] == 0.0)


def test_motion_jacobian_matches_finite_differences(setup):
    model, motion, rot = setup
    jac = model.jacobians(motion_context(rotations=rot, t0_ns=10**18 - 3 * 10**9, **motion), free=list(SIZES))
    for j, key in enumerate(("omega", "omega_dot", "specific_force")):
        for c in range(3):
            h = 1e-6 * np.abs(motion[key]).max()
            up = {**motion, key: motion[key].copy()}
            dn = {**motion, key: motion[key].copy()}
            up[key][:, c] += h
            dn[key][:, c] -= h
            num = (predict6(model, up, rot) - predict6(model, dn, rot)) / (2 * h)
            np.testing.assert_allclose(jac.motion[..., 3 * j + c], num, rtol=1e-6, atol=1e-6 * np.abs(num).max(),
                                       err_msg=f"d y / d {key}[{c}]")


def test_identity_terms_give_the_rigid_body_model(setup, rng):
    """All terms at identity except positions: y_acc = R^T s(r), y_gyr = R^T omega (skog2016 eq. 1-5)."""
    model, motion, rot = setup
    bare = model.with_terms(**{n: REGISTRY[n].default_values(model.n_imus) for n in term_names() if n != "position"})
    y = predict6(bare, motion, rot)
    p = model.terms["position"].values
    w, wd, s = motion["omega"], motion["omega_dot"], motion["specific_force"]
    f = s[:, None] + np.cross(w[:, None], np.cross(w[:, None], p[None])) + np.cross(wd[:, None], p[None])
    np.testing.assert_allclose(y[..., :3], np.einsum("kji,nkj->nki", rot, f), rtol=1e-13, atol=1e-12)
    np.testing.assert_allclose(y[..., 3:], np.einsum("kji,nj->nki", rot, w), rtol=1e-13, atol=1e-12)


def test_forward_model_agrees_with_the_fusion_linear_model(array32, rng):
    """With the nilsson2014 terms (gain, non-orthogonality, misalignment, bias, positions) the chain
    equals K L (I + [xi]x) R^T s(r) + b, written out here independently of both, and the fusion's
    linear form (read off probe motions) reproduces it."""
    from imu_array_ros.model.kinematics import skew, specific_force_at
    from imu_array_ros.model.terms.triad import nonorthogonality_matrix

    desc = perturbed(array32, rng, {"position": 1e-3, "accelerometer_gain": 0.01,
                                    "accelerometer_nonorthogonality": 0.01, "accelerometer_misalignment": 0.01,
                                    "accelerometer_bias": 0.3, "gyroscope_gain": 0.01, "gyroscope_nonorthogonality": 0.01,
                                    "gyroscope_misalignment": 0.01, "gyroscope_bias": 0.01})
    truth = random_motion(50, 10.0, 100.0, rng)
    acc, gyr = SensorModel.from_description(desc).predict(
        motion_context(truth.stamps, truth.omega, truth.omega_dot, truth.specific_force, desc.orientations))
    mats = {}
    for sensor in ("accelerometer", "gyroscope"):
        v = {f: np.array([imu.value(f"{sensor}.{f}") for imu in desc.imus])
             for f in ("gain", "nonorthogonality", "misalignment", "bias")}
        mats[sensor] = (np.array([np.diag(g) @ nonorthogonality_matrix(n) @ (np.eye(3) + skew(m)) @ r.T for g, n, m, r
                                  in zip(v["gain"], v["nonorthogonality"], v["misalignment"], desc.orientations)]),
                        v["bias"])
    f = specific_force_at(truth.specific_force, truth.omega, truth.omega_dot, desc.positions)
    np.testing.assert_allclose(acc, np.einsum("kij,nkj->nki", mats["accelerometer"][0], f) + mats["accelerometer"][1],
                               rtol=0, atol=1e-12)
    np.testing.assert_allclose(gyr, np.einsum("kij,nj->nki", mats["gyroscope"][0], truth.omega) + mats["gyroscope"][1],
                               rtol=0, atol=1e-12)
    lin = LinearArrayModel.from_description(desc)
    z = np.concatenate([quadratic_monomials(truth.omega), truth.omega_dot, truth.specific_force], axis=1)
    np.testing.assert_allclose(np.einsum("kiz,nz->nki", lin.acc_design, z) + lin.acc_bias, acc, rtol=0, atol=1e-11)
    np.testing.assert_allclose(lin.acc_matrix, mats["accelerometer"][0], rtol=0, atol=1e-13)
    np.testing.assert_allclose(lin.gyro_matrix, mats["gyroscope"][0], rtol=0, atol=1e-13)


def test_linear_form_is_exact_with_per_axis_lever_arms(setup):
    """Every linear term (axis offsets included) enters the fusion's design exactly; the
    non-linear terms are exactly what it leaves out."""
    model, motion, rot = setup
    lin = LinearArrayModel.from_sensor_model(model)
    ctx = motion_context(rotations=rot, t0_ns=10**18 - 3 * 10**9, **motion)
    acc, gyr = model.linear_part().predict(ctx)
    z = np.concatenate([quadratic_monomials(motion["omega"]), motion["omega_dot"], motion["specific_force"]], axis=1)
    np.testing.assert_allclose(np.einsum("kiz,nz->nki", lin.acc_design, z) + lin.acc_bias, acc, rtol=0, atol=1e-10)
    np.testing.assert_allclose(np.einsum("kij,nj->nki", lin.gyro_matrix, motion["omega"]) + lin.gyro_bias, gyr,
                               rtol=0, atol=1e-12)
    assert set(model.nonlinear_terms) == {"time_offset", "sample_clock", "gyroscope_sample_clock",
                                          "accelerometer_sample_clock", "stamp_clock", "accelerometer_nonlinearity",
                                          "gyroscope_g_sensitivity", "bias_drift"}
    full = model.predict(ctx)
    assert np.abs(full[0] - acc).max() > 1e-3 and np.abs(full[1] - gyr).max() > 1e-4  # they do act
