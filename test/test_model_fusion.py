"""Fusion with the whole sensor model (linear terms exact, the others compensated):
NEES consistency on a recording simulated with every term."""

from __future__ import annotations

import numpy as np
import pytest

from imu_array_ros.fusion.model_fusion import ModelFusion, fuse_model
from imu_array_ros.fusion.stream import fuse_chunked
from imu_array_ros.model.sensor_model import SensorModel
from imu_array_ros.model.terms import REGISTRY, term_names
from imu_array_ros.simulation.simulator import simulate_twist

#: 1-sigma sizes of every term, a realistic MEMS array
TRUE_SIZES = {
    "position": 1e-3, "axis_offsets": 5e-4, "time_offset": 1e-3,
    "accelerometer_misalignment": 5e-3, "accelerometer_nonorthogonality": 2e-3, "accelerometer_nonlinearity": 5e-4,
    "accelerometer_gain": 0.01, "accelerometer_bias": 0.2, "bias_drift": 2e-3,
    "gyroscope_misalignment": 5e-3, "gyroscope_nonorthogonality": 2e-3, "gyroscope_gain": 0.01,
    "gyroscope_g_sensitivity": 5e-4, "gyroscope_bias": 0.02,
}


def nees(fused, truth):
    """(N,) normalised estimation error squared of [omega, omega_dot, s], 9 dof."""
    idx = np.searchsorted(truth.stamps, fused.stamps)
    e = np.concatenate([fused.omega - truth.omega[idx], fused.omega_dot - truth.omega_dot[idx],
                        fused.specific_force - truth.specific_force[idx]], axis=1)
    return np.einsum("ni,nij,nj->n", e, np.linalg.inv(fused.covariance), e)


@pytest.fixture(scope="module")
def every_term():
    from imu_array_ros.model.layouts import grid_array32

    rng = np.random.default_rng(20261121)
    nominal = SensorModel.from_description(grid_array32())
    # every term but the sample clocks (the time-aware tests cover those, with their session states)
    assert set(TRUE_SIZES) == set(REGISTRY) - {"sample_clock", "gyroscope_sample_clock", "accelerometer_sample_clock",
                                               "stamp_clock"}
    values = {n: REGISTRY[n].default_values(32) + rng.normal(0, TRUE_SIZES[n], (32, REGISTRY[n].dim()))
              for n in term_names() if n in TRUE_SIZES}
    values["position"] = nominal.positions + rng.normal(0, TRUE_SIZES["position"], (32, 3))
    true = nominal.with_terms(**values)
    samples, truth = simulate_twist(true, 4.0, 500.0, rng, rms_rate=np.deg2rad(600))
    return nominal, true, samples, truth


def test_every_term_fused_with_the_true_description_is_nees_consistent(every_term):
    """Mean NEES within 4 standard errors of its 9 dof with the true terms; far outside with the nominal."""
    nominal, true, samples, truth = every_term
    fused, stats = fuse_model(samples, true)
    assert stats.fused == len(samples)
    v = nees(fused, truth)
    se = np.sqrt(2 * 9 / len(v))  # NEES ~ chi2(9): mean 9, variance 18
    assert abs(v.mean() - 9) < 4 * se, (v.mean(), se)
    bad = nees(fuse_model(samples, nominal)[0], truth).mean()
    assert bad > 9 + 100 * se, bad


def test_compensation_is_what_makes_it_consistent(every_term):
    """Without compensating the non-linear terms (linear part only) the same recording is not consistent."""
    _, true, samples, truth = every_term
    linear_only = fuse_model(samples, true, passes=0)[0]
    assert nees(linear_only, truth).mean() > 9 + 10 * np.sqrt(18 / len(samples))


def test_chunked_stream_uses_the_recording_first_stamp(every_term):
    """Fusing in chunks gives the same drift reference (t0 = first stamp) and nearly the same values: the
    timing terms are compensated along local cubics through each chunk's estimate (a window of ~25 ms, which
    reaches one window further per pass at a chunk's edge) with the gyroscopes' rate offset estimated per
    chunk, so away from the edges the values agree to a tenth of their standard deviation (measured: 0.03)."""
    _, true, samples, truth = every_term
    whole = fuse_model(samples, true)[0]
    fusion = ModelFusion(true)
    parts, _ = fuse_chunked(fusion, samples, chunk=500)
    assert fusion.t0_ns == int(samples.stamps[0])
    inner = np.ones(len(samples), bool)
    for edge in range(0, len(samples) + 1, 500):
        inner[max(edge - 40, 0):edge + 40] = False
    std = np.sqrt(np.einsum("nii->ni", whole.covariance[:, :3, :3]))
    assert np.all(np.abs(parts.omega[inner] - whole.omega[inner]) < 0.1 * std[inner])
    assert abs(nees(parts, truth).mean() - 9) < 4 * np.sqrt(18 / len(samples))


def test_compensation_passes_keep_saturated_gyros_saturated_not_missing():
    """A non-linear term (time offsets) makes the fusion compensate and re-fuse; a saturated gyro
    reading must stay 'saturated' in those passes (its sign starts the solver, skog2016 Sec. III),
    not become 'missing': with the whole array's gyros clipped no sample may be lost."""
    from imu_array_ros.model.layouts import grid_array32

    rng = np.random.default_rng(31)
    nominal = SensorModel.from_description(grid_array32())
    model = nominal.with_terms(time_offset=rng.normal(0, 1e-3, (32, 2)))
    samples, _ = simulate_twist(model, 2.0, 200.0, rng, rms_rate=np.deg2rad(1800.0))
    clipped = ~model.gyro_unsaturated(samples.gyro)
    every_gyro_clipped = clipped.any(axis=2).all(axis=1)
    assert every_gyro_clipped.sum() >= 5  # the case: no gyro of the sample has all axes valid
    linear, _ = ModelFusion(model, passes=0).fuse(samples)
    full, stats = ModelFusion(model).fuse(samples)
    assert len(full) == len(linear) == len(samples.stamps), (len(full), len(linear), stats)
