"""The stages of ``calibrate all`` (imu_array_ros.calibration.array.calibrate_array) never build on nonsense:
the timing stage recovers known gyroscope time offsets and keeps the moving stage's terms, the accelerometers'
delays too; the engine's timing approximation (local quartics) leaves the fitted offsets unbiased on fast motion
at 62.5 Hz; the simulated session reads a timed model at the true sample times; a moving stage that did not converge or is physically
implausible is refused (skipped with the reason, the static stage's model kept, no timing
stage on it); a timing fit the data cannot identify is skipped with the reason; the command line says so in one
line, non-zero only when nothing could be calibrated."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

import imu_array_ros.fitting.engine as engine
from imu_array_ros.calibration.array import MOVING_TERMS, calibrate_array
from imu_array_ros.errors import CalibrationError, IdentifiabilityError
from imu_array_ros.model.description import save_description
from imu_array_ros.model.layouts import tetrahedron4
from imu_array_ros.model.sensor_model import SensorModel
from imu_array_ros.simulation.icosahedron import simulate_icosahedron
from imu_array_ros.simulation.simulator import simulate_twist

from conftest import START, assert_user_error, cli

#: the moving stage's terms which the timing stage holds (it refits the gyroscope gains with the time offsets)
HELD = ("position", "gyroscope_misalignment", "gyroscope_nonorthogonality")
#: still poses of 1 s at 62.5 Hz (the MIMU4444BT's read rate) are found with these
STILL = dict(window_s=0.3, min_duration_s=0.3, settle_s=0.1)


@pytest.fixture(scope="module")
def nominal():
    return SensorModel.from_description(tetrahedron4())


@pytest.fixture(scope="module")
def offsets(nominal):
    """(K, 2) true time offsets, s (accelerometer, gyroscope): two gyroscopes 3 ms late and 2 ms early."""
    to = np.zeros((nominal.n_imus, 2))
    to[1, 1], to[3, 1] = 3e-3, -2e-3
    return to


@pytest.fixture(scope="module")
def session(nominal, offsets):
    """An icosahedron session of the tetrahedron with those offsets: 20 still poses of 1 s joined by 0.3 s of
    handling, then 1.2 s of hand twisting, at 62.5 Hz."""
    samples, _, _ = simulate_icosahedron(nominal.with_terms(time_offset=offsets), np.random.default_rng(1),
                                         rate_hz=62.5, still_s=1.0, transition_s=0.3, twist_s=1.2)
    return samples


@pytest.fixture(scope="module")
def twist(nominal):
    """3.2 s of twisting at 62.5 Hz (200 samples) and no still pose."""
    return simulate_twist(nominal, 3.2, 62.5, np.random.default_rng(2))[0]


def test_the_timing_stage_recovers_known_offsets_and_keeps_the_moving_stage(session, nominal, offsets):
    """Every fitted gyroscope offset within 4 of its std of the truth; the reference gyroscope's held (the gauge
    of time); the written positions, gyroscope misalignment and non-orthogonality are the moving stage's, bit for
    bit, and so is the gyroscope gains' std (the reference IMU's gain held).  The accelerometers' offsets:
    test_the_accelerometers_delays_are_within_their_std."""
    cal = calibrate_array(session, nominal, timing=True, clock_period=None, still_options=STILL)
    assert cal.skipped == {} and cal.static is not None and cal.moving is not None and cal.timing is not None
    assert cal.timed and "-> timing" in cal.method()
    est, std = cal.model.terms["time_offset"].values, cal.stds()["time_offset"]
    fitted = np.isfinite(std) & (std > 0)
    assert fitted.sum() == 2 * nominal.n_imus - 1 and not fitted[0, 1]
    assert est[0, 1] == 0.0
    z = (est - offsets) / std
    print(f"\ntime offsets, us: {np.round(est * 1e6).tolist()}; z {np.round(z, 2).tolist()}")
    assert np.max(np.abs(z[1:, 1])) < 4.0, z
    for term in HELD:
        assert np.array_equal(cal.model.terms[term].values, cal.moving.model.terms[term].values), term
    assert cal.timing.free == ("time_offset", "gyroscope_gain")
    gain_std = cal.stds()["gyroscope_gain"]
    assert np.array_equal(gain_std, cal.moving.std_robust["gyroscope_gain"], equal_nan=True)
    assert cal.model.terms["gyroscope_gain"].values[0, 0] == cal.moving.model.terms["gyroscope_gain"].values[0, 0]
    assert [s["stage"] for s in cal.record()["stages"]][-1] == "timing"


def test_the_accelerometers_delays_are_within_their_std(session, nominal, offsets):
    """Every fitted accelerometer offset within 4 of its std of the truth (true 0) on this seed.  With the engine's
    former local cubics over >= 5 samples (64 ms at 62.5 Hz) the accelerometers' common delay came out 3.7-4.3 std
    early here (over 24 fresh seeds z averaged -0.71, benchmarks/results/calibrate_timing_trust_before.md; -0.01
    at f04ca81, calibrate_timing_trust.md at 84712b5); with the local quartics 3.1-3.6, and since the timing stage fits the gyroscope gains
    with the offsets (1b968b0) 0.3-1.2 (with the true moving-stage terms held about 1 std early here,
    test_the_engine_timing_approximation_is_unbiased)."""
    cal = calibrate_array(session, nominal, timing=True, clock_period=None, still_options=STILL)
    est, std = cal.model.terms["time_offset"].values[:, 0], cal.stds()["time_offset"][:, 0]
    z = (est - offsets[:, 0]) / std
    print(f"\naccelerometer offsets, us: {np.round(est * 1e6).tolist()}; z {np.round(z, 2).tolist()}")
    assert np.max(np.abs(z)) < 4.0, z


def test_the_engine_timing_approximation_is_unbiased(nominal, offsets):
    """With every other term true, the time offsets the engine fits on the session (0.3 s transitions at 62.5 Hz)
    are unbiased: over 6 seeds the mean z of the accelerometers' common delay and of each moved gyroscope's
    offset is within 1 of 0 (standard error ~0.4).  The engine's former local cubics over >= 5 samples smoothed
    the transitions: accelerometers -1.73, gyroscopes +1.53 and -1.17 (their offsets' magnitudes too large);
    the local quartics (interpolating at this rate): -0.25, 0.25, -0.02 (docs/timing.md)."""
    z = []
    for seed in range(1, 7):
        samples = simulate_icosahedron(nominal.with_terms(time_offset=offsets), np.random.default_rng(seed),
                                       rate_hz=62.5, still_s=1.0, transition_s=0.3, twist_s=1.2)[0]
        fit = engine.fit_terms(samples, nominal.with_terms(time_offset=np.zeros_like(offsets)), ("time_offset",),
                               hold=["imu_00 gyroscope.time_offset"], t0_ns=int(samples.stamps[0]))
        e = (fit.model.terms["time_offset"].values - offsets) / fit.std_robust["time_offset"]
        z.append([e[:, 0].mean(), e[1, 1], e[3, 1]])
    mean = np.mean(z, axis=0)
    print(f"\nmean z: accelerometers {mean[0]:.2f}, imu_01 gyroscope {mean[1]:.2f}, imu_03 gyroscope {mean[2]:.2f}")
    assert np.all(np.abs(mean) < 1.0), mean


def test_the_simulated_session_reads_a_timed_model_at_the_true_sample_times(nominal):
    """A gyroscope one sample period late reads the next sample's motion, an accelerometer one period early the
    previous one's, to rounding (noise off).  Before 2026-11-28 simulate_icosahedron shifted the readings along
    local cubics of the truth at the stamps, 0.7 rad/s off on the 0.3 s transitions at 62.5 Hz: with the true
    model held, the timing fit then put the accelerometers ~300 us late and the gyroscope offsets 1 % short, 10
    of their std (benchmarks/results/calibrate_timing_trust.md)."""
    quiet = replace(nominal, acc_std=0 * nominal.acc_std, gyro_std=0 * nominal.gyro_std)
    period = 1 / 62.5
    to = np.zeros((nominal.n_imus, 2))
    to[1, 1], to[2, 0] = period, -period
    run = dict(rate_hz=62.5, still_s=1.0, transition_s=0.3, twist_s=1.2)
    timed = simulate_icosahedron(quiet.with_terms(time_offset=to), np.random.default_rng(3), **run)[0]
    plain = simulate_icosahedron(quiet, np.random.default_rng(3), **run)[0]
    assert np.ptp(plain.gyro[:, 1]) > 5.0  # the session moves
    np.testing.assert_allclose(timed.gyro[:-1, 1], plain.gyro[1:, 1], rtol=0, atol=1e-9)
    np.testing.assert_allclose(timed.accel[1:, 2], plain.accel[:-1, 2], rtol=0, atol=1e-9)
    np.testing.assert_array_equal(timed.gyro[:, [0, 2, 3]], plain.gyro[:, [0, 2, 3]])


def test_the_gyroscope_offsets_repeat_within_their_std(nominal, offsets):
    """On other seeds of the session the late and the early gyroscope's offsets are each within 4 of their written
    std of the truth, and their magnitudes are not short: the mean over the 6 seeds and the two of z signed along
    the true offset ((z_late - z_early) / 2; < 0: too small) is within 0.6 of 0 (2 standard errors of a mean of 12
    unit-variance z).  Before the timing stage fitted the gyroscope gains with the offsets, the gains the moving
    stage had fitted without the delays absorbed part of them: here -0.82 (mean z -0.79 / +0.86), over 32 fresh
    seeds -1.49 / +1.27 (benchmarks/results/calibrate_timing_trust.md); now +0.25 here."""
    z = []
    for seed in range(2, 8):
        samples = simulate_icosahedron(nominal.with_terms(time_offset=offsets), np.random.default_rng(seed),
                                       rate_hz=62.5, still_s=1.0, transition_s=0.3, twist_s=1.2)[0]
        cal = calibrate_array(samples, nominal, timing=True, clock_period=None, still_options=STILL)
        assert cal.timing is not None, cal.skipped
        est, std = cal.model.terms["time_offset"].values[[1, 3], 1], cal.stds()["time_offset"][[1, 3], 1]
        z.append((est - offsets[[1, 3], 1]) / std)
        print(f"\nseed {seed}: gyroscope offsets {np.round(est * 1e6).tolist()} us, z {np.round(z[-1], 2).tolist()}")
    z = np.array(z)
    shortfall = np.mean(z * np.sign(offsets[[1, 3], 1]))
    print(f"mean z {np.round(z.mean(axis=0), 2).tolist()}; along the true offsets {shortfall:.2f}")
    assert np.all(np.abs(z) < 4.0), z
    assert abs(shortfall) < 0.6, shortfall


def test_a_moving_stage_that_did_not_converge_is_refused_and_nothing_is_built_on_it(twist, nominal):
    """The short twist without still poses, one iteration allowed: nothing to calibrate, one line naming both
    stages (before: the unconverged moving stage was returned and the timing stage ran on it)."""
    with pytest.raises(CalibrationError) as err:
        calibrate_array(twist, nominal, timing=True, clock_period=None, max_iterations=1)
    text = str(err.value)
    assert "\n" not in text and text.startswith("nothing to calibrate: static stage: only 0 static poses")
    assert "moving stage: refused: not converged" in text


def far_apart(monkeypatch, spread: float = 1e3):
    """fit_terms returns, for the moving terms, positions ``spread`` m apart (what the moving stage wrote on a
    3.2 s clocked twist: ~3 km), converged; counts its calls per terms."""
    real, calls = engine.fit_terms, []

    def fake(samples, model, terms, **kwargs):
        calls.append(tuple(terms))
        fit = real(samples, model, terms, **kwargs)
        if "position" not in terms:
            return fit
        far = fit.model.positions + spread * np.arange(model.n_imus)[:, None] * np.array([1.0, 0.0, 0.0])
        return replace(fit, model=fit.model.with_terms(position=far), converged=True)

    monkeypatch.setattr(engine, "fit_terms", fake)
    return calls


def test_an_implausible_moving_stage_is_refused_the_static_model_kept_and_timing_not_run(session, nominal,
                                                                                       monkeypatch):
    calls = far_apart(monkeypatch)
    cal = calibrate_array(session, nominal, timing=True, clock_period=None, still_options=STILL)
    assert calls == [MOVING_TERMS]  # no timing fit
    assert cal.moving is None and cal.timing is None and not cal.timed
    assert cal.skipped["moving"].startswith("refused: imu_03 position moved 3000000.")
    assert "physically implausible" in cal.skipped["moving"] and "\n" not in cal.skipped["moving"]
    assert "moving stage was skipped" in cal.skipped["timing"]
    assert cal.model is cal.static.model and cal.moving_window is None and cal.moving_samples == (0, 0)
    assert [s["stage"] for s in cal.record()["stages"]] == ["still poses", "static"]
    assert "moving skipped: refused" in cal.summary()


def test_checks_false_keeps_the_stages_as_they_come(session, nominal, monkeypatch):
    """The dispatcher's checks=False (experts) reaches the stages: the 3 km moving stage is kept."""
    from imu_array_ros.calibration.methods import calibrate

    far_apart(monkeypatch)
    cal = calibrate("all", session, nominal, checks=False, still_options=STILL)
    assert cal.details.moving is not None and "moving" not in cal.details.skipped
    assert np.ptp(cal.model.positions[:, 0]) > 1e3


def test_a_timing_fit_the_data_cannot_identify_is_skipped_with_the_reason(session, nominal, monkeypatch):
    """An IdentifiabilityError in the timing fit (as ModelFusion raised on the 3 km array): skipped with the
    reason, the moving stage's model kept (before: the traceback)."""
    real = engine.fit_terms

    def fake(samples, model, terms, **kwargs):
        if "time_offset" in terms:
            raise IdentifiabilityError("array 'imu_array': the IMU positions span 3e+03 m")
        return real(samples, model, terms, **kwargs)

    monkeypatch.setattr(engine, "fit_terms", fake)
    cal = calibrate_array(session, nominal, timing=True, clock_period=None, still_options=STILL)
    assert cal.moving is not None and cal.timing is None and not cal.timed
    assert cal.skipped == {"timing": "array 'imu_array': the IMU positions span 3e+03 m; the moving stage's result "
                                     "is kept"}
    assert cal.model is cal.moving.model and "timing" not in cal.method()


def test_the_command_line_refuses_in_one_line_only_when_nothing_could_be_calibrated(tmp_path, capsys, monkeypatch):
    """calibrate all --timing on a recording with no still poses whose moving stage is implausible: exit 2, one
    line naming both stages, no traceback, nothing written."""
    desc = tmp_path / "tetra.yaml"
    save_description(tetrahedron4(), desc)
    rec, out = tmp_path / "rec", tmp_path / "out.yaml"
    assert cli(capsys, "simulate", "--array", desc, "--out", rec, "--duration", "3.2", "--rate", "62.5",
               "--seed", "2", "--start-time", START, "-q")[0] == 0
    far_apart(monkeypatch)
    line = assert_user_error(cli(capsys, "calibrate", "all", rec, "--array", desc, "--out", out, "--timing",
                                 "--clock-period", "0", "-q"),
                             "nothing to calibrate", "static stage: only 0 static poses", "moving stage: refused",
                             "physically implausible")
    assert "timing" not in line and not out.exists()
