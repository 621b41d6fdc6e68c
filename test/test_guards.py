"""Never write nonsense (imu_array_ros.calibration.guards): every calibration result is refused, with one line
naming the reason and nothing written, when it did not converge, when a value it changed is physically
implausible, or when it fits its own data worse than the model it started from; and geometry drops still
samples by the gyroscopes, so real windows that mix still poses and motion are refused or plausible."""

from __future__ import annotations

import os
from dataclasses import replace

import numpy as np
import pytest

from imu_array_ros.calibration.guards import POSITION_BOUND, check_calibration, check_fits_better, check_plausible
from imu_array_ros.calibration.result import backup_path
from imu_array_ros.errors import CalibrationError
from imu_array_ros.model.layouts import tetrahedron4
from imu_array_ros.model.sensor_model import SensorModel
from imu_array_ros.simulation.simulator import simulate_twist
from imu_array_ros.workflows import calibrate

from conftest import REPO, assert_user_error, cli

DATA = REPO.parent / "shared" / "data" / "openshoe_mimu4444bt"


def _twist(offsets: np.ndarray, seed: int = 13):
    """(nominal description, 4 s of twisting at 200 Hz by the tetrahedron whose positions are the nominal ones
    plus ``offsets`` (4, 3) m)."""
    desc = tetrahedron4()
    model = SensorModel.from_description(desc)
    rng = np.random.default_rng(seed)
    s, _ = simulate_twist(model.with_terms(position=model.positions + offsets), 4.0, 200.0, rng)
    return desc, s


@pytest.fixture(scope="module")
def twist():
    """Positions off by ~1 mm (imu_00 at nominal: the reference)."""
    rng = np.random.default_rng(5)
    offsets = rng.normal(0, 1e-3, (4, 3))
    offsets[0] = 0.0
    return _twist(offsets)


@pytest.fixture(scope="module")
def good(twist):
    """The geometry calibration of ``twist``: converged, plausible, fits better (it passes every check)."""
    desc, s = twist
    return calibrate("geometry", s, desc)


def test_a_good_calibration_passes(good, twist):
    desc, _ = twist
    start = SensorModel.from_description(desc)
    assert good.converged
    change = np.linalg.norm(good.model.positions - start.positions, axis=1)
    assert 0.5e-3 < change.max() < POSITION_BOUND  # it moved the positions, by a plausible amount
    check_calibration(good, start)  # no error


def test_not_converged_is_refused_naming_the_iterations(twist):
    desc, s = twist
    with pytest.raises(CalibrationError, match=r"^geometry: refused: not converged \(1 iterations\); nothing written"):
        calibrate("geometry", s, desc, max_iterations=1)
    # the expert override returns it, marked unconverged
    assert not calibrate("geometry", s, desc, max_iterations=1, checks=False).converged


def test_a_position_beyond_the_bound_is_refused():
    """The array's imu_02 really sits 8 mm from its described position: the calibration finds it (converged,
    fits better) but a chip 8 mm from its drawing is not believed: refused, naming it."""
    offsets = np.zeros((4, 3))
    offsets[2] = [8e-3, 0.0, 0.0]
    desc, s = _twist(offsets)
    with pytest.raises(CalibrationError, match=r"refused: imu_02 position moved 8\.\d\d mm from the description it "
                                               r"started from \(more than 5 mm: physically implausible\)"):
        calibrate("geometry", s, desc)
    cal = calibrate("geometry", s, desc, checks=False)
    assert cal.converged and abs(np.linalg.norm(cal.model.positions[2] - cal.details.initial_positions[2]) - 8e-3) < 3e-4
    # the bound is an option: a user who says 1 cm gets it written
    assert calibrate("geometry", s, desc, position_bound=10e-3).converged


def test_the_position_bound_is_an_option(good, twist):
    desc, _ = twist
    start = SensorModel.from_description(desc)
    moved = np.linalg.norm(good.model.positions - start.positions, axis=1)
    with pytest.raises(CalibrationError, match=f"refused: {good.names[int(np.argmax(moved))]} position moved"):
        check_plausible(good, start, position_bound=0.5 * moved.max())
    with pytest.raises(CalibrationError, match="bound must be > 0"):
        check_plausible(good, start, position_bound=0.0)


@pytest.mark.parametrize("term, column, value, fragment", [
    ("gyroscope_gain", 1, 1.3, r"imu_01 gyroscope\.gain\[1\] = 1\.3, more than 0\.2 from 1"),
    ("accelerometer_misalignment", 2, -0.15, r"imu_01 accelerometer\.misalignment\[2\] = -0\.15 rad, more than 0\.1"),
    ("gyroscope_nonorthogonality", 0, 0.2, r"imu_01 gyroscope\.nonorthogonality\[0\] = 0\.2 rad"),
    ("time_offset", 1, 0.5, r"imu_01 gyroscope\.time_offset = 0\.5 s, more than 0\.1 from 0"),
])
def test_a_field_beyond_its_declared_bound_is_refused(good, twist, term, column, value, fragment):
    """Bounds come from the term registry (Field.plausible); a value just inside is accepted."""
    desc, _ = twist
    start = SensorModel.from_description(desc)
    values = good.model.terms[term].values.copy() if term in good.model.terms else None
    if values is None:
        from imu_array_ros.model.terms import REGISTRY

        values = REGISTRY[term].default_values(4)
    values[1, column] = value
    bad = replace(good, model=good.model.with_terms(**{term: values}))
    with pytest.raises(CalibrationError, match=fragment + ".*physically implausible"):
        check_plausible(bad, start)
    default = 1.0 if "gain" in term else 0.0
    values[1, column] = default + 0.9 * (value - default) / abs(value - default) * (0.2 if "gain" in term else 0.1)
    check_plausible(replace(good, model=good.model.with_terms(**{term: values})), start)


def test_a_bias_beyond_a_tenth_of_the_range_is_refused(good, twist):
    desc, _ = twist
    start = SensorModel.from_description(desc)
    full_scale = start.gyro_clip
    assert np.isfinite(full_scale)
    b = np.zeros((4, 3))
    b[3, 0] = 0.12 * full_scale
    with pytest.raises(CalibrationError, match=r"imu_03 gyroscope\.bias\[0\] = .* rad/s, more than .* from 0"):
        check_plausible(replace(good, model=good.model.with_terms(gyroscope_bias=b)), start)
    b[3, 0] = 0.08 * full_scale
    check_plausible(replace(good, model=good.model.with_terms(gyroscope_bias=b)), start)


def test_a_value_the_calibration_did_not_change_is_not_judged(good, twist):
    """A starting description the user wrote with an odd value is not the calibration's doing."""
    desc, _ = twist
    start = SensorModel.from_description(desc)
    gains = np.ones((4, 3))
    gains[0, 0] = 1.5
    check_plausible(replace(good, model=good.model.with_terms(gyroscope_gain=gains)),
                    start.with_terms(gyroscope_gain=gains))


def test_a_calibration_that_fits_worse_than_its_start_is_refused(good, twist):
    """The positions moved 2 mm the wrong way (within the position bound): its own window says it is worse."""
    desc, _ = twist
    start = SensorModel.from_description(desc)
    wrong = start.positions - 2.0 * (good.model.positions - start.positions)
    wrong[0] = start.positions[0]
    assert np.linalg.norm(wrong - start.positions, axis=1).max() < POSITION_BOUND
    worse = replace(good, model=start.with_terms(position=wrong), score=None)
    check_plausible(worse, start)  # plausible: only the fit says no
    with pytest.raises(CalibrationError, match=r"^geometry: refused: the calibrated model fits its own window worse "
                                               r"than the one it started from \(log-likelihood .* < .*\); nothing"):
        check_fits_better(worse, start)
    check_fits_better(good, start)


def test_the_command_line_refuses_in_one_line_and_writes_nothing(twist, tmp_path, capsys):
    from imu_array_ros.io.rosbag.recording import write_imu_recording
    from imu_array_ros.model.description import save_description

    desc, s = twist
    save_description(desc, tmp_path / "array.yaml")
    write_imu_recording(tmp_path / "rec", s, desc)
    out = tmp_path / "cal.yaml"
    args = ("calibrate", "geometry", tmp_path / "rec", "--array", tmp_path / "array.yaml", "--out", out, "-q")
    assert_user_error(cli(capsys, *args, "--max-iterations", "1"), str(tmp_path / "rec"),
                      "refused: not converged (1 iterations); nothing written")
    assert not out.exists()
    assert cli(capsys, *args)[0] == 0  # converged and plausible: written
    before = (out.read_bytes(), os.stat(out).st_mtime_ns)
    assert_user_error(cli(capsys, *args, "--max-iterations", "1", "--force"), "refused: not converged")
    assert (out.read_bytes(), os.stat(out).st_mtime_ns) == before and not backup_path(out).exists()


@pytest.mark.skipif(not (DATA / "exp_1.bin").exists(), reason="shared real data not present")
def test_a_real_window_of_still_poses_is_refused_not_written(tmp_path):
    """exp_1 0-60 s: the static poses with short turns between them.  Before the guards, geometry used all but
    14 of its samples (a still array's fused omega_dot, from uncalibrated accelerometers, passed as rotation)
    and wrote positions moved by 35 mm, NOT converged, exit 0 (benchmarks/results/real_data_guards.md).  Now
    the gyroscopes drop the still samples and what is left is refused, or plausible if written."""
    from imu_array_ros.calibration.selection import select_rotating
    from imu_array_ros.io.openshoe.capture import import_capture
    from imu_array_ros.model.description import load_description

    desc = load_description(REPO / "config" / "mimu4444bt_corners.yaml")
    samples, _ = import_capture(DATA / "exp_1.bin", desc)
    window = samples.window(0.0, 60.0)
    model = SensorModel.from_description(desc)
    old = select_rotating(window, model)
    new = select_rotating(window, model, gyroscopes=True)
    assert old.n_used > 0.99 * len(window)  # what the accelerometer-based test let through
    assert new.dropped["still_by_gyroscopes"] > 0.9 * len(window)
    try:
        cal = calibrate("geometry", window, desc)
    except CalibrationError as err:
        assert "refused" in str(err) and "\n" not in str(err)
    else:
        change = np.linalg.norm(cal.model.positions - model.positions, axis=1)
        assert cal.converged and change.max() <= POSITION_BOUND, (cal.summary(), change)
