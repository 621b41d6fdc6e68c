"""The array's coordinate frames as static transforms (what the nodes put on ``/tf_static``).

One transform per IMU, parent the array frame (the description's ``frame_id``, the frame of the
fused messages), child the IMU's sensor frame, named as the raw messages name it
(``<frame_prefix><imu name>``, :mod:`imu_array_ros.io.messages`).  As ROS transforms go
(REP-103, tf2), the transform parent -> child gives the child frame's pose in the parent frame:

* translation: the IMU's ``position`` (its accelerometer triad) in the array frame, m;
* rotation: the IMU's ``orientation`` R (sensor frame -> array frame), as a unit quaternion
  ``(x, y, z, w)`` with ``w >= 0``, so a vector v in the sensor frame is ``R @ v`` in the array
  frame and a point p of the sensor frame is ``R @ p + position``.

This is the inverse of Kalibr's ``T_i_b`` (:func:`imu_array_ros.io.kalibr.kalibr_transform`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from imu_array_ros.model.description import ArrayDescription

__all__ = ["FrameTransform", "static_frames", "quaternion_from_matrix"]


@dataclass(frozen=True)
class FrameTransform:
    """A static transform ``parent -> child``: ``translation`` (3,) m, ``quaternion`` (4,) x, y, z, w."""

    parent: str
    child: str
    translation: tuple[float, float, float]
    quaternion: tuple[float, float, float, float]


def quaternion_from_matrix(r: np.ndarray) -> np.ndarray:
    """Unit quaternion (x, y, z, w), ``w >= 0``, of the rotation matrix ``r`` (3, 3).

    Shepperd's method: from the largest of the four squared components, so every rotation
    (also half turns, where w is 0) is exact to rounding."""
    r = np.asarray(r, dtype=float).reshape(3, 3)
    t = np.trace(r)
    diag = np.array([r[0, 0], r[1, 1], r[2, 2], t])
    k = int(np.argmax(diag))
    if k == 3:
        s = 2.0 * np.sqrt(1.0 + t)
        q = np.array([(r[2, 1] - r[1, 2]) / s, (r[0, 2] - r[2, 0]) / s, (r[1, 0] - r[0, 1]) / s, s / 4.0])
    else:
        i, j, m = k, (k + 1) % 3, (k + 2) % 3
        s = 2.0 * np.sqrt(max(1.0 + r[i, i] - r[j, j] - r[m, m], 0.0))
        q = np.empty(4)
        q[i] = s / 4.0
        q[j] = (r[j, i] + r[i, j]) / s
        q[m] = (r[m, i] + r[i, m]) / s
        q[3] = (r[m, j] - r[j, m]) / s
    q /= np.linalg.norm(q)
    return -q if q[3] < 0 else q


def static_frames(description: ArrayDescription, frame_prefix: str = "") -> list[FrameTransform]:
    """One transform array frame -> IMU sensor frame per IMU of ``description``, in its order
    (module docstring); the IMU frames are named ``frame_prefix + name``."""
    return [FrameTransform(parent=description.frame_id, child=frame_prefix + imu.name,
                           translation=tuple(float(x) for x in np.asarray(imu.position, dtype=float).reshape(3)),
                           quaternion=tuple(float(x) for x in quaternion_from_matrix(imu.orientation)))
            for imu in description.imus]
