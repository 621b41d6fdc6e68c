"""Plots of a mismatch-discovery report (matplotlib, imported only when a plot is asked for).

Every quantity plotted is a *ratio to the noise level*, so 1 means "the model
explains the data down to the white sensor noise" and 100 means residuals ten
times the noise (:mod:`imu_array_ros.fusion.residuals`):

* :func:`plot_residual_maps`: observed / expected squared normalised residual per
  IMU and axis (:data:`~imu_array_ros.fusion.residuals.AXES`), before and
  after the discovered terms, as two heatmaps on one shared logarithmic colour scale;
* :func:`plot_spectra`: power spectral density of the normalised residual relative
  to white noise (1 = white at the noise level), for the worst cells -- a narrowband
  peak is a vibration mode, a rising low-frequency end coloured noise or drift;
* :func:`plot_evidence`: the log-likelihood gain (delta loglik) of every candidate
  term, accepted ones highlighted, against the per-step significance threshold;
* :func:`plot_time`: the residual ratio per time window, with shaded spans;
* :func:`plot_mode`: a narrowband mode's shape across the array and its line in the spectrum.

PNG files are written atomically (:func:`~imu_array_ros.util.plotting.save_png`):
a failed plot leaves no partial file and no temporary behind; the figure is
always closed.  Without matplotlib the functions raise
:class:`~imu_array_ros.errors.OutputError`.
"""

from __future__ import annotations

from pathlib import Path
from typing import Iterable, Sequence

import numpy as np

from imu_array_ros.fusion.residuals import AXES
from imu_array_ros.util.plotting import pyplot, save_png  # the lazy matplotlib import, one copy

__all__ = ["plot_residual_maps", "plot_spectra", "plot_evidence", "plot_time", "plot_timing", "plot_mode", "EVIDENCE_FLOOR"]

#: delta loglik shown at the left edge of :func:`plot_evidence` (smaller and negative values are drawn there).
EVIDENCE_FLOOR = 0.1
_NAN_COLOR = "0.82"
_DPI = 110


def _fmt(v: float) -> str:
    """Short cell label of a ratio: "0.52", "3.2", "41", "2e+03"."""
    if not np.isfinite(v):
        return "—"
    if v < 0.995:
        return f"{v:.2f}"
    if v < 9.95:
        return f"{v:.1f}"
    if v < 999.5:
        return f"{v:.0f}"
    return f"{v:.0e}"


def _no_data(ax, text: str) -> None:
    ax.text(0.5, 0.5, text, ha="center", va="center", fontsize=12, color="0.4", transform=ax.transAxes)
    ax.set_axis_off()


def _ratio_map(values, names: Sequence[str], label: str) -> np.ndarray:
    r = np.asarray(values, dtype=float)
    if r.shape != (len(names), len(AXES)):
        raise ValueError(f"{label} has shape {r.shape}, expected {(len(names), len(AXES))} (IMU x axis)")
    return r


# --------------------------------------------------------------------------- residual maps


def plot_residual_maps(before, after, names: Sequence[str], path: str | Path, *, title: str = "") -> None:
    """PNG of two heatmaps, before and after: (K, 6) ratios of observed to expected squared
    normalised residual (1 = noise level, NaN = no data) per IMU (rows, ``names``) and axis
    (columns, :data:`AXES`).  Shared logarithmic colour scale from min(0.5, smallest) to the
    largest ratio; each cell annotated with its value, NaN cells grey.  ``after`` may be None."""
    names = [str(n) for n in names]
    maps = [("before", _ratio_map(before, names, "before"))]
    if after is not None:
        maps.append(("after", _ratio_map(after, names, "after")))
    plt = pyplot(path)
    from matplotlib.colors import LogNorm

    finite = np.concatenate([m[np.isfinite(m) & (m > 0)] for _, m in maps])
    vmin = min(0.5, float(finite.min())) if finite.size else 0.5
    vmax = max(float(finite.max()), 2.0 * vmin) if finite.size else 2.0
    norm = LogNorm(vmin=vmin, vmax=vmax)
    cmap = plt.get_cmap("viridis").with_extremes(bad=_NAN_COLOR)
    k = len(names)
    fig, axes = plt.subplots(1, len(maps), figsize=(4.2 * len(maps) + 1.4, max(2.5, 0.32 * k + 1.6)),
                             squeeze=False, constrained_layout=True)
    try:
        image = None
        for ax, (label, m) in zip(axes[0], maps):
            shown = np.ma.masked_invalid(np.where(m > 0, m, vmin))  # zero ratios drawn at the bottom of the scale
            image = ax.imshow(shown, cmap=cmap, norm=norm, aspect="auto", interpolation="nearest")
            ax.set_xticks(np.arange(len(AXES)), AXES, fontsize=8)
            ax.set_yticks(np.arange(k), names, fontsize=8 if k <= 16 else 6)
            ax.set_title(label, fontsize=10)
            cell_font = 8 if k <= 16 else 6
            for i, j in np.ndindex(m.shape):
                v = m[i, j]
                if np.isfinite(v):
                    r, g, b, _ = cmap(norm(max(v, vmin)))
                    color = "black" if 0.299 * r + 0.587 * g + 0.114 * b > 0.5 else "white"
                else:
                    color = "0.35"
                ax.text(j, i, _fmt(v), ha="center", va="center", fontsize=cell_font, color=color)
        fig.colorbar(image, ax=list(axes[0]), shrink=0.9,
                     label="observed / expected residual² (1 = noise level)")
        if title:
            fig.suptitle(title, fontsize=11)
        save_png(fig, path, _DPI, close=False)
    finally:
        plt.close(fig)


# --------------------------------------------------------------------------- spectra


def _worst_cells(psd: np.ndarray, n: int) -> list[tuple[int, int]]:
    """The ``n`` (k, a) cells with the largest mean PSD (cells without finite values last, then dropped)."""
    with np.errstate(invalid="ignore"):
        finite = np.isfinite(psd)
        count = finite.sum(axis=2)
        mean = np.where(count > 0, np.where(finite, psd, 0.0).sum(axis=2) / np.maximum(count, 1), -np.inf)
    order = np.argsort(-mean, axis=None, kind="stable")[:n]
    return [tuple(int(i) for i in np.unravel_index(o, mean.shape)) for o in order if np.isfinite(mean.flat[o])]


def plot_spectra(freqs, psd_before, psd_after, names: Sequence[str], path: str | Path, *,
                 cells: Iterable[tuple[int, int]] | None = None) -> None:
    """PNG of residual spectra: freqs (F,) Hz; psd_before, psd_after (K, 6, F) PSD relative to
    white noise at the noise level (1 = white), psd_after may be None.  One panel per (k, a) in
    ``cells`` (default: the 6 cells with the largest mean ``psd_before``), log y, dashed line at 1."""
    names = [str(n) for n in names]
    f = np.asarray(freqs, dtype=float).reshape(-1)
    shape = (len(names), len(AXES), len(f))
    before = np.asarray(psd_before, dtype=float)
    if before.shape != shape:
        raise ValueError(f"psd_before has shape {before.shape}, expected {shape} (IMU x axis x frequency)")
    after = None if psd_after is None else np.asarray(psd_after, dtype=float)
    if after is not None and after.shape != shape:
        raise ValueError(f"psd_after has shape {after.shape}, expected {shape} (IMU x axis x frequency)")
    if cells is None:
        cells = _worst_cells(before, 6)
    else:
        cells = [(int(k), int(a)) for k, a in cells]
        for k, a in cells:
            if not (0 <= k < shape[0] and 0 <= a < shape[1]):
                raise ValueError(f"cell {(k, a)} outside the {shape[0]} IMUs x {shape[1]} axes")
    plt = pyplot(path)
    n = max(len(cells), 1)
    cols = min(3, n)
    rows = -(-n // cols)
    fig, axes = plt.subplots(rows, cols, figsize=(4.2 * cols, 3.0 * rows), squeeze=False, constrained_layout=True)
    try:
        flat = list(axes.flat)
        if not cells:
            _no_data(flat[0], "no spectra (no finite PSD)")
        for ax, (k, a) in zip(flat, cells):
            ax.set_title(f"{names[k]} {AXES[a]}", fontsize=10)
            lines = [("before", before[k, a], dict(color="0.55", lw=1.8))]
            if after is not None:
                lines.append(("after", after[k, a], dict(color="C3", lw=1.0)))
            drawn = False
            for label, p, style in lines:
                good = np.isfinite(p) & (p > 0) & np.isfinite(f)
                if good.any():
                    ax.plot(f, np.where(good, p, np.nan), label=label, **style)
                    drawn = True
            if not drawn:
                _no_data(ax, f"{names[k]} {AXES[a]}: no data")
                continue
            ax.set_yscale("log")
            ax.axhline(1.0, color="black", ls="--", lw=0.8, label="white noise")
            ax.set_xlabel("Hz")
            ax.set_ylabel("PSD / white-noise level", fontsize=8)
            ax.legend(fontsize=7)
        for ax in flat[len(cells):] if cells else flat[1:]:
            ax.set_axis_off()
        save_png(fig, path, _DPI, close=False)
    finally:
        plt.close(fig)


# --------------------------------------------------------------------------- evidence


def _candidate_label(c: dict) -> str:
    sensors = c.get("sensors") or []
    if isinstance(sensors, str):
        sensors = [sensors]
    effect = str(c.get("effect", "?"))
    return f"{effect} @ {', '.join(str(s) for s in sensors)}" if len(sensors) else effect


def plot_evidence(candidates: Sequence[dict], path: str | Path, *, threshold: float | None = None,
                  top: int = 30) -> None:
    """PNG bar chart of the ``top`` candidates with the largest delta loglik (log x, values below
    :data:`EVIDENCE_FLOOR` drawn at it), accepted ones coloured, a dashed line at ``threshold``.

    candidates: dicts {"effect": str, "sensors": [str], "delta_loglik": float, "accepted": bool,
    "step": int}; bars labelled "effect @ imu_3", annotated with the value and the step.
    An empty list writes a plot saying "no candidates"."""
    def key(c):
        d = float(c.get("delta_loglik", np.nan))
        return -d if np.isfinite(d) else (np.inf if np.isnan(d) else -d)

    shown = sorted(candidates, key=key)[:max(int(top), 0)]
    plt = pyplot(path)
    from matplotlib.patches import Patch

    fig, ax = plt.subplots(figsize=(8.0, max(2.5, 0.28 * len(shown) + 1.4)), constrained_layout=True)
    try:
        if not shown:
            _no_data(ax, "no candidates")
            ax.set_title("candidate evidence", fontsize=10)
            save_png(fig, path, _DPI, close=False)
            return
        delta = np.array([float(c.get("delta_loglik", np.nan)) for c in shown])
        accepted = np.array([bool(c.get("accepted", False)) for c in shown])
        base = EVIDENCE_FLOOR / 1.5
        value = np.clip(np.nan_to_num(delta, nan=EVIDENCE_FLOOR, posinf=1e300, neginf=EVIDENCE_FLOOR),
                        EVIDENCE_FLOOR, None)
        y = np.arange(len(shown))[::-1]  # largest at the top
        ax.barh(y, value - base, left=base, color=np.where(accepted, "C3", "0.65"), height=0.7)
        ax.set_xscale("log")
        for yi, v, d, c in zip(y, value, delta, shown):
            step = c.get("step")
            note = ("n/a" if np.isnan(d) else f"{d:.3g}") + ("" if step is None else f", step {step}")
            ax.text(v * 1.08, yi, note, va="center", fontsize=7, color="0.25")
        ax.set_yticks(y, [_candidate_label(c) for c in shown], fontsize=8)
        handles = [Patch(color="C3", label="accepted"), Patch(color="0.65", label="not accepted")]
        right = float(value.max())
        if threshold is not None and np.isfinite(threshold):
            t = max(float(threshold), EVIDENCE_FLOOR)
            handles.append(ax.axvline(t, color="black", ls="--", lw=1.0,
                                      label=f"threshold (Δ loglik {float(threshold):.3g})"))
            right = max(right, t)
        ax.set_xlim(base, right * 4.0)
        ax.set_xlabel("Δ log-likelihood (log scale)")
        ax.set_title(f"candidate evidence (top {len(shown)} of {len(candidates)})", fontsize=10)
        ax.legend(handles=handles, fontsize=8, loc="lower right")
        save_png(fig, path, _DPI, close=False)
    finally:
        plt.close(fig)


# --------------------------------------------------------------------------- time


def plot_time(windows, ratio_before, ratio_after, path: str | Path, *, spans=()) -> None:
    """PNG of the residual ratio per time window: windows (W,) s (window centres or starts),
    ratio_before, ratio_after (W,) (1 = noise level; ratio_after may be None), log y, dashed line
    at 1; ``spans``: (t0, t1) or (t0, t1, label) intervals in s, shaded."""
    t = np.asarray(windows, dtype=float).reshape(-1)
    series = [("before", ratio_before, dict(color="0.45", marker=".", lw=1.0)),
              ("after", ratio_after, dict(color="C3", marker=".", lw=1.0))]
    data = []
    for label, r, style in series:
        if r is None:
            continue
        r = np.asarray(r, dtype=float).reshape(-1)
        if r.shape != t.shape:
            raise ValueError(f"ratio_{label} has {r.size} values for {t.size} windows")
        data.append((label, r, style))
    spans = [tuple(s) for s in spans]
    for s in spans:
        if len(s) not in (2, 3):
            raise ValueError(f"span {s!r} is not (t0, t1) or (t0, t1, label)")
    plt = pyplot(path)
    fig, ax = plt.subplots(figsize=(9.0, 3.6), constrained_layout=True)
    try:
        drawn = False
        for label, r, style in data:
            good = np.isfinite(r) & (r > 0) & np.isfinite(t)
            if good.any():
                ax.plot(t, np.where(good, r, np.nan), label=label, **style)
                drawn = True
        for s in spans:
            ax.axvspan(float(s[0]), float(s[1]), color="C0", alpha=0.15, lw=0,
                       label=str(s[2]) if len(s) == 3 else None)
        if drawn:
            ax.set_yscale("log")
            ax.axhline(1.0, color="black", ls="--", lw=0.8, label="noise level")
            ax.legend(fontsize=8)
        else:
            ax.text(0.5, 0.5, "no data", ha="center", va="center", fontsize=12, color="0.4",
                    transform=ax.transAxes)
        ax.set_xlabel("time (s)")
        ax.set_ylabel("observed / expected residual²")
        ax.set_title("residual ratio per window", fontsize=10)
        save_png(fig, path, _DPI, close=False)
    finally:
        plt.close(fig)


# --------------------------------------------------------------------------- timing


def plot_timing(evidence: dict, path: str | Path, *, window_s: float = 3.0) -> None:
    """PNG of a sample clock's evidence (:func:`imu_array_ros.discovery.timing.timing_stage`): left, one IMU's
    reading delay relative to the other IMUs vs time (moving samples, the ``window_s`` seconds with the most
    samples) with its fitted sawtooth (-age); right, its residual RMS (noise units) vs |omega_dot| before and
    after the clocks."""
    t = np.asarray(evidence["t"], dtype=float)
    plt = pyplot(path)
    fig, (a, b) = plt.subplots(1, 2, figsize=(11.0, 3.8), constrained_layout=True)
    try:
        if t.size:
            starts = np.searchsorted(t, t + window_s, side="right") - np.arange(t.size)
            i = int(np.argmax(starts))
            sel = slice(i, i + int(starts[i]))
            a.plot(t[sel], np.asarray(evidence["delay"])[sel] * 1e6, ".", ms=3, color="0.4",
                   label="reading delay (from the residuals)")
            a.plot(t[sel], np.asarray(evidence["sawtooth"])[sel] * 1e6, ".", ms=3, color="C3",
                   label="sample clock found (-age)")
            a.set_xlabel("time (s)")
            a.set_ylabel("delay relative to the other IMUs (µs)")
            a.legend(fontsize=8)
        else:
            _no_data(a, "no moving samples")
        a.set_title(f"{evidence['imu']} {evidence['sensor']}: reading age vs time", fontsize=10)
        x = np.asarray(evidence["omega_dot_bins"], dtype=float)
        b.plot(x, evidence["rms_before"], "o-", color="0.45", label="without the clocks")
        b.plot(x, evidence["rms_after"], "o-", color="C3", label="with the clocks")
        b.axhline(1.0, color="black", ls="--", lw=0.8, label="noise level")
        b.set_xlabel("|angular acceleration| (rad/s²)")
        b.set_ylabel(f"{evidence['sensor']} residual RMS (noise std)")
        b.set_title(f"{evidence['imu']}: residual vs angular acceleration", fontsize=10)
        b.legend(fontsize=8)
        save_png(fig, path, _DPI, close=False)
    finally:
        plt.close(fig)


# --------------------------------------------------------------------------- narrowband modes


def plot_mode(mode: dict, names: Sequence[str], positions, freqs, pooled, threshold: float,
              path: str | Path) -> None:
    """PNG of a narrowband mode (:meth:`imu_array_ros.discovery.modes.Mode.to_dict`): left, the IMUs at their
    (x, y) positions (mm) coloured by the signed amplitude of the mode shape (its ``shape`` entry; the arrow:
    the in-plane part of the mode's direction scaled by it); right, the pooled line statistic (mean over
    channels of PSD / local floor) against frequency with its detection threshold and the mode's band."""
    names = [str(n) for n in names]
    p = np.asarray(positions, dtype=float).reshape(len(names), 3) * 1e3
    shape = mode.get("shape") or {}
    s = np.asarray(shape.get("signed_amplitude") or np.zeros(len(names)), dtype=float)
    d = np.asarray(shape.get("direction_array_frame") or [0.0, 0.0, 1.0], dtype=float)
    plt = pyplot(path)
    fig, (a, b) = plt.subplots(1, 2, figsize=(11.0, 4.2), constrained_layout=True)
    try:
        lim = float(np.abs(s).max()) if s.size and np.abs(s).max() > 0 else 1.0
        sc = a.scatter(p[:, 0], p[:, 1], c=s, cmap="coolwarm", vmin=-lim, vmax=lim, s=160, edgecolors="k")
        span = float(max(np.ptp(p[:, 0]), np.ptp(p[:, 1]), 1.0))
        if np.linalg.norm(d[:2]) > 1e-6:
            a.quiver(p[:, 0], p[:, 1], s / lim * d[0], s / lim * d[1], angles="xy", scale_units="xy",
                     scale=1.0 / (0.25 * span), color="0.2", width=0.006)
        for (x, y, _), n in zip(p, names):
            a.annotate(n, (x, y), textcoords="offset points", xytext=(0, 9), ha="center", fontsize=7)
        unit = "m/s²" if shape.get("sensor") == "accelerometer" else "rad/s"
        fig.colorbar(sc, ax=a, label=f"signed amplitude ({unit} RMS, or noise std without stds)")
        best = shape.get("best") or "—"
        r2 = (shape.get("fits") or {}).get(best, {}).get("r2")
        a.set_title(f"mode at {mode['frequency_hz']:.3g} Hz, {shape.get('sensor', '')}: shape {best}"
                    + (f" (R² {r2:.2f})" if r2 is not None else ""), fontsize=10)
        a.set_xlabel("x (mm)")
        a.set_ylabel("y (mm)")
        a.set_aspect("equal", adjustable="datalim")
        f = np.asarray(freqs, dtype=float)
        q = np.asarray(pooled, dtype=float)
        if f.size:
            b.plot(f, q, color="0.35", lw=1.0, label="mean PSD / local floor over channels")
            b.axhline(threshold, color="C3", ls="--", lw=0.9, label="detection threshold")
            lo, hi = mode["band_hz"]
            b.axvspan(lo, hi, color="C1", alpha=0.35, label=f"band {lo:.3g}–{hi:.3g} Hz")
            b.set_yscale("log")
            b.set_xlabel("Hz")
            b.legend(fontsize=8)
        else:
            _no_data(b, "no spectrum")
        b.set_title(f"line statistic: p = {mode['p_value']:.2g}, present in "
                    f"{(mode.get('presence') or {}).get('fraction_present', float('nan')):.0%} of the blocks",
                    fontsize=10)
        save_png(fig, path, _DPI, close=False)
    finally:
        plt.close(fig)
