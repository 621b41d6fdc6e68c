"""``imu-array calibrate all --report DIR`` and :func:`write_calibration_report` on simulated icosahedron sessions
(nilsson14, 20 still poses then twisting, seeded errors): the files, the tables against the written description,
the residual maps, the repeatability over two recordings of the same sensors, and the refusals."""

from __future__ import annotations

import json
import re

import numpy as np
import pytest

from imu_array_ros import workflows
from imu_array_ros.calibration.report import MANIFEST, check_report_dir, write_calibration_report
from imu_array_ros.errors import OutputError
from imu_array_ros.model.description import load_description
from imu_array_ros.model.sensor_model import SensorModel

from conftest import REPO, START, assert_user_error, cli

NILSSON14 = REPO / "config" / "nilsson14.yaml"
PNG = b"\x89PNG\r\n\x1a\n"
FILES = {"index.md", "calibration.json", MANIFEST, "residual_map.png", "residual_time.png", "residual_rate.png"}


def _simulate(d, name: str, seed: int):
    from imu_array_ros.cli import main

    assert main(["simulate", "--array", str(NILSSON14), "--out", str(d / name), "--motion", "icosahedron",
                 "--still-seconds", "3", "--transition-seconds", "1", "--twist-seconds", "4", "--rate", "100",
                 "--error-seed", "4", "--seed", str(seed), "--start-time", START, "-q"]) == 0
    return d / name


@pytest.fixture(scope="module")
def session(tmp_path_factory):
    """Two recordings of the same (seeded, erroneous) sensors, different motion and noise."""
    d = tmp_path_factory.mktemp("report")
    return d, _simulate(d, "rec1", 5), _simulate(d, "rec2", 6)


@pytest.fixture(scope="module")
def reported(session):
    """``calibrate all rec1 --out all.yaml --report rep`` (once for the module; positions only in the moving
    stage, to keep it short: the report does not depend on the terms)."""
    import io
    from contextlib import redirect_stderr

    from imu_array_ros.cli import main

    d, rec, _ = session
    err = io.StringIO()
    with redirect_stderr(err):
        code = main(["calibrate", "all", str(rec), "--array", str(NILSSON14), "--reference", "imu_14",
                     "--moving-terms", "position", "--out", str(d / "all.yaml"), "--report", str(d / "rep")])
    assert code == 0, err.getvalue()
    return d / "rep", d / "all.yaml", err.getvalue()


def test_report_files_and_values_equal_the_written_description(reported):
    rep, out, err = reported
    assert f"wrote the report {rep / 'index.md'}" in err
    assert {p.name for p in rep.iterdir()} == FILES
    assert set(json.loads((rep / MANIFEST).read_text())["files"]) == FILES - {MANIFEST}
    for png in FILES:
        if png.endswith(".png"):
            assert (rep / png).read_bytes()[:8] == PNG
    desc = load_description(out)
    model = SensorModel.from_description(desc)
    data = json.loads((rep / "calibration.json").read_text())
    assert data["imus"] == list(desc.names)
    assert set(data["terms"]) == {"accelerometer_gain", "accelerometer_nonorthogonality", "accelerometer_misalignment",
                                  "accelerometer_bias", "gyroscope_bias", "position"}
    raw = {imu["name"]: imu for imu in __import__("yaml").safe_load(out.read_text())["imu_array"]["imus"]}
    for t, e in data["terms"].items():
        value = np.array(e["value"], dtype=float)
        std = np.array([[np.nan if s is None else s for s in row] for row in e["std"]], dtype=float)
        # the report's values are the description's, to the precision the YAML keeps
        np.testing.assert_allclose(value, model.terms[t].values, rtol=1e-9, atol=1e-12, err_msg=t)
        if t == "accelerometer_gain":  # the std the description writes beside the field
            written = np.array([raw[n]["accelerometer"]["gain_std"] for n in desc.names], dtype=float)
            np.testing.assert_allclose(std, written, rtol=1e-9, err_msg=t)
        assert e["crb"] is not None and np.all(np.isfinite(std) <= np.isfinite(np.array(e["crb"], dtype=float)))
    md = (rep / "index.md").read_text()
    for t in data["terms"]:
        # one table per term, one row per IMU, the value shown as value ± std
        section = md.split(f"### {t}\n\n", 1)[1].split("\n\n", 1)[0]
        rows = [line for line in section.splitlines() if line.startswith("| imu_")]
        assert [r.split(" | ")[0][2:] for r in rows] == list(desc.names), t
    row = next(line for line in md.split("### accelerometer_bias\n", 1)[1].splitlines() if line.startswith("| imu_01"))
    shown = [float(m) for m in re.findall(r"(-?\d+\.\d+) ± ", row)]
    np.testing.assert_allclose(shown, model.terms["accelerometer_bias"].values[0], atol=0.011)
    assert "## Stages" in md and "| static |" in md and "| moving |" in md
    for f in FILES - {"index.md", MANIFEST}:
        assert f in md  # every file written is shown or named


def test_residual_maps_show_the_calibration_explaining_its_data(reported):
    """Seeded Table I-sized errors: the poses far from the noise under the nominal description, at the noise
    level under the calibration (a simulation: the sensor model is exact); the moving window too."""
    rep, _, _ = reported
    rms = json.loads((rep / "calibration.json").read_text())["residual_rms"]
    assert rms["axes"] == ["acc_x", "acc_y", "acc_z", "gyr_x", "gyr_y", "gyr_z"]
    for part in ("still", "moving"):
        before, after = (np.array(rms[part][w], dtype=float) for w in ("before", "after"))
        print(f"\n{part}: median RMS before {np.nanmedian(before):.3g}, after {np.nanmedian(after):.3g}, "
              f"largest after {np.nanmax(after):.3g}")
        assert before.shape == after.shape == (14, 6)
        assert 0.6 < np.nanmedian(after) < 1.3 and np.nanmax(after) < 2.0
    assert np.nanmedian(np.array(rms["still"]["before"], dtype=float)) > 10


def test_repeatability_over_two_recordings(session, tmp_path):
    """calibrate all (positions in the moving stage, to keep it short) on two recordings of the same sensors:
    the spread between them is what the reported std say.  Each term's sqrt(chi^2/dof) is computed as
    documented, and within a factor 1.6 of 1: its sampling std would be 1/sqrt(2 dof) ~ 0.11 for independent
    parameters, but the parameters of a term share the reference IMU's errors (every misalignment is relative
    to its axes), so fewer are independent; pooled over every term it is within 0.25 of 1."""
    d, rec1, rec2 = session
    desc = workflows.load_array(NILSSON14)[0]
    cals = [workflows.calibrate("all", workflows.read_imu_recording(r, desc)[0], desc, reference="imu_14",
                                moving_terms=("position",)) for r in (rec1, rec2)]
    out = tmp_path / "rep2"
    written = write_calibration_report(out, cals, start=desc, sources=["rec1", "rec2"])
    assert {p.name for p in written} == FILES | {"repeatability.png"}
    rep = json.loads((out / "calibration.json").read_text())["repeatability"]
    assert set(rep) == set(cals[0].std)
    chi2 = dof = 0.0
    for t, r in rep.items():
        v, s = (np.array(r[k], dtype=float) for k in ("value", "std"))
        ok = np.isfinite(s).all(axis=0)
        # the documented statistic, from the per-recording values and std the report gives
        mean = (v / s ** 2).sum(axis=0) / (1 / s ** 2).sum(axis=0)
        c = float(np.nansum(((v - mean) / s) ** 2))
        assert r["ratio"] == pytest.approx(np.sqrt(c / ok.sum()), rel=1e-12), t
        chi2, dof = chi2 + c, dof + ok.sum()
        print(f"{t}: ratio {r['ratio']:.3f} over {ok.sum()} parameters")
        assert 1 / 1.6 < r["ratio"] < 1.6, t
    print(f"pooled: {np.sqrt(chi2 / dof):.3f} over {dof} parameters")
    assert abs(np.sqrt(chi2 / dof) - 1) < 0.25
    md = (out / "index.md").read_text()
    assert "## Repeatability across recordings" in md and "`rec1`, `rec2`" in md


def test_a_non_empty_report_directory_is_refused_and_nothing_written(session, capsys):
    d, rec, _ = session
    rep, out = d / "foreign", d / "refused.yaml"
    rep.mkdir()
    (rep / "notes.txt").write_text("mine")
    for force in ((), ("--force",)):
        res = cli(capsys, "calibrate", "all", rec, "--array", NILSSON14, "--out", out, "--report", rep, "-q", *force)
        assert_user_error(res, str(rep), "notes.txt")
        assert not out.exists()
        assert [p.name for p in rep.iterdir()] == ["notes.txt"] and (rep / "notes.txt").read_text() == "mine"
    # the folder holding the input
    res = cli(capsys, "calibrate", "all", rec, "--array", NILSSON14, "--out", out, "--report", d, "-q")
    assert_user_error(res, str(d), "input")
    assert not out.exists()


def test_a_previous_report_is_replaced_only_with_force_and_only_if_all_ours(reported, tmp_path):
    rep, _, _ = reported
    copy = tmp_path / "rep"
    copy.mkdir()
    for p in rep.iterdir():
        (copy / p.name).write_bytes(p.read_bytes())
    with pytest.raises(OutputError, match="--force"):
        check_report_dir(copy, [], False)
    assert check_report_dir(copy, [], True) == copy
    (copy / "extra.csv").write_text("1")
    with pytest.raises(OutputError, match="extra.csv"):
        check_report_dir(copy, [], True)
    (copy / "extra.csv").unlink()
    (copy / MANIFEST).write_text('{"kind": "something else", "files": []}')
    with pytest.raises(OutputError, match="no calibration report of ours"):
        check_report_dir(copy, [], True)
    with pytest.raises(OutputError, match="holds the input"):
        check_report_dir(tmp_path, [copy / "index.md"], True)
    empty = tmp_path / "empty"
    empty.mkdir()
    assert check_report_dir(empty, [], False) == empty
