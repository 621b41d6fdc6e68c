"""The plot of ``calibrate noise --plot``: Allan deviation per IMU (matplotlib, imported only when asked for)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from imu_array_ros.calibration.noise import B_FACTOR, SENSORS
from imu_array_ros.util.plotting import pyplot, save_png

__all__ = ["plot_noise"]

_AXES = "xyz"


def plot_noise(result, path: str | Path) -> None:
    """One row per IMU, an accelerometer and a gyroscope panel: the pooled Allan deviation of each axis (points;
    the fitted tau range solid), the fitted white-noise line N/sqrt(tau) (slope -1/2), the random-walk line
    K sqrt(tau/3) (slope +1/2) where it is seen, and the bias-instability floor 0.664 B where it is seen."""
    plt = pyplot(path)
    k = len(result.names)
    fig, axes = plt.subplots(k, 2, figsize=(11.0, 2.6 * k + 0.8), squeeze=False)
    colours = ("tab:blue", "tab:orange", "tab:green")
    for row, name in enumerate(result.names):
        for col, (sensor, unit) in enumerate(SENSORS.items()):
            ax = axes[row, col]
            s = result.sensors[sensor][row]
            ax.set_title(f"{name} {sensor}", fontsize=9)
            if s is None:
                ax.text(0.5, 0.5, "no still data", ha="center", va="center", transform=ax.transAxes)
                continue
            t = s.taus
            line = np.geomspace(t[0], t[-1], 50)
            for i, c in enumerate(colours):
                ax.loglog(t, s.adev[:, i], "o", ms=3, color=c, alpha=0.4)
                ax.loglog(t[s.used], s.adev[s.used, i], "-o", ms=3, color=c, label=f"{_AXES[i]}")
                ax.loglog(line, s.noise_density[i] / np.sqrt(line), ":", color=c, lw=1)
                if np.isfinite(s.random_walk[i]):
                    ax.loglog(line, s.random_walk[i] * np.sqrt(line / 3), "--", color=c, lw=1)
                if np.isfinite(s.instability[i]):
                    ax.axhline(B_FACTOR * s.instability[i], color=c, lw=1, ls="-.")
            lo, hi = s.tau_range
            ax.axvspan(lo, hi, color="0.9", zorder=0)
            ax.set_ylabel(f"sigma [{unit}]", fontsize=8)
            ax.grid(True, which="both", alpha=0.3)
            if row == 0:
                ax.legend(fontsize=7, loc="lower left", ncol=3)
            if row == k - 1:
                ax.set_xlabel("tau [s]")
    fig.suptitle("Allan deviation of the still intervals: dotted -1/2 (white noise N), dashed +1/2 (random walk K, "
                 "where seen), dash-dot bias-instability floor 0.664 B (where seen); shaded: tau range fitted",
                 fontsize=9)
    fig.tight_layout(rect=(0, 0, 1, 0.98))
    save_png(fig, path)
