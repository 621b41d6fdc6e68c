"""The one saturation rule of the package (clip level minus a quantisation tolerance)."""

from __future__ import annotations

import numpy as np

__all__ = ["CLIP_RELATIVE_TOLERANCE", "unsaturated"]

#: Quantisation tolerance of a clip level, relative to it, when the description
#: gives no LSB (simulated floats: a clipped reading equals the clip level up to
#: rounding).
CLIP_RELATIVE_TOLERANCE = 1e-9


def unsaturated(values: np.ndarray, clip: float, tolerance: float | None = None) -> np.ndarray:
    """True where a reading is finite and not saturated (NaN and +-inf -> False).

    The one saturation rule of the package: a raw reading is saturated when
    ``|y| >= clip - tolerance``, with ``clip`` the magnitude the sensor clips at
    (same unit as ``values``) and ``tolerance`` half an LSB for quantised
    readings, or ``CLIP_RELATIVE_TOLERANCE * clip`` when None.  Use
    :meth:`LinearArrayModel.acc_unsaturated` / :meth:`~LinearArrayModel.gyro_unsaturated`,
    which pass the description's clip levels.  ``values`` any shape -> bool, same shape.
    """
    if tolerance is None:
        tolerance = CLIP_RELATIVE_TOLERANCE * clip
    level = clip - tolerance
    return (values < level) & (values > -level)  # no float temporary, unlike abs(values) < level
