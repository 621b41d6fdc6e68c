"""Scoring a discovery against the truth of a suite scenario (:mod:`.suites`).

Library classes: *correct* when the findings name exactly the injected terms, each on exactly its IMUs (one
finding per IMU or one finding at a group/shared scope: a finding covers the IMUs of its ``sensors``), and
nothing else; each effect is also scored on its own (``detected``).  A wrong answer whose finding discovery
itself named indistinguishable from an alternative (the tie of :func:`~imu_array_ros.discovery.confirm.settle_ties`:
exact gains within ln(1/alpha); or a narrowed scope's set that fits as well up to the gauge, ``Candidate.equivalents``)
is marked ``named_alternative`` when taking that alternative instead would be correct: not counted correct (a report
that says "this or that" has not found which), reported apart.
Vibration: *located* (an unexplained entry whose band holds the mode's frequency and whose IMUs include a
largest-amplitude one: the quadratic mode shapes are symmetric, so several IMUs often share the largest
amplitude exactly) and nothing forced (no finding at all).  Null: correct without a finding.
The suite's recordings have exact stamps and no sample clock: a sample clock the discovery keeps (its timing stage's
``timing.findings``, which ``--apply`` writes) is a false finding in every class.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from imu_array_ros.simulation.suites import BuiltScenario

__all__ = ["score"]


def _found(d, names) -> dict[str, set[int]]:
    """term -> the IMUs its findings cover (a finding's ``sensors`` in the report schema)."""
    out: dict[str, set[int]] = {}
    for f in d.findings:
        sensors = f.to_dict().get("sensors") or [f.sensor]
        out.setdefault(f.effect, set()).update(names.index(s) for s in sensors)
    return out


def _magnitudes(d, built: BuiltScenario) -> dict[str, float | None]:
    """max |estimate - truth| / std per finding on an injected (term, IMU); a time offset on every IMU modulo the
    gauge of time (a shift of every delay, absorbed by the motion: the differences' weighted mean removed).  A
    pooled finding's values are the change from the nominal model (discover.Finding), a per-IMU one's the
    model's values: each is compared with the truth in its own convention."""
    out = {}
    truth = {(e.term, k): v for e, v in zip(built.effects, built.values) for k in e.imus}
    n_imus = len(built.nominal.names)
    for f in d.findings:
        v = truth.get((f.effect, f.k))
        if v is None or np.shape(f.values) != np.shape(v):
            continue
        if getattr(f, "scope", "imu") != "imu":  # a change from the nominal value (a gain's nominal is 1)
            v = v - np.asarray(built.nominal.terms[f.effect].values[f.k], dtype=float)
        diff, std = np.asarray(f.values, dtype=float) - v, np.asarray(f.std, dtype=float)
        if f.effect == "time_offset" and len(getattr(f, "imus", ()) or ()) == n_imus:
            w = np.where(np.isfinite(std) & (std > 0), 1.0 / np.where(std > 0, std, 1.0) ** 2, 0.0)
            if w.sum() > 0:
                diff = diff - np.sum(w * np.nan_to_num(diff)) / w.sum()
        with np.errstate(invalid="ignore", divide="ignore"):
            z = np.abs(diff) / std
        out[f"{f.effect}@{f.sensor}"] = float(np.nanmax(z)) if np.isfinite(z).any() else None
    return out


def _alternative_correct(d, found: dict, truth: dict, names) -> bool:
    """Whether taking an alternative discovery named indistinguishable from one of its findings (an entry with
    ``alternatives``: the kept hypothesis first) instead of that finding would make the answer correct."""
    for e in d.indistinguishable:
        alts = e.get("alternatives") or []
        if len(alts) < 2:
            continue
        kept = alts[0]
        held = {names.index(s) for s in kept["sensors"]}
        if not held <= found.get(kept["effect"], set()):
            continue
        for alt in alts[1:]:
            swapped = {t: set(ks) for t, ks in found.items()}
            swapped[kept["effect"]] -= held
            swapped.setdefault(alt["effect"], set()).update(names.index(s) for s in alt["sensors"])
            if {t: ks for t, ks in swapped.items() if ks} == truth:
                return True
    return False


def score(built: BuiltScenario, d) -> dict:
    """How discovery ``d`` (a Discovery: ``findings`` with ``effect``, ``sensor``, ``k``, ``values``, ``std``
    and ``to_dict()["sensors"]``; ``unexplained`` entries with ``sensors`` and ``band_hz``) did on ``built``."""
    sc = built.scenario
    names = list(built.nominal.names)
    found = _found(d, names)
    truth: dict[str, set[int]] = {}
    for e in built.effects:
        truth.setdefault(e.term, set()).update(e.imus)
    label = lambda t, ks: f"{t}@{','.join(names[k] for k in sorted(ks))}"  # noqa: E731
    out = {"scenario": sc.name, "class": sc.cls, "variant": sc.variant, "array": sc.array, "rate_hz": sc.rate_hz,
           "still_poses": sc.still_poses, "duration_s": sc.duration_s,
           "injected": [label(e.term, e.imus) for e in built.effects],
           "found": [label(t, ks) for t, ks in sorted(found.items())],
           "detected": [found.get(e.term) == set(e.imus) for e in built.effects],
           "false_findings": [label(t, ks - truth.get(t, set())) for t, ks in sorted(found.items())
                              if ks - truth.get(t, set())],
           "evidence_target": built.oracle_target, "evidence_noise_free": built.oracle_noise_free,
           "evidence": built.oracle, "max_abs_z": _magnitudes(d, built),
           "indistinguishable": [e.get("effects") for e in d.indistinguishable],
           "unexplained_entries": len(d.unexplained), "notes": built.notes}
    timing = getattr(d, "timing", None)
    clocks = [f"{c.to_dict()['effect']}@{c.imu}" for c in (timing.findings if timing is not None else [])]
    out["clocks"] = clocks
    out["false_findings"] += clocks
    out["correct"] = found == truth and not clocks
    out["named_alternative"] = not out["correct"] and not clocks and _alternative_correct(d, found, truth, names)
    if sc.vibration is not None:
        vib = sc.vibration
        amp = np.abs(np.asarray(vib.shape, dtype=float))
        leads = [names[k] for k in np.flatnonzero(amp >= amp.max() * (1.0 - 1e-9))]  # symmetric shapes tie
        lead = leads[0]
        f = vib.frequency_hz
        out["vibration"] = {"frequency_hz": f, "amplitude": built.amplitude, "lead_imu": lead, "lead_imus": leads,
                            "shape": list(vib.shape)}
        out["located"] = any(set(leads) & set(e["sensors"]) and e["band_hz"][0] <= f <= e["band_hz"][1]
                             for e in d.unexplained)
        out["unexplained"] = [{"sensors": e["sensors"], "axes": e["axes"], "band_hz": e["band_hz"]}
                              for e in d.unexplained]
        out["detected"] = [out["located"]]
        out["correct"] = out["located"] and not found and not clocks
    out["power_evidence"] = min(built.oracle) if built.oracle else None
    out["power_detected"] = bool(out["correct"])
    return out
