"""``imu-array calibrate fit``: the fitting engine from the command line, end to end."""

from __future__ import annotations

import numpy as np
import pytest

from imu_array_ros.model.description import load_description
from imu_array_ros.model.forward import SensorModel

from conftest import ARRAY32, START, assert_user_error, cli


@pytest.fixture(scope="module")
def recording(tmp_path_factory):
    """A twisting recording of array32 with seeded position, gyro gain and time-offset errors."""
    from imu_array_ros.cli import main
    from imu_array_ros.model.description import save_description

    d = tmp_path_factory.mktemp("cal")
    rng = np.random.default_rng(11)
    nominal = load_description(ARRAY32)
    model = SensorModel.from_description(nominal)
    pos, gain, dt = rng.normal(0, 5e-4, (32, 3)), 1 + rng.normal(0, 0.01, (32, 3)), rng.normal(0, 1e-3, (32, 2))
    # the reference IMU (imu_00) at nominal: the fit holds its position, one gyro gain and the
    # accelerometer time offset to fix the gauge (common shift, scale and time), so the truth
    # must agree there for errors to be comparable
    pos[0], gain[0, 0], dt[0, 0] = 0.0, 1.0, 0.0
    true = model.with_terms(position=model.positions + pos, gyroscope_gain=gain, time_offset=dt)
    save_description(true.to_description(nominal), d / "true.yaml")
    assert main(["simulate", "--array", str(ARRAY32), "--true-array", str(d / "true.yaml"), "--out", str(d / "rec"),
                 "--duration", "3", "--rate", "200", "--seed", "2", "--start-time", START, "-q"]) == 0
    return d


def test_fit_writes_values_stds_and_a_calibration_record(recording, capsys):
    out = recording / "cal.yaml"
    code, stdout, err = cli(capsys, "calibrate", "fit", recording / "rec", "--array", ARRAY32,
                            "--terms", "position,gyroscope_gain,time_offset", "--out", out)
    assert code == 0 and stdout == "", err
    assert "fitting: iteration 1" in err and "held" in err and f"wrote {out}" in err
    cal = load_description(out)
    rec = cal.calibration
    assert rec["terms"] == ["position", "gyroscope_gain", "time_offset"] and rec["converged"] is True
    assert rec["log_likelihood_after"] > rec["log_likelihood_before"]
    assert 0.9 < rec["nis_after"] < 1.1 < rec["nis_before"]
    true = SensorModel.from_description(load_description(recording / "true.yaml"))
    fitted = SensorModel.from_description(cal)
    assert {"imu_00 position[0]", "imu_00 gyroscope.gain[0]", "imu_00 accelerometer.time_offset"} <= set(
        rec["held_for_gauge"])
    err_pos = fitted.positions - true.positions
    std_pos = np.array([imu.stds["position"] if "position" in imu.stds else np.full(3, np.nan) for imu in cal.imus])
    est = np.isfinite(std_pos) & (std_pos > 0)  # held (std 0) and unfitted (no std) left out
    z = err_pos[est] / std_pos[est]
    assert len(z) >= 90 and 0.7 < np.sqrt(np.mean(z ** 2)) < 1.4, np.sqrt(np.mean(z ** 2))
    for imu in cal.imus:  # every fitted field has its _std beside it
        assert "gyroscope.gain" in imu.values and "gyroscope.gain" in imu.stds
        assert "gyroscope.time_offset" in imu.values


@pytest.mark.parametrize("args, fragments", [
    (("--terms", "position,warp_drive"), ("--terms", "unknown term 'warp_drive'")),
    (("--terms", ""), ("--terms", "at least one term")),
    (("--terms", "position", "--imus", "imu_00,imu_99"), ("unknown IMU name 'imu_99'",)),
    (("--terms", "position", "--reference", "nope"), ("unknown IMU name 'nope'",)),
    (("--terms", "position", "--max-iterations", "0"), ("--max-iterations",)),
])
def test_bad_options_are_one_line_errors(recording, capsys, args, fragments):
    out = recording / "bad.yaml"
    assert_user_error(cli(capsys, "calibrate", "fit", recording / "rec", "--array", ARRAY32, *args, "--out", out),
                      *fragments)
    assert not out.exists()


def test_existing_output_is_kept_without_force(recording, capsys):
    out = recording / "keep.yaml"
    out.write_text("precious: true\n")
    assert_user_error(cli(capsys, "calibrate", "fit", recording / "rec", "--array", ARRAY32, "--terms", "position",
                          "--out", out), "keep.yaml")
    assert out.read_text() == "precious: true\n"


def test_motion_that_cannot_identify_the_term_is_refused(tmp_path, capsys):
    """Rotation about one axis only cannot locate the accelerometers along it: a clear error."""
    from imu_array_ros.io.rosbag.recording import write_imu_recording
    from imu_array_ros.simulation.motion import random_motion
    from imu_array_ros.simulation.simulator import simulate_measurements

    desc = load_description(ARRAY32)
    rng = np.random.default_rng(3)
    truth = random_motion(400, 10.0, 50.0, rng, omega_direction=[0, 0, 1], rate_hz=200.0)
    truth.omega_dot[:] = truth.omega_dot[:, 2:3] * [0, 0, 1]  # about z only, also in acceleration
    samples = simulate_measurements(desc, truth, rng)
    write_imu_recording(tmp_path / "rec", samples, desc)
    line = assert_user_error(cli(capsys, "calibrate", "fit", tmp_path / "rec", "--array", ARRAY32,
                                 "--terms", "position", "--out", tmp_path / "c.yaml", "-q"), "position")
    assert "axes" in line, line
    assert not (tmp_path / "c.yaml").exists()
