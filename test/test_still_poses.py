"""Static-pose extraction (calibration/still.py) on simulated icosahedron sessions and a real capture."""

from __future__ import annotations

import time
from dataclasses import replace

import numpy as np
import pytest

from imu_array_ros.calibration.still import MIN_EIGENVALUE, StillPoses, check_poses, find_still_poses
from imu_array_ros.errors import CalibrationError
from imu_array_ros.model.constants import STANDARD_GRAVITY
from imu_array_ros.model.description import load_description
from imu_array_ros.model.sensor_model import SensorModel, motion_context
from imu_array_ros.model.layouts import nilsson14
from imu_array_ros.model.samples import ImuSamples, MotionTruth
from imu_array_ros.simulation.icosahedron import simulate_icosahedron
from imu_array_ros.simulation.perturb import perturb
from imu_array_ros.simulation.simulator import simulate_measurements, simulate_twist

from conftest import REPO, SHARED_DATA


@pytest.fixture(scope="module")
def model():
    """nilsson2014's array with nilsson2014 Table I-sized errors (DEFAULT_ERROR_SCALES)."""
    return perturb(SensorModel.from_description(nilsson14()), np.random.default_rng(11))


@pytest.fixture(scope="module")
def session(model):
    return simulate_icosahedron(model, np.random.default_rng(5), rate_hz=100.0, twist_s=5.0)


@pytest.fixture(scope="module")
def poses(session, model):
    samples, _, _ = session
    return find_still_poses(samples, model)


def _find(samples, model, **kw) -> StillPoses:
    return find_still_poses(samples, model, **kw)


def test_all_twenty_faces_and_nothing_else(session, poses):
    samples, _, info = session
    assert len(poses) == 20 and poses.rejected == [], poses.summary()
    face_of = [np.unique(info.face[a:b]) for a, b in poses.intervals]
    assert all(len(f) == 1 and f[0] >= 0 for f in face_of), "a pose overlaps handling motion"
    assert sorted(int(f[0]) for f in face_of) == list(range(20))
    # every accepted sample is truly at rest; the true rests are mostly accepted (minus settling)
    assert np.all(info.face[poses.still] >= 0)
    assert poses.still.sum() > 0.5 * (info.face >= 0).sum()
    # the moving phase: the middle of each transition and the hand twisting
    for (a, b), (c, _) in zip(info.intervals[:-1], info.intervals[1:]):
        assert poses.moving[(b + c) // 2]
    assert poses.moving[info.twist_start + 100:].mean() > 0.95
    assert not np.any(poses.still & poses.moving)
    assert poses.stamps.dtype == np.int64 and np.all(poses.stamps[:, 1] > poses.stamps[:, 0])
    np.testing.assert_array_equal(poses.stamps[:, 0], samples.stamps[poses.intervals[:, 0]])


def test_averages_match_the_truth_within_noise(session, poses, model):
    samples, truth, info = session
    ctx = motion_context(truth.stamps, truth.omega, truth.omega_dot, truth.specific_force, model.rotations,
                         derivatives=True)
    acc, gyr = model.predict(ctx)  # noise-free readings of the true (perturbed) sensors
    expect_a = np.array([acc[a:b].mean(axis=0) for a, b in poses.intervals])
    expect_g = np.array([gyr[a:b].mean(axis=0) for a, b in poses.intervals])
    np.testing.assert_array_equal(poses.counts, np.diff(poses.intervals, axis=1) * np.ones((1, model.n_imus), int))
    sqrt_n = np.sqrt(poses.counts)[..., None]
    za = (poses.accel - expect_a) / (model.acc_std / sqrt_n)
    zg = (poses.gyro - expect_g) / (model.gyro_std / sqrt_n)
    assert np.abs(za).max() < 5 and np.abs(zg).max() < 5
    assert 0.8 < za.std() < 1.2 and 0.8 < zg.std() < 1.2  # the averages are as good as the noise allows
    np.testing.assert_allclose(np.median(poses.accel_std / model.acc_std), 1.0, atol=0.05)
    np.testing.assert_allclose(np.median(poses.gyro_std / model.gyro_std), 1.0, atol=0.05)
    # directions: nominal rotations, mean over IMUs; errors of ~0.5 deg misalignment and 0.3 m/s^2 bias
    faces = np.array([info.face[a] for a, _ in poses.intervals])
    cos = np.sum(poses.directions * info.directions[faces], axis=1)
    assert np.degrees(np.arccos(np.clip(cos, -1, 1))).max() < 2.0
    np.testing.assert_allclose(np.linalg.norm(poses.directions, axis=1), 1.0, atol=1e-12)


def test_spread_and_check(poses):
    s = poses.spread()
    assert s["poses"] == 20
    assert s["min_eigenvalue"] > 0.3  # 1/3 for the exact icosahedron
    assert 35.0 < s["coverage_deg"] < 41.0  # 37.4 exact
    assert 35.0 < s["min_separation_deg"] < 47.0  # 41.8 exact
    check_poses(poses)
    assert "20 static poses" in poses.summary()


def test_saturated_pose_is_rejected(session, model):
    samples, _, info = session
    a, b = info.intervals[7]
    accel = samples.accel.copy()
    accel[a:b, 3, 2] = model.acc_clip  # imu stuck at full scale during face 7
    p = _find(replace(samples, accel=accel), model)
    assert len(p) == 19
    assert [r for r in p.rejected if r[2].startswith("saturated")] and len(p.rejected) == 1
    start, stop, _ = p.rejected[0]
    assert start <= a + 100 < stop


def test_missing_imu_keeps_the_poses(session, model):
    samples, _, info = session
    accel, gyro = samples.accel.copy(), samples.gyro.copy()
    accel[:, 4] = np.nan  # imu dead for the whole session
    gyro[:, 4] = np.nan
    a, b = info.intervals[2]
    accel[a:b, 9] = np.nan  # another imu lost during one rest only
    gyro[a:b, 9] = np.nan
    p = _find(replace(samples, accel=accel, gyro=gyro), model)
    assert len(p) == 20, p.summary()
    assert np.isnan(p.accel[:, 4]).all() and np.isnan(p.gyro_std[:, 4]).all() and np.all(p.counts[:, 4] == 0)
    lost = [i for i, (s0, s1) in enumerate(p.intervals) if s0 >= a and s1 <= b]
    assert len(lost) == 1
    assert np.isnan(p.accel[lost[0], 9]).all()
    others = np.delete(np.arange(model.n_imus), 4)
    assert np.isfinite(np.delete(p.accel, lost[0], axis=0)[:, others]).all()
    assert "missing" in p.summary() and p.names[4] in p.summary()


def test_accelerating_and_drifting_rests_are_rejected(session, model):
    samples, truth, info = session
    s = truth.specific_force.copy()
    a, b = info.intervals[4]
    s[a:b] *= 1.08  # 8 % more than gravity: e.g. in an accelerating lift
    a2, b2 = info.intervals[12]
    # a slow tilt of 3 deg over the rest about an axis normal to gravity (too slow for the window test)
    axis = np.cross(s[a2], [1.0, 0.0, 0.0])
    axis /= np.linalg.norm(axis)
    ang = np.deg2rad(3.0) * np.linspace(0, 1, b2 - a2)[:, None]
    v = s[a2]
    s[a2:b2] = v * np.cos(ang) + np.cross(axis, v) * np.sin(ang) + axis * (axis @ v) * (1 - np.cos(ang))
    sim = simulate_measurements(model, replace(truth, specific_force=s), np.random.default_rng(9))
    p = _find(sim, model)
    reasons = [r[2] for r in p.rejected]
    assert len(p) == 18, (p.summary(), reasons)
    assert any(r.startswith("not gravity") for r in reasons) and any(r.startswith("drifting") for r in reasons)


def test_too_few_poses_raise(session, model):
    samples, _, info = session
    cut = info.intervals[8, 0] - 20  # the first 8 rests only
    p = _find(samples.select(slice(0, cut)), model)
    assert len(p) == 8
    with pytest.raises(CalibrationError, match=r"only 8 static poses found, the full model needs at least 12: "
                                               r"set the array down on more faces") as err:
        check_poses(p)
    assert "\n" not in str(err.value)
    check_poses(p, needed=8, what="bias only")
    with pytest.raises(CalibrationError, match="without misalignment needs at least 9"):
        check_poses(p, needed=9, what="the model without misalignment")


def test_coplanar_poses_raise(model):
    # 12 rests turning about the array x axis only: every direction in the y-z plane
    rate, rest = 100.0, 300
    theta = np.repeat(np.linspace(0, 2 * np.pi, 12, endpoint=False), rest)
    n = len(theta)
    s = STANDARD_GRAVITY * np.column_stack([np.zeros(n), np.sin(theta), np.cos(theta)])
    truth = MotionTruth(stamps=np.round(np.arange(n) * 1e9 / rate).astype(np.int64), omega=np.zeros((n, 3)),
                        omega_dot=np.zeros((n, 3)), specific_force=s)
    p = _find(simulate_measurements(model, truth, np.random.default_rng(2)), model)
    assert len(p) == 12
    assert p.spread()["min_eigenvalue"] < 1e-3 < MIN_EIGENVALUE
    with pytest.raises(CalibrationError, match="12 static poses are clustered or coplanar .* more different"):
        check_poses(p)


def test_no_still_interval(model):
    samples, _ = simulate_twist(model, 5.0, 100.0, np.random.default_rng(4))
    p = _find(samples, model)
    assert len(p) == 0 and p.accel.shape == (0, model.n_imus, 3) and p.intervals.shape == (0, 2)
    assert not p.still.any() and p.moving.mean() > 0.9
    assert p.spread() == {"poses": 0, "min_eigenvalue": 0.0, "coverage_deg": 180.0,
                          "min_separation_deg": pytest.approx(float("nan"), nan_ok=True)}
    assert p.summary().startswith("0 static poses")
    with pytest.raises(CalibrationError, match="only 0 static poses found"):
        check_poses(p)
    # shorter than one window: nothing, no error
    p = _find(samples.select(slice(0, 10)), model)
    assert len(p) == 0 and p.moving.all()


def test_fast_on_a_long_recording():
    """600 s at 62.5 Hz x 8 IMUs (the real captures' size) in well under a second."""
    desc = load_description(REPO / "config" / "mimu4444bt_corners.yaml")
    model = SensorModel.from_description(desc)
    rng = np.random.default_rng(0)
    n = int(600 * 62.5)
    stamps = np.round(np.arange(n) * 16e6).astype(np.int64)
    accel = rng.normal(0, 0.045, (n, 8, 3)) + np.einsum("kji,j->ki", model.rotations, [0, 0, STANDARD_GRAVITY])
    gyro = rng.normal(0, 0.0039, (n, 8, 3))
    samples = ImuSamples(stamps, accel, gyro, model.names)
    find_still_poses(samples.select(slice(None, 1000)), model)  # warm-up
    t0 = time.perf_counter()
    p = find_still_poses(samples, model)
    assert time.perf_counter() - t0 < 1.0
    assert len(p) == 1 and p.still.mean() > 0.99


CAPTURE = SHARED_DATA / "exp_1.bin"


def test_real_capture_has_about_twenty_poses():
    if not CAPTURE.is_file():
        pytest.skip(f"real capture not found: {CAPTURE}")
    from imu_array_ros.io.openshoe.capture import import_capture

    desc = load_description(REPO / "config" / "mimu4444bt_corners.yaml")
    samples, _ = import_capture(CAPTURE, desc)
    p = _find(samples, SensorModel.from_description(desc))
    s = p.spread()
    assert 18 <= len(p) <= 24, p.summary()
    assert s["min_eigenvalue"] > 0.25 and s["coverage_deg"] < 45.0, p.summary()
    check_poses(p)
    # the static phase comes first and the twisting after it (README); twisting saturates nothing still
    assert p.moving[int(520 * 62.5):int(590 * 62.5)].mean() > 0.9
    assert np.all(np.abs(np.linalg.norm(p.accel, axis=2) / STANDARD_GRAVITY - 1) < 0.08)  # raw, uncalibrated
