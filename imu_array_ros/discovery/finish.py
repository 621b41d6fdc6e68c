"""The end of the search: every finding re-tested given all the others, then the whole recording under them.

After the forward search (:mod:`.search`) :func:`finish_search`

0. when the search found nothing while the timing stage kept sample clocks, lets the clocks compete with the most
   likely library candidate (:func:`clocks_or_candidate`): a clock can absorb a missing gain's or misalignment's
   misfit so that no library term passes (or the one that does needs implausible values) given it;
1. re-tests the timing stage's sample clocks given the library findings (:func:`~.timing.retest_clocks`): the
   timing stage runs before the library search, so a missing gain or misalignment, whose residual follows the
   motion, can be taken for a clock (its "delays" beat with the twisting); a clock the search does not find again
   under the findings is dropped and the findings refitted without it, reported in the timing notes.  First, so
   that a finding the stand-in brought in (its misfit) faces the backward elimination without it;
2. drops the findings no longer significant given the others (:func:`~.eliminate.backward_eliminate`);
3. re-tests each IMU of a finding for a simpler hypothesis (:func:`~.eliminate.simplest_adequate`), and when it
   narrowed or replaced one, every finding again as in 2 (a finding narrowed to the one IMU it keeps is tested
   there: the narrowing keeps at least one);
4. names, for each finding holding one value on some of the IMUs, the opposite value on the others when it fits
   as well up to the fit's gauge (:func:`~.complement.complement_ties`; "indistinguishable", the finding kept);
5. fits the whole recording's motion under the final model when the search ended on a subsample.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from imu_array_ros.discovery.complement import complement_ties
from imu_array_ros.discovery.confirm import confirm, refit, update_finding
from imu_array_ros.discovery.eliminate import backward_eliminate, dropped_notes, simplest_adequate, wald_given_others
from imu_array_ros.discovery.search import fill, residuals_only
from imu_array_ros.discovery.timing import retest_clocks
from imu_array_ros.errors import CalibrationError
from imu_array_ros.fitting.engine import fit_motion
from imu_array_ros.model.sensor_model import SensorModel

__all__ = ["Finished", "finish_search", "drop_stand_in_clocks", "clocks_or_candidate"]


@dataclass
class Finished:
    """What the search ends with: the findings kept, the model with them, the whole recording's ML motion under it
    and its residuals (search.residuals_only of the samples the report is of)."""

    findings: list
    model: SensorModel
    motion: np.ndarray
    scores: object


def drop_stand_in_clocks(samples, fit_on, start: SensorModel, findings: list, current: SensorModel, motion, timing,
                         alpha: float, say=lambda text: None):
    """The timing stage's clocks (``timing``, changed in place) a search of ``samples`` (the whole recording, as the
    timing stage searched) does not find again under ``current`` (the model with the findings) dropped from it, the
    findings (changes from ``start``) refitted on ``fit_on`` (the samples they were fitted on; ``motion`` theirs).
    Returns (fit, current, motion): fit the refit without the clocks dropped (FitResult), None when none is (every
    clock is found again, or the refit without the stand-ins fails: then kept, and said in the timing notes)."""
    if timing is None or not timing.findings or not findings:
        return None, current, motion
    say(f"timing: searching again for the {len(timing.findings)} sample clock(s), given the {len(findings)} findings")
    gone = retest_clocks(samples, current, timing)
    if not gone:
        timing.notes.append(f"re-tested given the library findings ({len(findings)}): every clock found again")
        return None, current, motion
    base = timing.without(current, gone)
    try:
        fit = refit(fit_on, base, [(g.effect, g.imus) for g in findings], motion)
    except CalibrationError as err:
        timing.notes.append(f"the clocks of {_named(gone)} were not found again given the library findings, but the "
                            f"findings could not be refitted without them ({err}): kept")
        return None, current, motion
    for g in findings:
        update_finding(g, fit, start, alpha)
    terms = ", ".join(dict.fromkeys(f.effect for f in findings))
    timing.drop(gone, f"not found again given the library findings ({terms}): a "
                      "stand-in for them (a misfit that follows the motion beats with the twisting like a clock's "
                      "delays), dropped; the findings refitted without it")
    say(f"timing: {len(gone)} sample clock(s) not found again given the findings; dropped")
    return fit, fit.model, np.where(np.isfinite(fit.motion), fit.motion, motion)


def clocks_or_candidate(samples, data, start: SensorModel, state, timing, alpha: float, say=lambda text: None) -> bool:
    """When the search (``state``, on ``data``) ended with no finding while the timing stage kept sample clocks
    (``timing``): the clocks against the most likely library candidate of the search's first step (the smallest
    BIC given the clocks, whatever became of it).  The candidate is confirmed exactly (:func:`~.confirm.confirm`,
    at that step's level on ``data``) from the model without any of the clocks, then the clocks are searched again
    (:func:`~.timing.retest_clocks`, on ``samples``, the whole recording) given it.  The clocks not found again
    were a stand-in for it (a misfit that follows the motion beats with the twisting like a clock's delays): they
    are dropped and the candidate becomes the search's one finding (step 1), refitted with the clocks found again
    (and re-tested, Wald given them, at the same level).  A chip's own clock is found again given any library
    term: then nothing changes.  Returns True when the candidate replaced clocks (``state``: its finding, fit,
    model; ``data.motion`` and ``timing`` updated), else False (the reason in the timing notes).  The search is
    not run again after the change: a second missing term would have to pass given the first on its own."""
    scored = [c for c in state.candidates if np.isfinite(c.delta_bic)]
    if timing is None or not timing.findings or state.accepted or not scored or not state.counts:
        return False
    best = min(scored, key=lambda c: c.delta_bic)
    c = replace(best, note="", accepted=False)  # confirm narrows its candidate in place: the search's stays as it was
    level = alpha * data.share / state.counts[0]
    say(f"timing: no library finding given the {len(timing.findings)} sample clock(s): testing the most likely "
        f"candidate, {c.effect} on {c.sensor}, without them")
    result = confirm(data.samples, timing.without(state.current, timing.findings), {}, c, data.motion, level, start,
                     alpha, say)
    if isinstance(result, str):
        timing.notes.append(f"no library finding given the clocks; the most likely candidate, {c.effect} on "
                            f"{c.sensor}, without them: {result}: the clocks kept")
        return False
    fit, delta = result
    gone = retest_clocks(samples, fit.model, timing)
    if not gone:
        timing.notes.append(f"no library finding given the clocks; every clock found again given the most likely "
                            f"candidate, {c.effect} on {c.sensor}: kept")
        return False
    if len(gone) < len(timing.findings):  # the candidate refitted with the clocks found again, and re-tested
        try:
            fit = refit(data.samples, timing.without(state.current, gone), [(c.effect, c.imus)], data.motion)
        except CalibrationError as err:
            timing.notes.append(f"the clocks of {_named(gone)} were not found again given {c.effect} on {c.sensor}, "
                                f"but it could not be refitted with the others ({err}): kept")
            return False
        stat, dof, p = wald_given_others(fit, c, start, alpha)
        if not p < level:
            timing.notes.append(f"the clocks of {_named(gone)} were not found again given {c.effect} on {c.sensor}, "
                                f"but with the other clocks it is not significant (Wald {stat:.3g} on {dof} dof, "
                                f"p = {p:.2g} >= {level:.2g}): kept")
            return False
        delta = fit.loglik_after - fit.loglik_before
    c.accepted = True
    state.set_level(1, level, state.counts[0])
    state.candidates.append(c)
    finding = state.make_finding(c, delta, 1)
    state.accepted[c.key] = finding
    state.fit, state.current, state.step = fit, fit.model, 1
    update_finding(finding, fit, start, alpha)
    data.motion = np.where(np.isfinite(fit.motion), fit.motion, data.motion)
    timing.drop(gone, f"not found again given {c.effect} on {c.sensor}, the most likely library candidate (no "
                      f"candidate was found given the clocks; without them it is, log-likelihood +{delta:.4g}): a "
                      "stand-in for it (a misfit that follows the motion beats with the twisting like a clock's "
                      "delays), dropped; the candidate kept as the search's finding")
    say(f"timing: {len(gone)} sample clock(s) not found again given {c.effect} on {c.sensor}; dropped, it kept")
    return True


def _named(clocks) -> str:
    return ", ".join(f"{f.imu} {f.sensor}" for f in clocks)


def finish_search(samples, model: SensorModel, data, whole, state, start_motion, scores, whole_scores, *, terms,
                  alpha: float, groups, timing, notes: list, say=lambda text: None) -> Finished:
    """Steps 0-5 of the module docstring.  samples: the whole recording; model: the input model (the findings are
    changes from it); data: the SearchData the search ended on, whole: the whole recording's; state: the
    SearchState (its rejected and notes extended here); start_motion: the motion the search started from (filled
    in where a subsample left samples out); scores / whole_scores: residuals_only of ``data`` under the search's
    model and of the whole recording (None: not computed); timing: the timing stage's TimingDiscovery or None."""
    swapped = clocks_or_candidate(samples, data, model, state, timing, alpha, say)  # 0: nothing found given clocks
    findings = sorted(state.accepted.values(), key=lambda f: f.step)
    current, motion, fit = state.current, data.motion, state.fit
    # the timing stage's clocks first: a stand-in the findings explain can have brought in findings of its own
    clock_fit, current, motion = (fit, current, motion) if swapped else drop_stand_in_clocks(
        samples, data.samples, model, findings, current, motion, timing, alpha, say)
    if clock_fit is not None:
        fit = clock_fit
        notes.append("timing: " + timing.notes[-1])
    dropped = []
    if len(findings) > 1:  # every finding re-tested given all the others (.eliminate)
        say(f"backward: re-testing each of the {len(findings)} findings given the others")
        findings, dropped, fit, current, motion = backward_eliminate(data.samples, model, findings, fit, motion,
                                                                     state.levels, alpha, say)
        notes += dropped_notes(dropped)
    # each IMU of a finding re-tested for a simpler hypothesis given all the others (.eliminate, .nested)
    findings, simpler, fit, current, motion = simplest_adequate(data.samples, model, findings, fit, motion, terms,
                                                              alpha, state.make_finding, groups, current, say)
    notes += [f"simplest adequate: {r['reason']} (see rejected)" for r in simpler]
    if simpler and fit is not None:  # a finding narrowed to fewer IMUs: is it still significant on them?
        say(f"backward: re-testing each of the {len(findings)} findings after the simpler hypotheses")
        findings, again, fit, current, motion = backward_eliminate(data.samples, model, findings, fit, motion,
                                                                   state.levels, alpha, say)
        notes += dropped_notes(again)
        dropped += again
    state.rejected += dropped + simpler
    complement_ties(data.samples, model, current, findings, motion, alpha, state.indist, say)  # 4
    if dropped or simpler or clock_fit is not None:
        motion, _, _ = fit_motion(data.samples, current, motion)
        scores, whole_scores = residuals_only(data.samples, current, motion, data.blocks), None
    if data is not whole:  # the findings were fitted on a subsample: the whole recording under them
        n, m = len(samples.stamps), len(data.index)
        if findings:
            notes.append(f"the findings were fitted on a subsample, {data.label} ({m} of {n} samples): their values, "
                         f"std and evidence are the subsample's (a fit of the whole recording would narrow their std "
                         f"by about {np.sqrt(n / m):.2g}x); the other blocks are their held-out check")
        if whole_scores is not None:  # the last look scored the whole recording under the final model
            motion, scores = whole.motion, whole_scores
        else:
            say("fitting the whole recording's motion with the findings")
            motion, _, _ = fit_motion(samples, current, fill(whole.motion, start_motion))
            scores = residuals_only(samples, current, motion, whole.blocks)
    return Finished(findings, current, motion, scores)
