"""Builders for the array geometries of the papers (descriptions in memory).

``config/array32.yaml``, ``config/planar4.yaml`` and ``config/nilsson14.yaml`` are generated from these
(``python -m imu_array_ros.model.layouts config/``), and the tests build the
same arrays from them.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

from imu_array_ros.model.description import ArrayDescription, ImuSpec, save_description

__all__ = ["grid_array32", "planar_square4", "tetrahedron4", "nilsson14", "make_description", "ROT_180_ABOUT_Y_EQ_X",
           "NILSSON14_NOT_WORKING"]

#: 180 deg about the axis y = x (unit axis n = [1, 1, 0]/sqrt 2): R = 2 n n^T - I.
ROT_180_ABOUT_Y_EQ_X = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])

#: Noise figures of the MPU-9150 as used by carlsson2017 Sec. IV.
MPU9150 = dict(
    accelerometer_noise_std=0.04,          # m/s^2
    gyroscope_noise_std=float(np.deg2rad(0.06)),  # rad/s
    gyroscope_range=float(np.deg2rad(2000.0)),    # rad/s
    accelerometer_range=16 * 9.80665,      # m/s^2
)


def make_description(positions, orientations=None, *, names=None, frame_id="imu_array", **noise) -> ArrayDescription:
    """Description from (K, 3) positions and optional (K, 3, 3) orientations."""
    positions = np.asarray(positions, dtype=float).reshape(-1, 3)
    k = len(positions)
    if orientations is None:
        orientations = np.broadcast_to(np.eye(3), (k, 3, 3))
    names = names or [f"imu_{i:02d}" for i in range(k)]
    figures = dict(MPU9150)
    figures.update(noise)
    imus = tuple(
        ImuSpec(name=n, position=p.copy(), orientation=np.array(o, dtype=float)) for n, p, o in zip(names, positions, orientations)
    )
    return ArrayDescription(frame_id=frame_id, imus=imus, **figures)


def grid_array32(pitch: float = 6.3e-3, dz: float = 2e-3, **noise) -> ArrayDescription:
    """The 32-IMU array of carlsson2017 Fig. 2 / skog2016 Fig. 1.

    4 x 4 grid with ``pitch`` spacing centred on the origin, 16 IMUs on top at
    z = +dz/2 and 16 underneath at z = -dz/2 (2 mm lower), the underside ones
    rotated 180 deg about the axis y = x.  imu_00..imu_15 on top (row-major in
    x then y), imu_16..imu_31 below at the same xy positions.
    """
    c = (np.arange(4) - 1.5) * pitch
    xy = np.array([(x, y) for y in c for x in c])
    top = np.column_stack([xy, np.full(16, dz / 2)])
    bottom = np.column_stack([xy, np.full(16, -dz / 2)])
    rot = np.concatenate([np.broadcast_to(np.eye(3), (16, 3, 3)), np.broadcast_to(ROT_180_ABOUT_Y_EQ_X, (16, 3, 3))])
    return make_description(np.vstack([top, bottom]), rot, **noise)


def planar_square4(side: float = 0.02, **noise) -> ArrayDescription:
    """Planar array of 4 triads on a square of ``side`` m in the xy-plane (skog2016 Fig. 4a).

    The paper does not give the side length in its text; 2 cm is our choice.
    """
    h = side / 2
    pos = np.array([[h, h, 0.0], [-h, h, 0.0], [-h, -h, 0.0], [h, -h, 0.0]])
    return make_description(pos, **noise)


def tetrahedron4(side: float = 0.02, **noise) -> ArrayDescription:
    """Non-planar array of 4 triads on alternate corners of a cube (cf. skog2016 Fig. 4b)."""
    h = side / 2
    pos = np.array([[h, h, h], [-h, -h, h], [-h, h, -h], [h, -h, -h]])
    return make_description(pos, **noise)


#: The four IMUs of nilsson2014's 18 that did not work (footnote 2 of the paper; which ones is our choice).
NILSSON14_NOT_WORKING = ("imu_10", "imu_12", "imu_16", "imu_18")


def nilsson14(pitch: float = 8e-3, dz: float = 2e-3, **noise) -> ArrayDescription:
    """The in-house 18 x MPU-9150 array of nilsson2014 (Fig. 3), the 14 IMUs that worked.

    3 x 3 grid with ``pitch`` spacing centred on the origin, 9 IMUs on top at z = +dz/2
    (imu_01..imu_09, row-major in x then y) and 9 underneath at z = -dz/2 at the same xy
    positions (imu_10..imu_18), the underside ones rotated 180 deg about the axis y = x as in
    :func:`grid_array32`.  The paper gives no dimensions: the 8 mm pitch and 2 mm between the
    top and underside sensing elements are our choice.  Only 14 IMUs worked (footnote 2);
    which 4 failed is not said: we drop the underside corners :data:`NILSSON14_NOT_WORKING`,
    keeping the names of the 18 so that imu_14 (the paper's reference IMU, underside centre)
    keeps its number.
    """
    c = (np.arange(3) - 1.0) * pitch
    xy = np.array([(x, y) for y in c for x in c])
    pos = np.vstack([np.column_stack([xy, np.full(9, dz / 2)]), np.column_stack([xy, np.full(9, -dz / 2)])])
    rot = np.concatenate([np.broadcast_to(np.eye(3), (9, 3, 3)), np.broadcast_to(ROT_180_ABOUT_Y_EQ_X, (9, 3, 3))])
    names = [f"imu_{i:02d}" for i in range(1, 19)]
    keep = [i for i, n in enumerate(names) if n not in NILSSON14_NOT_WORKING]
    return make_description(pos[keep], rot[keep], names=[names[i] for i in keep], **noise)


def _main(out_dir: str) -> None:
    out = Path(out_dir)
    save_description(grid_array32(), out / "array32.yaml")
    save_description(planar_square4(), out / "planar4.yaml")
    save_description(nilsson14(), out / "nilsson14.yaml")


if __name__ == "__main__":  # pragma: no cover
    _main(sys.argv[1] if len(sys.argv) > 1 else "config")
