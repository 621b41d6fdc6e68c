"""The reading age of a free-running sample clock: a sawtooth, found by its spectrum and refined on
its shape.

A chip sampling every T = period / (1 + rate 1e-6) seconds, read by the host at its stamps t_n, delivers
a reading aged ``age = (t - phase) mod T`` (:mod:`imu_array_ros.model.terms.sample_clock`).  Its delay
-age has the Fourier series -T/2 + (T/pi) sum_m sin(2 pi m (t - phase) / T) / m, so the delays' weighted
correlation with exp(-2 pi i t / T),

    S(T) = sum_n w_n d_n exp(-2 pi i t_n / T) / sum_n w_n  =  T e^{-2 pi i phase / T} / (2 pi i)  (+ noise),

peaks at the chip's period (|S| = T / 2 pi) and its angle gives the phase.  Evaluated on the true
stamps t_n, not sample indexes.  When the host reads at an exact multiple of T's nominal value
(62.5 Hz reads of a 1 kHz clock) the periods T and the mirror 2 T_nom - T give the same |S|:
a rising and a falling sawtooth of the same beat.  The sawtooth's shape tells them apart: both are fitted
and the one with the smaller residual is kept.

Every search is vectorised over frequencies x samples in blocks of bounded memory.
"""

from __future__ import annotations

import numpy as np

from imu_array_ros.model.terms.sample_clock import clock_ticks

__all__ = ["spectrum", "search_rates", "fit_phases", "sawtooth_delay", "refine_rates"]

#: complex exponentials evaluated per block (bounded memory)
BLOCK = 2_000_000
#: seconds of the most informative data the coarse rate search runs on
COARSE_WINDOW_S = 20.0


def sawtooth_delay(t: np.ndarray, period: np.ndarray, rate: np.ndarray, phase: np.ndarray) -> np.ndarray:
    """(N, K) -age of each IMU's clock at t (N,) s."""
    return -clock_ticks(t[:, None], period[None], rate[None], phase[None])[1]


def spectrum(t: np.ndarray, d: np.ndarray, w: np.ndarray, periods: np.ndarray) -> np.ndarray:
    """(R, K) S at R candidate periods per IMU: periods (R, K) s; t (N,), d, w (N, K); d's weighted mean
    per IMU is removed first."""
    periods = np.asarray(periods, dtype=float)
    r, k = periods.shape
    out = np.zeros((r, k), dtype=complex)
    use = np.flatnonzero(w.sum(axis=1) > 0)
    wsum = w[use].sum(axis=0)
    mean = np.sum(w[use] * d[use], axis=0) / np.where(wsum > 0, wsum, 1.0)  # a constant aliases to a multiple
    t, wd = t[use], (w * (d - mean))[use]  # of the read rate: removed
    step = max(1, BLOCK // max(len(t), 1))
    for j in range(k):
        if not np.all(periods[:, j] > 0):  # no clock (period 0): nothing to correlate with
            continue
        for lo in range(0, r, step):
            f = 1.0 / periods[lo:lo + step, j]
            out[lo:lo + step, j] = np.exp(-2j * np.pi * np.outer(f, t)) @ wd[:, j]
    return out / np.where(wsum > 0, wsum, 1.0)[None]


def _phase_of(s: np.ndarray, periods: np.ndarray) -> np.ndarray:
    """Phase in [0, T) from S = T e^{-2 pi i phase / T} / (2 pi i)."""
    safe = np.where(periods > 0, periods, 1.0)  # period 0: no clock, phase 0
    return np.where(periods > 0, np.mod(-np.angle(2j * s) / (2 * np.pi) * safe, safe), 0.0)


def _sse(t, d, w, period, rate, phase, with_constant: bool = False):
    """(K,) weighted sum of squares of d - (-age) - its weighted mean per IMU (and that mean)."""
    m = d - sawtooth_delay(t, period, rate, phase)
    wsum = np.where(w.sum(axis=0) > 0, w.sum(axis=0), 1.0)
    c = np.sum(w * m, axis=0) / wsum
    sse = np.sum(w * (m - c) ** 2, axis=0)
    return (sse, c) if with_constant else sse


def fit_phases(t: np.ndarray, d: np.ndarray, w: np.ndarray, period: np.ndarray, rate: np.ndarray,
               grid: int = 41, constants: bool = False):
    """(phase (K,), sse (K,)[, constant (K,)]): each IMU's phase for known period and rate, from the
    fundamental then a grid of ``grid`` phases within +-T/10 of it (the sawtooth's wraps are not smooth in
    the phase), with a free constant per IMU (returned with ``constants``: d's weighted mean minus the
    sawtooth's, a delay the sawtooth does not explain)."""
    big_t = period / (1.0 + rate * 1e-6)
    phase = _phase_of(spectrum(t, d, w, big_t[None])[0], big_t)
    best, best_sse = phase.copy(), _sse(t, d, w, period, rate, phase)
    for off in np.linspace(-0.1, 0.1, grid):
        trial = np.where(big_t > 0, np.mod(phase + off * big_t, np.where(big_t > 0, big_t, 1.0)), 0.0)
        sse = _sse(t, d, w, period, rate, trial)
        better = sse < best_sse
        best[better], best_sse[better] = trial[better], sse[better]
    if constants:
        return best, best_sse, _sse(t, d, w, period, rate, best, with_constant=True)[1]
    return best, best_sse


def search_rates(t: np.ndarray, d: np.ndarray, w: np.ndarray, period: np.ndarray, *, span_ppm: float = 8000.0,
                 step_ppm: float | None = None, window_s: float = COARSE_WINDOW_S) -> tuple[np.ndarray, np.ndarray]:
    """(rate (K,) ppm, amplitude (K,) s): each IMU's clock rate by the peak of |S| over +-``span_ppm``,
    then refined; the mirror ambiguity resolved by the sawtooth's residual.

    The coarse search runs on the ``window_s`` seconds with the most information (a wide peak: a coarse
    grid cannot step over it), at a quarter of that peak's width (``step_ppm``); the refinement on all
    samples (:func:`refine_rates`)."""
    k = d.shape[1]
    nominal = float(np.min(period[period > 0])) if np.any(period > 0) else 1e-3
    near = _densest(t, w, window_s)
    span = max(float(np.ptp(t[near])) if len(near) else 1.0, 1e-3)
    step = step_ppm if step_ppm is not None else 0.25e6 * nominal / span
    rates = np.arange(-span_ppm, span_ppm + step, step)
    periods = period[None, :] / (1.0 + rates[:, None] * 1e-6)
    amp = np.abs(spectrum(t[near], d[near], w[near], periods))
    rate = rates[np.argmax(amp, axis=0)]
    rate = refine_rates(t, d, w, period, rate, step)
    # the mirror: with reads at a multiple of the nominal period, -rate beats the same way
    mirror = refine_rates(t, d, w, period, -rate, step)
    _, sse = fit_phases(t, d, w, period, rate)
    _, sse_m = fit_phases(t, d, w, period, mirror)
    rate = np.where(sse_m < sse, mirror, rate)
    big_t = np.where(period > 0, period, 1.0) / (1.0 + rate * 1e-6)
    amp = np.abs(spectrum(t, d, w, big_t[None])[0])
    return np.where(period > 0, rate, 0.0)[:k], amp


def _densest(t: np.ndarray, w: np.ndarray, window_s: float) -> np.ndarray:
    """Indexes of the samples in the ``window_s`` seconds holding the most weight."""
    has = w.sum(axis=1) > 0
    if not has.any():
        return np.flatnonzero(has)
    tw, ww = t[has], w[has].sum(axis=1)
    cum = np.concatenate([[0.0], np.cumsum(ww)])
    end = np.searchsorted(tw, tw + window_s, side="right")
    i = int(np.argmax(cum[end] - cum[np.arange(len(tw))]))
    return np.flatnonzero(has)[i:end[i]]


def refine_rates(t, d, w, period, rate, width_ppm: float, rounds: int = 3) -> np.ndarray:
    """Each IMU's rate at the peak of |S| within +-``width_ppm`` of ``rate``: a fine grid, narrowed
    ``rounds`` times."""
    rate = np.asarray(rate, dtype=float).copy()
    for _ in range(rounds):
        grid = np.linspace(-width_ppm, width_ppm, 21)
        cand = rate[None, :] + grid[:, None]
        amp = np.abs(spectrum(t, d, w, period[None, :] / (1.0 + cand * 1e-6)))
        rate = cand[np.argmax(amp, axis=0), np.arange(len(rate))]
        width_ppm /= 10.0
    return rate
