"""Each sample's reading rates within the chips' clock spread (fitting/reading_rates.py): the engine's motion
coordinates when the motion changes within the spread by more than the read rate follows, and discovery's
decision to use them."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from imu_array_ros.discovery.timing import timing_stage
from imu_array_ros.fitting.engine import fit_motion, fit_terms
from imu_array_ros.fitting.reading_rates import keep_rates, rates_on, rates_scope, reading_rates
from imu_array_ros.model.description import load_description
from imu_array_ros.model.sensor_model import SensorModel
from imu_array_ros.simulation.clocks import mimu_like_clocks
from imu_array_ros.simulation.motion import TwistTrajectory
from imu_array_ros.simulation.simulator import simulate_trajectory

ROOT = Path(__file__).resolve().parents[1]
#: 62.5 Hz reads, as the MIMU4444BT captures
STAMPS = (np.arange(250) * 16_000_000).astype(np.int64)


@pytest.fixture(scope="module")
def corners() -> SensorModel:
    return SensorModel.from_description(load_description(ROOT / "config/mimu4444bt_corners.yaml"))


def twist(rng, fast: float) -> TwistTrajectory:
    """Hand-like twisting (~1 Hz) plus, scaled by ``fast``, components at 34-43 Hz: above the 31 Hz the reads
    can follow, within what a ~1 kHz chip clock samples."""
    a = np.array([[8.0, 1.4], [6.0, 1.2], [7.0, 1.3]]) * [1.0, fast]
    f = np.array([[1.1, 34.0], [1.7, 38.0], [0.9, 41.0]])
    sa = np.array([[2.0, 8.0], [2.0, 7.0], [2.0, 9.0]]) * [1.0, fast]
    sf = np.array([[0.7, 36.0], [1.2, 43.0], [0.5, 39.0]])
    return TwistTrajectory(a, f, rng.uniform(0, 2 * np.pi, (3, 2)), sa, sf, rng.uniform(0, 2 * np.pi, (3, 2)),
                           np.array([1.0, 0.0, 0.0, 0.0]))


def recording(corners, seed: int, fast: float):
    rng = np.random.default_rng(seed)
    clocked = mimu_like_clocks(corners, rng, acc_lag=0.8e-3, gyro_lag=2.9e-3)
    return clocked, simulate_trajectory(clocked, twist(rng, fast), STAMPS, rng)[0]


def test_rates_absorb_motion_faster_than_the_reads_and_keep_time_offsets_honest(corners):
    clocked, samples = recording(corners, 11, fast=1.0)
    motion, ll0, z0 = fit_motion(samples, clocked)
    with reading_rates():
        _, ll1, z1 = fit_motion(samples, clocked, motion)
    assert np.nanmean(z1 ** 2) < np.nanmean(z0 ** 2) / 5  # ~77 -> ~7 on this motion
    truth = clocked.terms["time_offset"].values
    for on, worst in ((False, 10.0), (True, 4.0)):
        with reading_rates(on):
            fit = fit_terms(samples, clocked, ["time_offset"], motion0=motion, max_iterations=10)
        err = fit.model.terms["time_offset"].values - truth
        std = fit.std["time_offset"]
        rel = np.abs(err - err[0]) / np.where(np.isfinite(std) & (std > 0), std, np.inf)  # the reference's gauge
        assert (np.nanmax(rel) > worst) if not on else (np.nanmax(rel) < worst), (on, np.nanmax(rel))


def test_time_offsets_with_reading_rates_converge_in_few_iterations(corners):
    # from zero offsets the back-substituted motion of the undamped step raised the cost, and the damped steps
    # crept on: 75 iterations here (the first round stopped at 50 unconverged) before the motion followed a
    # failed step by a Gauss-Newton step of its own at the new parameters (fitting/optimiser.py); 17 after
    clocked, samples = recording(corners, 12, fast=1.0)
    start = clocked.with_terms(time_offset=np.zeros_like(clocked.terms["time_offset"].values))
    motion, _, _ = fit_motion(samples, start)
    with reading_rates():
        fit = fit_terms(samples, start, ["time_offset"], motion0=motion, max_iterations=50)
    assert fit.converged and fit.iterations < 40, fit.iterations

def test_without_sample_clocks_nothing_changes(corners):
    rng = np.random.default_rng(3)
    samples = simulate_trajectory(corners, twist(rng, 1.0), STAMPS, rng)[0]
    a = fit_motion(samples, corners)
    with reading_rates():
        b = fit_motion(samples, corners)
    assert a[1] == b[1] and np.array_equal(a[0], b[0])


def test_discovery_keeps_rates_only_when_the_recording_wants_them_and_only_in_its_scope(corners):
    assert not keep_rates(True) and not rates_on()  # outside a scope nothing switches
    for fast, wanted in ((0.0, False), (1.0, True)):
        clocked, samples = recording(corners, 7, fast)
        with rates_scope():
            out = timing_stage(samples, clocked)
            assert out.rates["kept"] is wanted and rates_on() is wanted, out.rates
        assert not rates_on()
