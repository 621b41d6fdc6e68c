"""The motion-line check of the mode search (discovery/motioncheck.py): a missing library term's residual over a
band 1-2 Hz wide where the hand twisting is (what matched.py flags) follows the motion and is no mode; a board
mode 1.5 Hz wide at 2 Hz, in the same motion band, stays a mode; a mode's JSON kind says what is known."""

from __future__ import annotations

import numpy as np
import pytest

from imu_array_ros.discovery.modes import MODE_KIND, detect_modes
from imu_array_ros.discovery.motioncheck import MOTION_SHARE, motion_check
from imu_array_ros.fitting.engine import fit_motion
from imu_array_ros.model.samples import ImuSamples
from imu_array_ros.model.sensor_model import SensorModel
from imu_array_ros.simulation.effects import narrowband_process
from imu_array_ros.simulation.perturb import TERM_TEST_SIZES
from imu_array_ros.simulation.simulator import simulate_twist
from imu_array_ros.simulation.suites import array_description

FS, SECONDS = 200.0, 20.0


@pytest.fixture(scope="module")
def corners():
    return SensorModel.from_description(array_description("corners8"))


def _search(samples, model):
    motion, _, r = fit_motion(samples, model)
    s = detect_modes(r, FS, positions=model.positions, rotations=model.rotations, std=model.std, motion=motion,
                     heldout=False)
    return s, r.reshape(len(r), -1), motion


def test_missing_library_term_over_a_wide_low_band_is_no_mode(corners):
    """The 8 corner IMUs, 20 s of hand twisting at 200 Hz, imu 2's accelerometer gain 4 test sizes off and left
    out of the model: no mode is reported; the bands 1-2 Hz wide around 2 Hz that matched.py flags (on 3 of
    the 4 recordings) are set aside as following the motion.  Learning the relation only outside the band (one fold: the check until b4592a6)
    called it a mode on one of these recordings (share -0.8 on seed 3)."""
    before = []
    for seed in range(4):
        rng = np.random.default_rng([seed, 58])
        v = corners.terms["accelerometer_gain"].values.copy()
        v[2] += rng.normal(size=v[2].shape) * TERM_TEST_SIZES["accelerometer_gain"] * 4.0
        samples, _ = simulate_twist(corners.with_terms(accelerometer_gain=v), SECONDS, FS, rng)
        s, x, motion = _search(samples, corners)
        assert s.modes == [], (seed, [(m.frequency_hz, m.band_hz, m.motion) for m in s.modes])
        for m in s.motion_lines:
            if not (m.band_hz[1] - m.band_hz[0] > 1.0 and m.band_hz[0] < 2.0 < m.band_hz[1]):
                continue
            assert m.motion["follows_motion"] and m.motion["folds"] >= 4     # 0.25 Hz folds
            cols = [k * 6 + a for k, a in m.channels]
            one = motion_check(x[:, cols], np.isfinite(x[:, cols]), motion, FS, m.band_hz, fold_hz=100.0)
            before.append(one["explained_share"])
    assert len(before) >= 2 and min(before) < MOTION_SHARE  # the check before would have reported a mode


def test_board_mode_in_the_motion_band_stays_a_mode(corners):
    """The same twisting under the true model plus a 2 Hz resonance 1.5 Hz wide on the accelerometers (saddle
    shape, 0.5 noise std at the largest IMU): whatever the search finds is reported as a mode (none set aside as
    following the motion, share well below one half), and on at least one recording its band holds 2 Hz."""
    p = corners.positions - corners.positions.mean(axis=0)
    shape = p[:, 0] * p[:, 1] / np.max(np.abs(p[:, 0] * p[:, 1])) - 0.3
    shape /= np.max(np.abs(shape))
    at_2 = 0
    for seed in range(2):
        rng = np.random.default_rng([seed, 59])
        samples, _ = simulate_twist(corners, SECONDS, FS, rng)
        x = narrowband_process(samples.stamps, 2.0, 1.5, rng)
        field = 0.5 * x[:, None, None] * shape[None, :, None] * np.array([0.1, 0.25, 1.0])   # noise stds
        acc = np.einsum("kji,nkj->nki", corners.rotations, field) * corners.std[:, :3][None]
        s, _, _ = _search(ImuSamples(samples.stamps, samples.accel + acc, samples.gyro, samples.names), corners)
        assert s.modes and s.motion_lines == [], (seed, [(m.frequency_hz, m.motion) for m in s.motion_lines])
        assert all(m.motion["explained_share"] < 0.25 for m in s.modes)
        at_2 += any(m.band_hz[0] - 0.5 <= 2.0 <= m.band_hz[1] + 0.5 and m.motion["folds"] > 1 for m in s.modes)
    assert at_2 >= 1


def test_mode_kind_says_what_is_known():
    """A mode's JSON kind is a narrowband excess the fitted model leaves, not "outside the library": before the
    library search it may still be a term's misfit."""
    rng = np.random.default_rng(5)
    n, k = 4000, 4
    r = rng.normal(size=(n, k, 6))
    r[:, :2, 2] += 0.4 * np.sin(2 * np.pi * 37.0 * np.arange(n) / FS + 1.0)[:, None]
    m = detect_modes(r, FS, heldout=False).modes[0]
    d = m.to_dict([f"imu_{i}" for i in range(k)])
    assert d["kind"] == MODE_KIND and "library" not in d["kind"]
