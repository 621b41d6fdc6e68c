"""Reports of a Bayesian position calibration (:class:`~imu_array_ros.calibration.bayes_sampler.BayesPosterior`).

:func:`write_report` writes into one directory:

``diagnostics.json``
    Strict JSON: the sampler settings, the run (chains, draws, warm-up, N and
    the Var[log-likelihood] table it was tuned on, acceptances, ESS, R-hat,
    wall and CPU time, convergence), and :func:`diagnostics_table`'s rows,
    one per free coordinate.
``diagnostics.md``
    The same for a human: a summary, the N-tuning table, the table of rows,
    and one line naming where the MCMC posterior and its Laplace (Gaussian /
    Cramér-Rao) approximation disagree: |z| > ``Z_LIMIT`` with z = (MCMC mean -
    Laplace mean) / MCMC sd, or a Laplace / MCMC sd ratio outside
    ``SD_RATIO_RANGE``.
``ellipses.png`` (:func:`plot_ellipses`, after carlsson2021 Fig. 5)
    One panel per IMU, placed as the IMUs sit on the board when their nominal
    positions form a grid (one block per z level, side by side), in mm
    relative to the IMU's nominal position: the x-y 50 % credible ellipses
    and means of the MCMC posterior and of the Laplace approximation, the
    prior's ellipse (cyan), the package outline (dashed) and, when known,
    the true position (black x).  Every panel has the same scale.
``trace.png`` (:func:`plot_trace`)
    ArviZ trace plot (density per chain and the chains' draws) of the
    coordinates with the lowest bulk ESS, in um relative to nominal, and the
    log posterior; below, the log posterior during the discarded warm-up.
``autocorr.png`` (:func:`plot_autocorr`)
    Autocorrelation per chain of the same coordinates (slow decay = low ESS).
``posterior.nc``
    The chains as ArviZ InferenceData (netCDF), metres, for later analysis.

Everything is written atomically (a temporary sibling renamed over the target).
"""

from __future__ import annotations

import dataclasses
import json
import re
import textwrap
import warnings
from pathlib import Path
from typing import Iterable, Mapping, Sequence

import numpy as np

from imu_array_ros.util.files import atomic_path, atomic_write_text
from imu_array_ros.util.plotting import pyplot, save_png
from imu_array_ros.util.jsontools import json_safe

__all__ = ["ellipse_points", "ellipse_radius", "plot_ellipses", "panel_layout", "plot_trace", "plot_autocorr",
           "lowest_ess_coords", "diagnostics_table", "disagreements", "write_report", "Z_LIMIT", "SD_RATIO_RANGE",
           "PRIOR_COLOR", "ESTIMATE_COLORS"]

#: |z| (MCMC vs Laplace mean, in MCMC sds) above which :func:`disagreements` names a coordinate
Z_LIMIT = 2.0
#: Laplace / MCMC sd ratios outside this range are named by :func:`disagreements`
SD_RATIO_RANGE = (0.8, 1.25)
#: colour of the prior's ellipse
PRIOR_COLOR = "cyan"
#: colours of the estimates, in order (cyan is the prior's)
ESTIMATE_COLORS = ("tab:blue", "tab:red", "tab:green", "tab:purple", "tab:orange", "tab:brown", "tab:pink",
                   "tab:olive")
AXES = ("x", "y", "z")
UM = 1e6  # metres -> micrometres
MM = 1e3  # metres -> millimetres


# --------------------------------------------------------------------------- ellipses


def ellipse_radius(level: float) -> float:
    """Mahalanobis radius of the ``level`` credible region of a 2-D Gaussian: sqrt(chi2.ppf(level, 2)).

    The chi-square distribution with 2 degrees of freedom is exponential: ppf(p) = -2 log(1 - p)."""
    level = float(level)
    if not 0.0 < level < 1.0:
        raise ValueError(f"credible level {level}: must be in (0, 1)")
    return float(np.sqrt(-2.0 * np.log1p(-level)))


def ellipse_points(mean2, cov2, level: float = 0.5, n: int = 100) -> np.ndarray:
    """(n, 2) points on the boundary of the ``level`` credible ellipse of N(mean2, cov2).

    Every point has Mahalanobis distance^2 chi2.ppf(level, 2); the first and last point coincide
    (a closed curve).  A singular covariance gives a degenerate ellipse (a segment or a point)."""
    mean2 = np.asarray(mean2, dtype=float).reshape(2)
    cov2 = np.asarray(cov2, dtype=float)
    if cov2.shape != (2, 2):
        raise ValueError(f"covariance of shape {cov2.shape}, expected (2, 2)")
    if n < 3:
        raise ValueError(f"n = {n}: an ellipse needs at least 3 points")
    w, v = np.linalg.eigh(0.5 * (cov2 + cov2.T))
    half_axes = v * np.sqrt(np.clip(w, 0.0, None))  # columns: the semi-axes of the unit-Mahalanobis ellipse
    t = np.linspace(0.0, 2.0 * np.pi, n)
    circle = np.stack([np.cos(t), np.sin(t)], axis=1)
    return mean2 + ellipse_radius(level) * circle @ half_axes.T


def _ellipse_extent(mean2, cov2, radius: float) -> float:
    """Largest |coordinate| of the ellipse (same units as mean2)."""
    sd = np.sqrt(np.clip(np.diag(cov2), 0.0, None))
    return float(np.max(np.abs(mean2) + radius * sd))


# --------------------------------------------------------------------------- the ellipse figure


def panel_layout(nominal, max_columns: int = 8, tol: float = 5e-4) -> tuple[dict[int, tuple[int, int]], int, list]:
    """Where each IMU's panel goes: ({index: (row, column)}, rows, column widths).

    When the nominal positions form a grid -- per z level (levels closer than ``tol`` m are one)
    every IMU has its own (x, y) cell and the cells are at most 1.5 per IMU -- the panels sit as
    the IMUs do seen from above (x to the right, y up), one block per z level (highest first) side
    by side with a narrow spacer column (width 0.25) between blocks.  Otherwise the IMUs are
    ordered by z (descending), y (descending), x and laid out in rows of up to ``max_columns``.
    """
    pos = np.asarray(nominal, dtype=float)
    k = len(pos)

    def levels(values: np.ndarray, descending: bool) -> tuple[np.ndarray, int]:
        order = np.argsort(-values if descending else values, kind="stable")
        idx = np.empty(len(values), dtype=int)
        level, last = -1, None
        for i in order:
            if last is None or abs(values[i] - last) > tol:
                level += 1
                last = values[i]
            idx[i] = level
        return idx, level + 1

    zl, nz = levels(pos[:, 2], descending=True)
    blocks, cells = [], 0
    for z in range(nz):
        members = np.flatnonzero(zl == z)
        xi, nx = levels(pos[members, 0], descending=False)
        yi, ny = levels(pos[members, 1], descending=True)
        blocks.append((members, xi, yi, nx, ny))
        cells += nx * ny
    grid_ok = k > 1 and cells <= 1.5 * k and all(len(set(zip(b[1], b[2]))) == len(b[0]) for b in blocks)
    n_cols = sum(b[3] for b in blocks) + len(blocks) - 1
    if grid_ok and n_cols <= 2 * max_columns:
        place, widths, col0 = {}, [], 0
        rows = max(b[4] for b in blocks)
        for j, (members, xi, yi, nx, ny) in enumerate(blocks):
            if j:
                widths.append(0.25)
                col0 += 1
            for m, cx, cy in zip(members, xi, yi):
                place[int(m)] = (int(cy), int(col0 + cx))
            widths += [1.0] * nx
            col0 += nx
        return place, rows, widths
    order = np.lexsort((pos[:, 0], -pos[:, 1], -pos[:, 2]))
    cols = max(1, min(max_columns, k))
    place = {int(m): (i // cols, i % cols) for i, m in enumerate(order)}
    return place, int(np.ceil(k / cols)), [1.0] * cols


def _colors(labels: Sequence[str], colors) -> dict[str, str]:
    if colors is None:
        return {lab: ESTIMATE_COLORS[i % len(ESTIMATE_COLORS)] for i, lab in enumerate(labels)}
    if isinstance(colors, Mapping):
        return {lab: colors.get(lab, ESTIMATE_COLORS[i % len(ESTIMATE_COLORS)]) for i, lab in enumerate(labels)}
    colors = list(colors)
    return {lab: colors[i % len(colors)] for i, lab in enumerate(labels)}


def plot_ellipses(path: str | Path, names: Sequence[str], nominal, estimates: Mapping[str, tuple], *,
                  prior_std=None, prior_mean=None, package=(4e-3, 4e-3, 1e-3), truth=None,
                  reference: str | None = None, level: float = 0.5, colors=None, title: str | None = None,
                  view: float | None = None, origin: str = "nominal") -> dict[str, tuple[int, int]]:
    """PNG of the x-y credible ellipses of each IMU's position (carlsson2021 Fig. 5).

    Parameters
    ----------
    path : the PNG to write (atomically).
    names : (K,) IMU names; nominal : (K, 3) nominal positions, m (each panel's origin).
    estimates : label -> (mean (K, 3), covariance (K, 3, 3)), m / m^2; one colour per label.
    prior_std : (K, 3) prior standard deviations (m), drawn as the prior's ``level`` ellipse in cyan,
        centred at ``prior_mean`` (K, 3) (default: nominal).
    package : (3,) package size, m: a dashed rectangle +-package/2 about nominal (None: none).
    truth : (K, 3) true positions, a black x.  reference : the held IMU's name ("reference (held)").
    level : credible level of every ellipse.  colors : list, or label -> colour.
    view : half width of every panel, mm (None: automatic -- the estimates, truth, prior and package
        all fit when the prior/package are at most 5 times the estimates' extent; otherwise the view
        zooms on the estimates and a note says what lies outside).
    origin : what the ``nominal`` positions are, for the axis labels and the default title ("nominal";
        e.g. "true" when the panels are centred on the true positions).

    Returns
    -------
    {name: (row, column)} of each panel (:func:`panel_layout`).
    """
    plt = pyplot(path)
    from matplotlib.lines import Line2D
    from matplotlib.patches import Rectangle
    from matplotlib.ticker import MaxNLocator

    names = list(names)
    nominal = np.asarray(nominal, dtype=float)
    k = len(names)
    if nominal.shape != (k, 3):
        raise ValueError(f"nominal positions of shape {nominal.shape}, expected {(k, 3)}")
    est = {}
    for label, (mean, cov) in estimates.items():
        mean, cov = np.asarray(mean, dtype=float), np.asarray(cov, dtype=float)
        if mean.shape != (k, 3) or cov.shape != (k, 3, 3):
            raise ValueError(f"estimate {label!r}: mean {mean.shape} / covariance {cov.shape}, expected "
                             f"{(k, 3)} / {(k, 3, 3)}")
        est[label] = ((mean - nominal) * MM, cov * MM ** 2)
    prior_std = None if prior_std is None else np.broadcast_to(np.asarray(prior_std, dtype=float), (k, 3))
    prior_off = np.zeros((k, 3)) if prior_mean is None else \
        (np.broadcast_to(np.asarray(prior_mean, dtype=float), (k, 3)) - nominal) * MM
    truth_off = None if truth is None else (np.asarray(truth, dtype=float) - nominal) * MM
    if reference is not None and reference not in names:
        raise ValueError(f"reference {reference!r} is not one of the IMUs")
    ref = names.index(reference) if reference is not None else None
    radius = ellipse_radius(level)
    color = _colors(list(est), colors)

    # one scale for every panel
    free = [i for i in range(k) if i != ref]
    est_extent = 0.0
    for off, cov in est.values():
        for i in free:
            if np.all(np.isfinite(off[i, :2])) and np.all(np.isfinite(cov[i, :2, :2])):
                est_extent = max(est_extent, _ellipse_extent(off[i, :2], cov[i, :2, :2], radius))
    if truth_off is not None:
        est_extent = max(est_extent, float(np.nanmax(np.abs(truth_off[free, :2]), initial=0.0)))
    context = []  # (extent, what) of the prior and the package
    if prior_std is not None:
        r = float(np.max(np.abs(prior_off[free, :2]) + radius * prior_std[free, :2] * MM, initial=0.0))
        context.append((r, f"the prior (cyan, {level:.0%} ellipse up to {r:.3g} mm)"))
    if package is not None:
        half = 0.5 * np.asarray(package, dtype=float)[:2] * MM
        context.append((float(np.max(half)), f"the package outline (±{half[0]:.3g} x ±{half[1]:.3g} mm)"))
    ctx_extent = max([e for e, _ in context], default=0.0)
    note = None
    if view is not None:
        half_width = float(view)
    elif est_extent <= 0.0:
        half_width = 1.1 * ctx_extent if ctx_extent > 0 else 1.0
    elif ctx_extent <= 5.0 * est_extent:
        half_width = 1.1 * max(est_extent, ctx_extent)
    else:
        half_width = 1.2 * est_extent
    outside = [what for e, what in context if e > half_width]
    if outside:
        note = f"view ±{half_width:.3g} mm: " + " and ".join(outside) + f" reach{'es' if len(outside) == 1 else ''} beyond it"

    place, rows, widths = panel_layout(nominal)
    ncols = len(widths)
    # blocks of columns between spacers (one per z level when laid out as on the board)
    edges = [-1] + [j for j, w in enumerate(widths) if w < 1.0] + [ncols]
    blocks = [(a + 1, b) for a, b in zip(edges[:-1], edges[1:])] if len(edges) > 2 else []
    # sizes in inches: panels of ``panel``, the grid centred, text wrapped to the width
    panel = 1.9
    grid_w = panel * sum(widths)
    width = max(7.5, grid_w + 1.0)
    title = title or f"{level:.0%} credible ellipses of the x-y positions, mm relative to {origin}"
    title_lines = textwrap.wrap(title, int(12.5 * width))
    note_lines = textwrap.wrap(note, int(17 * width)) if note else []
    n_handles = len(est) + (prior_std is not None) + (package is not None) + (truth_off is not None)
    leg_cols = max(1, min(n_handles, int(width / 1.8)))
    leg_rows = int(np.ceil(n_handles / leg_cols)) if n_handles else 0
    top_in = 0.3 + 0.2 * len(title_lines) + (0.3 if blocks else 0.0)
    leg_in = 0.22 * leg_rows + 0.05
    note_in = 0.15 * len(note_lines) + (0.05 if note_lines else 0.0)
    bottom_in = leg_in + note_in + 0.45
    height = panel * rows + top_in + bottom_in
    side = (width - grid_w - 1.0) / 2
    fig = plt.figure(figsize=(width, height))
    grid = fig.add_gridspec(rows, ncols, width_ratios=widths, left=(0.7 + side) / width,
                            right=1 - (0.3 + side) / width, bottom=bottom_in / height, top=1 - top_in / height,
                            wspace=0.35, hspace=0.45)
    for i, name in enumerate(names):
        r, c = place[i]
        ax = fig.add_subplot(grid[r, c])
        ax.set_title(name, fontsize=8, pad=2)
        ax.set_xlim(-half_width, half_width)
        ax.set_ylim(-half_width, half_width)
        ax.set_aspect("equal", adjustable="box")
        ax.tick_params(labelsize=6, length=2, pad=1)
        ax.xaxis.set_major_locator(MaxNLocator(3, symmetric=True))
        ax.yaxis.set_major_locator(MaxNLocator(3, symmetric=True))
        ax.axhline(0.0, color="0.85", lw=0.5, zorder=0)
        ax.axvline(0.0, color="0.85", lw=0.5, zorder=0)
        if package is not None:
            hx, hy = 0.5 * package[0] * MM, 0.5 * package[1] * MM
            ax.add_patch(Rectangle((-hx, -hy), 2 * hx, 2 * hy, fill=False, ls="--", lw=0.8, color="0.4"))
        if i == ref:
            ax.text(0.5, 0.5, "reference\n(held)", transform=ax.transAxes, ha="center", va="center",
                    fontsize=8, color="0.3")
            continue
        if prior_std is not None:
            pts = ellipse_points(prior_off[i, :2], np.diag(prior_std[i, :2] * MM) ** 2, level)
            ax.plot(pts[:, 0], pts[:, 1], color=PRIOR_COLOR, lw=1.0)
        for label, (off, cov) in est.items():
            if not (np.all(np.isfinite(off[i, :2])) and np.all(np.isfinite(cov[i, :2, :2]))):
                continue
            pts = ellipse_points(off[i, :2], cov[i, :2, :2], level)
            ax.plot(pts[:, 0], pts[:, 1], color=color[label], lw=1.0)
            ax.plot(off[i, 0], off[i, 1], "o", ms=2.5, color=color[label])
        if truth_off is not None and np.all(np.isfinite(truth_off[i, :2])):
            ax.plot(truth_off[i, 0], truth_off[i, 1], "x", ms=5, mew=1.2, color="k")
    handles = [Line2D([], [], color=color[lab], marker="o", ms=3, lw=1.0, label=lab) for lab in est]
    if prior_std is not None:
        handles.append(Line2D([], [], color=PRIOR_COLOR, lw=1.0, label="prior"))
    if package is not None:
        handles.append(Line2D([], [], color="0.4", ls="--", lw=0.8, label="package outline"))
    if truth_off is not None:
        handles.append(Line2D([], [], color="k", marker="x", ls="none", ms=5, label="truth"))
    if handles:
        fig.legend(handles=handles, loc="lower center", ncol=leg_cols, fontsize=8, frameon=False,
                   bbox_to_anchor=(0.5, 0.02 / height), borderaxespad=0.0)
    fig.suptitle("\n".join(title_lines), fontsize=10, y=1 - 0.12 / height, va="top")
    fig.text(0.5, (leg_in + note_in + 0.05) / height, f"x - {origin} (mm)", ha="center", va="bottom", fontsize=8)
    fig.text((0.15 + side) / width, (bottom_in + 0.5 * panel * rows) / height, f"y - {origin} (mm)", ha="left",
             va="center", rotation=90, fontsize=8)
    x_of = np.concatenate([[0.0], np.cumsum(widths)]) * panel + 0.7 + side  # column edges, inches
    for a, b in blocks:
        z = [nominal[i, 2] for i in range(k) if a <= place[i][1] < b]
        fig.text(0.5 * (x_of[a] + x_of[b]) / width, 1 - (top_in - 0.3) / height,
                 f"z = {np.mean(z) * MM:+.3g} mm (seen from above: x right, y up)", ha="center", va="bottom",
                 fontsize=8, color="0.3")
    if note_lines:
        fig.text(0.5, (leg_in + 0.03) / height, "\n".join(note_lines), ha="center", va="bottom", fontsize=7,
                 color="0.3")
    save_png(fig, path)
    return {names[i]: place[i] for i in range(k)}


# --------------------------------------------------------------------------- chains


_LABEL = re.compile(r"^position\[(?P<imu>.+), (?P<axis>[xyz])\]$")


def _coord_index(post) -> dict[tuple[str, str], int]:
    """(imu, axis) -> column of post.draws."""
    return {(name, a): 3 * j + i for j, name in enumerate(post.free_names) for i, a in enumerate(AXES)}


def lowest_ess_coords(post, n: int = 6) -> list[tuple[str, str]]:
    """The ``n`` free coordinates (imu, axis) with the lowest bulk ESS (post.summary), lowest first."""
    index = _coord_index(post)
    ess = _summary_values(post, "ess_bulk")
    if not ess:  # no (or an unexpected) summary: the coordinates in order
        return list(index)[:n]
    # NaN (ArviZ could not compute it) counts as lowest; ties in the draws' order
    key = [(v if np.isfinite(v) else -1.0, index[c], c) for c, v in ess.items() if c in index]
    return [c for _, _, c in sorted(key)[:n]]


def _chosen(post, coords, max_coords: int) -> list[tuple[str, str]]:
    if coords is None:
        return lowest_ess_coords(post, max_coords)
    index, out = _coord_index(post), []
    for c in coords:
        if isinstance(c, str):
            m = _LABEL.match(c)
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
    from imu_array_ros.calibration.bayes_sampler import arviz

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
    ess = _summary_values(post, "ess_bulk")
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
    ess = _summary_values(post, "ess_bulk")
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


def _summary_values(post, column: str) -> dict[tuple[str, str], float]:
    out = {}
    if post.summary is None or column not in post.summary:
        return out
    for label, value in post.summary[column].items():
        m = _LABEL.match(str(label))
        if m:
            out[m["imu"], m["axis"]] = float(value)
    return out


# --------------------------------------------------------------------------- the table


def diagnostics_table(post) -> list[dict]:
    """One row per free coordinate (the order of ``post.draws``' columns).

    imu, axis; nominal_mm; mean_um, sd_um (MCMC, mean relative to nominal); hdi_low_um, hdi_high_um
    (ArviZ's highest density interval, 94 % by default: hdi_3%/hdi_97%, relative to nominal);
    mcse_mean_um, mcse_sd_um, ess_bulk, ess_tail, r_hat (ArviZ summary); laplace_mean_um,
    laplace_sd_um (the Gaussian approximation, relative to nominal); ml_um, crb_sd_um (the ML estimate
    and its Cramér-Rao std it is built from); z = (mean - laplace_mean) / sd; sd_ratio =
    laplace_sd / sd.  Values are floats (NaN where ArviZ gave none).
    """
    s = post.summary
    hdi = sorted([c for c in s.columns if str(c).startswith("hdi_")],
                 key=lambda c: float(str(c)[4:].rstrip("%"))) if s is not None else []
    lap = post.laplace
    lap_sd = np.sqrt(np.clip(np.diag(lap.covariance), 0.0, None))
    crb_sd = np.sqrt(np.clip(np.diag(lap.crb), 0.0, None))
    nominal = post.problem.theta_of(post.problem.positions)
    mean, sd = post.mean, post.flat.std(axis=0, ddof=1)
    rows = []
    for (imu, axis), j in _coord_index(post).items():
        label = f"position[{imu}, {axis}]"
        stat = s.loc[label] if s is not None and label in s.index else None

        def col(name, scale=1.0, shift=0.0):
            if stat is None or name not in stat:
                return float("nan")
            return (float(stat[name]) - shift) * scale

        row = {
            "imu": imu, "axis": axis, "nominal_mm": float(nominal[j] * MM),
            "mean_um": float((mean[j] - nominal[j]) * UM), "sd_um": float(sd[j] * UM),
            "hdi_label": f"{hdi[0]}..{hdi[-1]}" if len(hdi) >= 2 else None,
            "hdi_low_um": col(hdi[0], UM, nominal[j]) if len(hdi) >= 2 else float("nan"),
            "hdi_high_um": col(hdi[-1], UM, nominal[j]) if len(hdi) >= 2 else float("nan"),
            "mcse_mean_um": col("mcse_mean", UM), "mcse_sd_um": col("mcse_sd", UM),
            "ess_bulk": col("ess_bulk"), "ess_tail": col("ess_tail"), "r_hat": col("r_hat"),
            "laplace_mean_um": float((lap.mean[j] - nominal[j]) * UM), "laplace_sd_um": float(lap_sd[j] * UM),
            "ml_um": float((lap.ml[j] - nominal[j]) * UM), "crb_sd_um": float(crb_sd[j] * UM),
        }
        row["z"] = (row["mean_um"] - row["laplace_mean_um"]) / row["sd_um"] if row["sd_um"] > 0 else float("nan")
        row["sd_ratio"] = row["laplace_sd_um"] / row["sd_um"] if row["sd_um"] > 0 else float("nan")
        rows.append(row)
    return rows


def disagreements(rows: Sequence[dict], z_limit: float = Z_LIMIT, sd_range=SD_RATIO_RANGE) -> list[dict]:
    """The rows (of :func:`diagnostics_table`) where MCMC and Laplace disagree: |z| > z_limit or the sd
    ratio outside sd_range (a NaN counts as a disagreement); each {imu, axis, z, sd_ratio, why}."""
    out = []
    for r in rows:
        why = []
        if not np.isfinite(r["z"]) or abs(r["z"]) > z_limit:
            why.append(f"z = {r['z']:+.2f}")
        if not np.isfinite(r["sd_ratio"]) or not sd_range[0] <= r["sd_ratio"] <= sd_range[1]:
            why.append(f"sd ratio {r['sd_ratio']:.2f}")
        if why:
            out.append({"imu": r["imu"], "axis": r["axis"], "z": r["z"], "sd_ratio": r["sd_ratio"],
                        "why": ", ".join(why)})
    return out


def _disagreement_line(dis: list[dict]) -> str:
    crit = (f"|z| > {Z_LIMIT:g} or Laplace/MCMC sd ratio outside "
            f"[{SD_RATIO_RANGE[0]:g}, {SD_RATIO_RANGE[1]:g}]")
    if not dis:
        return f"**MCMC vs Laplace:** agree everywhere (no coordinate with {crit})."
    return (f"**MCMC vs Laplace:** disagree at {len(dis)} coordinate(s) ({crit}): "
            + "; ".join(f"{d['imu']} {d['axis']} ({d['why']})" for d in dis) + ".")


# --------------------------------------------------------------------------- the report


def _imu_covariances(problem, cov: np.ndarray) -> np.ndarray:
    out = np.zeros((len(problem.names), 3, 3))
    for j, k in enumerate(problem.free):
        out[k] = cov[3 * j:3 * j + 3, 3 * j:3 * j + 3]
    return out


def _fmt(v, spec: str) -> str:
    return "-" if v is None or not np.isfinite(v) else format(v, spec)


def _markdown(post, rows, dis, nc_note: str | None, truth_rows: list | None) -> str:
    p = post.problem
    c, m, _ = post.draws.shape
    lines = ["# Bayesian position calibration: diagnostics", "",
             f"{post.summary_line()}", "",
             f"* IMUs: {len(p.names)}, reference {p.names[p.reference]} (held); {p.n_samples} samples; "
             f"prior {p.prior.kind}; rho {p.rho:g}; omega covariance {p.omega_covariance}; proposal "
             f"{post.settings.proposal}; runner {post.runner}",
             f"* chains {c}, draws per chain {m}, warm-up per chain {post.warmup}, N = {post.n_draws}",
             f"* random-walk acceptance per chain: {', '.join(_fmt(a, '.1%') for a in post.acceptance)}; "
             f"independence: {', '.join(_fmt(a, '.1%') for a in post.acceptance_independence)}",
             f"* ESS bulk >= {post.ess_bulk_min:.0f}, ESS tail >= {post.ess_tail_min:.0f}, "
             f"R-hat <= {post.rhat_max:.4f} (targets: ESS {post.settings.ess:g}, R-hat {post.settings.rhat:g}) "
             f"-> {'converged' if post.converged else '**NOT converged**'}",
             f"* {post.seconds:.1f} s wall, {post.cpu_seconds:.1f} CPU s", "",
             _disagreement_line(dis), ""]
    if nc_note:
        lines += [f"**posterior.nc not written:** {nc_note}", ""]
    lines += ["## Draws per time sample (N)", ""]
    if post.var_loglik:
        lines += ["| N | Var[log-likelihood estimate] |", "|---:|---:|"]
        lines += [f"| {n} | {v:.4g} |" for n, v in post.var_loglik]
        lines += ["", f"Target variance {post.settings.loglik_var:g}; chosen N = {post.n_draws}.", ""]
    else:
        lines += [f"N = {post.n_draws} was given (not tuned).", ""]
    hdi = rows[0]["hdi_label"] if rows and rows[0]["hdi_label"] else "hdi"
    lines += ["## Per coordinate", "",
              "Micrometres relative to the nominal position; z = (MCMC mean - Laplace mean) / MCMC sd; "
              "sd ratio = Laplace sd / MCMC sd.", "",
              f"| IMU | axis | mean | sd | {hdi} | MCSE mean | ESS bulk | ESS tail | R-hat | Laplace mean | "
              "Laplace sd | z | sd ratio |" + (" truth | (mean-truth)/sd |" if truth_rows else ""),
              "|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|" + ("---:|---:|" if truth_rows else "")]
    for i, r in enumerate(rows):
        line = (f"| {r['imu']} | {r['axis']} | {_fmt(r['mean_um'], '.2f')} | {_fmt(r['sd_um'], '.2f')} | "
                f"{_fmt(r['hdi_low_um'], '.1f')} .. {_fmt(r['hdi_high_um'], '.1f')} | {_fmt(r['mcse_mean_um'], '.2f')} | "
                f"{_fmt(r['ess_bulk'], '.0f')} | {_fmt(r['ess_tail'], '.0f')} | {_fmt(r['r_hat'], '.4f')} | "
                f"{_fmt(r['laplace_mean_um'], '.2f')} | {_fmt(r['laplace_sd_um'], '.2f')} | {_fmt(r['z'], '+.2f')} | "
                f"{_fmt(r['sd_ratio'], '.2f')} |")
        if truth_rows:
            line += f" {_fmt(r['truth_um'], '.2f')} | {_fmt(r['z_truth'], '+.2f')} |"
        lines.append(line)
    lines += ["", "Files: diagnostics.json (the same, machine-readable), ellipses.png (posterior vs Laplace vs "
              "prior, x-y), trace.png, autocorr.png, posterior.nc (the chains, ArviZ netCDF).", ""]
    return "\n".join(lines)


def write_report(post, out_dir: str | Path, *, plots: bool = True, truth=None, extra: Mapping | None = None) -> list[Path]:
    """Write the report of ``post`` into ``out_dir`` (module docstring); returns the paths written.

    truth : (K, 3) true positions (simulations): added to the rows (truth_um, z_truth = (mean - truth) /
    sd) and to the ellipse plot.  extra : merged into diagnostics.json at the top level.  With
    ``plots=False`` no PNG is written.  A posterior.nc that cannot be written (no netCDF engine) is
    skipped and noted in diagnostics.md and diagnostics.json (``netcdf_error``).
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    p = post.problem
    rows = diagnostics_table(post)
    truth_rows = None
    if truth is not None:
        truth = np.asarray(truth, dtype=float)
        if truth.shape != p.positions.shape:
            raise ValueError(f"truth of shape {truth.shape}, expected {p.positions.shape}")
        t = p.theta_of(truth) - p.theta_of(p.positions)
        for r, tj in zip(rows, t):
            r["truth_um"] = float(tj * UM)
            r["z_truth"] = (r["mean_um"] - r["truth_um"]) / r["sd_um"] if r["sd_um"] > 0 else float("nan")
        truth_rows = rows
    dis = disagreements(rows)
    written: list[Path] = []

    nc_note = None
    nc = out / "posterior.nc"
    try:
        idata = post.inference_data()
        with atomic_path(nc) as tmp:
            idata.to_netcdf(str(tmp))
        written.append(nc)
    except Exception as err:  # no netCDF engine, or one that refuses: the report goes on without it
        nc_note = f"{type(err).__name__}: {err}".splitlines()[0]

    c, m, _ = post.draws.shape
    doc = {
        "summary": post.summary_line(),
        "settings": dataclasses.asdict(post.settings),
        "run": {
            "chains": c, "draws_per_chain": m, "warmup_per_chain": post.warmup, "n_draws": post.n_draws,
            "var_loglik": [{"n_draws": int(n), "variance": float(v)} for n, v in post.var_loglik],
            "acceptance_random_walk": post.acceptance, "acceptance_independence": post.acceptance_independence,
            "ess_bulk_min": post.ess_bulk_min, "ess_tail_min": post.ess_tail_min, "rhat_max": post.rhat_max,
            "converged": bool(post.converged), "seconds": post.seconds, "cpu_seconds": post.cpu_seconds,
            "runner": post.runner,
        },
        "problem": {
            "names": list(p.names), "reference": p.names[p.reference], "free": post.free_names,
            "samples": p.n_samples, "prior": p.prior.kind, "rho": p.rho, "omega_covariance": p.omega_covariance,
        },
        "units": "rows: um relative to the nominal position (nominal_mm: mm)",
        "criteria": {"z_limit": Z_LIMIT, "sd_ratio_range": list(SD_RATIO_RANGE)},
        "disagreements": dis,
        "rows": rows,
    }
    if nc_note:
        doc["netcdf_error"] = nc_note
    doc.update(dict(extra or {}))
    path = out / "diagnostics.json"
    atomic_write_text(path, json.dumps(json_safe(doc), indent=1, allow_nan=False) + "\n")
    written.append(path)
    path = out / "diagnostics.md"
    atomic_write_text(path, _markdown(post, rows, dis, nc_note, truth_rows))
    written.append(path)

    if plots:
        pr = p.prior
        k = len(p.names)
        if pr.kind == "gaussian":
            prior_std = np.zeros((k, 3))
            prior_std[p.free] = pr.std.reshape(-1, 3)
            prior_mean = p.positions.copy()
            prior_mean[p.free] = pr.mean.reshape(-1, 3)
            from imu_array_ros.calibration.bayes import PACKAGE_SIZE
            package = PACKAGE_SIZE
            title = ("50 % credible ellipses (x-y): MCMC posterior vs Laplace approximation vs prior, "
                     "mm relative to nominal")
        else:  # the uniform prior is a box: drawn as the package outline
            prior_std = prior_mean = None
            package = tuple(2.0 * pr.std[:3])
            title = ("50 % credible ellipses (x-y): MCMC posterior vs Laplace approximation; the uniform prior "
                     "is the dashed box; mm relative to nominal")
        lap = post.laplace
        estimates = {"posterior (MCMC)": (post.positions_mean(), post.imu_covariances()),
                     "Laplace": (p.full_positions(lap.mean), _imu_covariances(p, lap.covariance))}
        path = out / "ellipses.png"
        plot_ellipses(path, p.names, p.positions, estimates, prior_std=prior_std, prior_mean=prior_mean,
                      package=package, truth=truth, reference=p.names[p.reference], title=title)
        written.append(path)
        path = out / "trace.png"
        plot_trace(path, post)
        written.append(path)
        path = out / "autocorr.png"
        plot_autocorr(path, post)
        written.append(path)
    return written
