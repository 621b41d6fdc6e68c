"""Sample-clock search on recordings with exact stamps but a library term the model lacks: the misfit's "delays"
beat with the twisting and peaked like a sawtooth (helper-58: seed 733850's whole-pipeline nulls 902, 909), at an
amplitude no sawtooth of the searched period has (timing.clocks: AMPLITUDE_Z); and the search's divide by zero."""

import warnings

import numpy as np

from imu_array_ros.model.layouts import grid_array32, planar_square4
from imu_array_ros.model.sensor_model import SensorModel
from imu_array_ros.simulation.perturb import TERM_TEST_SIZES
from imu_array_ros.simulation.simulator import simulate_twist
from imu_array_ros.timing.clocks import find_sample_clocks

MISFIT_TERMS = ("accelerometer_gain", "gyroscope_gain", "accelerometer_misalignment", "gyroscope_misalignment",
                "position", "gyroscope_g_sensitivity")


def _misaligned(layout, k, scale, seed, rate, duration):
    """A twisting recording (exact stamps, no clock) whose IMU k has a gyroscope misalignment ``scale`` x its
    test size the model lacks: (model, samples)."""
    model = SensorModel.from_description(layout())
    rng = np.random.default_rng(seed)
    v = model.terms["gyroscope_misalignment"].values.copy()
    v[k] += rng.normal(size=v[k].shape) * TERM_TEST_SIZES["gyroscope_misalignment"] * scale
    samples, _ = simulate_twist(model.with_terms(gyroscope_misalignment=v), duration, rate, rng)
    return model, samples


def _clocks(model, samples):
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)  # the search's divide by zero (periods of 0) is gone
        search = find_sample_clocks(samples, model)
    return {s: int(f.sum()) for s, f in search.found.items()}, search


def test_a_missing_misalignment_on_one_of_four_is_no_sample_clock():
    # seed 733850909's recording as benchmarks/discovery_modes.py --pipeline draws it (planar4, 62.5 Hz, 21 s): all
    # four IMUs had a gyroscope clock (12-59x the spectrum's median; amplitude 1.7-2.6 x T / 2 pi)
    rng = np.random.default_rng([733850909, 3])
    array, term = str(rng.choice(["planar4", "corners8", "grid32"])), str(rng.choice(MISFIT_TERMS))
    assert (array, term) == ("planar4", "gyroscope_misalignment")
    model = SensorModel.from_description(planar_square4())
    v = model.terms[term].values.copy()
    k = int(rng.integers(model.n_imus))
    v[k] += rng.normal(size=v[k].shape) * TERM_TEST_SIZES[term] * rng.uniform(1.0, 5.0)
    assert rng.random() >= 0.3  # twisting, not still poses
    rate = float(rng.choice([62.5, 100.0, 200.0, 500.0, 1000.0]))
    samples, _ = simulate_twist(model.with_terms(**{term: v}), float(min(rng.uniform(10.0, 30.0), 120_000 / (rate * 4))),
                                rate, rng)
    found, search = _clocks(model, samples)
    assert found == {"gyroscope": 0, "accelerometer": 0}, search.notes
    assert any("above a sawtooth's amplitude" in n for n in search.notes)


def test_a_missing_misalignment_on_one_of_32_and_its_mirror_on_the_others():
    # 32 IMUs, one misaligned: its excess, and its mirror on the other 31 through the relative delays
    model, samples = _misaligned(grid_array32, 19, 4.0, 20261129, 100.0, 12.0)
    found, search = _clocks(model, samples)
    assert found == {"gyroscope": 0, "accelerometer": 0}, search.notes


def _drawn(seed):
    """benchmarks/discovery_modes.py --pipeline's recording ``seed`` (a twisting one): (model, truth, samples)."""
    from imu_array_ros.model.description import load_description
    arrays = {"planar4": planar_square4, "corners8": lambda: load_description("config/mimu4444bt_corners.yaml"),
              "grid32": grid_array32}
    rng = np.random.default_rng([seed, 3])
    array, term = str(rng.choice(list(arrays))), str(rng.choice(MISFIT_TERMS))
    model = SensorModel.from_description(arrays[array]())
    v = model.terms[term].values.copy()
    k = int(rng.integers(model.n_imus))
    v[k] += rng.normal(size=v[k].shape) * TERM_TEST_SIZES[term] * rng.uniform(1.0, 5.0)
    assert rng.random() >= 0.3  # twisting, not still poses
    rate = float(rng.choice([r for r in (62.5, 100.0, 200.0, 500.0, 1000.0) if 8.0 * r * model.n_imus <= 120_000]))
    truth = model.with_terms(**{term: v})
    samples, _ = simulate_twist(truth, float(min(rng.uniform(10.0, 30.0), 120_000 / (rate * model.n_imus))), rate, rng)
    return model, truth, samples


def test_clocks_standing_in_for_a_missing_gain_are_not_found_again_given_it():
    # 733850900 (corners8, 1 kHz, an accelerometer gain missing on imu_5): accelerometer clocks on two IMUs at
    # 8.0-8.1x (8 needed), amplitude ~1 x T / 2 pi (the amplitude rule cannot tell); given the gain, none
    from imu_array_ros.discovery.timing import ClockFinding, TimingDiscovery, retest_clocks

    model, truth, samples = _drawn(733850900)
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)  # no invalid remainder for chips without a clock (period 0)
        search = find_sample_clocks(samples, model, sensors=("accelerometer",))
    found = search.found["accelerometer"]
    assert found.any()  # the stand-in, before the library term is known
    timing = TimingDiscovery(model, findings=[ClockFinding("accelerometer", int(k), model.names[k], 1e-3,
                                                           float(search.rates["accelerometer"][k]), 8.0)
                                              for k in np.flatnonzero(found)])
    assert retest_clocks(samples, truth, timing) == timing.findings


def test_real_clocks_are_found_again_under_a_model_with_a_library_finding():
    from conftest import gyro_chip_clocks
    from imu_array_ros.discovery.timing import timing_stage, retest_clocks
    from imu_array_ros.model.description import load_description

    nominal = SensorModel.from_description(load_description("config/mimu4444bt_corners.yaml"))
    rng = np.random.default_rng(5)
    k = nominal.n_imus
    bias = nominal.terms["gyroscope_bias"].values.copy()
    bias[2] = (0.01, -0.01, 0.005)
    with_bias = nominal.with_terms(gyroscope_bias=bias)
    true = with_bias.with_terms(gyroscope_sample_clock=gyro_chip_clocks(k, rng),
                                time_offset=np.column_stack([np.full(k, -1.6e-3), np.zeros(k)]))
    samples, _ = simulate_twist(true, 20.0, 62.5, rng, start_ns=10**9)
    timing = timing_stage(samples, nominal)
    assert len(timing.findings) >= 6
    assert retest_clocks(samples, with_bias, timing) == []
    assert retest_clocks(samples, timing.model.with_terms(gyroscope_bias=bias), timing) == []


def test_discover_drops_the_clocks_that_stood_in_for_its_findings():
    # 733850900: the timing stage takes two accelerometer clocks (imu_3, imu_4) for the missing gain on imu_6; given
    # the gain the search does not find them again, so discover drops them (and what they brought in) and keeps the gain
    import json

    from imu_array_ros.discovery.discover import DiscoveryOptions, discover
    from imu_array_ros.timing.session import active_clocks

    model, truth, samples = _drawn(733850900)
    d = discover(samples, model, options=DiscoveryOptions(terms=("accelerometer_gain",), empirical=False))
    assert [(f.effect, f.sensor) for f in d.findings] == [("accelerometer_gain", "imu_6")]
    assert d.timing.findings == [] and not d.timing.used
    assert sorted((f.imu, f.sensor) for f in d.timing.dropped) == [("imu_3", "accelerometer"), ("imu_4", "accelerometer")]
    assert active_clocks(d.model) == []  # --apply writes no clock
    # ... nor the time offsets the clock search moved the sawtooths' constant parts into
    np.testing.assert_array_equal(d.model.terms["time_offset"].values, model.terms["time_offset"].values)
    assert any("not found again given the library findings" in n for n in d.notes)
    report = json.loads(json.dumps(d.to_dict(), allow_nan=False, default=float))
    assert [c["sensors"] for c in report["timing"]["dropped_given_findings"]] == [["imu_3"], ["imu_4"]]
    from imu_array_ros.discovery.report import markdown
    text = markdown(d)
    assert "No sample clock kept." in text and "then dropped" in text and "on imu_3 (accelerometer)" in text
    # the gain the findings hold, within 3 sigma of the truth
    f = d.findings[0]
    assert np.all(np.abs(f.values - truth.terms["accelerometer_gain"].values[5]) < 3 * f.std)
