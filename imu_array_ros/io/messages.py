"""The serialized messages of the live topics and of recordings: one module for both.

The driver node, the fusion node and the recording writer all build their
``sensor_msgs/msg/Imu`` and ``geometry_msgs/msg/AccelWithCovarianceStamped``
payloads here, column-wise over whole batches (:mod:`imu_array_ros.io.rosbag.cdr_columns`),
and the fusion node and the readers decode them here.  The nodes publish and
subscribe the CDR bytes as they are (rclpy ``publish(bytes)`` and
``create_subscription(..., raw=True)``): no per-message Python object is ever
built, and a message on a live topic is byte for byte the message a recording
holds (a test checks this against rclpy's own serializer).

Topics and fields (the recording contract, :mod:`imu_array_ros.io.rosbag.recording`):

``<prefix>/<name>/data_raw``  one Imu per IMU per array sample
    the IMU's own sensor frame, ``frame_id = <frame_prefix><name>``, the same stamp on
    every IMU of one sample, ``angular_velocity_covariance = diag(gyroscope_noise_std^2)``,
    ``linear_acceleration_covariance = diag(accelerometer_noise_std^2)`` (the IMU's own per-axis
    ``noise_std`` where the description has one, else the pooled figure), orientation
    zero with ``orientation_covariance[0] = -1`` (REP-145).
``<prefix>/fused/imu``, ``<prefix>/fused/accel``  the fusion output
    Imu: omega and specific force with their 3x3 CRB blocks;
    AccelWithCovarianceStamped: linear = specific force, angular = omega_dot,
    6x6 CRB in ROS order [linear, angular].  Frame: the array frame.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache
from typing import Sequence

import numpy as np

from imu_array_ros.io.rosbag.cdr_columns import (
    IMU_LAYOUT,
    back_to_back,
    decode_accel_with_covariance_stamped,
    decode_imu,
    encode_accel_with_covariance_stamped,
    encode_imu,
    gather_bytes,
)
from imu_array_ros.model.description import ArrayDescription
from imu_array_ros.model.samples import FusedSamples, ImuSamples

__all__ = [
    "NO_ORIENTATION",
    "accel_block",
    "put_accel_block",
    "raw_covariances",
    "raw_imu_payloads",
    "fused_payloads",
    "RawBatch",
    "decode_raw_imu",
    "decode_fused",
    "concat_payloads",
]

#: orientation_covariance of a message without orientation (REP-145).
NO_ORIENTATION = np.array([-1.0, 0, 0, 0, 0, 0, 0, 0, 0])

_W, _F = slice(0, 3), slice(6, 9)
#: rows/columns of the (9, 9) fusion covariance ([omega, omega_dot, specific_force]) that the
#: Accel message's 6x6 covariance ([linear, angular] = [specific_force, omega_dot]) holds
_ACCEL = np.r_[6:9, 3:6]


def accel_block(cov: np.ndarray) -> np.ndarray:
    """The Accel message's (N, 6, 6) covariance from the fusion's (N, 9, 9)."""
    return cov[:, _ACCEL[:, None], _ACCEL]


def put_accel_block(cov: np.ndarray, rows: np.ndarray | slice, block: np.ndarray) -> None:
    """Write Accel covariances ``block`` (n, 6, 6) into rows ``rows`` of the fusion's (N, 9, 9) ``cov``."""
    rows = np.arange(len(cov))[rows]
    cov[rows[:, None, None], _ACCEL[None, :, None], _ACCEL[None, None, :]] = block


def raw_covariances(description: ArrayDescription) -> tuple[np.ndarray, np.ndarray]:
    """(accelerometer, gyroscope) covariances of the raw Imu messages, each (K, 9) row-major per IMU: the IMU's
    own ``noise_std`` per axis where the description gives it (``imu-array calibrate noise``), else the pooled
    figure."""
    def cov(sensor: str) -> np.ndarray:
        std = description.noise_std(sensor)
        return np.einsum("ki,ij->kij", std ** 2, np.eye(3)).reshape(len(std), 9)
    return cov("accelerometer"), cov("gyroscope")


def raw_imu_payloads(
    samples: ImuSamples, description: ArrayDescription, frame_prefix: str = ""
) -> list[tuple[np.ndarray, np.ndarray]]:
    """Raw Imu payloads of a batch, per IMU in ``samples.names`` order.

    Returns, for every IMU k, ``(rows, payloads)``: the indices (m_k,) of the
    samples where IMU k is present (finite) and their CDR payloads (m_k, L_k) uint8.
    Raises ValueError for a stamp outside ``builtin_interfaces/Time``.
    """
    acc_cov, gyr_cov = raw_covariances(description)
    index = {n: i for i, n in enumerate(description.names)}
    present = samples.present
    out = []
    for k, name in enumerate(samples.names):
        d = index[name]
        rows = np.flatnonzero(present[:, k])
        payload = encode_imu(
            samples.stamps[rows],
            frame_prefix + name,
            angular_velocity=samples.gyro[rows, k],
            linear_acceleration=samples.accel[rows, k],
            angular_velocity_covariance=gyr_cov[d],
            linear_acceleration_covariance=acc_cov[d],
            orientation_covariance=NO_ORIENTATION,
        )
        out.append((rows, payload))
    return out


def fused_payloads(fused: FusedSamples, frame_id: str) -> tuple[np.ndarray, np.ndarray]:
    """Fusion output as (Imu payloads (N, L1), AccelWithCovarianceStamped payloads (N, L2)).

    ``fused.covariance`` (N, 9, 9) in parameter order [omega, omega_dot,
    specific_force]; the Imu carries the omega and specific-force 3x3 blocks,
    the Accel message the 6x6 block of [specific_force, omega_dot].
    """
    stamps = np.asarray(fused.stamps, dtype=np.int64).reshape(-1)
    n = len(stamps)
    cov = np.asarray(fused.covariance, dtype=float).reshape(n, 9, 9)
    imu = encode_imu(
        stamps,
        frame_id,
        angular_velocity=fused.omega,
        angular_velocity_covariance=cov[:, _W, _W].reshape(n, 9),
        linear_acceleration=fused.specific_force,
        linear_acceleration_covariance=cov[:, _F, _F].reshape(n, 9),
        orientation_covariance=NO_ORIENTATION,
    )
    acc = encode_accel_with_covariance_stamped(
        stamps, frame_id, linear=fused.specific_force, angular=fused.omega_dot, covariance=accel_block(cov).reshape(n, 36)
    )
    return imu, acc


def concat_payloads(payloads: Sequence[bytes]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Many serialized messages -> (buffer (S,) uint8, offsets (M,), lengths (M,)) for the decoders."""
    lengths = np.fromiter((len(p) for p in payloads), dtype=np.int64, count=len(payloads))
    offsets = np.concatenate([[0], np.cumsum(lengths)[:-1]]) if len(lengths) else lengths
    buf = np.frombuffer(b"".join(payloads), dtype=np.uint8)
    return buf, offsets.astype(np.int64), lengths


@dataclass
class RawBatch:
    """Raw Imu messages decoded column-wise.

    stamps (M,) int64 ns; accel, gyro (M, 3) sensor frame; ``decodable`` (M,) --
    little-endian CDR of the Imu layout; ``frame_ok`` (M,) -- frame_id equals the
    expected one; ``finite`` (M,) -- every value finite.  A message is usable when
    all three hold.
    """

    stamps: np.ndarray
    accel: np.ndarray
    gyro: np.ndarray
    decodable: np.ndarray
    frame_ok: np.ndarray
    finite: np.ndarray

    @property
    def usable(self) -> np.ndarray:
        return self.decodable & self.frame_ok & self.finite


def decode_raw_imu(payloads: Sequence[bytes], imu_index: np.ndarray, frame_ids: Sequence[str]) -> RawBatch:
    """Decode raw Imu payloads of several IMUs at once.

    payloads : M serialized messages; imu_index (M,) int: which IMU's topic each came
    from; frame_ids : the expected ``header.frame_id`` of every IMU (index ->
    str).  One gather per field and one frame_id comparison over the whole batch.
    """
    imu_index = np.asarray(imu_index, dtype=np.int64).reshape(-1)
    buf, offsets, lengths = concat_payloads(payloads)
    dec = decode_imu(buf, offsets, lengths, ("angular_velocity", "linear_acceleration"))
    frame_ok = np.zeros(len(offsets), dtype=bool)
    if len(offsets):
        # header.frame_id: its length field (incl. NUL) at payload[12:16], its bytes and NUL from payload[16].
        # Valid payloads have the length the layout implies for their frame_id; one comparison for the batch
        # of the length field, the bytes and the NUL against the expected ones
        expect, skip, need = _expected_frames(tuple(frame_ids))
        width = expect.shape[1]
        ok = dec.valid & (lengths == need[imu_index])
        rows = back_to_back(buf, offsets, lengths)
        if rows is not None and 12 + width <= rows.shape[1]:
            window = rows[:, 12:12 + width]  # one length: no gather
            frame_ok = ok & ((window == expect[imu_index]) | skip[imu_index]).all(axis=1)
        else:
            sel = np.flatnonzero(ok)
            window = gather_bytes(np.concatenate([buf, np.zeros(width, np.uint8)]), offsets[sel] + 12, width)
            frame_ok[sel] = ((window == expect[imu_index[sel]]) | skip[imu_index[sel]]).all(axis=1)
    accel, gyro = dec.fields["linear_acceleration"], dec.fields["angular_velocity"]
    finite = np.isfinite(accel).all(axis=1) & np.isfinite(gyro).all(axis=1)
    return RawBatch(dec.stamps, accel, gyro, dec.valid, frame_ok, finite & dec.valid)


@lru_cache(maxsize=8)
def _expected_frames(frame_ids: tuple[str, ...]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per IMU (K rows): the expected bytes from payload[12] (the frame_id's length field, its bytes, the NUL;
    zero-padded to one width), which of them not to compare (the padding), and the payload length the
    frame_id implies (K,)."""
    fids = [f.encode("utf-8") for f in frame_ids]
    flen = np.array([len(f) for f in fids], dtype=np.int64)
    expect = np.zeros((len(fids), 4 + int(flen.max(initial=0)) + 1), dtype=np.uint8)
    skip = np.ones(expect.shape, dtype=bool)
    for k, f in enumerate(fids):
        row = (len(f) + 1).to_bytes(4, "little") + f + b"\x00"
        expect[k, :len(row)] = np.frombuffer(row, dtype=np.uint8)
        skip[k, :len(row)] = False
    need = np.array([IMU_LAYOUT.payload_length(n + 1) for n in flen], dtype=np.int64)
    return expect, skip, need


def decode_fused(imu_payloads: Sequence[bytes], accel_payloads: Sequence[bytes]) -> FusedSamples:
    """Fused output back from pairs of (Imu, Accel) payloads of the same stamps, in order.

    covariance (N, 9, 9): the blocks the messages carry; the omega/omega_dot and
    omega/specific-force cross blocks are not transmitted and are NaN.
    Raises ValueError when the two lists differ in length or stamps.
    """
    if len(imu_payloads) != len(accel_payloads):
        raise ValueError(f"{len(imu_payloads)} fused Imu messages but {len(accel_payloads)} Accel messages")
    imu = decode_imu(*concat_payloads(imu_payloads))
    acc = decode_accel_with_covariance_stamped(*concat_payloads(accel_payloads))
    if not (imu.valid.all() and acc.valid.all()):
        raise ValueError("undecodable fused message")
    if not np.array_equal(imu.stamps, acc.stamps):
        raise ValueError("fused Imu and Accel stamps differ")
    n = len(imu.stamps)
    cov = np.full((n, 9, 9), np.nan)
    cov[:, _W, _W] = imu["angular_velocity_covariance"].reshape(n, 3, 3)
    put_accel_block(cov, slice(None), acc["covariance"].reshape(n, 6, 6))
    return FusedSamples(stamps=imu.stamps, omega=imu["angular_velocity"], omega_dot=acc["angular"],
                        specific_force=imu["linear_acceleration"], covariance=cov)
