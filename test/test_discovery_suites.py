"""The randomised discovery suite (imu_array_ros.simulation.suites): deterministic draws, every class, effects sized
by oracle evidence, and a scorer that tells a right answer from a wrong one."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from imu_array_ros.fitting.engine import fit_terms
from imu_array_ros.model.sensor_model import SensorModel
from imu_array_ros.simulation import suites
from imu_array_ros.simulation.suites import (CLASSES, BuiltScenario, Effect, SuiteScenario, Vibration, build,
                                             draw_scenario, draw_suite, score)


def test_draws_are_deterministic_per_seed_and_cover_every_class():
    a = draw_suite(123, 3, nulls=4)
    assert a == draw_suite(123, 3, nulls=4)
    assert [s.name for s in draw_suite(124, 3, nulls=4)] != [s.name for s in a]
    assert sorted({s.cls for s in a}) == sorted(CLASSES)
    assert sum(s.cls == "null" for s in a) == 4
    # a scenario does not depend on how many others are drawn
    assert draw_scenario(123, "pair", 2) == [s for s in a if s.cls == "pair"][2]


def test_draws_respect_the_ranges():
    lo, hi = 20.0, 500.0
    scs = draw_suite(7, 12, nulls=12, evidence=(lo, hi))
    for s in scs:
        k = suites.IMUS[s.array]
        assert s.rate_hz in suites.RATES
        assert s.duration_s * s.rate_hz * k <= suites.READINGS_CAP * 1.001
        assert s.duration_s >= 8.0
        for e in s.effects:
            assert all(0 <= i < k for i in e.imus)
        targets = [e.evidence for e in s.effects] + ([s.vibration.evidence] if s.vibration else [])
        if s.cls == "pair":
            assert len(s.effects) == 2 and s.effects[0].term != s.effects[1].term
            assert s.effects[0].imus != s.effects[1].imus
            assert 3.0 <= targets[0] / targets[1] <= 10.0 and lo <= targets[1] <= hi
        elif s.cls == "both":  # a constant bias and a drift of the same sensor of one IMU
            bias, drift = s.effects
            assert bias.term == f"{s.variant}_bias" and drift.term == "bias_drift" and bias.imus == drift.imus
            cols = slice(0, 3) if s.variant == "accelerometer" else slice(3, 6)
            assert np.any(drift.direction[cols]) and not np.any(np.delete(drift.direction, np.r_[cols]))
            assert 1 / 3 <= targets[0] / targets[1] <= 3.0 and lo <= targets[1] <= hi
        elif s.cls == "null":
            assert not targets
        else:
            assert len(targets) == 1 and lo <= targets[0] <= hi
        if s.cls == "shared":
            assert s.effects[0].imus == tuple(range(k))
        if s.cls == "group":
            assert 1 < len(s.effects[0].imus) < k
        if s.cls == "vibration":
            assert 0 < s.vibration.frequency_hz <= 0.4 * s.rate_hz and max(map(abs, s.vibration.shape)) == 1.0
    assert {s.array for s in scs} == set(suites.ARRAYS)
    assert {s.still_poses for s in scs} == {True, False}
    assert {s.variant for s in scs if s.cls == "drift"} == {"drift", "constant"}
    assert {s.variant for s in scs if s.cls == "both"} == {"accelerometer", "gyroscope"}


def test_a_class_added_later_changes_no_earlier_draw():
    """Each class draws from its own stream id (suites._STREAM): the vibration and null draws are those of the
    suite before the class 'both' was added (its ids 5 and 6 then were their places in CLASSES)."""
    ids = {"vibration": 5, "null": 6}
    for cls, sid in ids.items():
        for index in range(4):
            session = suites._session(np.random.default_rng([99, sid, index, 23]), cls)
            sc = draw_scenario(99, cls, index)
            assert {key: getattr(sc, key) for key in session} == session


def _small(cls, effects=(), vibration=None, seed=5):
    return SuiteScenario("test", cls, "planar4", 100.0, False, 0.0, 0.0, 12.0, list(effects), vibration, seed)


@pytest.mark.parametrize("term", ["accelerometer_gain", "time_offset"])
def test_effects_are_sized_by_oracle_evidence(term):
    target = 150.0
    rng = np.random.default_rng(3)
    e = Effect(term, (1,), suites._direction(rng, term), target)
    b = build(_small("single", [e]))
    assert b.oracle_noise_free[0] == pytest.approx(target, rel=0.35 if term == "time_offset" else 0.02)
    # realised: the target plus a chi-square(1) -- within 4 sigma of the non-centrality
    assert abs(b.oracle[0] - target - 1.0) < 4.0 * np.sqrt(2.0 + 4.0 * target)
    # the engine's exact refit of the whole term on its IMU, on the noise-free recording, agrees with the target
    from imu_array_ros.simulation.simulator import simulate_measurements
    truth = suites._motion(b.scenario, b.nominal)
    clean = simulate_measurements(b.truth_model, truth, None, noise=False)
    fit = fit_terms(clean, b.nominal, [term], imus=[1], only={term: [1]}, sandwich=False)
    assert 2.0 * (fit.loglik_after - fit.loglik_before) == pytest.approx(b.oracle_noise_free[0], rel=0.05)


def test_vibration_is_sized_by_oracle_evidence():
    target, got = 200.0, []
    for seed in range(4):
        vib = Vibration(12.0, 0.5, (0.0, 0.0, 1.0), (1.0, -1.0, 1.0, -1.0), target)
        b = build(_small("vibration", vibration=vib, seed=seed))
        assert b.oracle_noise_free[0] == pytest.approx(target, rel=1e-6)
        assert 0 < b.amplitude < suites.MAX_VIBRATION
        got.append(b.oracle[0])
    # realised: (target + u)^2 / target with u ~ N(0, target): mean target + 1, std ~ 2 sqrt(target)
    assert abs(np.mean(got) - target - 1.0) < 3.0 * 2.0 * np.sqrt(target) / 2.0


# --------------------------------------------------------------------------------------------- the scorer

NAMES = ("imu_01", "imu_02", "imu_03", "imu_04")


def _finding(effect, ks, value=0.0):
    ks = [ks] if isinstance(ks, int) else list(ks)
    return SimpleNamespace(effect=effect, k=ks[0], sensor=NAMES[ks[0]], values=np.full(3, value), std=np.ones(3),
                           to_dict=lambda: {"sensors": [NAMES[k] for k in ks]})


def _discovery(findings=(), unexplained=()):
    return SimpleNamespace(findings=list(findings), unexplained=list(unexplained), indistinguishable=[])


def _built(cls, effects=(), vibration=None):
    sc = _small(cls, effects, vibration)
    nominal = SimpleNamespace(names=NAMES)
    n = len(effects) + (vibration is not None)
    return BuiltScenario(sc, None, nominal, None, list(effects), [np.zeros(3)] * len(effects), [100.0] * n,
                         [100.0] * n, [120.0] * n)


def test_scorer_single_and_pair():
    b = _built("single", [Effect("gyroscope_gain", (2,), (0.0,) * 3, 100.0)])
    assert score(b, _discovery([_finding("gyroscope_gain", 2)]))["correct"]
    r = score(b, _discovery([_finding("gyroscope_gain", 2), _finding("gyroscope_bias", 2)]))
    assert not r["correct"] and r["false_findings"] == ["gyroscope_bias@imu_03"]
    assert not score(b, _discovery([_finding("gyroscope_gain", 1)]))["correct"]
    assert not score(b, _discovery())["correct"]
    p = _built("pair", [Effect("time_offset", (0,), (0.0,) * 2, 900.0), Effect("position", (3,), (0.0,) * 3, 100.0)])
    assert score(p, _discovery([_finding("time_offset", 0), _finding("position", 3)]))["correct"]
    r = score(p, _discovery([_finding("time_offset", 0)]))
    assert not r["correct"] and r["detected"] == [True, False] and r["power_evidence"] == 120.0


def test_scorer_counts_a_kept_sample_clock_as_a_false_finding():
    # the suite's recordings have exact stamps: a clock the timing stage keeps (--apply writes it) is false
    from imu_array_ros.discovery.timing import ClockFinding, TimingDiscovery

    b = _built("single", [Effect("gyroscope_gain", (2,), (0.0,) * 3, 100.0)])
    d = _discovery([_finding("gyroscope_gain", 2)])
    d.timing = TimingDiscovery(None, findings=[ClockFinding("accelerometer", 1, NAMES[1], 1e-3, 800.0, 9.0)])
    r = score(b, d)
    assert not r["correct"] and r["clocks"] == ["accelerometer_sample_clock@imu_02"]
    assert r["false_findings"] == ["accelerometer_sample_clock@imu_02"]
    d.timing.findings = []  # dropped (or never found): correct again
    assert score(b, d)["correct"]
    n = _built("null")
    d = _discovery()
    d.timing = TimingDiscovery(None, findings=[ClockFinding("gyroscope", 0, NAMES[0], 1e-3, -900.0, 12.0)])
    assert not score(n, d)["correct"]


def test_scorer_shared_scope_per_imu_or_shared_finding():
    b = _built("shared", [Effect("accelerometer_gain", (0, 1, 2, 3), (0.0,) * 3, 100.0)])
    assert score(b, _discovery([_finding("accelerometer_gain", k) for k in range(4)]))["correct"]
    assert score(b, _discovery([_finding("accelerometer_gain", range(4))]))["correct"]
    assert not score(b, _discovery([_finding("accelerometer_gain", k) for k in range(3)]))["correct"]
    g = _built("group", [Effect("accelerometer_gain", (1, 3), (0.0,) * 3, 100.0)])
    assert score(g, _discovery([_finding("accelerometer_gain", (1, 3))]))["correct"]
    assert not score(g, _discovery([_finding("accelerometer_gain", range(4))]))["correct"]


def test_scorer_names_a_wrong_answer_whose_stated_alternative_is_the_truth():
    """The effect on IMUs 0, 1 reported on 2, 3 with 'indistinguishable from 0, 1': not correct, but the named
    alternative is; an alternative that is also wrong, or none, is not marked."""
    g = _built("group", [Effect("gyroscope_bias", (0, 1), (0.0,) * 3, 400.0)])
    d = _discovery([_finding("gyroscope_bias", (2, 3))])
    assert not score(g, d)["correct"] and not score(g, d)["named_alternative"]
    alt = lambda ks: {"effect": "gyroscope_bias", "sensors": [NAMES[k] for k in ks]}  # noqa: E731
    d.indistinguishable = [{"effects": ["gyroscope_bias"] * 2, "alternatives": [alt((2, 3)), alt((0, 1))]}]
    r = score(g, d)
    assert not r["correct"] and r["named_alternative"]
    d.indistinguishable = [{"effects": ["gyroscope_bias"] * 2, "alternatives": [alt((2, 3)), alt((1, 2))]}]
    assert not score(g, d)["named_alternative"]
    right = _discovery([_finding("gyroscope_bias", (0, 1))])
    right.indistinguishable = [{"effects": ["gyroscope_bias"] * 2, "alternatives": [alt((0, 1)), alt((2, 3))]}]
    assert score(g, right)["correct"] and not score(g, right)["named_alternative"]


def test_scorer_vibration_and_null():
    vib = Vibration(20.0, 0.5, (0.0, 0.0, 1.0), (0.5, -1.0, 0.5, -0.5), 100.0)
    b = _built("vibration", vibration=vib)
    entry = {"sensors": ["imu_02", "imu_01"], "axes": ["acc_z"], "band_hz": [15.0, 25.0]}
    assert score(b, _discovery(unexplained=[entry]))["correct"]
    assert not score(b, _discovery([_finding("axis_offsets", 1)], [entry]))["correct"]  # forced into a term
    elsewhere = dict(entry, band_hz=[1.0, 5.0])
    assert not score(b, _discovery(unexplained=[elsewhere]))["correct"]
    assert not score(b, _discovery(unexplained=[dict(entry, sensors=["imu_03"])]))["correct"]
    tie = _built("vibration", vibration=Vibration(20.0, 0.5, (0.0, 0.0, 1.0), (1.0, 0.5, -1.0, 0.5), 100.0))
    assert score(tie, _discovery(unexplained=[dict(entry, sensors=["imu_03"])]))["correct"]  # imu_01, imu_03 tie
    assert not score(tie, _discovery(unexplained=[dict(entry, sensors=["imu_02", "imu_04"])]))["correct"]
    n = _built("null")
    assert score(n, _discovery(unexplained=[entry]))["correct"]
    assert not score(n, _discovery([_finding("gyroscope_bias", 0)]))["correct"]


def test_magnitudes_of_a_time_offset_on_every_imu_are_modulo_the_gauge_of_time():
    b = _built("shared", [Effect("time_offset", (0, 1, 2, 3), (0.0,) * 2, 100.0)])
    b.values[0] = np.array([1e-3, 3e-3])  # truth: accelerometer 1 ms, gyroscope 3 ms
    f = SimpleNamespace(effect="time_offset", k=0, sensor=NAMES[0], imus=(0, 1, 2, 3), values=np.array([0.0, 2e-3]),
                        std=np.array([1e-5, 1e-5]), to_dict=lambda: {"sensors": list(NAMES)})
    assert score(b, _discovery([f]))["max_abs_z"]["time_offset@imu_01"] < 1e-6  # shifted by 1 ms: the gauge
    f.values = np.array([0.0, 2.5e-3])  # the lag is wrong by 0.5 ms = 50 sigma
    assert score(b, _discovery([f]))["max_abs_z"]["time_offset@imu_01"] > 20
    one = SimpleNamespace(**{**vars(f), "imus": (0,)})  # on one IMU the others fix the gauge: no shift removed
    one.values = np.array([0.0, 2e-3])
    assert score(b, _discovery([one]))["max_abs_z"]["time_offset@imu_01"] > 50


def test_magnitudes_of_a_pooled_gain_are_its_change_from_nominal():
    """A pooled finding reports the change from the nominal model (a gain's nominal is 1), a per-IMU one the
    model's value: both compared with the truth in their own convention."""
    b = _built("group", [Effect("accelerometer_gain", (1, 3), (0.0,) * 3, 100.0)])
    b.values[0] = np.array([1.002, 0.999, 1.001])
    b = BuiltScenario(b.scenario, None, SimpleNamespace(names=NAMES, terms={
        "accelerometer_gain": SimpleNamespace(values=np.ones((4, 3)))}), None, b.effects, b.values, b.oracle_target,
        b.oracle_noise_free, b.oracle)
    std = np.full(3, 1e-4)
    label = "imu_02,imu_04 shared"
    pooled = SimpleNamespace(effect="accelerometer_gain", k=1, sensor=label, scope=label, imus=(1, 3),
                             values=np.array([0.002, -0.001, 0.001]), std=std,
                             to_dict=lambda: {"sensors": ["imu_02", "imu_04"]})
    assert score(b, _discovery([pooled]))["max_abs_z"][f"accelerometer_gain@{label}"] < 1e-6
    own = SimpleNamespace(effect="accelerometer_gain", k=1, sensor="imu_02", values=np.array([1.0023, 0.999, 1.001]),
                          std=std, to_dict=lambda: {"sensors": ["imu_02"]})
    assert abs(score(b, _discovery([own]))["max_abs_z"]["accelerometer_gain@imu_02"] - 3.0) < 1e-6


def test_unseen_draws_use_arrays_and_rates_the_suite_never_draws():
    """unseen=True: a random array (5-16 IMUs, 3D positions within 4 cm, orientations off the identity) at a rate
    outside suites.RATES, deterministic per (seed, class, index), its own stream: the default draw is unchanged."""
    scs = draw_suite(31, 3, nulls=3, unseen=True)
    assert scs == draw_suite(31, 3, nulls=3, unseen=True)
    for s in scs:
        assert s.array.startswith("random-") and s.rate_hz in suites.UNSEEN_RATES and s.rate_hz not in suites.RATES
        d = suites.array_description(s.array)
        k = suites.imu_count(s.array)
        assert 5 <= k <= 16 and len(d.imus) == k
        rot = SensorModel.from_description(d).rotations
        assert np.all(np.abs(np.trace(rot, axis1=1, axis2=2) - 3.0) > 1e-6)  # every IMU rotated
        assert np.ptp(d.positions, axis=0).min() > 1e-3 and np.abs(d.positions).max() <= 0.02
        assert s.duration_s * s.rate_hz * k <= suites.READINGS_CAP * 1.001
        for e in s.effects:
            assert all(0 <= i < k for i in e.imus)
    assert len({s.array for s in scs}) == len(scs)
    assert draw_scenario(31, "pair", 1) != draw_scenario(31, "pair", 1, unseen=True)
    assert draw_scenario(31, "pair", 1).array in suites.ARRAYS
