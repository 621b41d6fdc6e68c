"""Icosahedron calibration session simulator (nilsson2014 Sec. III) and ``simulate --motion icosahedron``."""

from __future__ import annotations

import numpy as np
import pytest

from imu_array_ros.io.rosbag.recording import read_imu_recording, read_truth
from imu_array_ros.model.constants import STANDARD_GRAVITY
from imu_array_ros.model.description import load_description
from imu_array_ros.model.sensor_model import SensorModel, motion_context, motion_derivative
from imu_array_ros.model.layouts import NILSSON14_NOT_WORKING, nilsson14
from imu_array_ros.simulation.icosahedron import icosahedron_face_normals, simulate_icosahedron
from imu_array_ros.simulation.motion import quat_multiply
from imu_array_ros.simulation.perturb import perturb

from conftest import REPO, assert_user_error, cli

NILSSON14 = REPO / "config" / "nilsson14.yaml"
TILT = np.deg2rad(1.0)


def _angle_deg(u, v):
    u = u / np.linalg.norm(u, axis=-1, keepdims=True)
    v = v / np.linalg.norm(v, axis=-1, keepdims=True)
    return np.degrees(np.arccos(np.clip(np.sum(u * v, axis=-1), -1.0, 1.0)))


@pytest.fixture(scope="module")
def model():
    return perturb(SensorModel.from_description(nilsson14()), np.random.default_rng(7))


@pytest.fixture(scope="module")
def session(model):
    return simulate_icosahedron(model, np.random.default_rng(3), rate_hz=100.0, still_s=2.0, transition_s=1.5,
                                tilt_std=TILT, twist_s=3.0)


def test_face_normals_are_the_icosahedron():
    n = icosahedron_face_normals()
    assert n.shape == (20, 3)
    np.testing.assert_allclose(np.linalg.norm(n, axis=1), 1.0, atol=1e-12)
    np.testing.assert_allclose(n.sum(axis=0), 0.0, atol=1e-12)
    ang = _angle_deg(n[:, None], n[None])
    np.fill_diagonal(ang, 180.0)
    # each face has exactly 3 edge neighbours at the dihedral supplement 41.81 deg, none closer
    assert np.isclose(ang.min(), 41.8103, atol=1e-3)
    assert np.all(np.isclose(ang, 41.8103, atol=1e-3).sum(axis=1) == 3)
    # even distribution: mean outer product is I/3
    np.testing.assert_allclose(n.T @ n / 20, np.eye(3) / 3, atol=1e-12)


def test_twenty_rests_with_gravity_along_the_face_normal(session):
    samples, truth, info = session
    n = len(samples)
    assert n == round((20 * 2.0 + 19 * 1.5 + 3.0) * 100)
    assert info.intervals.shape == (20, 2) and info.twist_start == round((20 * 2.0 + 19 * 1.5) * 100)
    assert np.array_equal(np.unique(info.face), np.arange(-1, 20))
    for i, (a, b) in enumerate(info.intervals):
        assert np.all(info.face[a:b] == i) and b - a == 200
        assert (a == 0 or info.face[a - 1] == -1) and info.face[b] == -1
    rest = info.face >= 0
    s = truth.specific_force
    np.testing.assert_allclose(np.linalg.norm(s[rest], axis=1), STANDARD_GRAVITY, rtol=0, atol=1e-12)
    assert np.all(truth.omega[rest] == 0) and np.all(truth.omega_dot[rest] == 0)
    # the rest direction is -n (the resting face points down) up to the tilt, and exactly info.directions
    ang = _angle_deg(s[info.intervals[:, 0]], -info.normals)
    assert 0.05 < np.median(ang) and ang.max() < 5 * np.degrees(TILT), ang
    np.testing.assert_allclose(s[info.intervals[:, 0]] / STANDARD_GRAVITY, info.directions, atol=1e-12)
    # the attitude does not move during a rest; the handling motion really moves
    for a, b in info.intervals:
        np.testing.assert_allclose(truth.attitude[a:b], np.broadcast_to(truth.attitude[a], (b - a, 4)), atol=1e-15)
    moving = (info.face < 0) & (np.arange(n) < info.twist_start)
    assert np.percentile(np.linalg.norm(truth.omega[moving], axis=1), 50) > 0.3


def test_motion_is_consistent(session):
    samples, truth, info = session
    t = (truth.stamps - truth.stamps[0]) * 1e-9
    faces = np.arange(len(t)) < info.twist_start
    # omega_dot is the derivative of omega (finite differences, 100 Hz: O(h^2) error)
    fd = motion_derivative(truth.stamps, truth.omega)
    scale = np.abs(truth.omega_dot[faces]).max()
    assert np.abs(fd - truth.omega_dot)[faces].max() < 0.03 * scale
    # the attitude turns with omega (body frame): q_k^-1 q_{k+1} = exp(omega_mid dt)
    q = truth.attitude
    dq = quat_multiply(q[:-1] * np.array([1.0, -1.0, -1.0, -1.0]), q[1:])
    rate = 2.0 * dq[:, 1:] * np.sign(dq[:, :1]) / np.diff(t)[:, None]
    mid = 0.5 * (truth.omega[:-1] + truth.omega[1:])
    assert np.abs(rate - mid)[faces[:-1]].max() < 1e-3 * np.abs(mid).max()
    assert np.abs(rate - mid).max() < 0.01 * np.abs(mid).max()  # also while twisting (integrated attitude)
    # omega starts continuously into the twisting (faded in)
    i = info.twist_start
    assert np.linalg.norm(truth.omega[i + 1]) < 0.01 and np.linalg.norm(truth.omega[i + 200]) > 0.5


def test_measurements_are_the_forward_model(session, model):
    samples, truth, info = session
    ctx = motion_context(truth.stamps, truth.omega, truth.omega_dot, truth.specific_force, model.rotations,
                         derivatives=True)
    acc, gyr = model.predict(ctx)
    za = (samples.accel - acc) / model.acc_std
    zg = (samples.gyro - gyr) / model.gyro_std
    assert 0.95 < za.std() < 1.05 and 0.95 < zg.std() < 1.05
    assert abs(za.mean()) < 0.02 and abs(zg.mean()) < 0.02


def test_validation():
    desc = nilsson14()
    with pytest.raises(ValueError):
        simulate_icosahedron(desc, np.random.default_rng(0), transition_s=0.0)
    with pytest.raises(ValueError):
        simulate_icosahedron(desc, np.random.default_rng(0), still_s=0.001, rate_hz=100.0)


def test_nilsson14_layout():
    desc = load_description(NILSSON14)
    assert len(desc.imus) == 14 and "imu_14" in desc.names
    assert not set(NILSSON14_NOT_WORKING) & set(desc.names)
    assert desc.names == nilsson14().names
    np.testing.assert_allclose(desc.positions, nilsson14().positions)
    top = desc.positions[:, 2] > 0
    assert top.sum() == 9 and np.allclose(desc.orientations[top], np.eye(3))
    assert np.allclose(desc.orientations[~top], [[0, 1, 0], [1, 0, 0], [0, 0, -1]])


def test_cli_writes_an_icosahedron_recording(tmp_path, capsys):
    from imu_array_ros.calibration.still import find_still_poses

    out = tmp_path / "ico.mcap"
    code, stdout, err = cli(capsys, "simulate", "--array", NILSSON14, "--out", out, "--motion", "icosahedron",
                            "--still-seconds", 1.5, "--transition-seconds", 1, "--tilt-std-deg", 2,
                            "--twist-seconds", 2, "--rate", 50, "--error-seed", 1, "--start-time", "0")
    assert code == 0 and stdout == "", err
    assert "icosahedron" in err
    desc = load_description(NILSSON14)
    samples, _ = read_imu_recording(out, desc)
    assert len(samples) == round((20 * 1.5 + 19 * 1.0 + 2.0) * 50)
    np.testing.assert_array_equal(samples.stamps, 20_000_000 * np.arange(len(samples)))
    truth = read_truth(out)
    rest_sf = np.linalg.norm(truth.specific_force, axis=1)
    assert np.sum(np.abs(rest_sf - STANDARD_GRAVITY) < 1e-9) >= 20 * 1.5 * 50 * 0.99
    poses = find_still_poses(samples, SensorModel.from_description(desc),
                             window_s=0.5, settle_s=0.1, min_duration_s=0.5)
    assert len(poses) == 20, poses.summary()
    # options that belong to another motion are user errors
    assert_user_error(cli(capsys, "simulate", "--array", NILSSON14, "--out", tmp_path / "x.mcap", "--motion",
                          "icosahedron", "--duration", 5), "--duration", "icosahedron")
    assert_user_error(cli(capsys, "simulate", "--array", NILSSON14, "--out", tmp_path / "y.mcap",
                          "--still-seconds", 2), "--still-seconds", "icosahedron")
    assert_user_error(cli(capsys, "simulate", "--array", NILSSON14, "--out", tmp_path / "z.mcap", "--motion",
                          "icosahedron", "--still-seconds", 0.01, "--rate", 50), "--still-seconds")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["ico.mcap"]
