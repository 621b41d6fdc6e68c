"""Rigid-body kinematics, motion generators and the simulator."""

from __future__ import annotations

import ast
from pathlib import Path

import numpy as np

from imu_array_ros.model.kinematics import (
    centripetal_matrix,
    quadratic_monomials,
    quadratic_monomials_jacobian,
    specific_force_at,
)
from imu_array_ros.simulation.motion import TwistTrajectory, quat_to_matrix
from imu_array_ros.model.linear import LinearArrayModel
from imu_array_ros.simulation.simulator import simulate_measurements, simulate_twist


def test_centripetal_term_is_linear_in_quadratic_monomials(rng):
    w = rng.normal(size=(50, 3))
    r = rng.normal(size=(50, 3))
    direct = np.cross(w, np.cross(w, r))
    np.testing.assert_allclose(np.einsum("nij,nj->ni", centripetal_matrix(r), quadratic_monomials(w)), direct, atol=1e-12)


def test_monomial_jacobian_matches_finite_differences(rng):
    w = rng.normal(size=3)
    jac = quadratic_monomials_jacobian(w)
    h = 1e-6
    num = np.stack([(quadratic_monomials(w + h * e) - quadratic_monomials(w - h * e)) / (2 * h) for e in np.eye(3)], 1)
    np.testing.assert_allclose(jac, num, atol=1e-8)


def test_specific_force_matches_differentiated_point_motion(rng):
    """s_r = s + w x (w x r) + w_dot x r, checked against the second derivative of
    a body point's world position along the twisting trajectory."""
    traj = TwistTrajectory.random(rng)
    dt = 1e-4
    stamps = np.round(np.arange(0, 2001) * dt * 1e9).astype(np.int64)
    truth = traj.sample(stamps)
    rot = quat_to_matrix(truth.attitude)
    r = np.array([[0.05, -0.02, 0.01]])
    # world position of the origin: double integral of the sway acceleration; of the point: + R r
    t = (stamps - stamps[0]) * 1e-9
    point = (rot @ r[0])  # origin acceleration is known analytically; differentiate only R r
    acc_point = (point[2:] - 2 * point[1:-1] + point[:-2]) / dt**2 + traj.acceleration_world(t[1:-1])
    g = np.array([0, 0, -9.80665])
    expected_body = np.einsum("nji,nj->ni", rot[1:-1], acc_point - g)
    model = specific_force_at(truth.specific_force[1:-1], truth.omega[1:-1], truth.omega_dot[1:-1], r)[:, 0]
    np.testing.assert_allclose(model, expected_body, atol=2e-4)


def test_twist_omega_dot_is_the_derivative_of_omega(rng):
    traj = TwistTrajectory.random(rng)
    t = np.linspace(0, 5, 1001)
    h = 1e-6
    num = (traj.omega(t + h) - traj.omega(t - h)) / (2 * h)
    np.testing.assert_allclose(traj.omega_dot(t), num, atol=1e-5)


def test_gravity_turns_in_body_frame(array32, rng):
    samples, truth = simulate_twist(array32, duration=3.0, rate_hz=200.0, rng=rng)
    g_dir = truth.specific_force / np.linalg.norm(truth.specific_force, axis=1, keepdims=True)
    assert np.ptp(g_dir, axis=0).min() > 0.5  # gravity direction sweeps in every body axis
    # default hand twisting stays inside the sensor ranges: the simulated readings are
    # the model's, not clipped ones (checked on the unclipped, noise-free readings)
    clean = simulate_measurements(array32, truth, rng, noise=False, saturate=False)
    assert np.abs(clean.accel).max() < 0.5 * array32.accelerometer_range
    assert np.abs(clean.gyro).max() < 0.5 * array32.gyroscope_range
    assert np.abs(clean.gyro).max() > 0.1 * array32.gyroscope_range  # ... while really twisting


def test_simulator_saturates_and_adds_noise_of_the_right_size(array32, rng):
    model = LinearArrayModel.from_description(array32)
    from imu_array_ros.simulation.motion import random_motion

    truth = random_motion(4000, np.deg2rad(2500), 0.0, rng, omega_direction=[0, 0, 1])
    noisy = simulate_measurements(array32, truth, rng)
    clean = simulate_measurements(array32, truth, rng, noise=False)
    assert np.all(np.abs(noisy.gyro[:, :, 2]) == model.gyro_range)  # every z gyro saturated ...
    assert np.all(np.sign(noisy.gyro[:, :, 2]) == np.sign(clean.gyro[:, :, 2]))  # ... with its sign kept
    # top (identity) and underside (180 deg about y = x) IMUs see z with opposite signs
    assert np.all(np.sign(noisy.gyro[:, :16, 2]) == -np.sign(noisy.gyro[:, 16:, 2]))
    assert np.all(np.abs(clean.accel) < model.acc_range)  # nothing clipped in the accelerometers
    unclipped = np.abs(clean.gyro[:, :, :2]) < model.gyro_range
    for res, std in (((noisy.accel - clean.accel).reshape(-1), array32.accelerometer_noise_std),
                     ((noisy.gyro - clean.gyro)[:, :, :2][unclipped], array32.gyroscope_noise_std)):
        # sample std of n Gaussian values: relative standard error 1 / sqrt(2 n); allow 4 of them
        assert abs(res.std() / std - 1) < 4 / np.sqrt(2 * res.size)
        assert abs(res.mean()) < 4 * std / np.sqrt(res.size)
    # independent across IMUs: correlation of two IMUs' noise within 4 / sqrt(n)
    a, b = (noisy.accel - clean.accel)[:, 0, 0], (noisy.accel - clean.accel)[:, 1, 0]
    assert abs(np.corrcoef(a, b)[0, 1]) < 4 / np.sqrt(len(a))


def test_measurement_model_against_a_hand_computed_case():
    """One IMU, every calibration field set, numbers worked out by hand (not through
    the code under test): y = K L (I + [xi]x) R^T s(r) + b and y_g = K (I + [xi]x) R^T w + b.

    Array frame: r = [0.1, 0, 0] m; sensor x = array y (90 deg about z); s = [0, 0, 9.81]
    m/s^2 at the origin, w = [0, 0, 2] rad/s, w_dot = [0, 0, 3] rad/s^2.
      w x (w x r) = [-0.4, 0, 0], w_dot x r = [0, 0.3, 0]   -> s(r) = [-0.4, 0.3, 9.81]
      R^T s(r) = [0.3, 0.4, 9.81]
      xi = [0, 0, 0.01]: + xi x u = [-0.004, 0.003, 0]      -> [0.296, 0.403, 9.81]
      L: l_yz = 0.02 (row y gets 0.02 * x)                  -> [0.296, 0.40892, 9.81]
      K = diag(1.1, 0.9, 1.0)                               -> [0.3256, 0.368028, 9.81]
      b = [0.1, -0.2, 0.05]                                 -> [0.4256, 0.168028, 9.86]
    Gyro: R^T w = [0, 0, 2]; xi = [0.01, 0, 0]: + [0, -0.02, 0]; K = diag(1, 1, 1.05);
      b = [0.001, 0, 0]                                     -> [0.001, -0.02, 2.1]
    """
    from imu_array_ros.model.description import ArrayDescription, ImuSpec
    from imu_array_ros.model.samples import MotionTruth

    imu = ImuSpec(
        name="imu_a",
        position=np.array([0.1, 0.0, 0.0]),
        orientation=np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]),  # columns: sensor axes in array
        values={"accelerometer.gain": np.array([1.1, 0.9, 1.0]),
                "accelerometer.nonorthogonality": np.array([0.02, 0.0, 0.0]),
                "accelerometer.misalignment": np.array([0.0, 0.0, 0.01]),
                "accelerometer.bias": np.array([0.1, -0.2, 0.05]),
                "gyroscope.gain": np.array([1.0, 1.0, 1.05]), "gyroscope.misalignment": np.array([0.01, 0.0, 0.0]),
                "gyroscope.bias": np.array([0.001, 0.0, 0.0])},
    )
    desc = ArrayDescription("a", 0.01, 0.001, 35.0, 160.0, (imu,))
    truth = MotionTruth(stamps=np.array([0]), omega=np.array([[0.0, 0.0, 2.0]]), omega_dot=np.array([[0.0, 0.0, 3.0]]),
                        specific_force=np.array([[0.0, 0.0, 9.81]]))
    y = simulate_measurements(desc, truth, np.random.default_rng(0), noise=False)
    np.testing.assert_allclose(y.accel[0, 0], [0.4256, 0.168028, 9.86], rtol=0, atol=1e-12)
    np.testing.assert_allclose(y.gyro[0, 0], [0.001, -0.02, 2.1], rtol=0, atol=1e-12)
    # the fusion's linear form of the same model reads the same
    lin = LinearArrayModel.from_description(desc)
    z = np.concatenate([quadratic_monomials(truth.omega[0]), truth.omega_dot[0], truth.specific_force[0]])
    np.testing.assert_allclose(lin.acc_design[0] @ z + lin.acc_bias[0], [0.4256, 0.168028, 9.86], rtol=0, atol=1e-12)
    np.testing.assert_allclose(lin.gyro_matrix[0] @ truth.omega[0] + lin.gyro_bias[0], [0.001, -0.02, 2.1],
                               rtol=0, atol=1e-12)


def test_core_does_not_import_ros():
    """The core (everything but imu_array_ros.nodes) must import neither rclpy nor messages."""
    pkg = Path(__file__).resolve().parents[1] / "imu_array_ros"
    banned = ("rclpy", "sensor_msgs", "geometry_msgs", "std_srvs", "diagnostic_msgs", "builtin_interfaces")
    for path in pkg.rglob("*.py"):
        if "nodes" in path.relative_to(pkg).parts:
            continue
        tree = ast.parse(path.read_text())
        for node in ast.walk(tree):
            names = []
            if isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom) and node.module:
                names = [node.module]
            for name in names:
                assert not name.split(".")[0] in banned, f"{path.name} imports {name}"
