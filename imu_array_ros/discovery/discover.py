"""Mismatch discovery: where a recording and the model's simulation of it differ, and which physics is missing.

:func:`discover` runs the workflow of ``imu-array discover``:

1. **Fit** the recording with the model as given: the ML motion of every
   sample (:func:`~imu_array_ros.fitting.engine.fit_motion`).
2. **Simulate**: the model's prediction of every reading for that motion; the
   residual recording - simulation is whitened by the noise model.  With a
   user's own simulation of the same run (``sim``), the localisation reads
   (recording - simulation) / (sqrt 2 sigma) instead (both are noisy).
3. **Locate** (:mod:`.locate`): the excess over noise by IMU x axis, regime,
   time span and frequency band, and the rigid-body test.
4. **Explain** (:mod:`.explain`): every candidate term (every registered term but the clock terms, which
   the timing step searches for, :mod:`.timing`) on every IMU is a candidate, tested with the fitting engine (score test with the motion
   profiled out, block-robust test, held-out blocks, BIC); greedy selection at a
   Bonferroni-corrected level, each finding confirmed by an exact refit
   (:func:`~imu_array_ros.fitting.engine.fit_terms` with ``only``), and
   confounded candidates reported as indistinguishable (:mod:`.search`).  A
   recording of more than ``search_readings`` and ``ladder_from`` readings
   (150,000: a 10-minute capture of 8 IMUs at 62.5 Hz has 300,000) is searched first on
   every k-th time block (:func:`~.blocks.search_rungs`): its strong
   effects are confirmed by refits of a k-th of the samples.  When that
   subsample runs out of candidates, every (k/2)-th block, ..., then the
   whole recording is scored given the findings and the search goes on there
   if a candidate passes, so an effect too weak for a subsample is still
   found; the subsamples share half of alpha, the whole recording the other
   half.  Findings fitted on a subsample are scored on the blocks it left out
   (their held-out check).  At the end (:mod:`.finish`) every finding is
   re-tested given the others (backward elimination, simplest adequate
   scope) and so are the timing stage's sample clocks (a clock not found
   again given the library findings stood in for them: dropped).
5. **Model what the library lacks** (:mod:`.empirical`): cells still in excess
   after the findings get a sparse regression on motion features, scored on
   held-out blocks, reported apart from the physical findings.
6. **Show the fit improve**: log-likelihood and NIS (still / moving) before and
   after, on the recording, on held-out blocks (the findings refitted on half of
   the blocks, scored on the other half, both ways; or the blocks a subsample
   search left out) and on validation recordings.

Everything is computed by the same fitting engine the calibrations use, so a
finding applied to the description (``--apply``) is a calibration result like
any other.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from imu_array_ros.discovery.blocks import (LADDER_FROM, SEARCH_READINGS, search_rungs, short_recording_options,
                                            time_blocks)
from imu_array_ros.discovery.confirm import both_found
from imu_array_ros.discovery.explain import Candidate
from imu_array_ros.discovery.finish import finish_search
from imu_array_ros.discovery.heldout import between_gain, complement_gain, heldout_gain
from imu_array_ros.discovery.scopes import OWN_MAX_IMUS, geometry_groups, scopes_for
from imu_array_ros.discovery.search import SearchData, SearchSpace, SearchState, ladder_search, residuals_only
from imu_array_ros.discovery.threads import on_one_blas_thread
from imu_array_ros.discovery.timing import session_model, timing_stage
from imu_array_ros.errors import CalibrationError
from imu_array_ros.fitting.engine import fit_motion, keep_schur
from imu_array_ros.fitting.optimiser import backtracking
from imu_array_ros.model.constants import STANDARD_GRAVITY
from imu_array_ros.model.sensor_model import SensorModel
from imu_array_ros.model.terms import REGISTRY, candidate_names, term_names
from imu_array_ros.util.names import did_you_mean

__all__ = ["DiscoveryOptions", "Discovery", "Finding", "discover", "fit_summary"]

#: near saturation: |reading| above this share of the clip level
NEAR_SATURATION = 0.9
#: the part of the family-wise false-finding rate alpha a long recording's subsamples share (equally) between them;
#: every look at the whole recording spends the rest, so that the looks at one step (one per rung at most) spend at
#: most alpha together and the first false finding, at whichever step and look, has probability <= alpha
SUBSAMPLE_SHARE = 0.5


@dataclass
class DiscoveryOptions:
    """terms: candidate registry names (default :func:`~imu_array_ros.model.terms.candidate_names`); alpha: family-wise false-finding rate
    per recording; block_s: time block (s) of the robust test and the held-out folds; folds: interleaved folds;
    max_findings: cap on the greedy steps; still_threshold: |omega| (rad/s) below which a sample is still;
    empirical: model the unexplained residual; heldout: exact held-out check of the final findings;
    timing: search for sample clocks the model lacks (:mod:`.timing`); search_readings: a recording of more
    readings (samples x IMUs) than search_readings and ladder_from is searched on evenly spread subsamples of its
    blocks first (:func:`~.blocks.search_rungs`; None: never)."""

    terms: tuple[str, ...] | None = None
    alpha: float = 0.01
    block_s: float = 0.5
    folds: int = 4
    max_findings: int = 8
    still_threshold: float = 0.2
    empirical: bool = True
    heldout: bool = True
    timing: bool = True
    search_readings: int | None = SEARCH_READINGS
    ladder_from: int = LADDER_FROM

    def candidate_terms(self) -> tuple[str, ...]:
        names = candidate_names() if self.terms is None else list(self.terms)
        unknown = [t for t in names if t not in REGISTRY]
        if unknown:
            near = did_you_mean(unknown[0], term_names())
            raise CalibrationError(f"unknown term {unknown[0]!r}{f'; did you mean {near!r}?' if near else ''} "
                                   f"(known: {', '.join(term_names())})")
        if not names:
            raise CalibrationError("no candidate terms")
        return tuple(dict.fromkeys(names))


@dataclass
class Finding:
    """A term found on one IMU or at a pooled scope (:mod:`.scopes`): values (P,) and their CRB std (SI), the
    evidence at the step it was added.  A pooled finding (scope "all shared", "top shared", "all own", ...;
    imus its IMUs, k the first) is fitted exactly with each IMU's own value (imu_values, imu_std (G, P)); tie:
    the test that they share one value (:func:`~.scopes.tie_test`); values/std: that shared value (the change
    from the input model's values); shared: whether the tie test accepts it (p >= alpha)."""

    effect: str
    k: int
    sensor: str
    values: np.ndarray
    std: np.ndarray
    candidate: Candidate
    exact_delta_loglik: float
    step: int
    scope: str = "imu"
    imus: tuple = ()
    imu_values: np.ndarray | None = None
    imu_std: np.ndarray | None = None
    tie: dict | None = None
    shared: bool = False

    def to_dict(self) -> dict:
        names = REGISTRY[self.effect].parameter_names()
        c = self.candidate
        pooled = {} if self.scope == "imu" else {
            "per_imu": {str(s): {n: float(v) for n, v in zip(names, vals)}
                        for s, vals in zip(c.sensors, self.imu_values)},
            "per_imu_std": {str(s): {n: _num(v) for n, v in zip(names, vals)}
                            for s, vals in zip(c.sensors, self.imu_std)},
            "shared_value": self.shared,
            "tie_test": {"statistic": _num(self.tie["statistic"]), "dof": self.tie["dof"], "p": self.tie["p"],
                         "method": "Wald test of one value shared by the IMUs in their own frames (GLS with the "
                                   "exact fit's CRB)"}}
        return {"effect": self.effect, "sensors": list(c.sensors), "scope": self.scope, **pooled,
                "parameters": {n: float(v) for n, v in zip(names, self.values)},
                "std": {n: _num(s) for n, s in zip(names, self.std)},
                "units": {f.key: f.unit for f in REGISTRY[self.effect].fields},
                "step": self.step,
                "evidence": {"delta_loglik": float(self.exact_delta_loglik), "lrt_p": float(c.lrt_p),
                             "log_lrt_p": float(c.log_p), "robust_p": float(c.robust_p),
                             "delta_bic": float(c.delta_bic), "heldout_delta_loglik": float(c.heldout),
                             "statistic": float(c.statistic), "dof": int(c.dof)}}


def _num(x):
    return None if x is None or not np.isfinite(x) else float(x)


@dataclass
class FitSummary:
    """How well a model explains a recording at its ML motion: log-likelihood and NIS by regime, (K, 6) maps; the
    motion (N, 9) (``--apply``'s scores start from it: :class:`~.apply.StartedScorer`)."""

    loglik: float
    nis_still: float
    nis_moving: float
    observed: dict = field(repr=False)
    expected: dict = field(repr=False)
    samples: dict = field(default_factory=dict)
    motion: np.ndarray | None = field(default=None, repr=False)

    def ratio(self, regime: str = "all") -> np.ndarray:
        with np.errstate(invalid="ignore", divide="ignore"):
            return self.observed[regime] / self.expected[regime]

    def to_dict(self) -> dict:
        return {"nis_still": _num(self.nis_still), "nis_moving": _num(self.nis_moving),
                "loglik": float(self.loglik), "samples": dict(self.samples)}


def _summarise(residuals, expected, motion, loglik, still_threshold) -> FitSummary:
    omega = np.linalg.norm(np.nan_to_num(motion[:, :3]), axis=1)
    still = omega < still_threshold
    obs, exp, counts = {}, {}, {}
    r2 = np.nan_to_num(residuals) ** 2
    e = np.nan_to_num(expected)
    for regime, sel in (("still", still), ("moving", ~still), ("all", np.ones_like(still))):
        obs[regime], exp[regime] = r2[sel].sum(axis=0), e[sel].sum(axis=0)
        counts[regime] = int(sel.sum())

    def nis(regime):
        total = exp[regime].sum()
        return float(obs[regime].sum() / total) if total > 0 else float("nan")
    return FitSummary(float(loglik), nis("still"), nis("moving"), obs, exp, counts, motion)


def fit_summary(samples, model: SensorModel, *, still_threshold: float = 0.2, motion0=None):
    """(FitSummary, motion, ScoreBlocks-like residuals/expected) of ``samples`` under ``model`` at its ML motion."""
    motion, _, _ = fit_motion(samples, model, motion0)
    sb = residuals_only(samples, model, motion, np.zeros(len(samples.stamps), dtype=np.int64))
    return _summarise(sb.residuals, sb.expected, motion, sb.loglik, still_threshold), motion, sb


@dataclass
class Discovery:
    """What :func:`discover` found; ``to_dict()`` is the report.json schema."""

    names: tuple[str, ...]
    model: SensorModel
    baseline: FitSummary
    after: FitSummary
    findings: list[Finding]
    candidates: list[Candidate]
    indistinguishable: list[dict]
    rejected: list[dict]
    localization_before: object
    localization_after: object
    unexplained: list[dict]
    empirical: list
    heldout: dict
    validation: list[dict]
    settings: dict
    timings: dict
    level_per_step: list[float]
    notes: list[str] = field(default_factory=list)
    sim_source: str = "model"
    timing: object = None

    def to_dict(self) -> dict:
        loc = self.localization_before
        return {
            "baseline": self.baseline.to_dict(),
            "localization": loc.entries() if loc is not None else [],
            "findings": [f.to_dict() for f in self.findings],
            "indistinguishable": self.indistinguishable,
            "unexplained": self.unexplained,
            "after": self.after.to_dict(),
            "heldout": self.heldout,
            "validation": self.validation,
            "rejected": self.rejected,
            "candidates": [c.to_dict() for c in self.candidates],
            "localization_detail": {"before": loc.to_dict() if loc is not None else None,
                                    "after": (self.localization_after.to_dict()
                                              if self.localization_after is not None else None),
                                    "source": self.sim_source},
            "settings": self.settings,
            "timings_s": self.timings,
            "notes": self.notes,
            "timing": self.timing.to_dict() if self.timing is not None else None,
        }


def _near_saturation(samples, model: SensorModel) -> np.ndarray:
    acc = np.abs(np.nan_to_num(samples.accel)) >= NEAR_SATURATION * model.acc_clip
    gyr = np.abs(np.nan_to_num(samples.gyro)) >= NEAR_SATURATION * model.gyro_clip
    return np.concatenate([acc, gyr], axis=2)


def _localize(residuals, expected, motion, samples, model, still_threshold):
    from imu_array_ros.discovery.locate import localize

    return localize(residuals, expected, motion, samples.stamps, model.names,
                    near_saturation=_near_saturation(samples, model), rotations=model.rotations,
                    positions=model.positions, acc_std=model.acc_std, still_threshold=still_threshold,
                    gravity=STANDARD_GRAVITY, std=model.std)


def _sim_residuals(samples, sim, model: SensorModel):
    """(recording - simulation) / (sqrt 2 sigma) and its expectation 1 on the axes valid in both."""
    if len(sim.stamps) != len(samples.stamps):
        raise CalibrationError(f"sim: the simulated recording has {len(sim.stamps)} samples, the recording "
                               f"{len(samples.stamps)}; simulate the same run (same stamps)")
    differ = np.flatnonzero(sim.stamps != samples.stamps)
    if differ.size:
        i = int(differ[0])
        raise CalibrationError(f"sim: the simulated recording's stamps do not match the recording's at "
                               f"{differ.size} of {len(sim.stamps)} samples (first: sample {i}, "
                               f"{int(sim.stamps[i])} vs {int(samples.stamps[i])} ns); simulate the same run")
    if tuple(sim.names) != tuple(samples.names):
        raise CalibrationError("sim: the simulated recording's IMUs differ from the recording's")
    valid = model.valid(samples.accel, samples.gyro) & model.valid(sim.accel, sim.gyro)
    d = np.concatenate([samples.accel - sim.accel, samples.gyro - sim.gyro], axis=2) / (np.sqrt(2) * model.std)
    return np.where(valid, d, np.nan), np.where(valid, 1.0, np.nan)


@on_one_blas_thread
@keep_schur()  # its exact refits' motion steps read each linearisation's G_n (fitting.problem.keep_schur)
@backtracking()  # its refits step along Gauss-Newton directions before they damp (fitting.optimiser.backtracking)
def discover(samples, model: SensorModel, *, options: DiscoveryOptions | None = None, sim=None,
             validate=(), progress=None) -> Discovery:
    """The mismatch-discovery workflow (module docstring) on ``samples`` (ImuSamples) under ``model``.

    sim: the user's simulated recording of the same run (ImuSamples, same stamps and IMUs) or None;
    validate: [(label, ImuSamples)] other recordings to score the findings on; progress(text): stage lines.
    """
    opts = options or DiscoveryOptions()
    say = progress or (lambda text: None)
    if tuple(samples.names) != tuple(model.names):
        raise CalibrationError("the recording's IMUs differ from the description's")
    terms = opts.candidate_terms()
    notes = []
    stamps = samples.stamps
    if "time_offset" in terms and np.any(np.diff(stamps) <= 0):
        terms = tuple(t for t in terms if t != "time_offset")
        notes.append("time_offset not tested: the stamps do not increase strictly")
    timings, t0 = {}, time.perf_counter()
    opts = short_recording_options(stamps, opts, notes, say)
    blocks = time_blocks(stamps, opts.block_s)
    nb = int(blocks[-1]) + 1
    fold_of_block = np.arange(nb) % opts.folds

    # 1-2. fit and simulate
    say("fitting the motion with the model as given")
    motion, base_ll, base_r = fit_motion(samples, model)
    base_motion = motion
    sb = residuals_only(samples, model, motion, blocks)
    baseline = _summarise(sb.residuals, sb.expected, motion, sb.loglik, opts.still_threshold)
    timings["fit"] = time.perf_counter() - t0

    # 3. locate
    t1 = time.perf_counter()
    if sim is not None:
        res, exp = _sim_residuals(samples, sim, model)
        sim_source = "recording - simulated recording (--sim), / (sqrt(2) sigma)"
    else:
        res, exp = sb.residuals, sb.expected
        sim_source = "recording - model prediction at the ML motion, / sigma"
    say("locating the excess over noise")
    loc_before = _localize(res, exp, motion, samples, model, opts.still_threshold)
    timings["locate"] = time.perf_counter() - t1

    # 3b. timing physics the model lacks (.timing): sample clocks, found by search; on a long recording their
    # likelihood tested on the subsample the search starts on, the whole recording's motion fitted only when needed
    rungs = search_rungs(blocks, model.n_imus, opts.search_readings, opts.folds, opts.ladder_from)
    on = rungs[0][0] if rungs else None
    timing, current, whole_ml = None, model, True
    if opts.timing:
        t1 = time.perf_counter()
        timing = timing_stage(samples, model, motion=motion, loglik=base_ll, residuals=base_r, say=say, on=on,
                              on_label=f"every {_nth(rungs[0][2])} time block" if rungs else "")
        if timing.model is not model:
            current = timing.model
            # the scores below start from its ML motion (the timing stage's own, when it kept it): of the first
            # subsample alone on a long recording, elsewhere the input model's as the start of a later fit
            part = samples if on is None else samples.select(on)
            found = timing.motion if timing.motion is not None else fit_motion(part, current, motion[on] if
                                                                               rungs else motion)[0]
            motion, whole_ml = (found, True) if on is None else (motion.copy(), False)
            if on is not None:
                motion[on] = found
        timings["timing"] = time.perf_counter() - t1

    # 4. explain (.search): on a long recording first on an evenly spread subsample of its blocks
    t1 = time.perf_counter()
    groups = geometry_groups(model.positions, model.rotations)
    scopes, tied = scopes_for(model.n_imus, groups)
    space = SearchSpace(model, terms, scopes, tied, terms if model.n_imus <= OWN_MAX_IMUS else (), opts.alpha,
                        opts.max_findings, opts.block_s, groups)
    state = SearchState(current, lambda c, delta, step: Finding(c.effect, c.k, c.sensor, np.zeros(0), np.zeros(0),
                                                                c, delta, step, c.scope, c.imus), notes=notes)
    whole = SearchData(samples, motion, blocks, fold_of_block)
    start_model, start_motion = current, motion
    ladder = [SearchData(samples.select(index), motion[index], sub_blocks,
                         np.arange(int(sub_blocks[-1]) + 1) % opts.folds, f"every {_nth(k)} time block",
                         SUBSAMPLE_SHARE / len(rungs), index) for index, sub_blocks, k in rungs] + [whole]
    whole.share = 1.0 - SUBSAMPLE_SHARE if rungs else 1.0
    if rungs:
        say(f"searching {len(rungs[0][0])} of {len(stamps)} samples first ({ladder[0].label} of {opts.block_s:g} s): "
            f"the recording holds more than {opts.search_readings} readings")
    say(f"scoring {len(terms)} terms x {model.n_imus} IMUs at {len(scopes) + model.n_imus} scopes")
    data, sb, sb_whole = ladder_search(ladder, state, space, say)
    done = finish_search(samples, model, data, whole, state, start_motion, sb, sb_whole, terms=terms,
                         alpha=opts.alpha, groups=groups, timing=timing, notes=notes, say=say)
    findings, current, motion, sb = done.findings, done.model, done.motion, done.scores
    if timing is not None and timing.dropped:  # stand-ins for findings: held out against the start without them
        start_model = timing.without(start_model)
    all_candidates, rejected, levels = state.candidates, state.rejected, state.levels
    indist = both_found(state.indist, findings, notes)
    timings["explain"] = time.perf_counter() - t1

    # 5-6. after, unexplained, held out
    t1 = time.perf_counter()
    after = _summarise(sb.residuals, sb.expected, motion, sb.loglik, opts.still_threshold)
    say("locating what is left")
    loc_after = _localize(sb.residuals, sb.expected, motion, samples, current, opts.still_threshold)
    unexplained, empirical = [], []
    if opts.empirical:
        say("modelling the unexplained residual empirically")
        unexplained, empirical = _unexplained(loc_after, sb, motion, samples, current, blocks, fold_of_block)
    heldout = {}
    if opts.heldout and findings and data is not whole and not whole_ml:
        # the timing stage fitted the start model on the first subsample only: held out, the blocks half-way
        # between the searched ones (as many), not a fit of the whole recording under the start model
        k = rungs[next(i for i, rung in enumerate(ladder) if rung is data)][2]
        say("held-out blocks: scoring the findings on the blocks half-way between the searched ones")
        heldout = between_gain(samples, current, start_model, motion, np.flatnonzero(blocks % k == k // 2),
                               data.label, f"every {_nth(k)} time block from the {_nth(k // 2 + 1)}")
    elif opts.heldout and findings and data is not whole:
        say("held-out blocks: scoring the findings on the blocks the subsample left out")
        start_r = residuals_only(samples, start_model, start_motion, blocks).residuals
        heldout = complement_gain(sb.residuals, start_r, data.index, data.label)
    elif opts.heldout and findings:
        say("held-out blocks: refitting the findings on half of the blocks, scoring on the other half")
        # under the model the search started from (the timing stage's clocks it kept), as the findings were found
        ref = (base_motion, base_r) if start_model is model else fit_motion(samples, start_model, start_motion)[::2]
        heldout = heldout_gain(samples, start_model, findings, blocks, *ref)
    validation = []
    for label, other in validate:
        say(f"validating on {label}")
        validation.append(_validate(label, other, model, current, opts.still_threshold))
    timings["after"] = time.perf_counter() - t1
    timings["total"] = time.perf_counter() - t0
    settings = {"terms": list(terms), "alpha": opts.alpha, "block_s": opts.block_s, "folds": opts.folds,
                "max_findings": opts.max_findings, "still_threshold": opts.still_threshold,
                "candidates_per_step": list(state.counts),
                "level_per_step": levels, "samples": int(len(stamps)), "imus": list(model.names),
                "false_finding_rate": (f"family-wise <= {opts.alpha:g} per recording (Bonferroni: each step tests "
                                       f"its m candidates at {opts.alpha:g}/m, both the score test and the "
                                       f"block-robust test, and needs a positive held-out gain)"
                                       + ("" if not rungs else
                                          f"; searched first on subsamples ({', '.join(r.label for r in ladder[:-1])}), "
                                          f"then the whole recording, each only when the one before ran out: every "
                                          f"look at a subsample tests at {SUBSAMPLE_SHARE / len(rungs):.3g} alpha/m, "
                                          f"at the whole recording at {1 - SUBSAMPLE_SHARE:g} alpha/m, so the "
                                          f"looks at one step spend at most alpha")),
                "search_readings": opts.search_readings,
                "search_subsamples": [{"every_kth_block": int(k), "samples": int(len(index)),
                                       "alpha_share": SUBSAMPLE_SHARE / len(rungs)} for index, _, k in rungs],
                "searched_on": "the whole recording" if data is whole else data.label}
    return Discovery(model.names, current, baseline, after, findings, all_candidates, indist, rejected,
                     loc_before, loc_after, unexplained, empirical, heldout, validation, settings, timings, levels,
                     notes, sim_source, timing)


def _validate(label, other, model: SensorModel, found: SensorModel, still_threshold) -> dict:
    if tuple(other.names) != tuple(model.names):
        raise CalibrationError(f"validate {label}: its IMUs differ from the description's")
    before, motion, _ = fit_summary(other, model, still_threshold=still_threshold)
    after, _, _ = fit_summary(other, session_model(other, found), still_threshold=still_threshold, motion0=motion)
    return {"recording": str(label), "before": before.to_dict(), "after": after.to_dict(),
            "delta_loglik": after.loglik - before.loglik}


def _unexplained(loc, sb, motion, samples, model, blocks, fold_of_block):
    """Entries of the localisation after the findings, each with the empirical models of its cells."""
    from imu_array_ros.discovery.empirical import fit_empirical, motion_features
    from imu_array_ros.fusion.residuals import AXES

    entries = loc.entries()
    if not entries:
        return [], []
    cells = sorted({(model.names.index(s), AXES.index(a)) for e in entries for s in e["sensors"] for a in e["axes"]})
    feats, fnames = motion_features(motion, samples.stamps)
    folds = fold_of_block[blocks]
    models = fit_empirical(sb.residuals, feats, fnames, cells, folds, std=model.std, expected=sb.expected)
    by_cell = {(m.k, m.axis): m for m in models}
    out = []
    for e in entries:
        ems = [by_cell[(model.names.index(s), a)] for s in e["sensors"] for a in e["axes"]
               if (model.names.index(s), a) in by_cell]
        out.append({"sensors": e["sensors"], "axes": e["axes"], "band_hz": e["band_hz"], "regime": e["regime"],
                    "share_of_residual": e["share_of_excess"],
                    "empirical_model": {
                        "method": "sequentially thresholded least squares of the normalised residual on motion "
                                  "features (SINDy-like), fitted on training folds, scored on held-out folds",
                        "improves_heldout": any(m.improves for m in ems),
                        "heldout_delta_loglik": float(sum(m.heldout_delta_loglik for m in ems)),
                        "cells": [m.to_dict() for m in ems]}})
        if "mode" in e:  # a narrowband mode (discovery/modes.py): its shape, presence and held-out model
            out[-1]["mode"] = e["mode"]
    return out, models


def _nth(k: int) -> str:
    return {2: "2nd", 3: "3rd"}.get(k, f"{k}th")
