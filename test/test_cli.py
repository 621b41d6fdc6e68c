"""The `imu-array` command line: outputs, exit codes, one-line errors.

Most tests call ``imu_array_ros.cli.main`` in-process (fast; stderr through
capsys); a few run the real programs (console script ``imu-array`` and
``python -m imu_array_ros``) as processes.  Outputs, options and start times
are tested in ``test_cli_outputs.py`` and ``test_cli_options.py``.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml

from imu_array_ros.cli import main
from imu_array_ros.fusion.ml_fusion import fuse
from imu_array_ros.fusion.model_fusion import fuse_model
from imu_array_ros.io.rosbag.recording import read_fused_recording, read_imu_recording, read_truth, write_imu_recording
from imu_array_ros.model.description import load_description, save_description
from imu_array_ros.model.sensor_model import SensorModel
from imu_array_ros.model.linear import LinearArrayModel
from imu_array_ros.simulation.perturb import DEFAULT_ERROR_SCALES, perturb
from imu_array_ros.simulation.simulator import simulate_twist

from conftest import ARRAY32, REPO, SHARED_DATA, START, assert_user_error, cli



def ok(capsys, *args):
    code, out, err = cli(capsys, *args)
    assert code == 0, err
    return out, err


def run(*args, program=None):
    """Run the real program as a process (default ``python -m imu_array_ros``)."""
    cmd = [*(program or [sys.executable, "-m", "imu_array_ros"]), *map(str, args)]
    return subprocess.run(cmd, capture_output=True, text=True, env=dict(os.environ, PYTHONUNBUFFERED="1"), timeout=300)


def nees_omega(fused, truth):
    err = fused.omega - truth.omega
    return np.einsum("ni,nij,nj->n", err, np.linalg.inv(fused.covariance[:, :3, :3]), err)


@pytest.fixture(scope="module")
def sim_recording(tmp_path_factory):
    out = tmp_path_factory.mktemp("sim") / "twist"
    assert main(["simulate", "--array", str(ARRAY32), "--out", str(out), "--duration", "0.5", "--rate", "400",
                 "--rms-rate", "1500", "--seed", "3", "--start-time", START, "-q"]) == 0
    return out


def test_simulate_then_fuse_matches_the_core_bit_for_bit(sim_recording, tmp_path, capsys):
    out = tmp_path / "fused.mcap"
    _, err = ok(capsys, "fuse", sim_recording, "--array", ARRAY32, "--out", out)
    assert "fused 200 of 200 samples" in err
    fused = read_fused_recording(out)
    desc = load_description(ARRAY32)
    samples, _ = read_imu_recording(sim_recording, desc)
    ref, _ = fuse_model(samples, SensorModel.from_description(desc))  # what the CLI (and the node) call
    np.testing.assert_array_equal(fused.stamps, ref.stamps)
    np.testing.assert_array_equal(fused.omega, ref.omega)
    np.testing.assert_array_equal(fused.specific_force, ref.specific_force)
    np.testing.assert_array_equal(fused.covariance[:, :3, :3], ref.covariance[:, :3, :3])
    nees = nees_omega(fused, read_truth(sim_recording))
    # NEES of omega ~ chi2(3) per sample (variance 6); the mean of n independent samples is within
    # 4 standard errors of 3 -- on both sides: too small means covariances too large, too large means too small
    assert abs(nees.mean() - 3) < 4 * np.sqrt(6 / len(nees)), nees.mean()


def test_the_public_api_fuses_with_every_term_as_the_cli_does(sim_recording, tmp_path, capsys):
    """``imu_array_ros.fuse(samples, desc)`` (the README's example) gives ``imu-array fuse``'s numbers bit for bit,
    also when the description holds non-linear terms (time offsets, g-sensitivity), which the linear form
    alone would drop."""
    import imu_array_ros

    cal = yaml.safe_load(ARRAY32.read_text())
    cal["imu_array"]["imus"][2]["accelerometer"] = {"time_offset": 0.002}
    cal["imu_array"]["imus"][4]["gyroscope"] = {"g_sensitivity": [[1e-3, 0, 0], [0, 0, 0], [0, 0, 0]]}
    cal_path = tmp_path / "cal.yaml"
    cal_path.write_text(yaml.safe_dump(cal))
    out = tmp_path / "fused.mcap"
    ok(capsys, "fuse", sim_recording, "--array", ARRAY32, "--calibration", cal_path, "--out", out)
    from_cli = read_fused_recording(out)
    desc, _ = imu_array_ros.load_array(ARRAY32, cal_path)
    samples, _ = imu_array_ros.read_imu_recording(sim_recording, desc)
    fused, _ = imu_array_ros.fuse(samples, desc)
    assert SensorModel.from_description(desc).nonlinear_terms  # the case the linear form gets wrong
    for name in ("stamps", "omega", "omega_dot", "specific_force"):
        np.testing.assert_array_equal(getattr(fused, name), getattr(from_cli, name))
    linear, _ = fuse(samples, LinearArrayModel.from_description(desc))
    assert not np.array_equal(linear.specific_force, fused.specific_force)


def test_simulate_with_errors_writes_truth_description(tmp_path, capsys):
    """The truth YAML holds exactly the seeded errors, and the recording was simulated with them."""
    truth_yaml, rec = tmp_path / "truth.yaml", tmp_path / "r.mcap"
    ok(capsys, "simulate", "--array", ARRAY32, "--out", rec, "--duration", 0.5, "--rate", 400, "--rms-rate", 900,
       "--seed", 2, "--error-seed", 5, "--truth-array-out", truth_yaml, "--start-time", START)
    nominal = load_description(ARRAY32)
    true_desc = load_description(truth_yaml)
    assert true_desc.calibration == {"method": "simulation ground truth", "seed": 2, "error_seed": 5}
    # the same errors, drawn independently here from the documented recipe
    expected = perturb(SensorModel.from_description(nominal), np.random.default_rng(5), dict(DEFAULT_ERROR_SCALES))
    for name, term in SensorModel.from_description(true_desc).terms.items():
        np.testing.assert_allclose(term.values, expected.terms[name].values, rtol=1e-12, atol=1e-15, err_msg=name)
    written = LinearArrayModel.from_description(true_desc)
    assert np.abs(true_desc.positions - nominal.positions).max() > 1e-5
    # the recording's measurements come from the true sensors: consistent with the truth file, not the nominal one
    samples, _ = read_imu_recording(rec, nominal)
    truth = read_truth(rec)
    with_truth = nees_omega(fuse(samples, written)[0], truth)
    with_nominal = nees_omega(fuse(samples, LinearArrayModel.from_description(nominal))[0], truth)
    assert abs(with_truth.mean() - 3) < 4 * np.sqrt(6 / len(with_truth)), with_truth.mean()
    assert with_nominal.mean() > 30


def test_true_array_simulates_every_term(tmp_path, capsys, rng):
    """--true-array T.yaml: the recording is SensorModel(T).predict of the motion, with every term of T;
    fusing it with T (all terms compensated) is consistent, with the nominal array it is not."""
    from imu_array_ros.model.terms import REGISTRY

    nominal = load_description(ARRAY32)
    model = SensorModel.from_description(nominal)
    sizes = {"position": 1e-3, "time_offset": 1e-3, "bias_drift": 1e-3, "accelerometer_nonlinearity": 5e-4,
             "gyroscope_g_sensitivity": 5e-4, "axis_offsets": 5e-4}
    true = model.with_terms(**{n: model.terms[n].values + rng.normal(0, sizes.get(n, 5e-3), model.terms[n].values.shape)
                               for n in REGISTRY if REGISTRY[n].candidate})
    true_yaml = tmp_path / "true.yaml"
    save_description(true.to_description(nominal), true_yaml)
    rec = tmp_path / "rec"
    ok(capsys, "simulate", "--array", ARRAY32, "--true-array", true_yaml, "--out", rec, "--duration", 1.0,
       "--rate", 400, "--seed", 4, "--start-time", START)
    samples, _ = read_imu_recording(rec, nominal)
    expected, truth = simulate_twist(SensorModel.from_description(load_description(true_yaml)), 1.0, 400.0,
                                     np.random.default_rng(4), start_ns=int(samples.stamps[0]))
    np.testing.assert_array_equal(samples.accel, expected.accel)
    np.testing.assert_array_equal(samples.gyro, expected.gyro)
    out = tmp_path / "f.mcap"
    ok(capsys, "fuse", rec, "--array", true_yaml, "--out", out)
    with_true = nees_omega(read_fused_recording(out), truth)
    assert abs(with_true.mean() - 3) < 4 * np.sqrt(6 / len(with_true)), with_true.mean()
    ok(capsys, "fuse", rec, "--array", ARRAY32, "--out", out, "--force")
    assert nees_omega(read_fused_recording(out), truth).mean() > 30


def test_calibration_file_is_used(sim_recording, tmp_path, capsys):
    cal = yaml.safe_load(ARRAY32.read_text())
    cal["imu_array"]["imus"][0]["accelerometer"] = {"bias": [0.5, 0.0, 0.0]}
    cal_path = tmp_path / "cal.yaml"
    cal_path.write_text(yaml.safe_dump(cal))
    ok(capsys, "fuse", sim_recording, "--array", ARRAY32, "--calibration", cal_path, "--out", tmp_path / "a.mcap")
    ok(capsys, "fuse", sim_recording, "--array", ARRAY32, "--out", tmp_path / "b.mcap")
    a, b = read_fused_recording(tmp_path / "a.mcap"), read_fused_recording(tmp_path / "b.mcap")
    assert not np.allclose(a.specific_force, b.specific_force)
    del cal["imu_array"]["imus"][5]
    cal_path.write_text(yaml.safe_dump(cal))
    assert_user_error(cli(capsys, "fuse", sim_recording, "--array", ARRAY32, "--calibration", cal_path,
                          "--out", tmp_path / "c.mcap"), "IMU names differ")
    assert not (tmp_path / "c.mcap").exists()


def test_bad_inputs_give_one_line_errors(sim_recording, tmp_path, capsys):
    out = tmp_path / "out.mcap"
    assert_user_error(cli(capsys, "fuse", tmp_path / "missing", "--array", ARRAY32, "--out", out), "missing")
    assert_user_error(cli(capsys, "fuse", sim_recording, "--array", tmp_path / "nope.yaml", "--out", out),
                      "nope.yaml", "not found")
    bad_yaml = tmp_path / "bad.yaml"
    bad_yaml.write_text("imu_array: [1, 2\n")
    assert_user_error(cli(capsys, "fuse", sim_recording, "--array", bad_yaml, "--out", out), "malformed YAML")
    # an IMU the recording does not have
    data = yaml.safe_load(ARRAY32.read_text())
    data["imu_array"]["imus"][7]["name"] = "imu_99"
    other = tmp_path / "other.yaml"
    other.write_text(yaml.safe_dump(data))
    assert_user_error(cli(capsys, "fuse", sim_recording, "--array", other, "--out", out), "imu_99")
    # collinear array: not identifiable, and the message names the description file
    data = yaml.safe_load(ARRAY32.read_text())
    for i, imu in enumerate(data["imu_array"]["imus"]):
        imu["position"] = [0.001 * i, 0.0, 0.0]
    line = tmp_path / "line.yaml"
    line.write_text(yaml.safe_dump(data))
    msg = assert_user_error(cli(capsys, "fuse", sim_recording, "--array", line, "--out", out), "collinear")
    assert msg.startswith(f"imu-array: error: {line}: accelerometer triads are collinear"), msg
    # not a recording
    junk = tmp_path / "junk.mcap"
    junk.write_bytes(b"this is not an mcap file at all" * 10)
    assert_user_error(cli(capsys, "fuse", junk, "--array", ARRAY32, "--out", out), "junk.mcap")
    assert not out.exists()
    # output would overwrite the input
    assert_user_error(cli(capsys, "fuse", junk, "--array", ARRAY32, "--out", junk, "--force"), "overwrite the input")
    assert junk.read_bytes() == b"this is not an mcap file at all" * 10
    # an existing output (a real recording) is kept without --force
    ok(capsys, "fuse", sim_recording, "--array", ARRAY32, "--out", out)
    before = out.read_bytes()
    assert_user_error(cli(capsys, "fuse", sim_recording, "--array", ARRAY32, "--out", out), "already exists", "--force")
    assert out.read_bytes() == before
    # and an existing file that is not one is kept even with --force
    keep = tmp_path / "keep.mcap"
    keep.write_bytes(b"keep me")
    assert_user_error(cli(capsys, "fuse", sim_recording, "--array", ARRAY32, "--out", keep, "--force"),
                      "not an MCAP file")
    assert keep.read_bytes() == b"keep me"
    assert not list(tmp_path.glob(".*"))  # no temporary leftovers


def test_nan_and_missing_messages_are_skipped_and_counted(tmp_path, rng, capsys):
    desc = load_description(ARRAY32)
    samples, _ = simulate_twist(desc, 0.05, 1000.0, rng)
    samples.accel[3, 4, 1] = np.nan  # one bad message
    samples.gyro[7, 9, 0] = np.inf  # another
    samples.accel[10, :30] = np.nan  # sample 10: only 2 IMUs left -> not identifiable
    samples.gyro[10, :30] = np.nan
    rec = tmp_path / "rec"
    write_imu_recording(rec, samples, desc)
    _, err = ok(capsys, "fuse", rec, "--array", ARRAY32, "--out", tmp_path / "f.mcap")
    assert "fused 49 of 50 samples; skipped (not identifiable) 1" in err
    fused = read_fused_recording(tmp_path / "f.mcap")
    assert samples.stamps[10] not in fused.stamps and len(fused) == 49
    assert np.all(np.isfinite(fused.omega))


@pytest.mark.skipif(not SHARED_DATA.exists(), reason="shared real data not present")
def test_import_openshoe_and_residuals_on_real_capture(tmp_path, capsys):
    arr = REPO / "config" / "mimu4444bt_corners.yaml"
    rec = tmp_path / "exp1.mcap"
    _, err = ok(capsys, "import-openshoe", SHARED_DATA / "exp_1.bin", "--array", arr, "--out", rec)
    assert "37439 packets" in err and "bad checksums 0" in err
    out, err = ok(capsys, "residuals", rec, "--array", arr, "--compare-simulated", "--json", "-", "-q")
    assert err == ""
    result = json.loads(out)
    real, sim = result["recording"], result["simulated_same_motion"]
    # the nominal model explains the simulation and not the real array
    for regime in ("still", "moving"):
        assert abs(sim[regime]["ratio_all"] - 1) < 0.05
        assert real[regime]["ratio_all"] > 10
    assert_user_error(cli(capsys, "import-openshoe", tmp_path / "none.bin", "--array", arr, "--out", tmp_path / "x"),
                      "none.bin")


def test_shipped_sample_recording_fuses_consistently():
    """bags/twist32_sample (README quickstart): readable, every sample fused, NEES ~ chi2(3)."""
    desc = load_description(ARRAY32)
    samples, stats = read_imu_recording(REPO / "bags" / "twist32_sample", desc)
    assert len(samples) == 1000 and stats.bad_messages == 0 and stats.incomplete_samples == 0
    fused, fstats = fuse(samples, LinearArrayModel.from_description(desc))
    assert fstats.fused == 1000
    nees = nees_omega(fused, read_truth(REPO / "bags" / "twist32_sample"))
    assert abs(nees.mean() - 3) < 4 * np.sqrt(6 / 1000)


# --------------------------------------------------------------------------- the real programs, as processes


def _console_script() -> Path:
    script = Path(sys.executable).parent / "imu-array"
    if not script.exists():
        pytest.skip(f"console script not installed next to {sys.executable}")
    return script


def test_python_m_and_console_script_run_the_same_cli(tmp_path):
    script = _console_script()
    for program in ([sys.executable, "-m", "imu_array_ros"], [str(script)]):
        proc = run("--version", program=program)
        assert proc.returncode == 0 and proc.stdout.startswith("imu-array "), (program, proc.stdout, proc.stderr)
    # a real simulate (python -m) then fuse (console script), as in the README
    rec, fused = tmp_path / "rec", tmp_path / "fused.mcap"
    proc = run("simulate", "--array", ARRAY32, "--out", rec, "--duration", 0.1, "--rate", 200, "--start-time", START)
    assert proc.returncode == 0, proc.stderr
    assert f"wrote {rec}" in proc.stderr
    proc = run("fuse", rec, "--array", ARRAY32, "--out", fused, program=[str(script)])
    assert proc.returncode == 0, proc.stderr
    assert "fused 20 of 20 samples" in proc.stderr
    assert len(read_fused_recording(fused)) == 20


@pytest.mark.parametrize("how", ["python -m", "console script"])
def test_user_errors_from_the_real_programs_are_one_line(tmp_path, how):
    program = [sys.executable, "-m", "imu_array_ros"] if how == "python -m" else [str(_console_script())]
    for args, fragment in [
        (["fuse", tmp_path / "missing", "--array", ARRAY32, "--out", tmp_path / "o.mcap"], "missing"),
        (["simulate", "--array", ARRAY32, "--out", tmp_path / "r", "--duration", "0"], "--duration"),
        (["fuse", "--array", ARRAY32], "required"),
    ]:
        proc = run(*args, program=program)
        assert proc.returncode == 2, (args, proc.stderr)
        assert "Traceback" not in proc.stderr
        assert len(proc.stderr.splitlines()) == 1 and proc.stderr.startswith("imu-array: error: "), proc.stderr
        assert fragment in proc.stderr
    assert not list(tmp_path.iterdir())


def test_recover_command_salvages_a_recording_cut_mid_write(capsys, tmp_path):
    """A recorder killed mid-write: reading names `imu-array recover`; the command keeps
    every complete chunk, says how many messages were kept and lost, and the result
    fuses; the damaged input is left as it was."""
    import re

    rec = tmp_path / "rec"
    ok(capsys, "simulate", "--array", ARRAY32, "--out", rec, "--duration", 2, "--rate", 500, "--seed", 3,
       "--start-time", START, "-q")
    desc = load_description(ARRAY32)
    full, _ = read_imu_recording(rec, desc)
    data_file = rec / "rec_0.mcap"
    data = data_file.read_bytes()
    data_file.write_bytes(data[: len(data) * 2 // 3])  # cut inside the data section
    damaged = data_file.read_bytes()
    assert_user_error(cli(capsys, "fuse", rec, "--array", ARRAY32, "--out", tmp_path / "f.mcap"),
                      str(data_file), "imu-array recover")
    _, err = ok(capsys, "recover", rec, "--out", tmp_path / "saved.mcap")
    assert data_file.read_bytes() == damaged and sorted(p.name for p in rec.iterdir()) == ["metadata.yaml", "rec_0.mcap"]
    m = re.search(r"kept (\d+) messages.*lost (\d+)", err)
    assert m, err
    kept, lost = int(m.group(1)), int(m.group(2))
    assert kept + lost == 1000 * (32 + 2)  # 32 IMU topics + 2 truth topics, 1000 samples
    saved, _ = read_imu_recording(tmp_path / "saved.mcap", desc)
    truth = read_truth(tmp_path / "saved.mcap")
    n_truth = int(np.isfinite(truth.omega[:, 0]).sum() + np.isfinite(truth.omega_dot[:, 0]).sum())
    assert kept == int(saved.present.sum()) + n_truth and 0 < len(saved) < len(full)
    # what was kept is the beginning of the original, value for value
    np.testing.assert_array_equal(saved.stamps, full.stamps[: len(saved)])
    present = saved.present
    np.testing.assert_array_equal(saved.accel[present], full.accel[: len(saved)][present])
    np.testing.assert_array_equal(saved.gyro[present], full.gyro[: len(saved)][present])
    assert present[:-1].all()  # only the last sample can miss IMUs (cut between their messages)
    ok(capsys, "fuse", tmp_path / "saved.mcap", "--array", ARRAY32, "--out", tmp_path / "f.mcap", "-q")
    assert_user_error(cli(capsys, "recover", rec, "--out", rec / "x.mcap"), "input")
