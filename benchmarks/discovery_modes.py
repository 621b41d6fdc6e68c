"""Narrowband-mode search (issue 23, item 3): false modes on nulls, detection power vs amplitude on fresh seeds.

Its own generator (not the suite's): per scenario an array (4 planar, the 8 MIMU4444BT corners, 32), a rate
(62.5-1000 Hz), a session (hand twisting, or 20 icosahedron rests then twisting) capped at 120 000 readings,
simulated with :mod:`imu_array_ros.simulation`, the motion fitted by the engine (``fit_motion``) with the
model it is analysed with, then :func:`imu_array_ros.discovery.modes.detect_modes` on the normalised residuals.

* **nulls** (three kinds, equal shares): ``white`` (the truth model, white noise); ``broadband`` (analysed
  with the truth model, but 1-3 IMUs carry first-order Gauss-Markov noise of 0.05-2 s and 0.5-2 noise stds on
  random sensors and a random-walk bias: a misfit spread over frequency); ``library`` (analysed without a
  library term the recording has: a gain, misalignment, position or g-sensitivity error 1-5x its test size
  on one IMU -- a misfit that follows the motion).  Any mode reported is a false finding.
* **modes**: a narrowband process (a pure sinusoid, or an AR(2) resonance 0.05-1.5 Hz wide, unit RMS) at a
  frequency log-uniform in 0.5 Hz .. 0.95 x Nyquist, on the accelerometers (70 %) or gyroscopes, on a
  random subset of IMUs with random gains 0.2-1, standing (phases 0 / pi) or travelling (random phases),
  a random direction per IMU; present all the time or (30 %) in one window of 30-70 % of the recording.
  Size: the RMS of the strongest channel, log-uniform 0.02-1 noise std; binned by the oracle evidence
  E = sum over channels of N a_c^2 / 2 (a_c: channel RMS in noise stds).  *Detected*: a mode whose band
  holds the frequency (+- one bin) and whose IMUs include the strongest one.

Each scenario's residuals are searched twice, with the mode search's array-wide test being
:mod:`~imu_array_ros.discovery.coherent` ("welch") and :mod:`~imu_array_ros.discovery.bank` ("bank"): columns side
by side (``--tests``: others, e.g. ``welch+matched``, the test ``discover`` uses: modes.COHERENT_TEST; the first
is the one the unsuffixed keys hold).
Baseline, same residuals, same run: the per-cell line test discovery used before (:func:`old_line_test`:
Welch of 256 samples, each bin against the cell's *white* floor, chi-square, Bonferroni over bins x cells at
0.01); it has no band, so it is credited with a detection when any cell of the strongest IMU is flagged.

``--kinds library`` runs only that kind of null, ``--mode-fmax 5`` draws the modes below 5 Hz (where the
motion is), ``--pipeline N`` runs N library nulls through ``discover`` itself (:func:`pipeline_case`: the modes
a user sees after the findings, not the mode search on a residual that still holds the missing term).

    python -m benchmarks.discovery_modes [--nulls 90] [--modes 200] [--seed 5150] [--tests welch+matched bank]
        [--kinds white broadband library] [--mode-fmax HZ] [--pipeline N]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import time

import numpy as np

from imu_array_ros.discovery.excess import regime_masks
from imu_array_ros.discovery.modes import COHERENT_TEST, MODE_ALPHA, detect_modes
from imu_array_ros.fitting.engine import fit_motion
from imu_array_ros.model.description import load_description
from imu_array_ros.model.layouts import grid_array32, planar_square4
from imu_array_ros.model.samples import ImuSamples
from imu_array_ros.model.sensor_model import SensorModel
from imu_array_ros.simulation.icosahedron import simulate_icosahedron
from imu_array_ros.simulation.perturb import TERM_TEST_SIZES
from imu_array_ros.simulation.simulator import simulate_twist

ARRAYS = {"planar4": planar_square4, "corners8": lambda: load_description("config/mimu4444bt_corners.yaml"),
          "grid32": grid_array32}
RATES = (62.5, 100.0, 200.0, 500.0, 1000.0)
CAP = 120_000
MISFIT_TERMS = ("accelerometer_gain", "gyroscope_gain", "accelerometer_misalignment", "gyroscope_misalignment",
                "position", "gyroscope_g_sensitivity")
EDGES = (0, 30, 100, 300, 1000, 3000, 10_000, np.inf)


def _session(rng, misfit: bool = False):
    """(array, rate, still poses, the model analysed with, the recording, the term left out or "", the IMU it is
    left out on (None: no term))."""
    array = str(rng.choice(list(ARRAYS)))
    model = SensorModel.from_description(ARRAYS[array]())
    k = model.n_imus
    sim, term, kk = model, "", None
    if misfit:
        term = str(rng.choice(MISFIT_TERMS))
        v = model.terms[term].values.copy()
        kk = int(rng.integers(k))
        v[kk] += rng.normal(size=v[kk].shape) * TERM_TEST_SIZES[term] * rng.uniform(1.0, 5.0)
        sim = model.with_terms(**{term: v})
    still = rng.random() < 0.3
    rates = [r for r in RATES if (38.0 if still else 8.0) * r * k <= CAP]
    rate = float(rng.choice(rates))
    if still:
        twist = float(min(rng.uniform(5.0, 15.0), CAP / (rate * k) - 20 * 0.8 - 19 * 0.6))
        samples, truth, _ = simulate_icosahedron(sim, rng, rate_hz=rate, still_s=0.8, transition_s=0.6,
                                                 twist_s=max(twist, 0.0))
    else:
        dur = float(min(rng.uniform(10.0, 30.0), CAP / (rate * k)))
        samples, truth = simulate_twist(sim, dur, rate, rng)
    return array, rate, still, model, samples, term, kk


def _process(rng, n, fs, f, bw):
    """Unit-RMS narrowband process: a sinusoid (bw 0) or an AR(2) resonance of full width bw Hz."""
    t = np.arange(n) / fs
    if bw <= 0:
        x = np.sin(2 * np.pi * f * t + rng.uniform(0, 2 * np.pi))
    else:
        from scipy.signal import lfilter
        rad = np.exp(-np.pi * bw / fs)
        x = lfilter([1.0], [1.0, -2 * rad * np.cos(2 * np.pi * f / fs), rad * rad], rng.normal(size=n + 2000))[2000:]
    return x / np.sqrt(np.mean(x ** 2))


def _add(samples: ImuSamples, added: np.ndarray) -> ImuSamples:
    return ImuSamples(samples.stamps, samples.accel + added[..., :3], samples.gyro + added[..., 3:], samples.names)


def old_line_test(r: np.ndarray, fs: float, nperseg: int = 256, alpha: float = 0.01) -> np.ndarray:
    """(K, 6) cells flagged by the previous line test (module docstring), on residuals r (N, K, 6)."""
    from scipy.stats import chi2

    from imu_array_ros.discovery.spectra import relative_psd

    n, k = r.shape[:2]
    _, psd = relative_psd(r.reshape(n, k * 6), fs, nperseg=nperseg)
    if psd.shape[-1] < 3:
        return np.zeros((k, 6), dtype=bool)
    floor = np.nanmean(np.isfinite(r), axis=0).reshape(k * 6) * 0 + 1.0  # E[r^2] = 1 (no leverage here)
    nper = int(min(nperseg, n))
    nu = 2.0 * (1 + max(0, (n - nper) // (nper // 2))) / 1.056
    inner = psd[:, 1:-1]
    limit = chi2.isf(alpha / (k * 6 * inner.shape[-1]), nu) / nu
    return (np.nan_to_num(inner / floor[:, None]) > limit).any(axis=1).reshape(k, 6)


#: the array-wide test of the mode search, each run on the same residuals ("welch": coherent.py, "bank": bank.py);
#: the first is the one the columns without a suffix show
COHERENT_TESTS = ("welch", "bank")
#: the array-wide tests ``--tests`` may name ("default": discover's, modes.COHERENT_TEST) and their names in the tables
TEST_NAMES = {"welch": "coherent.py", "bank": "bank.py", "matched": "matched.py",
              "welch+matched": "coherent.py + matched.py", "welch+matched+bank": "coherent.py + matched.py + bank.py"}


def _analyse(samples, model):
    """({test: ModeSearch}, fs, n, old line test's cells)."""
    motion, _, r = fit_motion(samples, model)
    fs = 1e9 / float(np.median(np.diff(samples.stamps)))
    still = regime_masks(motion, 0.2, 9.80665)["still"]
    searches = {t: detect_modes(r, fs, positions=model.positions, rotations=model.rotations, std=model.std,
                                still=still, motion=motion, coherent=t) for t in COHERENT_TESTS}
    return searches, fs, len(r), old_line_test(r, fs)


def _suffix(test: str) -> str:
    return "" if test == COHERENT_TESTS[0] else "_" + test.replace("+", "_")


def null_recording(seed: int, kind: str) -> tuple:
    """(kind as reported, array, rate, still poses, the model analysed with, the recording) of a null of the kind
    "white", "broadband" or "library" (module docstring)."""
    rng = np.random.default_rng([seed, 1])
    array, rate, still, model, samples, term, _ = _session(rng, misfit=kind == "library")
    n, k = samples.accel.shape[:2]
    if kind == "broadband":
        from scipy.signal import lfilter
        added = np.zeros((n, k, 6))
        for kk in rng.choice(k, size=int(rng.integers(1, min(3, k) + 1)), replace=False):
            tau, ratio = rng.uniform(0.05, 2.0), rng.uniform(0.5, 2.0)
            a = np.exp(-1.0 / (tau * rate))
            e = lfilter([np.sqrt(1 - a * a)], [1.0, -a], rng.normal(size=(n, 6)), axis=0)
            walk = np.cumsum(rng.normal(size=(n, 6)), axis=0) / np.sqrt(n)
            added[:, kk] = (ratio * e + walk) * model.std[kk][None]
        samples = _add(samples, added)
    elif kind == "library":
        kind = f"library ({term})"
    return kind, array, rate, still, model, samples


def null_case(seed: int, kind: str) -> dict:
    kind, array, rate, still, model, samples = null_recording(seed, kind)
    searches, fs, n, old = _analyse(samples, model)
    out = {"kind": kind, "seed": seed, "array": array, "rate_hz": rate, "still_poses": still, "samples": n,
           "old_test_cells": int(old.sum())}
    for t, search in searches.items():
        out["modes" + _suffix(t)] = [(round(m.frequency_hz, 3), m.p_value, m.test) for m in search.modes]
        out["motion_lines" + _suffix(t)] = len(search.motion_lines)
    return out


def mode_case(seed: int, fmax: float | None = None) -> dict:
    """A mode scenario (module docstring); fmax: its frequency drawn up to min(fmax, 0.95 Nyquist) Hz."""
    rng = np.random.default_rng([seed, 2])
    array, rate, still, model, samples, _, _ = _session(rng)
    n, k = samples.accel.shape[:2]
    nyq = rate / 2
    f = float(np.exp(rng.uniform(np.log(0.5), np.log(min(0.95 * nyq, fmax or np.inf)))))
    bw = 0.0 if rng.random() < 0.4 else float(rng.uniform(0.05, 1.5))
    x = _process(rng, n, rate, f, bw)
    gate = np.ones(n)
    if rng.random() < 0.3:
        w = rng.uniform(0.3, 0.7)
        s0 = rng.uniform(0, 1 - w)
        gate[: int(s0 * n)] = 0
        gate[int((s0 + w) * n):] = 0
    from scipy.signal import hilbert
    z = hilbert(x * gate)
    m = int(rng.integers(1, k + 1))
    imus = rng.choice(k, size=m, replace=False)
    gains = rng.uniform(0.2, 1.0, m)
    gains[0] = 1.0
    phases = rng.choice([0.0, np.pi], m) if rng.random() < 0.5 else rng.uniform(0, 2 * np.pi, m)
    acc = rng.random() < 0.7
    size = float(np.exp(rng.uniform(np.log(0.02), np.log(1.0))))
    added = np.zeros((n, k, 6))
    energy = 0.0
    for kk, g, ph in zip(imus, gains, phases):
        d = rng.normal(size=3)
        d /= np.linalg.norm(d)
        sl = slice(0, 3) if acc else slice(3, 6)
        sd = model.std[kk, sl]
        sig = np.real(z * np.exp(1j * ph))[:, None] * d[None] * g * size * sd.max()
        added[:, kk, sl] = sig
        energy += 0.5 * float(np.sum((sig / sd[None]) ** 2))
    searches, fs, _, old = _analyse(_add(samples, added), model)
    lead = int(imus[0])
    out = {"seed": seed, "array": array, "rate_hz": rate, "still_poses": still, "frequency_hz": f,
           "bandwidth_hz": bw, "sensor": "accelerometer" if acc else "gyroscope", "imus": len(imus),
           "gated": bool(gate.min() == 0), "size_noise_std": size, "evidence": energy,
           "old_test_detected": bool(old[lead].any())}
    for t, search in searches.items():
        df = search.freqs[1] - search.freqs[0] if len(search.freqs) > 1 else 0.0
        hit = [md for md in search.modes if md.band_hz[0] - df <= f <= md.band_hz[1] + df and lead in md.imus]
        false = [md for md in search.modes if not (md.band_hz[0] - 2 * df <= f <= md.band_hz[1] + 2 * df)]
        x = _suffix(t)
        out.update({"detected" + x: bool(hit), "band_hz" + x: list(hit[0].band_hz) if hit else None,
                    "test" + x: hit[0].test if hit else None,
                    "regime" + x: hit[0].presence.get("regime") if hit else None,
                    "fraction_present" + x: hit[0].presence.get("fraction_present") if hit else None,
                    "heldout_ratio" + x: hit[0].model.get("ratio_after_before") if hit else None,
                    "in_motion_lines" + x: any(md.band_hz[0] - df <= f <= md.band_hz[1] + df
                                               for md in search.motion_lines),
                    "other_modes" + x: len(false)})
    return out


def pipeline_case(seed: int) -> dict:
    """A library null through ``discover`` itself (the user's view): a recording with a library term the model
    analysed with lacks (as the ``library`` nulls), the whole search; a mode reported after the findings (the
    unexplained entries with a mode) is a false finding.  Also the modes of the localisation before the search,
    the term left out and its IMU (missing_term, missing_imu), each finding's IMUs (finding_imus), and the timing
    stage's sample clocks: those in the final model (clocks; the recordings are simulated with exact stamps and no
    clock, so any is false) and those dropped when re-tested given the library findings (clocks_dropped; None: the
    tree's report has no timing.dropped_given_findings)."""
    from imu_array_ros.discovery.discover import DiscoveryOptions, discover

    rng = np.random.default_rng([seed, 3])
    array, rate, still, model, samples, term, kk = _session(rng, misfit=True)
    t0 = time.time()
    d = discover(samples, model, options=DiscoveryOptions(heldout=False))
    after = d.localization_after.modes if d.localization_after is not None else None
    before = d.localization_before.modes if d.localization_before is not None else None
    timing = d.timing.to_dict() if d.timing is not None else {}

    def clocks(rows):
        return None if rows is None else [[c["sensor"], c["sensors"][0], c["rate_ppm"], c["snr"]] for c in rows]
    return {"kind": f"library ({term})", "seed": seed, "array": array, "rate_hz": rate, "still_poses": still,
            "samples": int(samples.accel.shape[0]), "seconds": time.time() - t0,
            "findings": [[f.effect, f.sensor] for f in d.findings],
            "finding_imus": [list(f.candidate.sensors) for f in d.findings],
            "missing_term": term, "missing_imu": model.names[kk],
            "clocks": clocks(timing.get("findings", [])), "clocks_dropped": clocks(timing.get("dropped_given_findings")),
            "modes_after": [] if after is None else [(round(m.frequency_hz, 3), m.p_value, m.test) for m in after.modes],
            "unexplained_with_mode": sum("mode" in u for u in d.unexplained),
            "modes_before": [] if before is None else [(round(m.frequency_hz, 3), m.p_value, m.test)
                                                       for m in before.modes]}


def pipeline_verdict(r: dict) -> dict:
    """One whole-pipeline null's answer (a :func:`pipeline_case` row): a false sample clock kept in the final model,
    a false mode reported after the findings, a wrong library finding (any whose term is not the missing one or whose
    IMUs are not exactly the missing term's IMU), the missing term found on its IMU alone, and correct (that finding
    only: no other finding, clock or mode).  None where the row does not record it (runs before the clocks were)."""
    right = [[r["missing_term"], [r["missing_imu"]]] == [e[0], imus] for e, imus in
             zip(r["findings"], r["finding_imus"])] if "missing_imu" in r else None
    out = {"false_clock": None if r.get("clocks") is None else bool(r["clocks"]), "false_mode": bool(r["modes_after"]),
           "wrong_finding": None if right is None else not all(right),
           "found": None if right is None else any(right)}
    out["correct"] = (None if None in out.values() else
                      out["found"] and not (out["false_clock"] or out["false_mode"] or out["wrong_finding"]))
    return out


def count_ci(k: int, n: int) -> str:
    """``k/n (lo–hi %)``: the count with its exact binomial (Clopper-Pearson) 95 % interval; "—" when n is 0."""
    from benchmarks.discovery_generalisation import clopper_pearson

    if n == 0:
        return "—"
    lo, hi = clopper_pearson(k, n)
    return f"{k}/{n} ({100 * lo:.0f}–{100 * hi:.0f} %)"


def render(res: dict, path: str, seconds: float) -> None:
    from benchmarks.harness import load_average, machine_header, write_results

    nulls, modes = res["nulls"], res["modes"]
    kinds = ("white", "broadband", "library")
    tests = [t for t in COHERENT_TESTS if ("modes" + _suffix(t)) in (nulls[0] if nulls else {})] or [COHERENT_TESTS[0]]
    names = {t: TEST_NAMES[t] + (" (discover's default)" if t == COHERENT_TEST else "") for t in TEST_NAMES}
    head = " | ".join(f"with a mode ({names[t]} test)" for t in tests)
    text = machine_header("Narrowband-mode search: false modes on nulls, power on fresh seeds",
                          extra=[f"load average: {load_average()}", f"run time: {seconds:.0f} s",
                                 f"detector alpha (family-wise per recording): {MODE_ALPHA}"])
    text += ("## Nulls (any mode reported = a false finding)\n\nThe mode search with each array-wide test on the "
             "same residuals.\n\n| kind | recordings | " + head + " | motion lines set aside | baseline (old line "
             "test): with a flagged cell |\n|---|---|" + "---|" * len(tests) + "---|---|\n")

    def null_row(label, rows):
        return (f"| {label} | {len(rows)} | "
                + " | ".join(count_ci(sum(bool(r["modes" + _suffix(t)]) for r in rows), len(rows)) for t in tests)
                + f" | {sum(r['motion_lines'] > 0 for r in rows)} | "
                f"{count_ci(sum(r['old_test_cells'] > 0 for r in rows), len(rows))} |\n")

    for kd in kinds:
        text += null_row(kd, [r for r in nulls if r["kind"].startswith(kd)])
    text += null_row("all", nulls) + "\n"
    text += "False modes on the nulls, by test:\n\n"
    for t in tests:
        found = [(r["kind"], m) for r in nulls for m in r["modes" + _suffix(t)]]
        text += f"- {names[t]}: " + ("; ".join(f"{k} at {m[0]:g} Hz (p {m[1]:.2g}, {m[2] if len(m) > 2 else '?'})"
                                              for k, m in found) or "none") + "\n"
    text += ("\n## Detection vs oracle evidence (modes located in band with the strongest IMU)\n\n"
             "| evidence | scenarios | " + " | ".join(f"detected, {names[t]} test (95 % CI)" for t in tests)
             + " | baseline: old line test flags the strongest IMU |\n|---|---|" + "---|" * len(tests) + "---|\n")
    ev = np.array([r["evidence"] for r in modes])
    for lo, hi in zip(EDGES[:-1], EDGES[1:]):
        sel = [r for r, e in zip(modes, ev) if lo <= e < hi]
        text += (f"| {lo:g}–{hi:g} | {len(sel)} | "
                 + " | ".join(count_ci(sum(r["detected" + _suffix(t)] for r in sel), len(sel)) for t in tests)
                 + f" | {count_ci(sum(r['old_test_detected'] for r in sel), len(sel))} |\n")
    strong = [r for r in modes if r["evidence"] >= 300]
    text += ("\n## Detection at evidence >= 300 by scenario trait\n\n| trait | "
             + " | ".join(f"detected, {names[t]}" for t in tests) + " |\n|---|" + "---|" * len(tests) + "\n")
    traits = [("array " + a, lambda r, a=a: r["array"] == a) for a in ARRAYS] + \
             [(f"{g:g} Hz", lambda r, g=g: r["rate_hz"] == g) for g in RATES] + \
             [("sinusoid", lambda r: r["bandwidth_hz"] == 0), ("resonance 0.05-1.5 Hz", lambda r: r["bandwidth_hz"] > 0),
              ("accelerometer", lambda r: r["sensor"] == "accelerometer"), ("gyroscope", lambda r: r["sensor"] == "gyroscope"),
              ("present part of the time", lambda r: r["gated"]), ("f < 3 Hz", lambda r: r["frequency_hz"] < 3),
              ("f >= 3 Hz", lambda r: r["frequency_hz"] >= 3)]
    for name, fn in traits:
        sel = [r for r in strong if fn(r)]
        text += f"| {name} | " + " | ".join(count_ci(sum(r["detected" + _suffix(t)] for r in sel), len(sel))
                                            for t in tests) + " |\n"
    for t in tests:
        x = _suffix(t)
        held = [r["heldout_ratio" + x] for r in modes if r["detected" + x] and r["heldout_ratio" + x] is not None]
        if held:
            text += (f"\n{names[t]} test: empirical model on held-out blocks (detected modes with >= 2 channels, "
                     f"{len(held)}): sum of squared residuals of the mode's channels x {np.median(held):.3f} (median; "
                     f"range {min(held):.3f}–{max(held):.3f}; {sum(h < 1 for h in held)} of {len(held)} below 1).\n")
        other = sum(r["other_modes" + x] for r in modes)
        text += f"\n{names[t]} test: modes reported away from the injected frequency in the mode scenarios: {other}.\n"
    pipe = res.get("pipeline") or []
    if pipe:
        text += ("\n## Whole pipeline (`discover`) on library nulls\n\nEach recording lacks one library term in the "
                 "model it is analysed with; `discover` (held-out check off) searches the terms, then locates what is "
                 "left. A mode reported after the findings (an unexplained entry with a mode) is a false finding.\n\n"
                 "| recordings | with a mode after the findings | with an unexplained entry holding a mode | "
                 "with a mode in the localisation before the search | with a finding |\n|---|---|---|---|---|\n"
                 f"| {len(pipe)} | {count_ci(sum(bool(r['modes_after']) for r in pipe), len(pipe))} | "
                 f"{count_ci(sum(r['unexplained_with_mode'] > 0 for r in pipe), len(pipe))} | "
                 f"{count_ci(sum(bool(r['modes_before']) for r in pipe), len(pipe))} | "
                 f"{count_ci(sum(bool(r['findings']) for r in pipe), len(pipe))} |\n\n")
        for r in pipe:
            text += (f"- {r['seed']} {r['kind']} ({r['array']}, {r['rate_hz']:g} Hz, {r['samples']} samples): findings "
                     + (", ".join(f"{e} on {s}" for e, s in r["findings"]) or "none") + "; sample clocks kept: "
                     + (", ".join(f"{c[1]} {c[0]} {c[2]:+.0f} ppm" for c in r.get("clocks") or []) or "none")
                     + "; modes before: "
                     + (", ".join(f"{m[0]:g} Hz (p {m[1]:.2g})" for m in r["modes_before"]) or "none")
                     + "; after: " + (", ".join(f"{m[0]:g} Hz (p {m[1]:.2g}, {m[2]})" for m in r["modes_after"])
                                      or "none") + "\n")
    write_results(path, text)


def main() -> None:
    global COHERENT_TESTS
    ap = argparse.ArgumentParser()
    ap.add_argument("--nulls", type=int, default=90)
    ap.add_argument("--modes", type=int, default=200)
    ap.add_argument("--seed", type=int, default=5150)
    ap.add_argument("--out", default="benchmarks/results/discovery_modes.json")
    ap.add_argument("--md", default="benchmarks/results/discovery_modes.md")
    ap.add_argument("--kinds", nargs="+", choices=["white", "broadband", "library"],
                    default=["white", "broadband", "library"], help="the nulls' kinds, in turn")
    ap.add_argument("--mode-fmax", type=float, default=None,
                    help="mode scenarios' frequency drawn up to this (Hz; default 0.95 Nyquist)")
    ap.add_argument("--pipeline", type=int, default=0,
                    help="library nulls run through discover itself (whole pipeline; slow)")
    ap.add_argument("--tests", nargs="+", choices=[*TEST_NAMES, "default"], default=list(COHERENT_TESTS),
                    help="the mode search's array-wide tests, each run on the same residuals (default: welch bank; "
                         f"'default': discover's, {COHERENT_TEST})")
    a = ap.parse_args()
    COHERENT_TESTS = tuple(dict.fromkeys(COHERENT_TEST if t == "default" else t for t in a.tests))
    t0 = time.time()
    nulls, modes = [], []
    kinds = tuple(a.kinds)
    for i in range(a.nulls):
        nulls.append(null_case(a.seed * 1000 + i, kinds[i % len(kinds)]))
        print(json.dumps(nulls[-1]), flush=True)
    for i in range(a.modes):
        modes.append(mode_case(a.seed * 1000 + 500 + i, a.mode_fmax))
        print(json.dumps(modes[-1]), flush=True)
    pipeline = []
    for i in range(a.pipeline):
        pipeline.append(pipeline_case(a.seed * 1000 + 900 + i))
        print(json.dumps(pipeline[-1], default=float), flush=True)
    ev = np.array([r["evidence"] for r in modes])
    summary = {"alpha": MODE_ALPHA, "nulls": len(nulls), "mode_scenarios": len(modes), "seconds": time.time() - t0,
               "machine": platform.processor() or platform.machine(), "cpus": os.cpu_count(),
               "load_average": os.getloadavg(), "coherent_tests": list(COHERENT_TESTS), "tests": {}}
    for t in COHERENT_TESTS:
        x = _suffix(t)
        det = np.array([r["detected" + x] for r in modes])
        power = []
        for lo, hi in zip(EDGES[:-1], EDGES[1:]):
            sel = (ev >= lo) & (ev < hi)
            power.append({"evidence": [lo, hi], "n": int(sel.sum()), "detected": int(det[sel].sum())})
        summary["tests"][t] = {
            "nulls_with_a_mode": sum(bool(r["modes" + x]) for r in nulls),
            "by_kind": {kd: [sum(bool(r["modes" + x]) for r in nulls if r["kind"].startswith(kd)),
                             sum(r["kind"].startswith(kd) for r in nulls)] for kd in kinds},
            "detected": int(det.sum()), "power": power,
            "false_modes_in_mode_scenarios": int(sum(r["other_modes" + x] for r in modes))}
    print(json.dumps(summary, indent=1))
    summary["pipeline"] = {"recordings": len(pipeline), "with_a_mode_after": sum(bool(r["modes_after"]) for r in pipeline),
                           "with_a_mode_before": sum(bool(r["modes_before"]) for r in pipeline)}
    summary["kinds"], summary["mode_fmax"] = list(kinds), a.mode_fmax
    res = {"summary": summary, "nulls": nulls, "modes": modes, "pipeline": pipeline}
    with open(a.out, "w") as fh:
        json.dump(res, fh, indent=1, default=float)
    render(res, a.md, time.time() - t0)


if __name__ == "__main__":
    main()
