"""Plots of the chains: ArviZ trace and autocorrelation plots of the coordinates that mix worst."""

from __future__ import annotations

import warnings
from pathlib import Path
from typing import Iterable

import numpy as np

from imu_array_ros.calibration.bayes.posterior import arviz
from imu_array_ros.calibration.bayes.report.tables import AXES, COORD_LABEL, UM, coord_index, lowest_ess_coords, \
    summary_values
from imu_array_ros.util.plotting import pyplot, save_png

__all__ = ["plot_trace", "plot_autocorr"]


def _chosen(post, coords, max_coords: int) -> list[tuple[str, str]]:
    if coords is None:
        return lowest_ess_coords(post, max_coords)
    index, out = coord_index(post), []
    for c in coords:
        if isinstance(c, str):
            m = COORD_LABEL.match(c)
            if m is None:
                raise ValueError(f"coordinate {c!r}: expected 'position[imu, axis]' or (imu, axis)")
            c = (m["imu"], m["axis"])
        c = (str(c[0]), str(c[1]))
        if c not in index:
            raise ValueError(f"coordinate {c}: not a free coordinate (free IMUs: {', '.join(post.free_names)})")
        out.append(c)
    return out


def _coord_data(post, coords: list[tuple[str, str]], lp: bool):
    """InferenceData of the chosen coordinates of post.inference_data(), um relative to nominal, one
    variable each (and the log posterior ``lp``)."""
    az = arviz()
    idata = post.inference_data()
    nominal = dict(zip(post.names, post.problem.positions))
    data = {}
    for imu, axis in coords:
        x = idata.posterior["position"].sel(imu=imu, axis=axis).values
        data[f"{imu} {axis} (µm)"] = (x - nominal[imu][AXES.index(axis)]) * UM
    if lp:
        data["log posterior"] = idata.sample_stats["lp"].values
    return az, az.from_dict(posterior=data)


def _chain_summary(post) -> str:
    c, m, _ = post.draws.shape
    return f"{c} chains x {m} draws (after {post.warmup} warm-up), N = {post.n_draws}"


def plot_trace(path: str | Path, post, coords: Iterable | None = None, max_coords: int = 6) -> list[tuple[str, str]]:
    """PNG of ArviZ's trace plot of ``coords`` ((imu, axis) pairs or 'position[imu, axis]' labels; default
    the ``max_coords`` with the lowest bulk ESS) in um relative to nominal, plus the log posterior, and
    the log posterior of the discarded warm-up.  Returns the coordinates shown."""
    plt = pyplot(path)
    what = "chosen coordinates" if coords is not None else "coordinates with the lowest bulk ESS"
    coords = _chosen(post, coords, max_coords)
    az, data = _coord_data(post, coords, lp=True)
    ess = summary_values(post, "ess_bulk")
    n_rows = len(coords) + 1
    warm = post.warmup_trace is not None and np.size(post.warmup_trace) > 0
    height = 1.7 * (n_rows + warm) + 1.3
    fig = plt.figure(figsize=(11.0, height))
    grid = fig.add_gridspec(n_rows + warm, 2, width_ratios=[1.0, 2.2], hspace=0.8, wspace=0.15,
                            top=1 - 0.95 / height, bottom=0.45 / height, left=0.06, right=0.98)
    axes = np.array([[fig.add_subplot(grid[r, 0]), fig.add_subplot(grid[r, 1])] for r in range(n_rows)])
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        az.plot_trace(data, axes=axes, compact=False, legend=False, show=False)
    for r, (imu, axis) in enumerate(coords):
        e = ess.get((imu, axis))
        if e is not None:
            axes[r, 1].set_title(f"{imu} {axis} (µm), ESS bulk {e:.0f}", fontsize=9)
    for ax in axes.ravel():
        ax.tick_params(labelsize=7)
        ax.title.set_fontsize(9)
    if warm:
        ax = fig.add_subplot(grid[n_rows, :])
        for c, row in enumerate(np.atleast_2d(post.warmup_trace)):
            ax.plot(row, lw=0.6, color=f"C{c % 10}")
        tail = np.asarray(post.warmup_trace)[:, post.warmup_trace.shape[1] // 2:]
        finite = tail[np.isfinite(tail)]
        if finite.size:  # the early, far-off values would squash the converged part
            lo, hi = np.percentile(finite, [0.5, 100.0])
            ax.set_ylim(lo - 0.5 * (hi - lo + 1.0), hi + 0.1 * (hi - lo + 1.0))
        ax.set_title("log posterior during the warm-up (discarded), per chain", fontsize=9)
        ax.set_xlabel("warm-up iteration", fontsize=8)
        ax.tick_params(labelsize=7)
    fig.suptitle(f"trace of the {len(coords)} {what} (µm relative to nominal) and the log posterior\n"
                 f"{_chain_summary(post)}", fontsize=10)
    save_png(fig, path)
    return coords


def plot_autocorr(path: str | Path, post, coords: Iterable | None = None, max_coords: int = 6) -> list[tuple[str, str]]:
    """PNG of ArviZ's autocorrelation plot of ``coords`` (as :func:`plot_trace`), one panel per chain and
    coordinate, up to a lag of about five integrated autocorrelation times.  Returns the coordinates."""
    plt = pyplot(path)
    what = "chosen coordinates" if coords is not None else "coordinates with the lowest bulk ESS"
    coords = _chosen(post, coords, max_coords)
    az, data = _coord_data(post, coords, lp=False)
    c, m, _ = post.draws.shape
    ess = summary_values(post, "ess_bulk")
    ess_min = min([ess[x] for x in coords if x in ess and ess[x] > 0] or [float(c * m)])
    tau = c * m / ess_min
    max_lag = int(min(m - 1, max(50, 5 * tau)))
    combined = len(coords) * c > 40
    n_panels = len(coords) * (1 if combined else c)
    cols = min(n_panels, c if not combined else 3)
    rows = int(np.ceil(n_panels / cols))
    fig, axes = plt.subplots(rows, cols, figsize=(2.6 * cols + 0.6, 1.8 * rows + 0.9), squeeze=False,
                             sharey=True)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        az.plot_autocorr(data, max_lag=max_lag, combined=combined, ax=axes.ravel()[:n_panels], show=False,
                         textsize=8)
    for ax in axes.ravel()[n_panels:]:
        ax.set_visible(False)
    if not combined:  # ArviZ titles a panel "variable\nchain"
        for ax in axes.ravel()[:n_panels]:
            head, _, chain = ax.get_title().rpartition("\n")
            if head and chain.isdigit():
                ax.set_title(f"{head}, chain {chain}", fontsize=8)
    fig.suptitle(f"autocorrelation of the {len(coords)} {what} "
                 f"({'chains combined' if combined else 'one panel per chain'}), "
                 f"lags up to {max_lag}\n{_chain_summary(post)}",
                 fontsize=10)
    fig.tight_layout(rect=(0, 0, 1, 1 - 0.5 / (1.8 * rows + 0.9)))
    save_png(fig, path)
    return coords
