"""Several recordings of one array (issue 22, item 4): device constants combined, biases kept as session states.

Three simulated power-ups of the same nilsson14 sensors (the same seeded device constants, new turn-on biases at
each), each 20 icosahedron poses then twisting; ``calibrate all`` on the three together.
"""

from __future__ import annotations

import numpy as np
import pytest

from imu_array_ros import workflows
from imu_array_ros.calibration.static import reframe_accelerometers
from imu_array_ros.calibration.sessions import SESSION_TERMS, combine_calibrations
from imu_array_ros.errors import CalibrationError
from imu_array_ros.model.description import load_description
from imu_array_ros.model.sensor_model import SensorModel

from conftest import REPO, cli

NILSSON14 = REPO / "config" / "nilsson14.yaml"
BIAS_TURN_ON = {"accelerometer_bias": 0.05, "gyroscope_bias": np.deg2rad(0.3)}  # per power-up, 1 sigma


@pytest.fixture(scope="module")
def power_ups():
    desc = load_description(NILSSON14)
    first = workflows.simulate(desc, motion="icosahedron", still_seconds=3.0, transition_seconds=1.0,
                               twist_seconds=4.0, rate=100.0, seed=11, error_seed=3)
    device = SensorModel.from_description(first.true_description)
    rng = np.random.default_rng(12)
    runs, truths = [first], [device]
    for seed in (13, 14):
        turned_on = device.with_terms(**{t: device.terms[t].values + s * rng.standard_normal(
            device.terms[t].values.shape) for t, s in BIAS_TURN_ON.items()})
        true_desc = turned_on.to_description(first.true_description, names=list(BIAS_TURN_ON))
        runs.append(workflows.simulate(desc, motion="icosahedron", still_seconds=3.0, transition_seconds=1.0,
                                       twist_seconds=4.0, rate=100.0, seed=seed, true_desc=true_desc))
        truths.append(turned_on)
    cal = workflows.calibrate("all", [r.samples for r in runs], desc, reference="imu_14",
                              source=["rec1", "rec2", "rec3"], moving_terms=("position",))
    return desc, runs, truths, cal


def test_device_constants_combined_and_biases_kept_per_recording(power_ups):
    desc, runs, truths, cal = power_ups
    details = cal.details
    assert len(details.recordings) == 3 and details.sources == ["rec1", "rec2", "rec3"]
    record = cal.record
    assert record["recordings"] == ["rec1", "rec2", "rec3"] and len(record["per_recording"]) == 3
    for t in SESSION_TERMS:
        assert record["terms"][t]["kind"] == "session state"
        # written: the mean over the power-ups, with the spread over them as its std
        v = details.values[t]
        assert np.allclose(cal.model.terms[t].values, v.mean(axis=0))
        assert np.allclose(cal.std[t], np.sqrt(np.mean(np.std(v, axis=0, ddof=1) ** 2)))  # pooled
        # the turn-on change is far above the within-recording std: the record says so
        assert record["terms"][t]["median_spread_over_within_std"] > 3.0
    # each recording's own biases are estimated close to that power-up's truth (within 5 of their std)
    for r, truth in enumerate(truths):
        for t in ("gyroscope_bias",):
            z = (details.values[t][r] - truth.terms[t].values) / details.within[t][r]
            assert np.nanmax(np.abs(z)) < 5.0, (r, t, np.nanmax(np.abs(z)))
    # device constants: the weighted mean lies between the recordings' estimates, its std not above the best
    # recording's (three recordings know more than one) unless their scatter says otherwise (Birge ratio)
    for t in ("accelerometer_gain", "position"):
        v, s, w = details.values[t], cal.std[t], details.within[t]
        assert record["terms"][t]["kind"] == "device constant"
        ok = np.isfinite(s)
        assert np.all(cal.model.terms[t].values[ok] <= v.max(axis=0)[ok] + 1e-15)
        assert np.all(cal.model.terms[t].values[ok] >= v.min(axis=0)[ok] - 1e-15)
        birge = np.maximum(1.0, details.birge[t][ok])
        assert np.allclose(s[ok], birge / np.sqrt(np.sum(w[:, ok] ** -2.0, axis=0)))


@pytest.mark.parametrize("term", ["accelerometer_gain", "accelerometer_nonorthogonality"])
def test_combined_device_constants_cover_the_truth(power_ups, term):
    """The combined device constants against the truth re-expressed in the reference imu_14's accelerometer
    frame (the static stage's gauge), in their written std."""
    desc, runs, truths, cal = power_ups
    truth = reframe_accelerometers(truths[0], "imu_14")
    s = cal.std[term]
    ok = np.isfinite(s) & (s > 0)
    z = (cal.model.terms[term].values[ok] - truth.terms[term].values[ok]) / s[ok]
    print(f"\n{term}: {ok.sum()} parameters, max |z| {np.abs(z).max():.2f}, rms z {np.sqrt(np.mean(z ** 2)):.2f}")
    assert np.abs(z).max() < 4.5 and np.sqrt(np.mean(z ** 2)) < 1.6


def test_one_recording_says_its_biases_are_session_states(power_ups):
    desc, runs, _, _ = power_ups
    one = workflows.calibrate("all", runs[0].samples, desc, reference="imu_14", moving_terms=())
    states = one.record["session_states"]
    assert set(states) == {"accelerometer_bias", "gyroscope_bias"}
    assert "not measured" in states["gyroscope_bias"]["turn_on_repeatability"]


def test_combining_refuses_different_terms_and_a_single_recording(power_ups):
    desc, runs, _, cal = power_ups
    a, b = cal.details.recordings[:2]
    with pytest.raises(CalibrationError, match="at least two"):
        combine_calibrations([a], ["x"])
    b_less = type(b)(method=b.method, model=b.model, std={k: v for k, v in b.std.items() if k != "position"},
                     record=b.record)
    with pytest.raises(CalibrationError, match="did not calibrate position"):
        combine_calibrations([a, b_less], ["rec1", "rec2"])
    with pytest.raises(CalibrationError, match="timing stage runs on one recording"):
        workflows.calibrate("all", [r.samples for r in runs[:2]], desc, timing=True)


def test_cli_calibrates_several_recordings_into_one_description(power_ups, tmp_path, capsys):
    """``imu-array calibrate all REC1 REC2``: one description, biases with their turn-on repeatability; the
    same recording twice and --timing with several are refused in one line, nothing written."""
    import yaml

    from imu_array_ros.io.rosbag.recording import write_imu_recording

    desc, runs, _, _ = power_ups
    recs = []
    for i, r in enumerate(runs[:2]):
        recs.append(tmp_path / f"rec{i}.mcap")
        write_imu_recording(recs[-1], r.samples, desc)
    out = tmp_path / "cal.yaml"
    code, _, err = cli(capsys, "calibrate", "all", *recs, "--array", NILSSON14, "--reference", "imu_14",
                       "--moving-terms", "position", "--out", out)
    assert code == 0, err
    record = yaml.safe_load(out.read_text())["calibration"]
    assert record["recordings"] == [str(r) for r in recs]
    assert record["terms"]["gyroscope_bias"]["kind"] == "session state"
    assert "2 recordings combined" in err
    for bad, fragment in (([recs[0], recs[0]], "the same recording is given twice"),
                          ([*recs, "--timing"], "--timing runs on one recording at a time")):
        target = tmp_path / "refused.yaml"
        code, _, err = cli(capsys, "calibrate", "all", *bad, "--array", NILSSON14, "--out", target)
        assert code == 2 and fragment in err and len(err.strip().splitlines()) == 1 and not target.exists()
