"""Mismatch discovery: the engine's score blocks, the tests' calibration, concealed effects, the command line.

The fast subset of the committed suite (benchmarks/discovery_suite.py) runs here; every recording is
simulated from a fixed seed.
"""

from __future__ import annotations

import json
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import yaml

from conftest import assert_user_error, cli
from imu_array_ros.discovery.discover import DiscoveryOptions, discover
from imu_array_ros.discovery.explain import evaluate_candidates
from imu_array_ros.fitting.engine import fit_motion, fit_terms, score_blocks
from imu_array_ros.model.description import load_description
from imu_array_ros.model.sensor_model import SensorModel
from imu_array_ros.model.terms import candidate_names
from imu_array_ros.simulation.concealed import Scenario, build, score, standard_suite

ROOT = Path(__file__).resolve().parents[1]
CORNERS = str(ROOT / "config" / "mimu4444bt_corners.yaml")


@pytest.fixture(scope="module")
def nominal():
    return SensorModel.from_description(load_description(CORNERS))


def _bias_recording(nominal, bias=(0.02, -0.01, 0.015), k=2, seed=3):
    """A session (still poses, then twisting) of the nominal array with an accelerometer bias on IMU k."""
    from imu_array_ros.simulation.icosahedron import simulate_icosahedron

    v = nominal.terms["accelerometer_bias"].values.copy()
    v[k] = bias
    samples, _, _ = simulate_icosahedron(nominal.with_terms(accelerometer_bias=v), np.random.default_rng(seed),
                                         rate_hz=100.0, still_s=0.5, transition_s=0.5, twist_s=20.0)
    return samples


def test_score_blocks_add_up_and_match_the_exact_fit(nominal):
    """Block sums equal the one-block computation; for a linear term the score test's T / 2 is the exact
    log-likelihood gain of the engine's fit of that term on that IMU (one Gauss-Newton step from the
    motion's optimum), to within 1 %."""
    s = _bias_recording(nominal)
    motion, _, _ = fit_motion(s, nominal)
    terms = ("accelerometer_bias", "position")
    blocks = ((s.stamps - s.stamps[0]) // int(0.5e9)).astype(np.int64)
    sb = score_blocks(s, nominal, terms, motion, blocks)
    one = score_blocks(s, nominal, terms, motion, np.zeros_like(blocks))
    np.testing.assert_allclose(sb.g.sum(axis=0), one.g[0], rtol=1e-9, atol=1e-9 * np.abs(one.g).max())
    np.testing.assert_allclose(sb.S.sum(axis=0), one.S[0], rtol=1e-9, atol=1e-9 * np.abs(one.S).max())
    cols = sb.columns("accelerometer_bias")
    g, S = one.g[0, 2, cols], one.S[0, 2, cols, cols]
    stat = float(g @ np.linalg.solve(S, g))
    fit = fit_terms(s, nominal, ["accelerometer_bias"], imus=[2], motion0=motion)
    assert stat > 100  # the effect is there
    assert abs(0.5 * stat - (fit.loglik_after - fit.loglik_before)) < 0.01 * 0.5 * stat
    # the one-step estimate is the fit's
    np.testing.assert_allclose(np.linalg.solve(S, g), fit.model.terms["accelerometer_bias"].values[2], atol=3e-4)
    # expected r^2 sums to (valid axes - 9) per sample
    per_sample = np.nansum(one.expected, axis=(1, 2))
    np.testing.assert_allclose(per_sample, 48 - 9, rtol=1e-6)


def test_fit_terms_only_fits_each_term_on_its_imus(nominal):
    s = _bias_recording(nominal)
    only = {"accelerometer_bias": ["imu_3"], "position": ["imu_6"]}
    fit = fit_terms(s, nominal, list(only), imus=["imu_3", "imu_6"], only=only)
    assert np.isfinite(fit.std["accelerometer_bias"][2]).all() and np.isnan(fit.std["accelerometer_bias"][5]).all()
    assert np.isfinite(fit.std["position"][5]).all() and np.isnan(fit.std["position"][2]).all()
    np.testing.assert_array_equal(fit.model.terms["position"].values[2], nominal.positions[2])
    np.testing.assert_array_equal(fit.model.terms["accelerometer_bias"].values[5], 0.0)
    z = (fit.model.terms["accelerometer_bias"].values[2] - [0.02, -0.01, 0.015]) / fit.std["accelerometer_bias"][2]
    assert np.abs(z).max() < 3.5
    assert not fit.held


def test_score_statistics_are_chi_square_on_a_null_recording(nominal):
    """Where the model is right, T / dof over every candidate (14 terms x 8 IMUs) averages 1 (chi-square), and
    the block-robust p-values are uniform: the tests are calibrated, so the Bonferroni level means what it says."""
    built = build(Scenario("null", CORNERS, seed=41))
    s = built.samples
    motion, _, _ = fit_motion(s, nominal)
    blocks = ((s.stamps - s.stamps[0]) // int(0.5e9)).astype(np.int64)
    sb = score_blocks(s, nominal, candidate_names(), motion, blocks)
    cands = evaluate_candidates(sb, nominal.names, np.arange(blocks[-1] + 1) % 4)
    assert len(cands) == 14 * 8
    ratio = np.mean([c.statistic / c.dof for c in cands])
    assert 0.8 < ratio < 1.25, ratio
    p = np.array([c.robust_p for c in cands])
    assert 0.35 < np.mean(p) < 0.65 and np.mean(p < 0.05) < 0.12
    assert np.mean([c.heldout < 0 for c in cands]) > 0.7  # noise does not predict held-out blocks


FAST = ("accelerometer_bias@imu_8", "time_offset@imu_3", "gyroscope_g_sensitivity@imu_5",
        "time_offset@imu_1+position@imu_6", "vibration 38 Hz", "coloured noise", "null 1", "null 2")


@pytest.mark.parametrize("name", FAST)
def test_concealed_effect_found_or_reported_unexplained(name):
    """The fast subset of the suite: right term on the right IMU and nothing else, magnitudes within 3 CRB
    std; out-of-library effects located among the unexplained residual, not forced into a term; nothing on
    null recordings."""
    sc = next(s for s in standard_suite() if s.name.startswith(name) and "32 IMUs" not in s.name)
    built = build(sc)
    d = discover(built.samples, built.nominal, options=DiscoveryOptions(heldout=False))
    r = score(built, d)
    assert r["correct"], r
    if sc.kind in ("single", "confounded_pair"):
        assert r["within_3sigma"], r["max_abs_z"]
        assert d.after.loglik > d.baseline.loglik
    if sc.kind == "null":
        assert not d.findings and not d.unexplained
    if sc.kind == "outside_library":
        assert not d.findings
        assert all(not u["empirical_model"]["improves_heldout"] for u in d.unexplained)


def test_injected_effect_is_concealed_per_sample():
    """The suite's effects are at 0.3 noise std RMS on the most affected axis: no single sample reveals them."""
    built = build(next(s for s in standard_suite() if s.name.startswith("position@")))
    (term, k), values = next(iter(built.injected.items()))
    from imu_array_ros.simulation.concealed import _effect_rms
    from imu_array_ros.simulation.icosahedron import simulate_icosahedron
    sc = built.scenario
    _, truth, _ = simulate_icosahedron(built.nominal, np.random.default_rng(sc.seed + 10_000), rate_hz=sc.rate_hz,
                                       still_s=sc.still_s, transition_s=sc.transition_s, twist_s=sc.twist_s)
    assert _effect_rms(built.nominal, term, k, values, truth) == pytest.approx(0.3, rel=0.02)


# --------------------------------------------------------------------------- command line


@pytest.fixture(scope="module")
def recordings(tmp_path_factory):
    """A recording of a true array with an accelerometer bias on imu_3 and a position error on imu_6, a
    second recording of the same array, and the nominal description."""
    from imu_array_ros.cli import main

    tmp = tmp_path_factory.mktemp("discover")
    d = yaml.safe_load(Path(CORNERS).read_text())
    d["imu_array"]["imus"][2]["accelerometer"] = {"bias": [0.02, -0.01, 0.015]}
    d["imu_array"]["imus"][5]["position"][0] += 0.0004
    truth = tmp / "truth.yaml"
    truth.write_text(yaml.safe_dump(d))
    out = []
    for i, seed in enumerate((5, 6)):
        rec = tmp / f"rec{i}"
        assert main(["simulate", "--array", str(truth), "--motion", "icosahedron", "--still-seconds", "0.5",
                     "--transition-seconds", "0.5", "--twist-seconds", "15", "--seed", str(seed),
                     "--start-time", "2026-01-01T00:00:00Z", "--out", str(rec), "-q"]) == 0
        out.append(rec)
    return tmp, out[0], out[1]


def test_cli_discover_report_apply_validate(capsys, recordings):
    tmp, rec, rec2 = recordings
    report, applied = tmp / "report", tmp / "applied.yaml"
    code, out, err = cli(capsys, "discover", str(rec), "--array", CORNERS, "--report", str(report),
                         "--apply", str(applied), "--validate", str(rec2))
    assert code == 0, err
    assert "found position on imu_6" in err and "found accelerometer_bias on imu_3" in err
    for name in ("report.json", "report.md", "residual_map.png", "spectra.png", "evidence.png", "time.png"):
        assert (report / name).stat().st_size > 0, name
    data = json.loads((report / "report.json").read_text())
    assert set(data) >= {"baseline", "localization", "findings", "indistinguishable", "unexplained", "after"}
    assert set(data["baseline"]) >= {"nis_still", "nis_moving", "loglik"}
    assert {(f["effect"], f["sensors"][0]) for f in data["findings"]} == {("position", "imu_6"),
                                                                          ("accelerometer_bias", "imu_3")}
    for f in data["findings"]:
        assert set(f["evidence"]) >= {"delta_loglik", "lrt_p", "delta_bic", "heldout_delta_loglik"}
        assert f["evidence"]["delta_loglik"] > 0 and f["evidence"]["heldout_delta_loglik"] > 0
    loc = data["localization"][0]
    assert set(loc) >= {"sensors", "axes", "regime", "band_hz", "share_of_excess"}
    assert data["after"]["loglik"] > data["baseline"]["loglik"]
    assert data["heldout"]["delta_loglik"] > 0
    assert data["validation"][0]["delta_loglik"] > 0  # the findings carry over to the other recording
    md = (report / "report.md").read_text()
    assert "## Findings" in md and "imu_6" in md
    manifest = json.loads((report / "manifest.json").read_text())
    assert manifest["kind"] == "imu_array_ros discovery report" and "report.md" in manifest["files"]
    # the applied description explains the recording: discovering again finds nothing
    desc = load_description(applied)
    bias = desc.imus[2].value("accelerometer.bias")
    assert np.allclose(bias, [0.02, -0.01, 0.015], atol=0.004)
    code, out, err = cli(capsys, "discover", str(rec), "--array", str(applied), "--report", str(tmp / "again"),
                         "--no-plots", "-q")
    assert code == 0, err
    again = json.loads((tmp / "again" / "report.json").read_text())
    assert again["findings"] == []
    assert not (tmp / "again" / "residual_map.png").exists()


def test_cli_discover_user_errors(capsys, recordings, tmp_path):
    tmp, rec, rec2 = recordings
    assert_user_error(cli(capsys, "discover", str(rec), "--array", CORNERS, "--report", str(tmp_path / "r"),
                          "--terms", "position,warp", "-q"), "--terms", "warp")
    # the user's simulation must be of the same run
    from imu_array_ros.cli import main
    other = tmp_path / "other"
    assert main(["simulate", "--array", CORNERS, "--duration", "3", "--out", str(other), "-q"]) == 0
    assert_user_error(cli(capsys, "discover", str(rec), "--array", CORNERS, "--report", str(tmp_path / "r"),
                          "--sim", str(other), "--no-empirical", "-q"), "--sim", "samples", "same stamps")
    # an existing report is replaced only with --force
    report = tmp_path / "rep"
    report.mkdir()
    (report / "report.json").write_text("{}\n")
    (report / "report.md").write_text("# old\n")
    assert_user_error(cli(capsys, "discover", str(rec), "--array", CORNERS, "--report", str(report), "-q"),
                      "discovery report", "--force")
    assert (report / "report.md").read_text() == "# old\n"
    # a directory holding anything else is never written into, even with --force; nor one holding an input
    (report / "notes.txt").write_text("mine\n")
    assert_user_error(cli(capsys, "discover", str(rec), "--array", CORNERS, "--report", str(report), "--force",
                          "-q"), "notes.txt", "choose an empty or new directory")
    assert (report / "notes.txt").read_text() == "mine\n" and (report / "report.md").read_text() == "# old\n"
    assert_user_error(cli(capsys, "discover", str(rec), "--array", CORNERS, "--report", str(rec.parent), "--force",
                          "-q"), "holds the input")
    # an input is never an output
    assert_user_error(cli(capsys, "discover", str(rec), "--array", CORNERS, "--report", str(tmp_path / "r2"),
                          "--apply", CORNERS, "-q"), "input")


def test_cli_discover_with_the_users_simulation(capsys, recordings, tmp_path):
    """--sim: the localisation reads recording - simulation; a simulation of the same run by the nominal
    model locates the imu_6 position error and the imu_3 bias."""
    from imu_array_ros.cli import main

    tmp, rec, _ = recordings
    sim = tmp_path / "sim"
    assert main(["simulate", "--array", CORNERS, "--motion", "icosahedron", "--still-seconds", "0.5",
                 "--transition-seconds", "0.5", "--twist-seconds", "15", "--seed", "5",
                 "--start-time", "2026-01-01T00:00:00Z", "--out", str(sim), "-q"]) == 0
    code, out, err = cli(capsys, "discover", str(rec), "--array", CORNERS, "--report", str(tmp_path / "r"),
                         "--sim", str(sim), "--no-plots", "--no-empirical", "-q")
    assert code == 0, err
    data = json.loads((tmp_path / "r" / "report.json").read_text())
    assert data["localization_detail"]["source"].startswith("recording - simulated recording")
    located = {s for e in data["localization"] for s in e["sensors"][:1]}
    assert {"imu_6", "imu_3"} <= located


def _pooled(effect, imus, values, std=1.0, scope="all shared"):
    imus = tuple(imus)
    v = np.asarray(values, dtype=float)
    return SimpleNamespace(effect=effect, k=imus[0], sensor=f"imu_{imus[0] + 1}", imus=imus, scope=scope,
                           values=v.mean(axis=0), std=np.full(v.shape[1], std), imu_values=v,
                           imu_std=np.full(v.shape, std))


def test_concealed_score_matches_pooled_findings_by_their_imu_set():
    """A pooled finding is right only when its effect was injected on every IMU of its scope (matched by the
    IMU set, not its first IMU); its per-IMU values are compared with each IMU's truth."""
    names = tuple(f"imu_{k + 1}" for k in range(8))
    truth = {("accelerometer_gain", k): np.full(3, 0.01 * (k + 1)) for k in (0, 2, 4, 6)}
    built = SimpleNamespace(scenario=Scenario("top gain", "x", [(t, k) for t, k in truth]),
                            nominal=SimpleNamespace(names=names), injected=truth, outside_sensors=[])

    def run(*findings):
        return score(built, SimpleNamespace(findings=list(findings), indistinguishable=[], unexplained=[]))

    exact = [truth[("accelerometer_gain", k)] for k in (0, 2, 4, 6)]
    r = run(_pooled("accelerometer_gain", (0, 2, 4, 6), exact, scope="top shared"))
    assert r["correct"] and not r["false_findings"] and r["within_3sigma"], r
    # the same first IMU, a wider scope: wrong (before: matched by imu_1 alone and counted right)
    r = run(_pooled("accelerometer_gain", range(8), exact * 2))
    assert not r["correct"] and r["false_findings"] == ["accelerometer_gain@all shared (" + ", ".join(names) + ")"]
    # a narrower scope leaves IMUs missed
    r = run(_pooled("accelerometer_gain", (0, 2), exact[:2], scope="pair"))
    assert not r["correct"] and r["missed"] == ["accelerometer_gain@imu_5", "accelerometer_gain@imu_7"]
    # per-IMU magnitudes: one IMU 5 std off fails the 3-sigma check
    off = [v.copy() for v in exact]
    off[2] = off[2] + 5.0
    assert run(_pooled("accelerometer_gain", (0, 2, 4, 6), off, scope="top shared"))["within_3sigma"] is False
    # one-IMU findings on each of them are right too
    single = [SimpleNamespace(effect="accelerometer_gain", k=k, sensor=names[k], imus=(k,), scope="imu",
                              values=truth[("accelerometer_gain", k)], std=np.ones(3), imu_values=None)
              for k in (0, 2, 4, 6)]
    assert run(*single)["correct"]
