"""Credible ellipses of the positions, one panel per IMU placed as on the board (after carlsson2021 Fig. 5)."""

from __future__ import annotations

import textwrap
from pathlib import Path
from typing import Mapping, Sequence

import numpy as np

from imu_array_ros.calibration.bayes.problem import PACKAGE_SIZE
from imu_array_ros.util.plotting import pyplot, save_png

__all__ = ["ellipse_points", "ellipse_radius", "plot_ellipses", "panel_layout", "PRIOR_COLOR", "ESTIMATE_COLORS"]

#: colour of the prior's ellipse
PRIOR_COLOR = "cyan"
#: colours of the estimates, in order (cyan is the prior's)
ESTIMATE_COLORS = ("tab:blue", "tab:red", "tab:green", "tab:purple", "tab:orange", "tab:brown", "tab:pink",
                   "tab:olive")
MM = 1e3  # metres -> millimetres


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
                  prior_std=None, prior_mean=None, package=PACKAGE_SIZE, truth=None,
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
        note = (f"view ±{half_width:.3g} mm: " + " and ".join(outside)
                + f" reach{'es' if len(outside) == 1 else ''} beyond it")

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
