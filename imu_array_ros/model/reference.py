"""Naming IMUs in a calibration: the one rule for the reference IMU and for lists of IMUs.

An IMU is named by its name (as in the description) or by its index in the
description's order.  The *reference* IMU fixes what a calibration cannot
observe (the array frame, a common shift of the positions, a common gyroscope
scale, ...): its parameters are held.  Every calibration resolves it with
:func:`reference_index`: none given means the first IMU (of those fitted).
"""

from __future__ import annotations

from typing import Iterable, Sequence

import numpy as np

from imu_array_ros.errors import CalibrationError

__all__ = ["imu_indexes", "reference_index"]


def _one(names: Sequence[str], item, label: str) -> int:
    if isinstance(item, (int, np.integer)) and not isinstance(item, bool) and 0 <= int(item) < len(names):
        return int(item)
    if isinstance(item, str) and item in names:
        return list(names).index(item)
    raise CalibrationError(f"{label}: unknown IMU {item!r} (the array has {', '.join(names)})")


def imu_indexes(names: Sequence[str], imus: str | int | Iterable | None, label: str = "imus") -> np.ndarray:
    """Sorted indexes (without repeats) of the IMUs ``imus`` (names or indexes; one or several; None: all).
    CalibrationError (one line naming ``label``) for an unknown IMU or an empty list."""
    if imus is None:
        return np.arange(len(names))
    items = [imus] if isinstance(imus, (str, int, np.integer)) else list(imus)
    out = sorted({_one(names, item, label) for item in items})
    if not out:
        raise CalibrationError(f"{label}: no IMU given")
    return np.array(out)


def reference_index(names: Sequence[str], reference: str | int | None = None, *,
                    among: Iterable[int] | None = None) -> int:
    """Index (in ``names``) of the reference IMU: ``reference`` (a name or an index), or when it is None or
    ``""`` the first of ``among`` (the IMUs fitted; default all).  The reference must be among them."""
    among = list(range(len(names))) if among is None else [int(i) for i in among]
    if reference is None or (isinstance(reference, str) and not reference):
        return among[0]
    k = _one(names, reference, "reference")
    if k not in among:
        raise CalibrationError(f"reference IMU {names[k]!r} is not among the fitted IMUs")
    return k
