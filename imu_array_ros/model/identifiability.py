"""Can an array geometry determine its motion? (skog2016 Sec. II-D)"""

from __future__ import annotations

import math

import numpy as np

from imu_array_ros.errors import IdentifiabilityError

__all__ = ["check_identifiable", "MAX_ARRAY_SPAN"]

#: largest distance, m, between two IMUs of a fusable array: the model is one rigid body, and a description
#: written in millimetres instead of metres reads 1000x too large (a 19 mm board as 19 m)
MAX_ARRAY_SPAN = 5.0


def check_identifiable(positions: np.ndarray, n_gyro_triads: int, *, where: str = "array") -> None:
    """Raise :class:`IdentifiabilityError` unless skog2016 Sec. II-D holds.

    Needs at least one gyroscope triad and at least three accelerometer triads
    whose positions are not collinear (span a plane after removing their mean), at most
    :data:`MAX_ARRAY_SPAN` apart (a unit mistake otherwise).
    """
    positions = np.asarray(positions, dtype=float).reshape(-1, 3)
    if n_gyro_triads < 1:
        raise IdentifiabilityError(f"{where}: no gyroscope triad, angular velocity is not identifiable (skog2016 Sec. II-D)")
    if len(positions) < 3:
        raise IdentifiabilityError(
            f"{where}: {len(positions)} accelerometer triad(s), at least 3 non-collinear are needed (skog2016 Sec. II-D)"
        )
    span = float(np.max(np.linalg.norm(positions[:, None] - positions[None], axis=2)))
    if not span <= MAX_ARRAY_SPAN:
        raise IdentifiabilityError(f"{where}: the IMU positions span {span:.3g} m; positions are in metres (were "
                                   f"they written in millimetres?); a rigid array wider than {MAX_ARRAY_SPAN:g} m "
                                   "is not fused")
    centred = positions - positions.mean(axis=0)
    sv = np.linalg.svd(centred, compute_uv=False)
    scale = max(float(np.abs(positions).max()), 1e-3)
    if sv[1] <= 1e-9 * scale * math.sqrt(len(positions)):
        raise IdentifiabilityError(
            f"{where}: accelerometer triads are collinear, at least 3 non-collinear are needed (skog2016 Sec. II-D)"
        )
