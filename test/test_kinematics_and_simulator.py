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
from imu_array_ros.model.sensor_model import LinearArrayModel
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
    assert np.all(np.abs(samples.accel) <= array32.accelerometer_range)


def test_simulator_saturates_and_adds_noise_of_the_right_size(array32, rng):
    model = LinearArrayModel.from_description(array32)
    from imu_array_ros.simulation.motion import random_motion

    truth = random_motion(4000, np.deg2rad(2500), 0.0, rng, omega_direction=[0, 0, 1])
    noisy = simulate_measurements(model, truth, rng)
    clean = simulate_measurements(model, truth, rng, noise=False)
    assert np.all(np.abs(noisy.gyro[:, :, 2]) == model.gyro_range)  # saturated, sign kept
    assert np.all(np.sign(noisy.gyro[:16, :, 2]) == np.sign(clean.gyro[:16, :, 2]))
    res = (noisy.accel - clean.accel).reshape(-1)
    assert abs(res.std() / array32.accelerometer_noise_std - 1) < 0.02


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
