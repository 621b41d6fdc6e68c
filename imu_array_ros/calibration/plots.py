"""Plots of calibration results (matplotlib, imported only when a plot is asked for)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from imu_array_ros.errors import OutputError
from imu_array_ros.io.atomic import atomic_path

__all__ = ["plot_geometry"]


def plot_geometry(result, path: str | Path) -> None:
    """PNG of a :class:`~imu_array_ros.calibration.geometry.GeometryCalibration`: per IMU the position
    change (x, y, z, mm) with its 3-sigma bar, and the accelerometer residual RMS before and after."""
    try:
        import matplotlib
    except ImportError:
        raise OutputError(f"{path}: writing a plot needs matplotlib (pip install 'matplotlib>=3.7')") from None
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

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
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png", dpi=110)
    plt.close(fig)
