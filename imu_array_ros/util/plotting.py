"""Plots: matplotlib, imported only when a plot is asked for (the ``[plots]`` extra)."""

from __future__ import annotations

from imu_array_ros.util.extras import require
from imu_array_ros.util.files import atomic_path

__all__ = ["pyplot", "save_png"]


def pyplot(path):
    """``matplotlib.pyplot`` on the Agg backend; a one-line error naming ``path`` and the extra when
    matplotlib is not installed."""
    matplotlib = require("matplotlib", "plots", f"{path}: writing a plot")
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def save_png(fig, path, dpi: int = 110, *, close: bool = True) -> None:
    """Write ``fig`` as a PNG to ``path`` atomically (a reader never sees half a file); close it unless
    ``close`` is False (a caller that closes it itself, also when drawing fails)."""
    import matplotlib.pyplot as plt

    try:
        with atomic_path(path) as tmp:
            fig.savefig(tmp, format="png", dpi=dpi)
    finally:
        if close:
            plt.close(fig)
