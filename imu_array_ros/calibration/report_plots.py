"""The plots of the calibration report (:mod:`~imu_array_ros.calibration.report`): matplotlib on the Agg backend,
imported only when a plot is drawn (the ``plots`` extra); every PNG written atomically, every figure closed.

Every residual is normalised by the noise std of its axis, so 1 is "explained down to the sensor noise":

* :func:`plot_residual_map`: RMS per IMU (rows) and axis (columns), still poses and moving window, before
  (starting description) and after (calibration), one shared logarithmic colour scale;
* :func:`plot_residual_time`: RMS over the IMUs, accelerometers and gyroscopes apart, in consecutive blocks of
  the moving window, before and after;
* :func:`plot_residual_rate`: the same against the angular rate (quantile bins of |omega|);
* :func:`plot_repeatability`: every field's deviation from the recordings' weighted mean in units of the std
  it reports, per term (about within ±2 when the std are honest).
"""

from __future__ import annotations

from pathlib import Path
from typing import Sequence

import numpy as np

from imu_array_ros.fusion.residuals import AXES
from imu_array_ros.util.plotting import pyplot, save_png

__all__ = ["draw_all", "plot_residual_map", "plot_residual_time", "plot_residual_rate", "plot_repeatability",
           "block_rms", "binned_rms"]

_DPI = 110
_NAN_COLOR = "0.85"
#: blocks of the moving window in the time plot (fewer when the window is shorter)
TIME_BLOCKS = 300
#: quantile bins of the angular rate
RATE_BINS = 16


def draw_all(data: dict, directory: Path) -> list[str]:
    """Every plot the data of :func:`~imu_array_ros.calibration.report.report_data` allow, into ``directory``;
    the file names written."""
    directory, out = Path(directory), []
    res, names = data["residuals"], data["imus"]
    parts = [(what, res[p]["before"], res[p]["after"]) for p, what in
             (("still", f"still poses ({res.get('still', {}).get('poses')})"),
              ("moving", f"moving window ({res.get('moving', {}).get('samples')} samples)")) if p in res]
    if parts:
        plot_residual_map(parts, names, directory / "residual_map.png")
        out.append("residual_map.png")
    s = res.get("series")
    if s is not None and len(s["t"]) >= 2:
        plot_residual_time(s["t"], s["before"], s["after"], directory / "residual_time.png")
        plot_residual_rate(s["rate"], s["before"], s["after"], directory / "residual_rate.png")
        out += ["residual_time.png", "residual_rate.png"]
    if data["repeatability"]:
        plot_repeatability(data["repeatability"], data["recordings"], directory / "repeatability.png")
        out.append("repeatability.png")
    return out


def _label(v: float) -> str:
    if not np.isfinite(v):
        return "—"
    return f"{v:.2f}" if v < 0.995 else f"{v:.1f}" if v < 9.95 else f"{v:.0f}" if v < 999.5 else f"{v:.0e}"


def plot_residual_map(parts: Sequence[tuple[str, np.ndarray, np.ndarray]], names: Sequence[str],
                      path: Path) -> None:
    """PNG of (title, before (K, 6), after (K, 6)) residual RMS maps: one row of panels per part, before
    left, after right; cells annotated when there are at most 24 IMUs."""
    plt = pyplot(path)
    from matplotlib.colors import LogNorm

    k = len(names)
    values = np.concatenate([np.ravel(m) for _, b, a in parts for m in (b, a)])
    values = values[np.isfinite(values) & (values > 0)]
    lo = min(0.5, float(values.min())) if values.size else 0.5
    hi = max(2.0, float(values.max())) if values.size else 2.0
    norm = LogNorm(vmin=lo, vmax=hi)
    cmap = plt.get_cmap("magma_r").with_extremes(bad=_NAN_COLOR)
    height = 0.9 + len(parts) * (0.6 + 0.28 * k)
    fig, axes = plt.subplots(len(parts), 2, figsize=(9.5, height), squeeze=False, constrained_layout=True)
    try:
        for row, (title, before, after) in enumerate(parts):
            for col, (when, m) in enumerate((("before", before), ("after", after))):
                ax = axes[row, col]
                m = np.asarray(m, dtype=float)
                im = ax.imshow(np.ma.masked_invalid(m), norm=norm, cmap=cmap, aspect="auto")
                ax.set_title(f"{title}: {when}", fontsize=10)
                ax.set_xticks(range(len(AXES)), AXES, fontsize=8)
                ax.set_yticks(range(k), names if col == 0 else [""] * k, fontsize=8 if k <= 16 else 6)
                if k <= 24:
                    for (i, j), v in np.ndenumerate(m):
                        dark = np.isfinite(v) and norm(v) > 0.6
                        ax.text(j, i, _label(v), ha="center", va="center", fontsize=7 if k <= 12 else 6,
                                color="white" if dark else "black")
        fig.colorbar(im, ax=axes, shrink=0.9, label="residual RMS / noise std (1 = noise)")
        fig.suptitle("normalised residual RMS per IMU and axis", fontsize=11)
        save_png(fig, path, _DPI, close=False)
    finally:
        plt.close(fig)


def _per_sample(r: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(squared residual sums, finite counts), each (N, 2): accelerometers, gyroscopes, over IMUs and axes."""
    r = np.asarray(r, dtype=float)
    ok = np.isfinite(r)
    sq = np.where(ok, r, 0.0) ** 2
    return (np.stack([sq[..., :3].sum(axis=(1, 2)), sq[..., 3:].sum(axis=(1, 2))], axis=1),
            np.stack([ok[..., :3].sum(axis=(1, 2)), ok[..., 3:].sum(axis=(1, 2))], axis=1))


def block_rms(t: np.ndarray, r: np.ndarray, blocks: int = TIME_BLOCKS) -> tuple[np.ndarray, np.ndarray]:
    """(B,) mean time and (B, 2) RMS [accelerometers, gyroscopes] of (N, K, 6) residuals in B consecutive
    blocks of about equal sample count."""
    sq, n = _per_sample(r)
    edges = np.linspace(0, len(t), min(blocks, len(t)) + 1).astype(int)
    idx = np.repeat(np.arange(len(edges) - 1), np.diff(edges))
    cnt = np.bincount(idx, minlength=len(edges) - 1).astype(float)
    tm = np.bincount(idx, weights=np.asarray(t, dtype=float)) / np.maximum(cnt, 1)
    s = np.stack([np.bincount(idx, weights=sq[:, c], minlength=len(cnt)) for c in range(2)], axis=1)
    m = np.stack([np.bincount(idx, weights=n[:, c], minlength=len(cnt)) for c in range(2)], axis=1)
    return tm, np.where(m > 0, np.sqrt(s / np.maximum(m, 1)), np.nan)


def binned_rms(rate: np.ndarray, r: np.ndarray, bins: int = RATE_BINS) -> tuple[np.ndarray, np.ndarray]:
    """(B,) median |omega| and (B, 2) RMS [accelerometers, gyroscopes] of (N, K, 6) residuals in B quantile
    bins of the angular rate (samples without a finite rate left out)."""
    rate = np.asarray(rate, dtype=float)
    ok = np.isfinite(rate)
    sq, n = _per_sample(np.asarray(r)[ok])
    rate = rate[ok]
    edges = np.unique(np.quantile(rate, np.linspace(0, 1, bins + 1))) if rate.size else np.array([0.0, 1.0])
    idx = np.clip(np.searchsorted(edges, rate, side="right") - 1, 0, max(len(edges) - 2, 0))
    nb = max(len(edges) - 1, 1)
    s = np.stack([np.bincount(idx, weights=sq[:, c], minlength=nb) for c in range(2)], axis=1)
    m = np.stack([np.bincount(idx, weights=n[:, c], minlength=nb) for c in range(2)], axis=1)
    order = np.argsort(idx, kind="stable")
    split = np.split(rate[order], np.cumsum(np.bincount(idx, minlength=nb))[:-1])
    centre = np.array([np.median(x) if x.size else np.nan for x in split])
    return centre, np.where(m > 0, np.sqrt(s / np.maximum(m, 1)), np.nan)


def _pair_axes(plt):
    return plt.subplots(2, 1, figsize=(9.5, 5.6), sharex=True, constrained_layout=True)


def plot_residual_time(t, before, after, path: Path) -> None:
    """PNG: residual RMS over the IMUs per block of the moving window (time from its first sample; the
    window skips the still intervals and the samples that rotate too little), before and after."""
    tb, rb = block_rms(t, before)
    ta, ra = block_rms(t, after)
    _plot_before_after((tb, rb), (ta, ra), path, style=".", ms=3, legend="upper right",
                       xlabel=f"time in the moving window (s from its first sample; {len(tb)} blocks)",
                       title="normalised residual over the moving window (RMS over IMUs and axes)")


def plot_residual_rate(rate, before, after, path: Path) -> None:
    """PNG: residual RMS over the IMUs against |omega| (deg/s, quantile bins), before and after."""
    cb, rb = binned_rms(rate, before)
    ca, ra = binned_rms(rate, after)
    _plot_before_after((np.rad2deg(cb), rb), (np.rad2deg(ca), ra), path, style="o-", ms=4, legend="upper left",
                       xlabel=f"angular rate |ω| (deg/s; {len(ca)} bins of equal sample count)",
                       title="normalised residual against the angular rate (moving window)")


def _plot_before_after(before, after, path: Path, *, style: str, ms: float, legend: str, xlabel: str,
                       title: str) -> None:
    """The accelerometer and gyroscope panels of a residual RMS (``(x, rms (n, 2))`` before and after) against
    x, on a log scale with the noise level."""
    plt = pyplot(path)
    fig, axes = _pair_axes(plt)
    try:
        for c, (ax, what) in enumerate(zip(axes, ("accelerometers", "gyroscopes"))):
            ax.plot(before[0], before[1][:, c], style, ms=ms, color="0.6", label="before (starting description)")
            ax.plot(after[0], after[1][:, c], style, ms=ms, color="C3", label="after (calibration)")
            ax.axhline(1.0, color="k", lw=0.8, ls="--", label="noise level")
            ax.set_yscale("log")
            ax.set_ylabel(f"{what}\nRMS / noise std")
            ax.grid(True, which="both", alpha=0.3)
        axes[0].legend(fontsize=8, loc=legend)
        axes[1].set_xlabel(xlabel)
        fig.suptitle(title, fontsize=11)
        save_png(fig, path, _DPI, close=False)
    finally:
        plt.close(fig)


def plot_repeatability(rep: dict, recordings: Sequence[str], path: Path) -> None:
    """PNG: per term, each recording's deviation z from the weighted mean in its own std (points), the ±1 and
    ±3 bands, and the term's sqrt(chi^2/dof) ratio in the label."""
    plt = pyplot(path)
    terms = list(rep)
    fig, ax = plt.subplots(figsize=(9.5, 1.2 + 0.45 * len(terms)), constrained_layout=True)
    try:
        rng = np.random.default_rng(0)  # jitter only, so points do not hide each other
        for i, t in enumerate(terms):
            z = rep[t]["z"]
            for r in range(z.shape[0]):
                v = np.ravel(z[r])
                v = v[np.isfinite(v)]
                lab = None
                if i == 0:
                    lab = Path(recordings[r]).name if r < len(recordings) and recordings[r] else f"#{r + 1}"
                ax.plot(np.clip(v, -10, 10), i + 0.25 * (r - (z.shape[0] - 1) / 2) / max(z.shape[0], 1)
                        + rng.uniform(-0.08, 0.08, v.size), ".", ms=4, color=f"C{r % 10}", label=lab)
        ax.axvspan(-1, 1, color="0.85", zorder=0)
        for x in (-3, 3):
            ax.axvline(x, color="0.5", lw=0.8, ls="--")
        ax.set_yticks(range(len(terms)), [f"{t} ({rep[t]['ratio']:.2g})" for t in terms], fontsize=8)
        ax.set_xlim(-10.5, 10.5)
        ax.invert_yaxis()
        ax.set_xlabel("deviation from the recordings' weighted mean / reported std (clipped at ±10)")
        ax.set_title("repeatability: term (√(χ²/dof), 1 = the std explain the spread)", fontsize=10)
        ax.legend(fontsize=8, loc="lower right")
        save_png(fig, path, _DPI, close=False)
    finally:
        plt.close(fig)
