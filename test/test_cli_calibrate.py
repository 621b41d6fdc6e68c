"""``imu-array calibrate fit`` (the fitting engine) and ``calibrate geometry`` from the command line, end to
end, and ``discover --apply``: each installs through the one install path (``OUT.bak``, never over a
better file)."""

from __future__ import annotations

import numpy as np
import pytest

from imu_array_ros.model.description import load_description
from imu_array_ros.model.sensor_model import SensorModel

from conftest import ARRAY32, REPO, START, assert_user_error, cli

CORNERS = REPO / "config" / "mimu4444bt_corners.yaml"


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
    (("--terms", "positon"), ("--terms: unknown term 'positon'; did you mean 'position'? (known: position, ",)),
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


def test_fit_installs_like_every_calibration_keeping_a_backup_and_never_a_worse_file(recording, capsys):
    """The one install path: with --force a worse file on disk (the nominal description) is replaced and
    kept as OUT.bak; a better one (the true sensors, which a position-only fit cannot match) is kept and
    the fit refused, nothing written."""
    out, bak = recording / "install.yaml", recording / "install.yaml.bak"
    out.write_bytes(ARRAY32.read_bytes())
    code, _, err = cli(capsys, "calibrate", "fit", recording / "rec", "--array", ARRAY32, "--terms", "position",
                       "--out", out, "--force")
    assert code == 0, err
    assert f"previous {out} kept as {bak}" in err and f"wrote {out}" in err
    assert bak.read_bytes() == ARRAY32.read_bytes()
    assert load_description(out).calibration["terms"] == ["position"]
    better = recording / "better.yaml"
    better.write_bytes((recording / "true.yaml").read_bytes())
    before = better.read_bytes()
    line = assert_user_error(cli(capsys, "calibrate", "fit", recording / "rec", "--array", ARRAY32, "--terms",
                                 "position", "--out", better, "--force", "-q"),
                             str(recording / "rec"), str(better), "not replaced: the calibration on file fits")
    assert "log-likelihood" in line
    assert better.read_bytes() == before and not (recording / "better.yaml.bak").exists()


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


# --------------------------------------------------------------------------- calibrate geometry


@pytest.fixture(scope="module")
def geometry_recordings(tmp_path_factory):
    """A 3 s twist of array32 with seeded 0.5 mm position errors (imu_00 at nominal), and a still one."""
    from imu_array_ros.cli import main
    from imu_array_ros.model.description import save_description

    d = tmp_path_factory.mktemp("geo")
    rng = np.random.default_rng(21)
    nominal = load_description(ARRAY32)
    model = SensorModel.from_description(nominal)
    pos = rng.normal(0, 5e-4, (32, 3))
    pos[0] = 0.0
    save_description(model.with_terms(position=model.positions + pos).to_description(nominal), d / "true.yaml")
    for name, rate in (("twist", "900"), ("still", "0.01")):
        assert main(["simulate", "--array", str(ARRAY32), "--true-array", str(d / "true.yaml"), "--out",
                     str(d / name), "--duration", "3", "--rate", "200", "--rms-rate", rate, "--seed", "3",
                     "--start-time", START, "-q"]) == 0
    return d


def test_geometry_writes_positions_stds_and_record_and_keeps_a_backup(geometry_recordings, capsys):
    d = geometry_recordings
    out = d / "geo.yaml"
    code, stdout, err = cli(capsys, "calibrate", "geometry", d / "twist", "--array", ARRAY32, "--out", out,
                            "--plot", d / "geo.png")
    assert code == 0 and stdout == "", err
    assert (d / "geo.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and f"wrote {d / 'geo.png'}" in err
    assert "calibrating: iteration 1" in err and "600 of 600 used" in err and f"wrote {out}" in err
    assert "imu_00: moved   0.0000 mm" in err and "(reference)" in err
    cal = load_description(out)
    rec = cal.calibration
    assert rec["reference"] == "imu_00" and rec["converged"] is True and rec["samples_used"] == 600
    assert rec["log_likelihood_after"] > rec["log_likelihood_before"] and 0.9 < rec["nis_after"] < 1.1
    assert set(rec["residual_rms_after"]) == set(cal.names)
    true = load_description(d / "true.yaml").positions
    std = np.array([imu.stds["position"] for imu in cal.imus])
    z = (cal.positions - true)[1:] / std[1:]
    assert np.all(np.abs(z) < 4.5) and 0.7 < np.sqrt(np.mean(z ** 2)) < 1.4, z
    # an existing --out needs --force; with it the old file is kept as OUT.bak
    assert_user_error(cli(capsys, "calibrate", "geometry", d / "twist", "--array", ARRAY32, "--out", out, "-q"),
                      str(out), "already exists (use --force")
    old = out.read_bytes()
    code, _, err = cli(capsys, "calibrate", "geometry", d / "twist", "--array", ARRAY32, "--out", out,
                       "--method", "bcd", "--force")
    assert code == 0 and f"previous {out} kept as {out}.bak" in err, err
    assert (d / "geo.yaml.bak").read_bytes() == old


def test_geometry_refuses_a_still_recording_and_a_worse_result_leaving_out_untouched(geometry_recordings, capsys):
    d = geometry_recordings
    out = d / "geo2.yaml"
    assert cli(capsys, "calibrate", "geometry", d / "twist", "--array", ARRAY32, "--out", out, "-q")[0] == 0
    before = out.read_bytes()
    assert_user_error(cli(capsys, "calibrate", "geometry", d / "still", "--array", ARRAY32, "--out", out,
                          "--force", "-q"),
                      str(d / "still"), "too few samples with rotation: 0 of 600", "twist the array")
    # one BCD iteration from the nominal positions: not converged, refused (calibration.guards)
    assert_user_error(cli(capsys, "calibrate", "geometry", d / "twist", "--array", ARRAY32, "--out", out,
                          "--method", "bcd", "--max-iterations", "1", "--force", "-q"),
                      str(d / "twist"), "refused: not converged (1 iterations)", "nothing written")
    assert out.read_bytes() == before and not (d / "geo2.yaml.bak").exists()
    assert_user_error(cli(capsys, "calibrate", "geometry", d / "twist", "--array", ARRAY32, "--out", d / "x.yaml",
                          "--reference", "imu_99", "-q"), "imu_99")
    assert_user_error(cli(capsys, "calibrate", "geometry", d / "twist", "--array", ARRAY32, "--out", d / "x.yaml",
                          "--start", "10", "-q"), "no samples from 10 s on")
    assert not (d / "x.yaml").exists()


# --------------------------------------------------------------------------- discover --apply


@pytest.fixture(scope="module")
def corners_recording(tmp_path_factory):
    """An icosahedron session then 6 s of twisting of the corners array, with an accelerometer bias on imu_3
    and a 0.4 mm position error on imu_6 (the true description saved beside it)."""
    import yaml

    from imu_array_ros.cli import main

    d = tmp_path_factory.mktemp("apply")
    data = yaml.safe_load(CORNERS.read_text())
    data["imu_array"]["imus"][2]["accelerometer"] = {"bias": [0.02, -0.01, 0.015]}
    data["imu_array"]["imus"][5]["position"][0] += 0.0004
    (d / "truth.yaml").write_text(yaml.safe_dump(data))
    assert main(["simulate", "--array", str(d / "truth.yaml"), "--motion", "icosahedron", "--still-seconds", "0.5",
                 "--transition-seconds", "0.5", "--twist-seconds", "6", "--seed", "5", "--start-time", START,
                 "--out", str(d / "rec"), "-q"]) == 0
    return d


DISCOVER_ONE = ("--no-plots", "--no-empirical", "--terms", "position,accelerometer_bias", "--max-findings", "1")


def test_discover_apply_replaces_a_worse_file_keeping_a_backup(corners_recording, capsys):
    d = corners_recording
    out = d / "applied.yaml"
    out.write_bytes(CORNERS.read_bytes())
    code, _, err = cli(capsys, "discover", d / "rec", "--array", CORNERS, "--report", d / "report", "--apply", out,
                       "--force", *DISCOVER_ONE)
    assert code == 0, err
    assert "found position on imu_6" in err
    assert f"previous {out} kept as {out}.bak" in err and f"wrote {out}" in err
    assert (d / "applied.yaml.bak").read_bytes() == CORNERS.read_bytes()
    applied = load_description(out)
    assert applied.calibration["findings"] == ["position on imu_6"]
    assert abs(applied.positions[5, 0] - load_description(CORNERS).positions[5, 0] - 0.0004) < 1e-4
    assert (d / "report" / "report.json").exists()


def test_discover_apply_never_replaces_a_better_file_and_writes_nothing(corners_recording, capsys):
    """The true description on disk explains the recording better than one finding does: refused, the
    file untouched and no backup; the report is written first, so the run's work is not lost."""
    d = corners_recording
    out = d / "true_copy.yaml"
    out.write_bytes((d / "truth.yaml").read_bytes())
    assert_user_error(cli(capsys, "discover", d / "rec", "--array", CORNERS, "--report", d / "refused", "--apply",
                          out, "--force", "-q", *DISCOVER_ONE),
                      str(out), "not replaced: the calibration on file fits", f"the report is in {d / 'refused'}")
    assert out.read_bytes() == (d / "truth.yaml").read_bytes()
    assert not (d / "true_copy.yaml.bak").exists() and (d / "refused" / "report.json").exists()
