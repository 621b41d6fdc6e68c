"""The `imu-array` command line, run as a real process: outputs, exit codes, one-line errors."""

from __future__ import annotations

import os
import subprocess
import sys

import numpy as np
import pytest
import yaml

from imu_array_ros.model.description import load_description
from imu_array_ros.estimation.ml_fusion import fuse
from imu_array_ros.io.rosbag.recording import read_fused_recording, read_imu_recording, read_truth, write_imu_recording
from imu_array_ros.model.sensor_model import LinearArrayModel
from imu_array_ros.simulation.simulator import simulate_twist

from conftest import REPO, SHARED_DATA

ARRAY32 = REPO / "config" / "array32.yaml"


def run(*args, check_ok=True):
    proc = subprocess.run([sys.executable, "-m", "imu_array_ros", *map(str, args)], capture_output=True, text=True,
                          env=dict(os.environ, PYTHONUNBUFFERED="1"), timeout=300)
    if check_ok:
        assert proc.returncode == 0, proc.stderr
    return proc


def assert_user_error(proc, *fragments):
    assert proc.returncode == 2, (proc.returncode, proc.stderr)
    errors = [line for line in proc.stderr.splitlines() if line.startswith("imu-array: error:")]
    assert len(errors) == 1, proc.stderr
    assert "Traceback" not in proc.stderr
    for frag in fragments:
        assert frag in errors[0], (frag, errors[0])


@pytest.fixture(scope="module")
def sim_recording(tmp_path_factory):
    out = tmp_path_factory.mktemp("sim") / "twist"
    run("simulate", "--array", ARRAY32, "--out", out, "--duration", 0.5, "--rate", 400, "--rms-rate", 1500, "--seed", 3)
    return out


def test_simulate_then_fuse_matches_the_core_bit_for_bit(sim_recording, tmp_path):
    out = tmp_path / "fused.mcap"
    proc = run("fuse", sim_recording, "--array", ARRAY32, "--out", out)
    assert "fused 200 of 200 samples" in proc.stderr
    fused = read_fused_recording(out)
    desc = load_description(ARRAY32)
    samples, _ = read_imu_recording(sim_recording, desc)
    ref, _ = fuse(samples, LinearArrayModel.from_description(desc))
    np.testing.assert_array_equal(fused.stamps, ref.stamps)
    np.testing.assert_array_equal(fused.omega, ref.omega)
    np.testing.assert_array_equal(fused.specific_force, ref.specific_force)
    np.testing.assert_array_equal(fused.covariance[:, :3, :3], ref.covariance[:, :3, :3])
    truth = read_truth(sim_recording)
    err = fused.omega - truth.omega
    nees = np.einsum("ni,nij,nj->n", err, np.linalg.inv(fused.covariance[:, :3, :3]), err)
    assert nees.mean() < 3 + 4 * np.sqrt(6 / len(nees))


def test_simulate_with_errors_writes_truth_description(tmp_path):
    truth_yaml = tmp_path / "truth.yaml"
    run("simulate", "--array", ARRAY32, "--out", tmp_path / "r.mcap", "--duration", 0.1, "--error-seed", 5,
        "--truth-array-out", truth_yaml)
    true_desc = load_description(truth_yaml)
    nominal = load_description(ARRAY32)
    assert np.abs(true_desc.positions - nominal.positions).max() > 1e-5
    assert true_desc.calibration["method"] == "simulation ground truth"


def test_calibration_file_is_used(sim_recording, tmp_path):
    desc = load_description(ARRAY32)
    cal = yaml.safe_load(ARRAY32.read_text())
    cal["imu_array"]["imus"][0]["accelerometer"] = {"bias": [0.5, 0.0, 0.0]}
    cal_path = tmp_path / "cal.yaml"
    cal_path.write_text(yaml.safe_dump(cal))
    run("fuse", sim_recording, "--array", ARRAY32, "--calibration", cal_path, "--out", tmp_path / "a.mcap")
    run("fuse", sim_recording, "--array", ARRAY32, "--out", tmp_path / "b.mcap")
    a, b = read_fused_recording(tmp_path / "a.mcap"), read_fused_recording(tmp_path / "b.mcap")
    assert not np.allclose(a.specific_force, b.specific_force)
    del cal["imu_array"]["imus"][5]
    cal_path.write_text(yaml.safe_dump(cal))
    assert_user_error(run("fuse", sim_recording, "--array", ARRAY32, "--calibration", cal_path, "--out", tmp_path / "c.mcap",
                          check_ok=False), "IMU names differ")
    del desc


def test_bad_inputs_give_one_line_errors(sim_recording, tmp_path):
    out = tmp_path / "out.mcap"
    assert_user_error(run("fuse", tmp_path / "missing", "--array", ARRAY32, "--out", out, check_ok=False), "missing")
    assert_user_error(run("fuse", sim_recording, "--array", tmp_path / "nope.yaml", "--out", out, check_ok=False),
                      "nope.yaml", "not found")
    bad_yaml = tmp_path / "bad.yaml"
    bad_yaml.write_text("imu_array: [1, 2\n")
    assert_user_error(run("fuse", sim_recording, "--array", bad_yaml, "--out", out, check_ok=False), "malformed YAML")
    # an IMU the recording does not have
    data = yaml.safe_load(ARRAY32.read_text())
    data["imu_array"]["imus"][7]["name"] = "imu_99"
    other = tmp_path / "other.yaml"
    other.write_text(yaml.safe_dump(data))
    assert_user_error(run("fuse", sim_recording, "--array", other, "--out", out, check_ok=False), "imu_99")
    # collinear array: not identifiable
    data = yaml.safe_load(ARRAY32.read_text())
    for i, imu in enumerate(data["imu_array"]["imus"]):
        imu["position"] = [0.001 * i, 0.0, 0.0]
    line = tmp_path / "line.yaml"
    line.write_text(yaml.safe_dump(data))
    assert_user_error(run("fuse", sim_recording, "--array", line, "--out", out, check_ok=False), "collinear")
    # not a recording
    junk = tmp_path / "junk.mcap"
    junk.write_bytes(b"this is not an mcap file at all" * 10)
    assert_user_error(run("fuse", junk, "--array", ARRAY32, "--out", out, check_ok=False), "junk.mcap")
    # output would overwrite the input; existing output without --force
    assert_user_error(run("fuse", junk, "--array", ARRAY32, "--out", junk, check_ok=False), "overwrite the input")
    out.write_bytes(b"keep me")
    assert_user_error(run("fuse", sim_recording, "--array", ARRAY32, "--out", out, check_ok=False), "already exists")
    assert out.read_bytes() == b"keep me"
    assert not list(tmp_path.glob(".*tmp"))  # no temporary leftovers


def test_nan_and_missing_messages_are_skipped_and_counted(tmp_path, rng):
    desc = load_description(ARRAY32)
    samples, _ = simulate_twist(desc, 0.05, 1000.0, rng)
    samples.accel[3, 4, 1] = np.nan  # one bad message
    samples.gyro[7, 9, 0] = np.inf  # another
    samples.accel[10, :30] = np.nan  # sample 10: only 2 IMUs left -> not identifiable
    samples.gyro[10, :30] = np.nan
    rec = tmp_path / "rec"
    write_imu_recording(rec, samples, desc)
    proc = run("fuse", rec, "--array", ARRAY32, "--out", tmp_path / "f.mcap")
    assert "fused 49 of 50 samples; skipped (not identifiable) 1" in proc.stderr
    fused = read_fused_recording(tmp_path / "f.mcap")
    assert samples.stamps[10] not in fused.stamps and len(fused) == 49
    assert np.all(np.isfinite(fused.omega))


@pytest.mark.skipif(not SHARED_DATA.exists(), reason="shared real data not present")
def test_import_openshoe_and_residuals_on_real_capture(tmp_path):
    arr = REPO / "config" / "mimu4444bt_corners.yaml"
    rec = tmp_path / "exp1.mcap"
    proc = run("import-openshoe", SHARED_DATA / "exp_1.bin", "--array", arr, "--out", rec)
    assert "37439 packets" in proc.stderr and "bad checksums 0" in proc.stderr
    proc = run("residuals", rec, "--array", arr, "--compare-simulated", "--json", "-", "-q")
    import json

    result = json.loads(proc.stdout)
    real, sim = result["recording"], result["simulated_same_motion"]
    # the nominal model explains the simulation and not the real array
    for regime in ("still", "moving"):
        assert abs(sim[regime]["ratio_all"] - 1) < 0.05
        assert real[regime]["ratio_all"] > 10
    assert_user_error(run("import-openshoe", tmp_path / "none.bin", "--array", arr, "--out", tmp_path / "x", check_ok=False),
                      "none.bin")


def test_shipped_sample_recording_fuses_consistently():
    """bags/twist32_sample (README quickstart): readable, every sample fused, NEES ~ chi2(3)."""
    desc = load_description(ARRAY32)
    samples, stats = read_imu_recording(REPO / "bags" / "twist32_sample", desc)
    assert len(samples) == 1000 and stats.bad_messages == 0 and stats.incomplete_samples == 0
    fused, fstats = fuse(samples, LinearArrayModel.from_description(desc))
    assert fstats.fused == 1000
    truth = read_truth(REPO / "bags" / "twist32_sample")
    err = fused.omega - truth.omega
    nees = np.einsum("ni,nij,nj->n", err, np.linalg.inv(fused.covariance[:, :3, :3]), err)
    assert abs(nees.mean() - 3) < 4 * np.sqrt(6 / 1000)
