"""The fitting engine (imu_array_ros/fitting/): the Schur-complement step is the joint Gauss-Newton
step, every term is recovered with errors that match the Cramér-Rao bound it reports, gauge
freedoms are held, missing motion and bad input are refused, saturated axes are masked."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from imu_array_ros.errors import CalibrationError
from imu_array_ros.fitting.engine import fit_terms
from imu_array_ros.fitting.problem import Problem
from imu_array_ros.model.layouts import grid_array32, make_description
from imu_array_ros.model.sensor_model import SensorModel
from imu_array_ros.model.samples import MotionTruth
from imu_array_ros.model.terms import REGISTRY, candidate_names
from imu_array_ros.simulation.motion import random_motion
from imu_array_ros.simulation.perturb import perturb
from imu_array_ros.simulation.simulator import simulate_measurements, simulate_twist
from test_sensor_terms import SIZES

#: 8 IMUs of the 32-IMU array: the top corners and four from the middle of the (flipped) underside
SUBSET = (0, 3, 12, 15, 17, 18, 29, 30)
RATE = 200.0
#: terms with gauge freedoms when fitted on every IMU (the readings fix them only relative to each other)
GAUGE_TERMS = {"position", "axis_offsets", "time_offset", "accelerometer_bias", "bias_drift"}
#: per term: Monte Carlo runs and recording length (s); hundreds of z-scores each, 1-7 s per term
MONTE_CARLO = {
    "position": (12, 1.5), "axis_offsets": (6, 1.0), "time_offset": (10, 1.5),
    "accelerometer_misalignment": (16, 1.0), "accelerometer_nonorthogonality": (16, 1.0),
    "accelerometer_nonlinearity": (16, 1.0), "accelerometer_gain": (16, 1.0), "accelerometer_bias": (16, 1.0),
    "bias_drift": (12, 1.5), "gyroscope_misalignment": (16, 1.0), "gyroscope_nonorthogonality": (16, 1.0),
    "gyroscope_gain": (16, 1.0), "gyroscope_g_sensitivity": (8, 1.0), "gyroscope_bias": (16, 1.0),
}


def subset_model(indexes=SUBSET) -> SensorModel:
    desc = grid_array32()
    imus = [desc.imus[i] for i in indexes]
    return SensorModel.from_description(make_description([i.position for i in imus], [i.orientation for i in imus],
                                                         names=[i.name for i in imus]))


def fit(samples, model, free, **kw):
    return fit_terms(samples, model, free, **kw)


def gauge_errors(res, truth: SensorModel):
    """Estimation errors of the estimated (not held) parameters, the truth moved along the reported gauge
    freedoms to agree with the estimate on the held parameters; with their covariance."""
    k = [truth.names.index(n) for n in res.imus]
    true = np.concatenate([truth.terms[t].values[k] for t in res.free], axis=1).reshape(-1)
    held = np.array([res.parameter_names.index(h) for h in res.held], dtype=int)
    if len(held):
        c = np.linalg.lstsq(res.gauge_directions[held], res.theta[held] - true[held], rcond=None)[0]
        true = true + res.gauge_directions @ c
    keep = np.ones(len(true), dtype=bool)
    keep[held] = False
    return (res.theta - true)[keep], res.covariance[np.ix_(keep, keep)]


# --------------------------------------------------------------------------- the reduced system


def test_schur_step_is_the_dense_joint_gauss_newton_step(rng):
    """On a tiny problem (3 fitted IMUs, 7 samples in chunks of 2), the reduced system's step and its
    inverse equal the joint step and the theta block of the inverse of the dense J^T J."""
    k, n = 4, 7
    model = subset_model(SUBSET[:k])
    model = perturb(model, rng, {t: SIZES[t] for t in candidate_names() if t != "position"})  # every term active
    truth = random_motion(n, 6.0, 60.0, rng, rate_hz=RATE)
    samples = simulate_measurements(model, truth, rng)
    free, fitted = ("position", "gyroscope_g_sensitivity", "time_offset", "accelerometer_gain"), np.array([1, 2, 3])
    prob = Problem(samples, model, free, fitted)
    prob.chunk = 2
    motion = np.concatenate([truth.omega, truth.omega_dot, truth.specific_force], axis=1)
    motion = motion + rng.normal(0, 0.05, motion.shape)  # away from the optimum
    lin = prob.linearize(model, motion)
    dtheta = np.linalg.solve(lin.S, lin.g)
    dx = prob.motion_step(model, motion, lin, dtheta)

    ctx = prob.context_at(model, motion, prob.derivatives(motion), slice(None))  # the engine's timing context
    jac = model.jacobians(ctx, free)
    w = 1.0 / model.std[None]
    y = np.concatenate([samples.accel, samples.gyro], axis=2)
    p = sum(REGISTRY[t].dim() for t in free)
    dense = np.zeros((n, k, 6, 9 * n + len(fitted) * p))
    for i in range(n):
        dense[i, :, :, 9 * i:9 * i + 9] = jac.motion[i] * w[0, :, :, None]
    jt = np.concatenate([jac.params[t] for t in free], axis=3) * w[..., None]
    for j, kk in enumerate(fitted):
        dense[:, kk, :, 9 * n + j * p:9 * n + (j + 1) * p] = jt[:, kk]
    dense = dense.reshape(n * k * 6, -1)
    r = (w * (y - jac.predicted)).reshape(-1)
    info = dense.T @ dense
    step = np.linalg.solve(info, dense.T @ r)
    np.testing.assert_allclose(dtheta, step[9 * n:], rtol=1e-7, atol=1e-9 * np.abs(step[9 * n:]).max())
    np.testing.assert_allclose(dx.reshape(-1), step[:9 * n], rtol=1e-7, atol=1e-9 * np.abs(step[:9 * n]).max())
    crb = np.linalg.inv(info)[9 * n:, 9 * n:]
    np.testing.assert_allclose(np.linalg.inv(lin.S), crb, rtol=1e-6, atol=1e-9 * np.abs(crb).max())
    assert lin.cost == pytest.approx(0.5 * r @ r, rel=1e-12)


# --------------------------------------------------------------------------- Monte Carlo per term


@pytest.mark.parametrize("name", sorted(MONTE_CARLO))
def test_monte_carlo_errors_match_the_reported_crb(name):
    """Twisting recordings simulated with the term perturbed (realistic sizes), the term fitted from
    identity: the z-scores (error / reported std) have RMS 0.8-1.25, and the errors whitened by the
    reported covariance (the CRB of the joint problem) have RMS 0.8-1.2, pooled over IMUs, parameters and runs.

    The whitened RMS is the error-to-CRB ratio with correlations accounted for: a few weakly
    identified common modes (e.g. the common scale of all gains) hold most of the variance, so the
    plain ratio RMS(error) / RMS(std) has about one degree of freedom per run."""
    assert set(MONTE_CARLO) == set(candidate_names())
    runs, seconds = MONTE_CARLO[name]
    rng = np.random.default_rng(20170 + sorted(MONTE_CARLO).index(name))
    nominal = subset_model()
    z, whitened, dof = [], 0.0, 0
    for _ in range(runs):
        truth = perturb(nominal, rng, {name: SIZES[name]})
        if name in GAUGE_TERMS:  # the reference IMU at the held (initial) values: no shift of the time base
            values = truth.terms[name].values.copy()
            values[0] = nominal.terms[name].values[0]
            truth = truth.with_terms(**{name: values})
        samples, _ = simulate_twist(truth, seconds, RATE, rng)
        res = fit(samples, nominal, [name])
        assert res.converged and res.samples_used == len(samples)
        assert bool(res.held) == (name in GAUGE_TERMS), res.held
        assert res.loglik_after > res.loglik_before and 0.85 < res.nis_after < 1.15
        err, cov = gauge_errors(res, truth)
        z.append(err / np.sqrt(np.diag(cov)))
        whitened += err @ np.linalg.solve(cov, err)
        dof += len(err)
    z = np.concatenate(z)
    assert len(z) >= 150
    assert 0.8 < np.sqrt(np.mean(z ** 2)) < 1.25, np.sqrt(np.mean(z ** 2))
    assert 0.8 < np.sqrt(whitened / dof) < 1.2, np.sqrt(whitened / dof)


# --------------------------------------------------------------------------- gauge


@pytest.fixture(scope="module")
def positions_recording():
    rng = np.random.default_rng(2017)
    nominal = subset_model()
    truth = perturb(nominal, rng, {"position": 2e-3})
    samples, motion = simulate_twist(truth, 1.5, RATE, rng)
    return nominal, truth, samples, np.concatenate([motion.omega, motion.omega_dot, motion.specific_force], axis=1)


def test_positions_on_every_imu_hold_the_reference_position(positions_recording):
    nominal, truth, samples, _ = positions_recording
    res = fit(samples, nominal, ["position"])
    assert res.held == ["imu_00 position[0]", "imu_00 position[1]", "imu_00 position[2]"]
    assert res.gauge == [f"{h} held" for h in res.held]
    est, std = res.model.positions, res.std["position"]
    np.testing.assert_array_equal(est[0], nominal.positions[0])
    assert np.isnan(std[0]).all() and np.isfinite(std[1:]).all()
    rel_err = (est[1:] - est[0]) - (truth.positions[1:] - truth.positions[0])  # relative to the reference
    assert np.sqrt(np.mean((rel_err / std[1:]) ** 2)) < 2.0
    assert np.abs(truth.positions[1:] - nominal.positions[1:]).max() > 100 * std[1:].max()  # it did move

    other = fit(samples, nominal, ["position"], reference="imu_15")
    assert other.held == [f"imu_15 position[{i}]" for i in range(3)]
    np.testing.assert_allclose(other.model.positions - other.model.positions[3],
                               res.model.positions - res.model.positions[3], atol=1e-9)


def test_mean_gauge_keeps_the_centroid(positions_recording):
    nominal, truth, samples, _ = positions_recording
    ref = fit(samples, nominal, ["position"])
    res = fit(samples, nominal, ["position"], gauge="mean")
    assert res.held == [] and len(res.gauge) == 3
    np.testing.assert_allclose(res.model.positions.mean(axis=0), nominal.positions.mean(axis=0), atol=1e-10)
    np.testing.assert_allclose(res.model.positions - res.model.positions[0],
                               ref.model.positions - ref.model.positions[0], atol=1e-9)
    assert np.linalg.matrix_rank(res.covariance, tol=1e-6 * np.abs(res.covariance).max()) == 24 - 3
    assert res.loglik_after == pytest.approx(ref.loglik_after, abs=1e-3)


def test_the_initial_motion_does_not_change_the_estimate(positions_recording):
    nominal, truth, samples, motion = positions_recording
    res = fit(samples, nominal, ["position"])
    given = fit(samples, nominal, ["position"], motion0=motion)
    np.testing.assert_allclose(given.theta, res.theta, rtol=0, atol=1e-3 * np.nanmin(res.std["position"]))
    np.testing.assert_allclose(given.motion, res.motion, rtol=0, atol=1e-6 * np.abs(res.motion).max())
    with pytest.raises(CalibrationError, match="motion0"):
        fit(samples, nominal, ["position"], motion0=motion[:-1])


def test_common_gyroscope_scale_trades_against_the_position_scale(positions_recording):
    """omega (1 + e), omega_dot (1 + e)^2, positions / (1 + e)^2 and gyroscope gains / (1 + e) predict the
    same readings: with positions free, one gyroscope gain of the reference is held too."""
    nominal, truth, samples, _ = positions_recording
    res = fit(samples, nominal, ["position", "gyroscope_gain"])
    assert res.held == [f"imu_00 position[{i}]" for i in range(3)] + ["imu_00 gyroscope.gain[0]"]
    est = res.model.terms["gyroscope_gain"].values
    np.testing.assert_array_equal(est[0, 0], 1.0)
    assert np.isfinite(res.std["gyroscope_gain"][0, 1:]).all()
    z = (est[1:] - 1.0) / res.std["gyroscope_gain"][1:]  # true gains are 1: only the held one is at its truth
    assert np.sqrt(np.mean(z ** 2)) < 2.0


def test_a_held_imu_fixes_the_frame(positions_recording):
    """IMUs not fitted keep their parameters and define the frame: nothing is held for the gauge."""
    nominal, truth, samples, _ = positions_recording
    res = fit(samples, truth.with_terms(position=np.where(np.arange(8)[:, None] < 5, nominal.positions,
                                                          truth.positions)), ["position"], imus=range(5))
    assert res.held == [] and res.imus == tuple(nominal.names[:5])
    assert np.isnan(res.std["position"][5:]).all()
    z = (res.model.positions[:5] - truth.positions[:5]) / res.std["position"][:5]
    assert np.sqrt(np.mean(z ** 2)) < 2.0


def test_rotation_about_one_axis_cannot_identify_positions(rng):
    nominal = subset_model()
    stamps = np.arange(300) * 5_000_000
    t = stamps * 1e-9
    f1, f2 = 2 * np.pi * 0.9, 2 * np.pi * 1.7
    rate = 6.0 * np.sin(f1 * t) + 3.0 * np.sin(f2 * t + 1.0)
    rate_dot = 6.0 * f1 * np.cos(f1 * t) + 3.0 * f2 * np.cos(f2 * t + 1.0)
    z = np.zeros_like(t)
    truth = MotionTruth(stamps, np.column_stack([z, z, rate]), np.column_stack([z, z, rate_dot]),
                        np.column_stack([3 * np.sin(t), 9.0 + 0 * t, 2 * np.cos(3 * t)]))
    samples = simulate_measurements(perturb(nominal, rng, {"position": 1e-3}), truth, rng)
    with pytest.raises(CalibrationError) as err:
        fit(samples, nominal, ["position"])
    msg = str(err.value)
    assert "\n" not in msg and "position[2]" in msg and "two different axes" in msg, msg
    assert "position[0]" not in msg and "position[1]" not in msg, msg


# --------------------------------------------------------------------------- masking, likelihood, refusals


def test_clipped_and_missing_readings_are_masked(rng):
    nominal = replace(subset_model(), gyro_clip=9.0)
    truth = perturb(nominal, rng, {"gyroscope_gain": SIZES["gyroscope_gain"]})
    samples, _ = simulate_twist(truth, 1.5, RATE, rng)
    clipped = ~nominal.gyro_unsaturated(samples.gyro)
    assert 0.01 < clipped.mean() < 0.3  # some gyro axes clipped
    samples.accel[10:14] = np.nan  # four samples without any reading
    samples.gyro[10:14] = np.nan
    samples.accel[50:80, 2] = np.nan  # one IMU missing for a while
    samples.gyro[50:80, 2] = np.nan
    res = fit(samples, nominal, ["gyroscope_gain"])
    assert res.converged and res.samples_used == len(samples) - 4 and res.samples_dropped == 4
    assert np.isnan(res.motion[10:14]).all() and np.isfinite(res.motion[20:]).all()
    assert np.isnan(res.residuals[..., 3:][clipped]).all() and np.isnan(res.residuals[50:80, 2]).all()
    assert 0.85 < res.nis_after < 1.15 and res.nis_before > 10
    z = (res.model.terms["gyroscope_gain"].values - truth.terms["gyroscope_gain"].values) / res.std["gyroscope_gain"]
    assert np.sqrt(np.mean(z ** 2)) < 2.0


def test_likelihood_rises_and_nis_is_one_on_the_correct_model(positions_recording):
    nominal, truth, samples, _ = positions_recording
    calls = []
    res = fit(samples, nominal, ["position", "gyroscope_bias"], progress=lambda i, c: calls.append((i, c)))
    assert res.loglik_after > res.loglik_before + 1000
    assert abs(res.nis_after - 1) < 4 * np.sqrt(2 / res.dof) and res.nis_before > 2
    assert [c[0] for c in calls] == list(range(res.iterations + 1)) and calls[-1][1] < calls[0][1]
    assert res.dof == 6 * 8 * len(samples) - 9 * len(samples) - (8 * 6 - 3)
    # already at the truth: nothing to gain beyond the noise
    again = fit(samples, truth, ["position", "gyroscope_bias"], imus=range(1, 8))
    assert abs(again.nis_after - 1) < 4 * np.sqrt(2 / again.dof)
    assert again.loglik_after - again.loglik_before < 3 * again.theta.size


@pytest.mark.parametrize("free, kwargs, fragment", [
    (["no_such_term"], {}, "unknown term 'no_such_term'"),
    ([], {}, "no free terms"),
    (["position"], {"imus": ["imu_99"]}, "unknown IMU 'imu_99'"),
    (["position"], {"imus": [1, 2], "reference": "imu_00"}, "not among the fitted IMUs"),
    (["position"], {"gauge": "median"}, "gauge must be"),
])
def test_bad_requests_are_refused_in_one_line(positions_recording, free, kwargs, fragment):
    nominal, _, samples, _ = positions_recording
    with pytest.raises(CalibrationError, match=fragment) as err:
        fit(samples.select(slice(0, 50)), nominal, free, **kwargs)
    assert "\n" not in str(err.value)


def test_too_few_or_no_valid_samples_are_refused(positions_recording):
    nominal, _, samples, _ = positions_recording
    with pytest.raises(CalibrationError, match="too few samples"):
        fit(samples.select(slice(0, 2)), nominal, ["position"])
    with pytest.raises(CalibrationError, match="too few samples"):  # 3 samples, 24 x 9 parameters
        fit(samples.select(slice(0, 3)), nominal, ["gyroscope_g_sensitivity", "axis_offsets"])
    empty = samples.select(slice(0, 20))
    empty.accel[:] = np.nan
    with pytest.raises(CalibrationError, match="no valid samples"):
        fit(empty, nominal, ["position"])


def test_named_parameters_are_held_outside_the_gauge_search(positions_recording):
    """``hold``: the parameters named keep their initial values (std NaN) and the gauge search works on the
    rest -- holding the reference position by name is the reference gauge itself (same estimate)."""
    nominal, truth, samples, _ = positions_recording
    ref = fit(samples, nominal, ["position", "gyroscope_gain"])
    names = ["imu_00 position[0]", "imu_00 position[1]", "imu_00 position[2]", "imu_00 gyroscope.gain[0]"]
    held = fit(samples, nominal, ["position", "gyroscope_gain"], hold=names)
    assert held.held == []  # nothing left for the gauge search to hold
    np.testing.assert_allclose(held.theta, ref.theta, rtol=0, atol=1e-3 * np.nanmin(ref.std["position"]))
    assert np.isnan(held.std["position"][0]).all() and np.isnan(held.std["gyroscope_gain"][0, 0])
    # holding another IMU's gain as well: it stays at its initial value
    more = fit(samples, nominal, ["position", "gyroscope_gain"],
               hold=names + [f"{nominal.names[1]} gyroscope.gain[2]"])
    assert more.model.terms["gyroscope_gain"].values[1, 2] == nominal.terms["gyroscope_gain"].values[1, 2]
    with pytest.raises(CalibrationError, match="hold: 'imu_00 gyroscope.bias\\[0\\]' is not a parameter"):
        fit(samples, nominal, ["position"], hold=["imu_00 gyroscope.bias[0]"])


def test_cost_tolerance_stops_once_a_step_gains_little_likelihood(positions_recording):
    """cost_tolerance (discovery's confirming refits): stop when a step lowers the cost by less; the
    log-likelihood is then within that of the full fit's, the default (None) fit unchanged."""
    nominal, truth, samples, _ = positions_recording
    full = fit(samples, nominal, ["position"], tolerance=1e-6)
    quick = fit(samples, nominal, ["position"], tolerance=1e-6, cost_tolerance=0.1)
    assert quick.converged and quick.iterations < full.iterations
    assert 0.0 <= full.loglik_after - quick.loglik_after < 0.1
    assert quick.loglik_after - quick.loglik_before > 100  # it did fit
