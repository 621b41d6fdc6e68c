"""The one saturation rule of the package (clip level minus a quantisation tolerance)."""

from __future__ import annotations

import numpy as np

__all__ = ["CLIP_RELATIVE_TOLERANCE", "clip_tolerance", "unsaturated"]

#: Quantisation tolerance of a clip level, relative to it, when the description
#: gives no LSB (simulated floats: a clipped reading equals the clip level up to
#: rounding).
CLIP_RELATIVE_TOLERANCE = 1e-9


def clip_tolerance(clip: float, tolerance: float | None = None) -> float:
    """The tolerance below ``clip`` at which a reading counts as saturated: ``tolerance``
    when given (half an LSB), else ``CLIP_RELATIVE_TOLERANCE * clip``; 0 for a sensor that
    never clips (``clip`` infinite)."""
    if tolerance is not None:
        return float(tolerance)
    return CLIP_RELATIVE_TOLERANCE * clip if np.isfinite(clip) else 0.0


def unsaturated(values: np.ndarray, clip: float, tolerance: float | None = None) -> np.ndarray:
    """True where a reading is finite and not saturated (NaN and +-inf -> False).

    The one saturation rule of the package: a raw reading is saturated when
    ``|y| >= clip - tolerance``, with ``clip`` the magnitude the sensor clips at
    (same unit as ``values``) and ``tolerance`` half an LSB for quantised
    readings, or as :func:`clip_tolerance` says when None.  Use
    :meth:`LinearArrayModel.acc_unsaturated` / :meth:`~LinearArrayModel.gyro_unsaturated`,
    which pass the description's clip levels.  ``values`` any shape -> bool, same shape.
    """
    level = clip - clip_tolerance(clip, tolerance)
    return (values < level) & (values > -level)  # no float temporary, unlike abs(values) < level
