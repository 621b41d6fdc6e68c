"""The calibration contract: every method returns one Calibration that applies to a description,
scores a model on its own data, records provenance and statistics, and installs through one path
that never replaces a file fitting the data better."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from imu_array_ros.calibration.result import Calibration, backup_path
from imu_array_ros.errors import CalibrationError
from imu_array_ros.model.description import load_description
from imu_array_ros.model.sensor_model import SensorModel
from imu_array_ros.simulation.perturb import perturb
from imu_array_ros.workflows import calibrate, load_array, simulate

from conftest import REPO

NILSSON14 = REPO / "config" / "nilsson14.yaml"


@pytest.fixture(scope="module")
def session():
    """nilsson14 on the 20 faces (3 s each at 100 Hz), then 5 s of twisting, with seeded sensor errors."""
    desc, _ = load_array(NILSSON14)
    sim = simulate(desc, motion="icosahedron", rate=100.0, still_seconds=3.0, transition_seconds=1.0,
                   twist_seconds=5.0, seed=3, error_seed=7)
    return desc, sim.samples


@pytest.fixture(scope="module")
def twist():
    """3 s of twisting at 200 Hz by an array whose positions and gyroscope gains are off by ~1 mm, 1 %."""
    desc, _ = load_array(NILSSON14)
    model = SensorModel.from_description(desc)
    rng = np.random.default_rng(12)
    true = perturb(model, rng, {"position": 1e-3, "gyroscope_gain": 1e-2})
    sim = simulate(desc, motion="twist", duration=3.0, rate=200.0, seed=11,
                   true_desc=true.to_description(desc, names=["position", "gyroscope_gain"]))
    return desc, sim.samples


CASES = [
    ("geometry", "twist", {}, ["position"]),
    ("fit", "twist", {"terms": ["position", "gyroscope_gain"]}, ["position", "gyroscope_gain"]),
    ("static", "session", {}, ["accelerometer_gain", "accelerometer_bias", "gyroscope_bias"]),
    ("all", "session", {}, ["accelerometer_gain", "position", "gyroscope_misalignment"]),
]


@pytest.mark.parametrize("method, data, options, fitted", CASES, ids=[c[0] for c in CASES])
def test_every_method_returns_one_contract(method, data, options, fitted, request, tmp_path):
    desc, samples = request.getfixturevalue(data)
    cal = calibrate(method, samples, desc, source="rec.mcap", **options)
    assert isinstance(cal, Calibration) and cal.method == method and cal.converged
    assert set(fitted) <= set(cal.std) and cal.summary()
    # recorded: provenance and statistics
    assert cal.record["software"].startswith("imu_array_ros ") and "time" in cal.record
    assert cal.record["recording"] == "rec.mcap"
    # applied: the description with the calibrated values and their std
    applied = cal.apply(desc)
    np.testing.assert_array_equal(SensorModel.from_description(applied).terms[fitted[0]].values,
                                  cal.model.terms[fitted[0]].values)
    key = next(f.key for f in type(cal.model.terms[fitted[0]]).fields)
    assert all(key in imu.stds for imu in applied.imus if not np.isnan(cal.std[fitted[0]][desc.index(imu.name)]).all())
    # scored on its own data: the calibration fits it better than the nominal description
    nominal = SensorModel.from_description(desc)
    assert cal.score_of(cal.model) > cal.score_of(nominal) + 10.0
    # installed through the one path: written, then never replaced by a worse calibration
    out = tmp_path / "cal.yaml"
    installed = cal.install(desc, out)
    assert installed.backup is None and load_description(out).calibration["recording"] == "rec.mcap"
    before = out.read_bytes()
    worse = replace(cal, model=nominal, score=None)
    with pytest.raises(CalibrationError, match="not replaced: the calibration on file fits"):
        worse.install(desc, out)
    assert out.read_bytes() == before and not backup_path(out).exists()
    # the same calibration again is not worse: replaced, the old file kept as the backup
    again = cal.install(desc, out)
    assert again.backup == backup_path(out) and again.backup.read_bytes() == before
    # applied to a calibrated description, the earlier record is kept (one level) as provenance
    chained = cal.apply(load_description(out)).calibration
    assert chained["previous"]["time"] == cal.record["time"] and "previous" not in chained["previous"]
    assert cal.apply(chained_desc := cal.apply(desc)).calibration["previous"] == cal.record
    assert "previous" not in cal.apply(desc).calibration and chained_desc.calibration == cal.record


def test_unknown_method_is_one_line(twist):
    desc, samples = twist
    with pytest.raises(CalibrationError, match="unknown calibration method 'magic' "
                                               r"\(known: geometry, static, all, fit, bayes, noise\)"):
        calibrate("magic", samples, desc)


def test_options_named_method_reach_the_method(twist):
    """``calibrate(method, ...)`` takes the method positionally, so geometry's own ``method`` (solver) passes."""
    desc, samples = twist
    cal = calibrate("geometry", samples, desc, method="bcd")
    assert cal.details.method == "bcd" and "block coordinate descent" in cal.record["method"]
