"""Timing physics as discovery candidates: per-chip sample clocks, found by search, not by Gauss-Newton.

A chip sampling on its own free-running clock and read by the host at the stamps delivers readings
0 to ~1 period old, the age a sawtooth in time (:mod:`imu_array_ros.timing.sawtooth`).  The engine's
score test cannot see it (the sawtooth's rate moves its wraps, which a first-order Jacobian does not
follow; the clock terms are not ``candidate`` terms), so :func:`timing_stage` searches for it as
``calibrate all --timing`` does (:func:`~imu_array_ros.timing.clocks.find_sample_clocks`): each
sensor's (gyroscope's, accelerometer's) reading delays relative to the other IMUs
(:func:`~imu_array_ros.timing.delays.reading_delays`) are searched for a sawtooth of period ``period``
within +-8000 ppm.

**False-finding control**: a chip's sensor has a clock when the sawtooth's spectral peak is at least
``MIN_SNR`` (8) times the median of its spectrum over the searched rates.  Under the null (no clock,
delays that are noise) |S| is Rayleigh at each rate, so P(peak / median >= 8) at one rate is
exp(-(8 sqrt(2 ln 2))^2 / 2) = 2^-64, and over the ~10^3-10^4 rates resolved in the search the
false-alarm rate per chip is below 1e-15.  Measured on simulated nulls (:data:`NULL_MEASURED`):
the largest ratio seen on any null chip.  The ratio alone is not enough when the model is wrong and the
motion periodic (regular pose changes beat with the reads): a sensor's clocks are kept only when they lower
its unexplained relative reading delays, and used only when they raise the log-likelihood.

When clocks are found, the model continues with them (rates: device constants; phases: this
recording's session states, :func:`~imu_array_ros.timing.session.estimate_session`; the constant delay
each sawtooth leaves moved into the sensor's ``time_offset``), and the log-likelihood gain is that of
the engine's ML motion (:func:`~imu_array_ros.fitting.engine.fit_motion`) under the model with the
clocks held against the model without.  ``discover --apply`` writes the periods and rates; phases are
session states, never written.

On a long recording (``on``: the samples of the first subsample discovery searches, every k-th time block,
:func:`~imu_array_ros.discovery.blocks.search_rungs`) the clocks are searched and their phases estimated on the
whole recording (the sawtooth's spectrum needs it), but the two likelihood comparisons -- the clocks' gain and
the reading rates' test -- are made on those samples alone, so that no motion fit of the whole recording under
the clocked model precedes the search; ``motion`` is then the ML motion of those samples.  Both are tests of
a difference on blocks chosen by their place in time, valid on any of them; the real captures pass them by
orders of magnitude (exp_3: the rates gain 1,200 times chance on the whole recording).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from imu_array_ros.calibration.timing import CLOCK_PERIOD
from imu_array_ros.fitting.engine import fit_motion
from imu_array_ros.fitting.reading_rates import RATES, keep_rates, reading_rates
from imu_array_ros.fusion.model_fusion import ModelFusion
from imu_array_ros.model.terms.time_offset import TimeOffset
from imu_array_ros.timing.clocks import MIN_SNR, SENSOR_CLOCKS, find_sample_clocks
from imu_array_ros.timing.delays import reading_delays
from imu_array_ros.timing.sawtooth import sawtooth_delay
from imu_array_ros.timing.session import active_clocks, estimate_session, session_weights

__all__ = ["TimingDiscovery", "ClockFinding", "timing_stage", "retest_clocks", "session_model", "false_alarm_bound", "NULL_MEASURED"]

#: peak / median of the sawtooth spectrum on simulated null chips (``python -m benchmarks.discovery_timing_null
#: --seeds 5``: 8 corner IMUs x gyroscope and accelerometer x 15 recordings of 30 s at 62.5, 100, 200 Hz):
#: chips, the largest ratio seen (median 2.8, 99th percentile 3.9), how many reached MIN_SNR and the exact
#: binomial 95 % upper bound on the per-chip rate that count allows
NULL_MEASURED = {"chips": 240, "max_snr": 4.33, "above_threshold": 0, "binomial_95_upper": 0.0124}
#: |omega_dot| bins (rad/s^2) of the evidence plot's residual curve
_BINS = 12
#: the reading rates (:func:`_rates_decision`) are kept when their likelihood-ratio test passes at RATES_ALPHA and
#: they gain at least RATES_EFFECT times what chance gives: a practical size, so that small errors of the session's
#: phases (a few us: ~1.4x chance on 8 s of simulated twisting) do not switch on six states per sample, which cost
#: time offsets most of their precision on smooth motion; the real captures gain 10^3-10^4 times chance
RATES_ALPHA = 1e-3
RATES_EFFECT = 2.0


def _rates_decision(samples, out: TimingDiscovery, motion, loglik, say) -> None:
    """With the chips' clocks known, whether this recording wants each sample's reading rates
    (:mod:`imu_array_ros.fitting.reading_rates`): the likelihood-ratio of the ML motion with them against
    without, 2 Delta log-lik ~ chi2(6 per sample with its motion identified) by chance, kept at RATES_ALPHA and
    RATES_EFFECT times chance;
    the rest of the enclosing :func:`~imu_array_ros.fitting.reading_rates.rates_scope` (``workflows.discover``)
    then fits with them.  Nothing happens outside such a scope."""
    from scipy.stats import chi2

    if not keep_rates(False):
        return
    say("timing: the readings' own rates within the chips' clock spread")
    if loglik is None:
        motion, loglik, _ = fit_motion(samples, out.model, motion)
    with reading_rates(True):
        motion1, loglik1, _ = fit_motion(samples, out.model, motion)
    dof = RATES * int(np.count_nonzero(samples.valid(out.model).reshape(len(samples), -1).sum(axis=1) >= 15))
    gain = float(loglik1 - loglik)
    p = float(chi2.sf(2 * gain, dof)) if dof else 1.0
    kept = p < RATES_ALPHA and gain >= RATES_EFFECT * dof / 2
    out.rates = {"delta_loglik": gain, "chance_delta_loglik": dof / 2, "dof": dof, "p": p, "alpha": RATES_ALPHA,
                 "effect": RATES_EFFECT, "kept": kept}
    if kept:
        keep_rates(True)
        out.motion = motion1
        out.notes.append(f"the readings' own rates within the chips' clock spread (6 per sample, profiled with the "
                         f"motion): log-likelihood +{gain:.4g}, chance +{dof / 2:.4g} (p = {p:.2g} < {RATES_ALPHA:g}): "
                         "the motion changes within the clock spread by more than the read rate follows; every fit "
                         "below carries them (NIS counts them as states)")
    else:
        out.notes.append(f"the readings' own rates within the chips' clock spread: log-likelihood +{gain:.4g}, chance "
                         f"+{dof / 2:.4g} (p = {p:.2g}; kept at p < {RATES_ALPHA:g} and {RATES_EFFECT:g}x chance): "
                         "not needed")


def false_alarm_bound(rates: int = 10_000) -> float:
    """Upper bound on P(a null chip's sawtooth reaches MIN_SNR) over ``rates`` resolved rates: Rayleigh
    |S| at each rate, the spectrum's median sigma sqrt(2 ln 2)."""
    return float(min(1.0, rates * np.exp(-0.5 * (MIN_SNR * np.sqrt(2 * np.log(2))) ** 2)))


@dataclass
class ClockFinding:
    """A sample clock found on one sensor of one IMU."""

    sensor: str
    k: int
    imu: str
    period: float
    rate_ppm: float
    snr: float

    def text(self) -> str:
        return (f"sample clock of period {self.period * 1e3:g} ms on {self.imu} ({self.sensor}), rate "
                f"{self.rate_ppm:+.1f} ppm, evidence: sawtooth {self.snr:.1f}x its spectrum's median "
                f"(>= {MIN_SNR:g} needed)")

    def to_dict(self) -> dict:
        return {"effect": SENSOR_CLOCKS[self.sensor], "sensors": [self.imu], "sensor": self.sensor,
                "period_s": self.period, "rate_ppm": self.rate_ppm, "snr": self.snr, "text": self.text()}


@dataclass
class TimingDiscovery:
    """model: the model the discovery continues with (the input's, or with the clocks found and this
    recording's phases); findings: ClockFinding per sensor and IMU; snr: sensor -> (K,) peak / median;
    delta_loglik: log-likelihood gain of the clocks at the ML motion (None: not computed); evidence: arrays
    for the plots (:func:`imu_array_ros.discovery.plots.timing_plot`); notes: what was done and why."""

    model: object
    tested: bool = False
    findings: list = field(default_factory=list)
    snr: dict = field(default_factory=dict)
    period: float = CLOCK_PERIOD
    loglik_before: float | None = None
    loglik_after: float | None = None
    evidence: dict = field(default_factory=dict, repr=False)
    notes: list = field(default_factory=list)
    #: the ML motion under ``model`` when the clocks were kept (so the discovery need not fit it again)
    motion: object = field(default=None, repr=False)
    #: the reading rates' test (:func:`_rates_decision`), when made
    rates: dict = field(default_factory=dict)
    #: the samples (indexes) the likelihood comparisons and ``motion`` are of (None: the whole recording); what they are
    on: object = field(default=None, repr=False)
    on_label: str = "the whole recording"
    #: clocks found, then dropped when re-tested given the library findings (:func:`retest_clocks`)
    dropped: list = field(default_factory=list)
    #: the model the timing stage was given (without its clocks and the time offsets they moved)
    given: object = field(default=None, repr=False)

    def drop(self, clocks: list, reason: str) -> None:
        """``clocks`` (of ``findings``) dropped for ``reason`` (said in the notes)."""
        self.findings = [f for f in self.findings if f not in clocks]
        self.dropped += clocks
        if any(f.imu == self.evidence.get("imu") and f.sensor == self.evidence.get("sensor") for f in clocks):
            self.evidence = {}  # its plot was of a dropped clock
        self.notes.append(f"clocks of {', '.join(f'{f.imu} {f.sensor}' for f in clocks)} {reason}")

    def without(self, model, clocks=None):
        """``model`` without ``clocks`` (ClockFinding list; None: those :meth:`drop` dropped): their chips' clock
        rows zero (no clock), and their sensors' time offsets back at ``given``'s (the search moved the constant
        part of each sawtooth into them)."""
        changes = {}
        for f in self.dropped if clocks is None else clocks:
            term = SENSOR_CLOCKS[f.sensor]
            v = changes.get(term, model.terms[term].values).copy()
            v[f.k] = 0.0
            changes[term] = v
            if self.given is not None:
                off = changes.get("time_offset", model.terms["time_offset"].values).copy()
                col = TimeOffset.column(f.sensor)
                off[f.k, col] = self.given.terms["time_offset"].values[f.k, col]
                changes["time_offset"] = off
        return model.with_terms(**changes) if changes else model

    @property
    def used(self) -> bool:
        """True when clocks were found and the discovery continued with them (``--apply`` writes them)."""
        return bool(self.findings) and self.delta_loglik is not None and self.delta_loglik > 0

    @property
    def delta_loglik(self) -> float | None:
        if self.loglik_before is None or self.loglik_after is None:
            return None
        return self.loglik_after - self.loglik_before

    def to_dict(self) -> dict:
        return {"tested": self.tested, "used": self.used, "period_s": self.period,
                "findings": [f.to_dict() for f in self.findings],
                "dropped_given_findings": [f.to_dict() for f in self.dropped],
                "snr": {s: [float(x) for x in v] for s, v in self.snr.items()},
                "delta_loglik": self.delta_loglik, "loglik_before": self.loglik_before,
                "loglik_after": self.loglik_after, "reading_rates": dict(self.rates),
                "loglik_on": self.on_label if self.on is None else f"{self.on_label} ({len(self.on)} samples)",
                "false_finding_control": {
                    "test": f"sawtooth spectral peak >= {MIN_SNR:g} x the spectrum's median over the searched rates",
                    "false_alarm_rate_per_chip_bound": false_alarm_bound(),
                    "measured_on_simulated_nulls": dict(NULL_MEASURED)},
                "notes": list(self.notes)}


def timing_stage(samples, model, *, period: float = CLOCK_PERIOD, motion=None, loglik: float | None = None,
                 residuals=None, say=None, on=None, on_label: str = "a subsample") -> TimingDiscovery:
    """Sample clocks of ``samples`` not in ``model`` (module docstring).  motion, loglik, residuals: what
    :func:`~imu_array_ros.fitting.engine.fit_motion` gives for ``samples`` under ``model``, when computed.  on: sample
    indexes the likelihood comparisons are made on (module docstring; ``on_label`` says what they are), None: the
    whole recording.  Never raises for too little motion: the reason goes into the notes."""
    say = say or (lambda text: None)
    out = TimingDiscovery(model, period=period, given=model)
    fit_on = samples
    if on is not None:
        out.on, out.on_label, fit_on = np.asarray(on), on_label, samples.select(on)
        motion, loglik, residuals = None if motion is None else np.asarray(motion)[on], None, None
    if active_clocks(model):
        session = estimate_session(samples, model)
        out.model = session.model
        out.notes.append("the description has sample clocks: not searched; " + "; ".join(session.notes))
        _rates_decision(fit_on, out, motion, None, say)
        return out
    say(f"timing: searching every chip's gyroscope and accelerometer for a sample clock of {period * 1e3:g} ms")
    try:
        search = find_sample_clocks(samples, model, period=period)
    except ValueError as err:
        out.notes.append(f"sample clocks not tested: {err}")
        return out
    out.tested = True
    out.snr = {s: np.asarray(v, dtype=float) for s, v in search.snr.items()}
    out.notes += search.notes
    # a sawtooth must explain the delays it was found in: a periodic motion (regular pose changes) beating with
    # the reads can peak in the spectrum, but the sawtooth it implies leaves the delays worse, not better
    worse = [s for s in search.rms_after if not search.rms_after[s] < search.rms_before[s]]
    for sensor in worse:
        out.notes.append(f"{sensor}s: the sawtooths found leave the relative reading delays worse "
                         f"({search.rms_before[sensor] * 1e6:.0f} -> {search.rms_after[sensor] * 1e6:.0f} us RMS): "
                         "not a sample clock (a periodic motion beating with the reads?); rejected")
    if worse:
        keep = tuple(s for s in search.rms_after if s not in worse)
        search = find_sample_clocks(samples, model, period=period, sensors=keep) if keep else None
        if search is None:
            return out
    for sensor, found in search.found.items():
        for k in np.flatnonzero(found):
            out.findings.append(ClockFinding(sensor, int(k), model.names[k], period,
                                             float(search.rates[sensor][k]), float(out.snr[sensor][k])))
    if not out.findings:
        return out
    session = estimate_session(samples, search.model, search_common=False)
    clocked = session.model if session.estimated else search.model
    say("timing: log-likelihood of the clocks at the ML motion"
        + ("" if on is None else f" of {out.on_label} ({len(out.on)} of {len(samples)} samples)"))
    if motion is None or residuals is None or loglik is None:
        motion, loglik, residuals = fit_motion(fit_on, model, motion)
    with reading_rates(False):  # like for like: the clocks' own gain, not that of the reading rates they allow
        motion1, loglik1, r1 = fit_motion(fit_on, clocked, motion)
    out.loglik_before, out.loglik_after = float(loglik), float(loglik1)
    if on is not None:
        out.notes.append(f"the clocks' log-likelihood gain and the reading rates' test are of {out.on_label} "
                         f"({len(out.on)} of {len(samples)} samples), the subsample the search starts on: no fit of "
                         f"the whole recording under the clocks before the search")
    if out.delta_loglik > 0:
        out.model, out.motion = clocked, motion1
        _rates_decision(fit_on, out, motion1, loglik1, say)
    else:
        out.notes.append(f"the clocks found ({', '.join(f'{f.imu} {f.sensor}' for f in out.findings)}) do not "
                         f"raise the log-likelihood ({out.delta_loglik:.4g}): rejected")
        out.findings = []
        return out
    out.evidence = _evidence(samples, model, clocked, out, motion1, residuals, r1, search.delays)
    return out


def _evidence(samples, model, clocked, out: TimingDiscovery, motion, r0, r1, known=None) -> dict:
    """Arrays of the timing evidence plot for the IMU whose clock is clearest: its reading delays relative
    to the other IMUs (moving samples) and its sawtooth; its gyroscope residual RMS vs |omega_dot| before
    and after the clocks.  known: sensor -> its reading delays under ``model``, when the search made them."""
    best = max(out.findings, key=lambda f: f.snr)
    sensor, k = best.sensor, best.k
    t0 = int(samples.stamps[0])
    delays = (known or {}).get(sensor)
    if delays is None:
        delays = reading_delays(samples, model, ModelFusion(model, t0_ns=t0).fuse(samples)[0], t0_ns=t0, sensor=sensor)
    w = session_weights(delays)[:, k]
    d = delays.relative()[:, k]
    clock = clocked.terms[SENSOR_CLOCKS[sensor]].values
    saw = sawtooth_delay(delays.t, clock[:, 0], clock[:, 1], clock[:, 2])[:, k]
    use = w > 0
    shift = float(np.sum(w[use] * (d[use] - saw[use])) / max(w[use].sum(), 1e-300)) if use.any() else 0.0
    cols = slice(3, 6) if sensor == "gyroscope" else slice(0, 3)
    wd = np.linalg.norm(np.nan_to_num(motion[:, 3:6]), axis=1)
    edges = np.quantile(wd, np.linspace(0, 1, _BINS + 1))
    which = np.clip(np.searchsorted(edges, wd, side="right") - 1, 0, _BINS - 1)

    def binned(r):
        e = np.nanmean(r[:, k, cols] ** 2, axis=1)
        return np.array([np.sqrt(np.nanmean(e[which == b])) if np.any(which == b) else np.nan
                         for b in range(_BINS)])
    return {"imu": best.imu, "sensor": sensor, "t": delays.t[use], "delay": d[use], "sawtooth": saw[use] + shift,
            "omega_dot_bins": 0.5 * (edges[1:] + edges[:-1]), "rms_before": binned(r0), "rms_after": binned(r1)}


def retest_clocks(samples, model, timing: TimingDiscovery) -> list:
    """The clock findings of ``timing`` a search under ``model`` does not find again (same sensor and IMU, rate
    within one resolution width, 1e6 period / span ppm): with ``model`` the description with the library findings
    and without the clocks, a clock that stood in for a missing term (its "delays" beat with the motion) is gone,
    while a chip's own clock is not explained by any library term.  The timing stage runs before the library
    search, so its findings are re-tested given the others as the backward elimination re-tests the library's."""
    if not timing.findings:
        return []
    k = model.n_imus
    plain = model.with_terms(**{t: np.zeros((k, 3)) for t in SENSOR_CLOCKS.values() if t in model.terms})
    try:
        search = find_sample_clocks(samples, plain, period=timing.period,
                                    sensors=tuple(dict.fromkeys(f.sensor for f in timing.findings)))
    except ValueError:
        return []
    width = 1e6 * timing.period / max(float(np.ptp(samples.stamps)) * 1e-9, 1e-3)
    return [f for f in timing.findings if not (search.found[f.sensor][f.k]
                                               and abs(search.rates[f.sensor][f.k] - f.rate_ppm) <= width)]


def session_model(samples, model):
    """``model`` with the session states (sample-clock phases) of ``samples`` when it has sample clocks (the
    phases found on one recording mean nothing on another), else ``model``."""
    if not active_clocks(model):
        return model
    session = estimate_session(samples, model)
    return session.model
