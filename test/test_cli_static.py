"""``imu-array calibrate static`` and ``calibrate all`` end to end on a simulated icosahedron session."""

from __future__ import annotations

import numpy as np
import pytest
import yaml

from imu_array_ros.calibration.static import STATIC_TERMS, reframe_accelerometers
from imu_array_ros.model.description import load_description
from imu_array_ros.model.sensor_model import SensorModel

from conftest import ARRAY32, REPO, START, assert_user_error, cli

NILSSON14 = REPO / "config" / "nilsson14.yaml"


@pytest.fixture(scope="module")
def session(tmp_path_factory):
    """nilsson14 on the 20 faces (3 s each at 100 Hz), then 6 s of twisting; seeded Table I-sized errors."""
    from imu_array_ros.cli import main

    d = tmp_path_factory.mktemp("static")
    assert main(["simulate", "--array", str(NILSSON14), "--out", str(d / "rec"), "--motion", "icosahedron",
                 "--still-seconds", "3", "--transition-seconds", "1", "--twist-seconds", "6", "--rate", "100",
                 "--error-seed", "4", "--truth-array-out", str(d / "truth.yaml"), "--seed", "5",
                 "--start-time", START, "-q"]) == 0
    assert main(["simulate", "--array", str(NILSSON14), "--out", str(d / "twist"), "--duration", "2", "--rate", "100",
                 "--seed", "6", "--start-time", START, "-q"]) == 0
    return d


def test_static_writes_every_term_with_std_and_a_record(session, capsys):
    out = session / "static.yaml"
    code, stdout, err = cli(capsys, "calibrate", "static", session / "rec", "--array", NILSSON14,
                            "--reference", "imu_14", "--out", out)
    assert code == 0 and stdout == "", err
    assert "20 poses" in err and "imu_14" in err and f"wrote {out}" in err
    cal = load_description(out)
    truth = SensorModel.from_description(load_description(session / "truth.yaml"))
    est = SensorModel.from_description(cal)
    aligned = reframe_accelerometers(truth, "imu_14")
    doc = yaml.safe_load(out.read_text())
    raw, record = doc["imu_array"], doc["calibration"]
    imu = raw["imus"][0]
    assert {"gain_std", "bias_std", "nonorthogonality_std", "misalignment_std"} <= set(imu["accelerometer"])
    assert "bias_std" in imu["gyroscope"]
    stages = [s["stage"] for s in record["stages"]]
    # calibrate static has no moving stage: none reported as skipped, in the file or on the console
    assert stages == ["still poses", "static"] and record["skipped"] == {}
    assert "moving" not in err and "moving" not in record["method"]
    assert record["method"].startswith("calibrate static: still poses -> static")
    # every parameter within 4 of its written std (CRB x sqrt(max(1, NIS))); the reference's misalignment
    # is held (no std written) and equal to the truth's re-expressed in its frame (0)
    z = []
    for t in STATIC_TERMS:
        sensor, name = t.split("_", 1)
        for k, entry in enumerate(raw["imus"]):
            std = entry[sensor].get(f"{name}_std")
            if std is None:
                assert t == "accelerometer_misalignment" and cal.names[k] == "imu_14"
                continue
            z.extend((est.terms[t].values[k] - aligned.terms[t].values[k]) / np.asarray(std))
    z = np.abs(np.array(z))
    print(f"\n{len(z)} parameters, max |z| {z.max():.2f}")
    assert len(z) == 14 * 15 - 3 and z.max() < 4.0


def test_all_calibrates_positions_and_gyros_after_the_poses(session, capsys):
    out = session / "all.yaml"
    code, _, err = cli(capsys, "calibrate", "all", session / "rec", "--array", NILSSON14, "--reference", "imu_14",
                       "--out", out, "--plot", session / "all.png")
    assert code == 0, err
    record = yaml.safe_load(out.read_text())["calibration"]
    assert [s["stage"] for s in record["stages"]] == ["still poses", "static", "moving"]  # no timing by default
    assert record["skipped"] == {}
    # the method names the stages that ran: no timing stage without --timing (in the file and the summary)
    assert record["method"].startswith("calibrate all: still poses -> static") and "-> moving" in record["method"]
    assert "timing" not in record["method"] and "timing" not in err
    cal = SensorModel.from_description(load_description(out))
    truth = SensorModel.from_description(load_description(session / "truth.yaml"))
    nominal = SensorModel.from_description(load_description(NILSSON14))
    ref = cal.names.index("imu_14")
    rel = lambda m: m.positions - m.positions[ref]  # noqa: E731 - only relative positions are observable
    before = np.linalg.norm(rel(nominal) - rel(truth), axis=1).max()
    after = np.linalg.norm(rel(cal) - rel(truth), axis=1).max()
    print(f"\nworst relative position error: nominal {before * 1e3:.3f} mm, calibrated {after * 1e3:.3f} mm")
    assert after < 0.5 * before
    assert (session / "all.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_pca_method(session, capsys):
    out = session / "pca.yaml"
    code, _, err = cli(capsys, "calibrate", "static", session / "rec", "--array", NILSSON14, "--method", "pca",
                       "--out", out)
    assert code == 0, err
    assert "pca: 20 poses" in err
    assert "closed-form PCA" in yaml.safe_load(out.read_text())["calibration"]["stages"][1]["method"]


def test_recording_without_still_poses_is_refused_and_nothing_written(session, capsys):
    out = session / "none.yaml"
    res = cli(capsys, "calibrate", "static", session / "twist", "--array", NILSSON14, "--out", out, "-q")
    assert_user_error(res, "twist", "poses")
    assert not out.exists()


def test_a_worse_static_calibration_does_not_replace_a_better_one(session, capsys):
    """--force with the full calibration on file and a reduced one (gains only): refused, file untouched."""
    out = session / "keep.yaml"
    assert cli(capsys, "calibrate", "static", session / "rec", "--array", NILSSON14, "--out", out)[0] == 0
    before = out.read_bytes()
    res = cli(capsys, "calibrate", "static", session / "rec", "--array", NILSSON14, "--out", out, "--force",
              "--terms", "accelerometer_gain", "-q")
    assert_user_error(res, "not replaced")
    assert out.read_bytes() == before


def test_all_installs_through_the_one_install_path(session, capsys):
    """calibrate all (with a moving stage) compares with the file on disk too, on the poses and the moving
    samples: a worse file (the nominal description) is replaced and kept as OUT.bak; a better one (the true
    sensors, which a position-only moving stage cannot match) is kept and the calibration refused."""
    out, bak = session / "all_install.yaml", session / "all_install.yaml.bak"
    out.write_bytes(NILSSON14.read_bytes())
    code, _, err = cli(capsys, "calibrate", "all", session / "rec", "--array", NILSSON14, "--moving-terms", "position",
                       "--out", out, "--force")
    assert code == 0, err
    assert f"previous {out} kept as {bak}" in err and f"wrote {out}" in err
    assert bak.read_bytes() == NILSSON14.read_bytes()
    record = yaml.safe_load(out.read_text())["calibration"]
    assert [s["stage"] for s in record["stages"]] == ["still poses", "static", "moving"]
    better = session / "truth_copy.yaml"
    better.write_bytes((session / "truth.yaml").read_bytes())
    assert_user_error(cli(capsys, "calibrate", "all", session / "rec", "--array", NILSSON14, "--moving-terms",
                          "position", "--out", better, "--force", "-q"),
                      str(session / "rec"), "not replaced: the calibration on file fits")
    assert better.read_bytes() == (session / "truth.yaml").read_bytes()
    assert not (session / "truth_copy.yaml.bak").exists()


def test_bad_terms_and_wrong_array(session, capsys):
    assert_user_error(cli(capsys, "calibrate", "static", session / "rec", "--array", NILSSON14, "--out",
                          session / "x.yaml", "--terms", "position", "-q"), "static terms")
    assert_user_error(cli(capsys, "calibrate", "static", session / "rec", "--array", ARRAY32, "--out",
                          session / "y.yaml", "-q"))
    assert not (session / "x.yaml").exists() and not (session / "y.yaml").exists()


def test_the_method_names_the_timing_stage_only_when_it_ran():
    from imu_array_ros.calibration.array import ArrayCalibration

    nominal = SensorModel.from_description(load_description(NILSSON14))
    run = lambda **kw: ArrayCalibration(model=nominal, poses=None, static=None, moving=None, **kw)  # noqa: E731
    moving = ("position",)
    assert "timing" not in run(moving_terms=moving).method()
    skipped = run(moving_terms=moving, skipped={"timing": "the refit did not converge"})
    assert "timing" not in skipped.method() and skipped.record()["skipped"] == {"timing": "the refit did not converge"}
    assert run(moving_terms=moving, timing=object()).method().endswith(  # a timing result kept: the stage ran
        "-> moving (positions, gyroscope gain, misalignment and non-orthogonality) -> timing (sample clocks, time "
        "offsets with the gyroscope gains; the moving stage's positions, gyroscope misalignment and "
        "non-orthogonality kept)")
    assert run().method() == "calibrate static: still poses -> static (accelerometer intrinsics, gyroscope biases)"
