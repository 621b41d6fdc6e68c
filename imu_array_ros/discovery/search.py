"""Discovery's greedy forward search (step 4 of :func:`~.discover.discover`), on the data it is given.

Every step scores every candidate (each registered term on one IMU and at every pooled scope) given the findings
so far, tests them at a Bonferroni-corrected level, and confirms the most likely by an exact refit (:mod:`.confirm`:
ties, narrowing, trading, plausibility).  The search runs on a :class:`SearchData`: the recording, or an evenly
spread subsample of its time blocks (:func:`~.blocks.search_rungs`) that a long recording is searched on first.
:class:`SearchState` carries what the search found and ruled out, so that a search ended on a subsample can go on on
a larger one or the whole recording with the same findings (:func:`ladder_search`).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable

import numpy as np
import scipy.stats

from imu_array_ros.discovery.confirm import IMPLAUSIBLE, TRADES, confirm, rejection, settle_ties, update_finding
from imu_array_ros.discovery.drift import drift_confounded
from imu_array_ros.discovery.explain import added_given, confounded, evaluate_candidates, evaluate_scopes
from imu_array_ros.discovery.extend import extension_candidates, extension_directions
from imu_array_ros.discovery.increment import increment_gate
from imu_array_ros.discovery.scopes import score_given
from imu_array_ros.discovery.subset import is_own
from imu_array_ros.fitting.engine import fit_motion, score_blocks
from imu_array_ros.model.sensor_model import SensorModel

__all__ = ["SearchData", "SearchState", "SearchSpace", "greedy_search", "ladder_search", "residuals_only", "fill",
           "rescore", "robust_gate",
           "NONE_PASS", "UNCONFIRMED", "CAP", "STOPPED"]

#: why a search ended: no candidate passed the step's level (or none was left to test)
NONE_PASS = "none pass"
#: every passing candidate failed its exact confirmation
UNCONFIRMED = "unconfirmed"
#: the cap on findings was reached
CAP = "cap"
#: the most likely candidate left was physically implausible
STOPPED = "implausible"


@dataclass
class SearchData:
    """The samples a search scores and confirms on: samples (ImuSamples), their ML motion under the current
    model, their time blocks (0 .. nb-1, non-decreasing) and each block's held-out fold; label: what they are
    (for the report's notes); share: the part of the family-wise rate alpha each step's test spends here."""

    samples: object
    motion: np.ndarray
    blocks: np.ndarray
    fold_of_block: np.ndarray
    label: str = "the recording"
    share: float = 1.0
    index: np.ndarray | None = None  # the recording's samples these are (None: all of them)


@dataclass
class SearchSpace:
    """What every step tests: the model discovery started from, the candidate terms, the pooled scopes and the
    groups tied in the score (:func:`~.scopes.scopes_for`), the terms scored with their cross-IMU blocks; groups:
    the geometry groups (the labels of the scopes an accepted finding is grown to, :mod:`.extend`)."""

    model: SensorModel
    terms: tuple
    scopes: list
    tied: list
    own: tuple
    alpha: float
    max_findings: int
    block_s: float
    groups: list = field(default_factory=list)  # the geometry groups, [(name, IMU indexes)] (scope labels)


@dataclass
class SearchState:
    """What the search has found and ruled out.  accepted: Candidate.key -> discover.Finding; fit: the last joint
    exact fit of every finding (None before the first); current: the model with them; excluded: (term, IMU) for
    good; retry: Candidate.key not confirmed, until the next finding; traded: keys trading with earlier findings
    (:mod:`.trading`), for good; candidates: every tested candidate once, then the passing ones; levels: each
    step's Bonferroni level and counts its number of candidates; step: the last step that added a finding."""

    current: SensorModel
    make_finding: Callable
    accepted: dict = field(default_factory=dict)
    fit: object = None
    excluded: set = field(default_factory=set)
    retry: set = field(default_factory=set)
    traded: set = field(default_factory=set)
    candidates: list = field(default_factory=list)
    indist: list = field(default_factory=list)
    rejected: list = field(default_factory=list)
    levels: list = field(default_factory=list)
    counts: list = field(default_factory=list)
    notes: list = field(default_factory=list)
    step: int = 0

    def set_level(self, step: int, level: float, count: int) -> None:
        """Step ``step``'s Bonferroni level and number of candidates (a later look at the step replaces them)."""
        del self.levels[step - 1:], self.counts[step - 1:]
        self.levels.append(level)
        self.counts.append(count)

    def found(self) -> list:
        """[(term, IMU indexes)] of the findings so far."""
        return [(f.effect, f.imus) for f in self.accepted.values()]


def residuals_only(samples, model: SensorModel, motion, blocks):
    """score_blocks of one small term: its normalised residuals, their expectation and the log-likelihood (which
    do not depend on the terms scored) without the cost of every candidate's information."""
    return score_blocks(samples, model, ("accelerometer_bias",), motion, blocks)


def fill(new: np.ndarray, old: np.ndarray) -> np.ndarray:
    return np.where(np.isfinite(new), new, old)


def rescore(data: SearchData, state: SearchState, space: SearchSpace):
    """Every candidate's score blocks on ``data`` given the findings so far."""
    dirs = [(t, v) for _, t, v in extension_directions(state.accepted, state.current, space.model, space.terms)]
    return score_given(data.samples, state.current, space.terms, data.motion, data.blocks, space.tied,
                       state.found(), own_terms=space.own, directions=dirs)


def robust_gate(sb, cands: list, passing: list, level: float, tied=()) -> tuple:
    """(the passing candidates a step may take, the most likely candidate when it failed only the block-robust
    test else None, the passing ones left out as confounded with it).

    The most likely candidate is the best by BIC among those passing the score test and gaining on held-out
    blocks.  When it fails only the block-robust test, the effect it stands for is there but not established
    across the recording's blocks; a runner-up that owes its evidence to the same signature would pass for it
    (another scope of the same term, a correlated term on the same IMU: a wrong finding).  A runner-up is left
    out when, given the most likely one, it adds nothing at the step's level (the joint score test of
    :func:`~.explain.confounded`, without its BIC gap: the better one is not taken, so no later step tells them
    apart); where ``sb`` holds no joint information of the two (:func:`~.explain.added_given`), when it puts its
    term on an IMU it does (an extension: on an IMU beyond the finding it grows).  Runners-up that add something
    given it are kept."""
    likely = [c for c in cands if c.lrt_p < level and c.heldout > 0.0]
    if not likely:
        return passing, None, []
    best = min(likely, key=lambda c: c.delta_bic)
    if best.robust_p < level:
        return passing, None, []
    kept, left = [], []
    for c in passing:
        a = added_given(sb, best, c, tied)
        if a is None:
            same = bool(c.added & best.added)
        else:
            same = a["added_dof"] <= 0 or scipy.stats.chi2.sf(max(a["added_statistic"], 0.0), a["added_dof"]) >= level
        (left if same else kept).append(c)
    return kept, best, left


def _not_established(best, left: list, level: float, step: int, label: str) -> str:
    p = f"{best.robust_p:.2g}" if np.isfinite(best.robust_p) else "not formed (too few blocks)"
    out = (f"step {step}: not established on {label}: the most likely candidate, {best.effect} on {best.sensor} "
           f"(score {best.statistic:.4g} on {best.dof} dof, p = {best.lrt_p:.2g}, held-out gain {best.heldout:.3g}), "
           f"fails only the block-robust test (robust p = {p}, level {level:.2g}): the evidence is there but not "
           f"robust across the recording's blocks")
    if left:
        out += "; not taken in its place, as they add nothing given it: " + ", ".join(
            f"{c.effect} on {c.sensor} (robust p = {c.robust_p:.2g})" for c in left)
    return out


def _increment_not_robust(c, simpler, inc, level: float, step: int, label: str) -> str:
    stat, dof, p = inc
    p = f"{p:.2g}" if np.isfinite(p) else "not formed"
    return (f"step {step}: {c.effect} on {c.sensor} left out on {label}: it holds {simpler.effect} on "
            f"{simpler.sensor}, and what it adds over it (score {stat:.4g} on {dof} dof) fails the block-robust "
            f"test (robust p = {p}, level {level:.2g}); the simpler one may be taken, the rest tested again given it")


def greedy_search(data: SearchData, sb, state: SearchState, space: SearchSpace, say) -> tuple:
    """Forward steps on ``data`` from its score blocks ``sb`` (given the findings in ``state``) until no candidate
    passes, none is confirmed, the cap is reached or the best is implausible.  ``state`` and ``data.motion`` are
    updated in place; returns (score blocks of the last model (residuals only at the cap), why it ended).  Each
    step tests at alpha x ``data.share`` / (its number of candidates); a step that adds no finding leaves
    ``state.step`` as it was (a later look on more data re-runs it).  A passing pooled candidate whose increment
    over a passing simpler one it holds is not block-robust is left out of the step (:mod:`.increment`)."""
    model, terms, scopes, alpha = space.model, space.terms, space.scopes, space.alpha
    names = model.names
    while state.step < space.max_findings:
        step = state.step + 1
        cover = {(f.effect, k) for f in state.accepted.values() for k in f.imus}
        skip = cover | state.excluded | {(t, imus[0]) for t, scope, imus in state.retry | state.traded
                                         if scope == "imu"}
        cands = evaluate_candidates(sb, names, data.fold_of_block, terms=terms, exclude=skip, step=step)
        gone = state.retry | state.traded | {
            (t, sc.label, sc.imus) for t in terms for sc in scopes
            if any((t, k) in cover for k in sc.imus) and (sc.kind == "own" or all((t, k) in cover for k in sc.imus))}
        cands += evaluate_scopes(sb, names, data.fold_of_block, scopes, terms=terms, exclude=gone, step=step)
        tried = state.retry | state.traded  # a pooled extension's key may name a scope the findings cover
        cands += [c for c in extension_candidates(sb, names, data.fold_of_block, state.accepted, state.current,
                                                  model, space.groups, exclude=cover | state.excluded, step=step)
                  if c.key not in (tried if is_own(c.scope) else gone)]
        if not cands:
            return sb, NONE_PASS
        level = alpha * data.share / len(cands)
        state.set_level(step, level, len(cands))
        passing = sorted((c for c in cands if c.passes(level)), key=lambda c: c.delta_bic)
        state.candidates += cands if not state.candidates else passing  # every candidate once, then the passing
        passing, likely, left = robust_gate(sb, cands, passing, level, space.tied)
        if likely is not None:
            likely.note = _not_established(likely, left, level, step, data.label)
            state.notes.append(likely.note)
            say(likely.note)
        passing, pooled = increment_gate(sb, passing, level, {key: v for key, _, v in extension_directions(
            state.accepted, state.current, model, terms)})
        for c, simpler, inc in pooled:
            c.note = _increment_not_robust(c, simpler, inc, level, step, data.label)
            state.notes.append(c.note)
            say(c.note)
        if not passing:
            say(f"step {step}: no candidate passes on {data.label} (level {level:.2g})")
            return sb, NONE_PASS
        best = stop = result = None
        for c in passing:
            say(f"step {step}: testing {c.effect} on {c.sensor} (score {c.statistic:.4g}, dof {c.dof}) exactly"
                + ("" if data.index is None else f" on {data.label}"))
            key = c.key
            result = confirm(data.samples, state.current, state.accepted, c, data.motion, level, model, alpha, say)
            if isinstance(result, str):
                c.note = result
                state.rejected.append(rejection(c, step, result))
                (state.traded if result.startswith(TRADES) else state.retry).update({key, c.key})  # as tested,
                if result.startswith(TRADES):  # as narrowed
                    state.indist.append({"effects": [c.effect], "sensors": [c.sensor], "reason": result})
                if result.startswith(IMPLAUSIBLE):
                    stop = c
                    break
                continue
            best, result = settle_ties(c, result, passing, lambda o: confirm(
                data.samples, state.current, state.accepted, o, data.motion, level, model, alpha, say), step, say,
                state.notes, state.rejected, alpha=alpha, indist=state.indist, n_imus=model.n_imus)
            break
        if stop is not None:
            state.notes.append(
                f"step {step}: stopped: the most likely candidate left, {stop.effect} on {stop.sensor}, is "
                f"{stop.note} -- a term that needs values no real sensor has stands in for physics the library "
                f"lacks, and any further finding could stand in for the same; what remains is reported unexplained")
            say(f"step {step}: {stop.effect} on {stop.sensor} is {IMPLAUSIBLE}; stopping")
            return sb, STOPPED
        if best is None:
            return sb, UNCONFIRMED
        fit, delta = result
        best.accepted = True
        state.fit, state.step = fit, step
        state.retry = set()  # the model changed: candidates the exact fit did not confirm are tested again
        for other in confounded(sb, best, passing, level) + drift_confounded(sb, best, level, space.block_s):
            state.indist.append({
                "effects": [best.effect, other["effect"]], "sensors": [best.sensor],
                "reason": other.get("reason") or (
                    f"after the motion is profiled out their signatures correlate {other['correlation']:.3f}; BIC "
                    f"gap {other['delta_bic_gap']:.1f} (< 10) and {other['effect']} adds nothing once {best.effect} "
                    f"is in (score {other['added_statistic']:.3g}); reported as {best.effect}"),
                "correlation": other["correlation"], "delta_bic_gap": other["delta_bic_gap"]})
            state.excluded.add((other["effect"], best.k))
        state.current = fit.model
        grown = state.accepted.pop(best.extends, None) if best.extends else None  # replaced by its extension
        state.accepted[best.key] = state.make_finding(best, delta, step)
        if grown is not None and grown.effect != best.effect:  # a richer term holding it (.nested)
            state.notes.append(f"step {step}: {grown.effect} on {grown.sensor} (step {grown.step}) replaced by "
                               f"{best.effect}: {best.note}")
        elif grown is not None:
            state.notes.append(f"step {step}: {best.effect} on {grown.sensor} (step {grown.step}) grown to "
                               f"{best.sensor}: {best.note}")
        for f in state.accepted.values():  # every finding's values and std from the latest joint fit
            update_finding(f, fit, model, alpha)
        say(f"step {step}: found {best.effect} on {best.sensor}: log-likelihood +{delta:.4g}")
        data.motion = fill(fit.motion, data.motion)
        data.motion, _, _ = fit_motion(data.samples, state.current, data.motion)
        if step == space.max_findings:  # no step left to test candidates: residuals only
            state.notes.append(
                f"the search stopped at its cap of {space.max_findings} findings (max_findings, --max-findings): "
                f"candidates were not re-tested after the last one; more may pass")
            return residuals_only(data.samples, state.current, data.motion, data.blocks), CAP
        say(f"step {step + 1}: re-scoring every candidate given the {len(state.accepted)} findings")
        sb = None  # memory: the last step's blocks go before the next ones are made
        sb = rescore(data, state, space)
    return sb, CAP


def ladder_search(ladder: list, state: SearchState, space: SearchSpace, say) -> tuple:
    """The search on ``ladder[0]``, then on each larger SearchData of ``ladder`` (its last the whole recording)
    only when the one before ran out of candidates (none passed or none was confirmed), its motion first refitted
    under the findings so far.  Returns (the SearchData the findings were last fitted on, its score blocks, the
    whole recording's score blocks under the final model when the last look made them there without a finding,
    else None)."""
    whole, data = ladder[-1], ladder[0]
    sb, why = greedy_search(data, rescore(data, state, space), state, space, say)
    sb_whole = None
    for rung in ladder[1:]:
        if why not in (NONE_PASS, UNCONFIRMED):
            break
        say(f"looking at {'the whole recording' if rung is whole else rung.label} for effects the samples so far "
            f"have too little evidence for")
        rung.motion = fit_motion(rung.samples, state.current, rung.motion)[0]
        before = len(state.accepted)
        sb_rung, why = greedy_search(rung, rescore(rung, state, space), state, space, say)
        if len(state.accepted) > before:  # the search went on there: the findings' fits are on those samples
            data, sb = rung, sb_rung
        sb_whole = sb_rung if rung is whole and data is not whole else None
    return data, sb, sb_whole
