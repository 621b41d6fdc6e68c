"""Plots of calibration results (matplotlib, imported only when a plot is asked for)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from imu_array_ros.util.plotting import pyplot, save_png

__all__ = ["plot_geometry", "plot_static"]


def plot_static(result, path: str | Path) -> None:
    """PNG of a static calibration (an :class:`~imu_array_ros.calibration.array.ArrayCalibration` with a
    static stage): the poses' gravity directions on the sphere (two hemispheres), the four accelerometer
    parameters per IMU with 3-sigma bars, and the residual RMS per IMU."""
    plt = pyplot(path)
    st, poses = result.static, result.poses
    names = list(st.names)
    k = np.arange(len(names))
    std = st.written_std()
    fig = plt.figure(figsize=(max(9.0, 0.4 * len(names) + 5), 8.0))
    grid = fig.add_gridspec(3, 3)
    d = poses.directions
    for j, (sign, label) in enumerate(((1, "z >= 0"), (-1, "z < 0"))):
        ax = fig.add_subplot(grid[j, 0], aspect="equal")
        sel = (d[:, 2] >= 0) if sign > 0 else (d[:, 2] < 0)
        ax.add_patch(plt.Circle((0, 0), 1.0, fill=False, color="0.6"))
        ax.scatter(d[sel, 0], d[sel, 1], s=18, color="C0")
        for i in np.flatnonzero(sel):
            ax.annotate(str(i), d[i, :2], fontsize=6, xytext=(2, 2), textcoords="offset points")
        ax.set_xlim(-1.1, 1.1), ax.set_ylim(-1.1, 1.1)
        ax.set_title(f"pose directions, {label}", fontsize=9)
    panels = (("accelerometer_gain", 1.0, "gain - 1"), ("accelerometer_bias", 1.0, "bias (m/s²)"),
              ("accelerometer_nonorthogonality", 180 / np.pi, "non-orthogonality (°)"),
              ("accelerometer_misalignment", 180 / np.pi, "misalignment (°)"))
    for i, (term, scale, label) in enumerate(panels):
        ax = fig.add_subplot(grid[i // 2, 1 + i % 2])
        v = st.model.terms[term].values * scale - (1.0 if term == "accelerometer_gain" else 0.0)
        e = np.nan_to_num(std.get(term, np.zeros_like(v))) * scale
        for j, color in enumerate(("C0", "C1", "C2")):
            ax.errorbar(k + (j - 1) * 0.2, v[:, j], yerr=3 * e[:, j], fmt="o", ms=3, color=color, capsize=2)
        ax.axhline(0.0, color="0.6", lw=0.8)
        ax.set_title(label + ("" if term in st.terms else " (held)"), fontsize=9)
        ax.set_xticks(k, names, rotation=90, fontsize=6)
    ax = fig.add_subplot(grid[2, 1:])
    ax.bar(k, st.residual_rms, color="C3")
    ax.set_ylabel("residual RMS (m/s²)", fontsize=8)
    ax.set_xticks(k, names, rotation=90, fontsize=6)
    ax.set_title(f"static ({st.method}): {st.poses} poses, consistency {st.improvement_db:+.1f} dB, "
                 f"NIS {st.nis_after:.3g}", fontsize=9)
    fig.tight_layout()
    save_png(fig, path)


def plot_geometry(result, path: str | Path) -> None:
    """PNG of a :class:`~imu_array_ros.calibration.geometry.GeometryCalibration`: per IMU the position
    change (x, y, z, mm) with its 3-sigma bar, and the accelerometer residual RMS before and after."""
    plt = pyplot(path)

    names = list(result.names)
    k = np.arange(len(names))
    change = (result.positions - result.initial_positions) * 1e3
    std = result.position_std * 1e3
    fig, (ax1, ax2) = plt.subplots(2, 1, figsize=(max(6.0, 0.35 * len(names) + 2), 6.5), sharex=True)
    for j, (axis, color) in enumerate(zip("xyz", ("C0", "C1", "C2"))):
        ax1.errorbar(k + (j - 1) * 0.2, change[:, j], yerr=3 * std[:, j], fmt="o", ms=3, color=color, capsize=2,
                     label=f"{axis}")
    ax1.axhline(0.0, color="0.6", lw=0.8)
    ax1.set_ylabel("position change (mm), bars 3σ (CRB)")
    ax1.legend(ncol=3, fontsize=8)
    ax1.set_title(f"geometry calibration ({result.method}): {result.samples_used} samples, "
                  f"reference {result.reference}", fontsize=10)
    ax2.bar(k - 0.2, result.rms_before, width=0.4, label="before", color="0.6")
    ax2.bar(k + 0.2, result.rms_after, width=0.4, label="after", color="C3")
    ax2.set_ylabel("accelerometer residual RMS (m/s²)")
    ax2.set_xticks(k, names, rotation=90, fontsize=7)
    ax2.legend(fontsize=8)
    fig.tight_layout()
    save_png(fig, path)
