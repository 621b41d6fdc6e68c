"""Discovery of timing physics (sample clocks, by search) and of drift vs constant biases (issue 23, items 5, 2).

Every recording is simulated from a fixed seed: the 8 corner IMUs of the MIMU4444BT layout.
"""

from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from imu_array_ros.discovery.discover import DiscoveryOptions, discover
from imu_array_ros.discovery.drift import drift_confounded
from imu_array_ros.discovery.report import write_report
from imu_array_ros.discovery.timing import timing_stage
from imu_array_ros.model.description import load_description
from imu_array_ros.model.sensor_model import SensorModel
from imu_array_ros.simulation.icosahedron import simulate_icosahedron
from imu_array_ros.simulation.simulator import simulate_twist

ROOT = Path(__file__).resolve().parents[1]
CORNERS = str(ROOT / "config" / "mimu4444bt_corners.yaml")
BIAS_TERMS = ("accelerometer_bias", "gyroscope_bias", "bias_drift")


@pytest.fixture(scope="module")
def nominal():
    return SensorModel.from_description(load_description(CORNERS))


def _session(model, seed=3):
    """Still poses, then 10 s of twisting, 100 Hz."""
    s, _, _ = simulate_icosahedron(model, np.random.default_rng(seed), rate_hz=100.0, still_s=0.5,
                                   transition_s=0.5, twist_s=10.0)
    return s


def _with(nominal, bias=False, drift=False, k=2):
    m = nominal
    if bias:
        a, g = m.terms["accelerometer_bias"].values.copy(), m.terms["gyroscope_bias"].values.copy()
        a[k], g[k] = (0.03, -0.02, 0.02), (0.004, -0.003, 0.002)
        m = m.with_terms(accelerometer_bias=a, gyroscope_bias=g)
    if drift:
        d = m.terms["bias_drift"].values.copy()
        d[k] = (0.002, -0.0015, 0.001, 0.0003, -0.0002, 0.0002)
        m = m.with_terms(bias_drift=d)
    return m


def _found(nominal, model):
    opts = DiscoveryOptions(terms=BIAS_TERMS, empirical=False, heldout=False, timing=False, max_findings=4)
    d = discover(_session(model), nominal, options=opts)
    return {(f.effect, f.sensor) for f in d.findings}, d


def test_constant_bias_is_a_bias_not_a_drift(nominal):
    """Accelerometer and gyroscope biases on imu_3: both found as biases, no drift anywhere (before the fix,
    a drift explained both biases at once with the lower BIC and was found first)."""
    found, d = _found(nominal, _with(nominal, bias=True))
    assert found == {("accelerometer_bias", "imu_3"), ("gyroscope_bias", "imu_3")}
    assert not d.indistinguishable


def test_drift_is_a_drift(nominal):
    found, _ = _found(nominal, _with(nominal, drift=True))
    assert ("bias_drift", "imu_3") in found
    assert all(s == "imu_3" for _, s in found)


def test_bias_and_drift_both(nominal):
    found, _ = _found(nominal, _with(nominal, bias=True, drift=True))
    assert {("accelerometer_bias", "imu_3"), ("gyroscope_bias", "imu_3"), ("bias_drift", "imu_3")} <= found
    assert all(s == "imu_3" for _, s in found)


def test_null_finds_nothing(nominal):
    found, _ = _found(nominal, nominal)
    assert found == set()


def _blocks_sb(times, theta, seed=0, per_block=1e4):
    """A ScoreBlocks-like object for one IMU with accelerometer_bias (3) and bias_drift (6) columns: blocks at
    ``times`` (s), each seeing the bias and its drift (t) with information ``per_block`` per axis; g = the
    information times ``theta`` (bias (3), accelerometer drift (3)) plus unit-information noise."""
    rng = np.random.default_rng(seed)
    offsets = {"accelerometer_bias": 0, "bias_drift": 3}
    nb = len(times)
    S, g = np.zeros((nb, 1, 9, 9)), np.zeros((nb, 1, 9))
    for b, t in enumerate(times):
        x = np.zeros((3, 9))
        x[:, 0:3] = np.eye(3)
        x[:, 3:6] = t * np.eye(3)
        S[b, 0] = per_block * x.T @ x
        full = np.r_[theta[:3], theta[3:], np.zeros(3)]
        g[b, 0] = S[b, 0] @ full + np.sqrt(per_block) * x.T @ rng.standard_normal(3)
    cols = {"accelerometer_bias": slice(0, 3), "bias_drift": slice(3, 9)}
    return SimpleNamespace(offsets=offsets, g=g, S=S, valid_axes=10_000, columns=lambda t: cols[t])


def test_drift_indistinguishable_when_the_information_lies_in_a_short_span():
    """A bias seen only within 1 s of a 60 s recording cannot be told from a drift: reported as
    indistinguishable with why; the same bias seen throughout the recording is told apart."""
    best = SimpleNamespace(effect="accelerometer_bias", k=0, sensor="imu_1")
    theta = np.array([0.02, -0.01, 0.015, 0.0, 0.0, 0.0])
    sb = _blocks_sb(np.linspace(30.0, 31.0, 3), theta)
    out = drift_confounded(sb, best, 1e-3, 0.5)
    assert len(out) == 1 and out[0]["effect"] == "bias_drift"
    assert out[0]["correlation"] > 0.99 and "why" in out[0]["reason"]
    spread = _blocks_sb(np.arange(0.0, 60.0, 0.5), theta)
    assert drift_confounded(spread, best, 1e-3, 0.5) == []


def _gyro_clocks(nominal, rng):
    k = nominal.n_imus
    c = np.column_stack([np.full(k, 1e-3), rng.uniform(-3000, 3000, k), np.zeros(k)])
    c[:, 2] = rng.uniform(0, 1, k) * c[:, 0] / (1 + c[:, 1] * 1e-6)
    return nominal.with_terms(gyroscope_sample_clock=c,
                              time_offset=np.column_stack([np.full(k, -1.6e-3), np.zeros(k)])), c


def test_gyroscope_clocks_found_reported_and_applied(nominal, tmp_path):
    """MIMU-like gyroscope chip clocks (1 ms, +-3000 ppm, random phases; 62.5 Hz reads): found on all 8 IMUs
    at their rates, none on the accelerometers; the report names them with the plot; the model discovery
    returns (what --apply writes) carries the periods and rates."""
    rng = np.random.default_rng(11)
    true, clock = _gyro_clocks(nominal, rng)
    s, _ = simulate_twist(true, 20.0, 62.5, rng, start_ns=10**9)
    opts = DiscoveryOptions(terms=("gyroscope_bias",), empirical=False, heldout=False, max_findings=1)
    d = discover(s, nominal, options=opts)
    t = d.timing
    assert t.tested and t.used and t.delta_loglik > 0
    gyro = sorted((f.k, f.rate_ppm) for f in t.findings if f.sensor == "gyroscope")
    assert [k for k, _ in gyro] == list(range(8))
    assert not [f for f in t.findings if f.sensor == "accelerometer"]
    # a rate is identified when the sawtooth wraps within the recording: its beat against the 62.5 Hz reads,
    # 1 kHz x |rate| 1e-6, at least 2 / duration (|rate| >= 100 ppm over 20 s); this seed has one chip at -4 ppm
    beats = np.abs(clock[:, 1]) >= 100.0
    assert beats.sum() == 7
    rates = np.array([r for _, r in gyro])
    np.testing.assert_allclose(rates[beats], clock[beats, 1], atol=10.0)
    written = d.model.terms["gyroscope_sample_clock"].values
    np.testing.assert_allclose(written[:, 0], 1e-3)
    np.testing.assert_allclose(written[beats, 1], clock[beats, 1], atol=10.0)
    desc = d.model.to_description(load_description(CORNERS), names=["gyroscope_sample_clock"])
    text = str(desc.imus[0])
    assert "clock_rate" in text and "clock_phase" not in text  # the phase is a session state
    paths = write_report(d, tmp_path, plots=True)
    md = (tmp_path / "report.md").read_text()
    assert "sample clock of period 1 ms on imu_1 (gyroscope)" in md
    assert any(p.name == "timing.png" for p in paths)


@pytest.mark.parametrize("seed", [21, 22, 23])
def test_no_clock_no_finding(nominal, seed):
    """Null recordings (no clock, no time offset; 62.5 and 100 Hz): no clock found, the model unchanged."""
    rng = np.random.default_rng(seed)
    s, _ = simulate_twist(nominal, 20.0, 62.5 if seed % 2 else 100.0, rng, start_ns=10**9)
    t = timing_stage(s, nominal)
    assert t.tested and not t.findings and t.model is nominal
    assert max(float(v.max()) for v in t.snr.values()) < 8.0


def _fake_fit(nominal, bias_z, drift_z, std=1e-4):
    """A joint exact fit (FitResult-like) of gyroscope_bias and bias_drift on imu_1: values bias_z and drift_z
    CRB std from the nominal, independent parameters."""
    theta = np.r_[np.full(3, bias_z * std), np.full(6, drift_z * std)]
    gb, dr = nominal.terms["gyroscope_bias"].values.copy(), nominal.terms["bias_drift"].values.copy()
    gb[0], dr[0] = theta[:3], theta[3:]
    sd = {"gyroscope_bias": np.full((8, 3), np.nan), "bias_drift": np.full((8, 6), np.nan)}
    sd["gyroscope_bias"][0], sd["bias_drift"][0] = std, std
    return SimpleNamespace(free=("gyroscope_bias", "bias_drift"), imus=("imu_1",), theta=theta,
                           covariance=np.eye(9) * std ** 2, model=nominal.with_terms(gyroscope_bias=gb, bias_drift=dr),
                           std=sd, motion=np.zeros((4, 9)), gauge_directions=np.zeros((9, 0)))


def _fake_finding(effect, step):
    return SimpleNamespace(effect=effect, k=0, imus=(0,), scope="imu", step=step, sensor="imu_1",
                           candidate=SimpleNamespace(sensors=("imu_1",), accepted=True, note=""),
                           values=None, std=None)


def test_backward_elimination_drops_a_finding_the_others_make_redundant(nominal, monkeypatch):
    """A bias found first, then its drift: at the joint fit the bias is 0.5 std from the start (p ~ 0.9 on 3
    dof) and is dropped (reported, the others refitted without it); the drift (20 std) stays.  A bias still
    significant given the drift (8 std) is kept and nothing is refitted."""
    from imu_array_ros.discovery import confirm, eliminate

    calls = []

    def refit(samples, model, free, **kw):
        calls.append((list(free), kw["only"]))
        assert np.all(model.terms["gyroscope_bias"].values[0] == nominal.terms["gyroscope_bias"].values[0])
        return _fake_fit(nominal, 0.0, 20.0)

    monkeypatch.setattr(confirm, "fit_terms", refit)  # the exact refit (confirm.refit, which eliminate calls)
    levels = [1e-3, 1e-3]
    found = [_fake_finding("gyroscope_bias", 1), _fake_finding("bias_drift", 2)]
    kept, dropped, _, model, _ = eliminate.backward_eliminate(None, nominal, found, _fake_fit(nominal, 0.5, 20.0),
                                                              np.zeros((4, 9)), levels, 0.01)
    assert [f.effect for f in kept] == ["bias_drift"]
    assert [r["effect"] for r in dropped] == ["gyroscope_bias"] and dropped[0]["p"] > 0.5
    assert "given the other findings" in dropped[0]["reason"] and not found[0].candidate.accepted
    assert calls == [(["bias_drift"], {"bias_drift": [0]})]
    np.testing.assert_allclose(kept[0].values, 20.0 * 1e-4)
    found = [_fake_finding("gyroscope_bias", 1), _fake_finding("bias_drift", 2)]
    kept, dropped, _, _, _ = eliminate.backward_eliminate(None, nominal, found, _fake_fit(nominal, 8.0, 20.0),
                                                          np.zeros((4, 9)), levels, 0.01)
    assert len(kept) == 2 and not dropped and len(calls) == 1


def test_backward_elimination_retests_at_alpha_over_the_findings(nominal, monkeypatch):
    """A bias admitted at a strict step level (1e-5: alpha over that step's candidates), given the drift found
    after it 2.5 std per axis from the start (W 18.75 on 3 dof, p 3.1e-4): a real effect the drift took most of
    the information of.  Re-tested at the larger of its admission level and alpha / 2 findings (0.005) it is kept;
    at p above alpha / 2 it is dropped, and the reason names both levels."""
    from imu_array_ros.discovery import confirm, eliminate

    monkeypatch.setattr(confirm, "fit_terms", lambda *a, **k: _fake_fit(nominal, 0.0, 20.0))
    assert eliminate.backward_level(1e-5, 0.01, 2) == 0.005 and eliminate.backward_level(0.01, 0.01, 4) == 0.01
    found = [_fake_finding("gyroscope_bias", 1), _fake_finding("bias_drift", 2)]
    kept, dropped, _, _, _ = eliminate.backward_eliminate(None, nominal, found, _fake_fit(nominal, 2.5, 20.0),
                                                          np.zeros((4, 9)), [1e-5, 1e-5], 0.01)
    assert len(kept) == 2 and not dropped
    found = [_fake_finding("gyroscope_bias", 1), _fake_finding("bias_drift", 2)]
    kept, dropped, _, _, _ = eliminate.backward_eliminate(None, nominal, found, _fake_fit(nominal, 1.9, 20.0),
                                                          np.zeros((4, 9)), [1e-5, 1e-5], 0.01)
    assert [r["effect"] for r in dropped] == ["gyroscope_bias"] and 0.005 < dropped[0]["p"] < 0.05
    assert "admitted at, 1e-05, and alpha / 2 findings" in dropped[0]["reason"]


def test_exact_fits_say_their_progress_and_the_cap_is_noted(nominal, monkeypatch):
    """The exact refits say their iterations (throttled; here every one) and a search ended by max_findings
    says so in the notes; a search that ends by itself does not."""
    from imu_array_ros.discovery import confirm

    monkeypatch.setattr(confirm, "PROGRESS_S", 0.0)
    said = []
    opts = DiscoveryOptions(terms=BIAS_TERMS, empirical=False, heldout=False, timing=False, max_findings=1)
    d = discover(_session(_with(nominal, bias=True)), nominal, options=opts, progress=said.append)
    assert len(d.findings) == 1
    assert any(t.startswith("exact fit of ") and ": iteration 1, cost " in t for t in said)
    assert any("stopped at its cap of 1 findings" in n for n in d.notes)
    opts.max_findings = 4
    d = discover(_session(_with(nominal, bias=True)), nominal, options=opts)
    assert len(d.findings) == 2 and not any("cap of" in n for n in d.notes)
