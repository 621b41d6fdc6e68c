"""Recording I/O: IMU-array recordings, ground truth and fused output as rosbag2 MCAP.

Topics (``prefix`` defaults to ``/imu_array``):

``<prefix>/<name>/data_raw``  sensor_msgs/msg/Imu, one per IMU
    measurements in the IMU's own sensor frame, ``header.frame_id = <name>``,
    the same ``header.stamp`` on every IMU's message of one array sample (or,
    for IMUs with their own drivers, each IMU's own stamps: paired on reading);
    ``angular_velocity_covariance = diag(gyroscope_noise_std^2)``,
    ``linear_acceleration_covariance = diag(accelerometer_noise_std^2)``,
    orientation zero with ``orientation_covariance[0] = -1`` (REP-145).
``<prefix>/truth/imu``, ``<prefix>/truth/accel``  ground truth (simulation only)
    Imu: angular_velocity = omega, linear_acceleration = specific force at the
    array origin, orientation = attitude [x y z w] (or zeros with
    orientation_covariance[0] = -1); AccelWithCovarianceStamped: linear =
    specific force, angular = omega_dot; covariances zero; frame = array frame.
``<prefix>/fused/imu``, ``<prefix>/fused/accel``  fusion output
    Imu: omega and specific force with their 3x3 covariances;
    AccelWithCovarianceStamped: linear = specific force, angular = omega_dot,
    6x6 covariance in ROS order [linear, angular].

This module holds what the topics mean (names, types, the fields read and
written, stamp alignment).  Reading decodes whole MCAP chunks column-wise
(:mod:`.topic_columns`: selected topics as decoded columns, topic checks;
:mod:`.mcap_recording`, :mod:`.cdr_columns`); there is no per-message Python
in the hot path.  Writing: :mod:`.mcap_writer`.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from typing import Callable, Sequence

import numpy as np

from imu_array_ros.io.rosbag.cdr_columns import (
    ACCEL_LAYOUT,
    IMU_LAYOUT,
    encode_accel_with_covariance_stamped,
    encode_imu,
)
from imu_array_ros.model.description import ArrayDescription
from imu_array_ros.errors import RecordingError
from imu_array_ros.io.messages import NO_ORIENTATION, fused_payloads, put_accel_block, raw_imu_payloads
from imu_array_ros.io.rosbag.mcap_recording import McapRecording
from imu_array_ros.io.rosbag.mcap_writer import ChannelData, write_recording
from imu_array_ros.io.rosbag.own_stamps import pair_recording
from imu_array_ros.io.rosbag.topic_columns import check_topic, list_topics, read_topics
from imu_array_ros.model.samples import FusedSamples, ImuSamples, MotionTruth, ReadStats

__all__ = [
    "IMU_TYPE",
    "ACCEL_TYPE",
    "imu_topic",
    "imu_payloads",
    "read_imu_recording",
    "write_imu_recording",
    "write_fused_recording",
    "read_fused_recording",
    "read_truth",
]

IMU_TYPE = IMU_LAYOUT.type_name
ACCEL_TYPE = ACCEL_LAYOUT.type_name


#: A topic's stamps "do not match" when more than this fraction of its samples
#: has no other IMU's message at the same stamp.
UNMATCHED_LIMIT = 0.5


def _prefix(prefix: str) -> str:
    prefix = prefix.rstrip("/")
    return prefix if prefix.startswith("/") or not prefix else "/" + prefix


def imu_topic(name: str, topic_prefix: str = "/imu_array") -> str:
    """``<prefix>/<name>/data_raw``."""
    return f"{_prefix(topic_prefix)}/{name}/data_raw"


# --------------------------------------------------------------------------- reading helpers


def _first_per_stamp(stamps: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unique sorted stamps and, for each, the index of its first occurrence."""
    return np.unique(stamps, return_index=True)


# --------------------------------------------------------------------------- IMU recordings


def read_imu_recording(
    path: str | os.PathLike,
    description: ArrayDescription,
    *,
    topic_prefix: str = "/imu_array",
    progress: Callable[[float], None] | None = None,
    reference: str | int | None = None,
    unused_rows: bool = False,
) -> tuple[ImuSamples, ReadStats]:
    """Read the IMU topics of ``description.names`` and align them by ``header.stamp``.

    Returns (samples, stats).  samples.stamps (N,) int64 ns sorted; accel/gyro
    (N, K, 3) in each IMU's sensor frame, NaN where the IMU's message is
    missing or bad.  A message is bad when its payload is not little-endian
    CDR of the Imu layout (dropped) or a value is non-finite (row left NaN).
    A second message of one topic at the same stamp is a duplicate; the first
    one (file order) is kept.  ``stats.incomplete_samples`` counts samples in
    which at least one IMU has no usable data.

    IMUs with their own stamps: when an IMU's stamps mostly (over
    ``UNMATCHED_LIMIT``) coincide with no other IMU's, the messages are not
    grouped by stamp but paired onto the stamps of the ``reference`` IMU (None:
    the first with two messages or more) by :mod:`imu_array_ros.io.pairing`;
    samples.own_stamps (N, K) then holds each message's own stamp and a note in
    stats.notes the pairing statistics; ``unused_rows`` adds the messages the
    pairing left unused as rows of their own (every message: for a replay).
    Otherwise own_stamps is None.

    Raises :class:`RecordingError` for a missing/garbled recording, a missing
    topic, a topic of the wrong type, or own stamps that cannot be paired (one
    going backwards or jumping by over a second, another clock base).
    """
    names = tuple(description.names)
    topics = [imu_topic(n, topic_prefix) for n in names]
    rec = McapRecording(path)

    def check(available) -> None:
        for name, topic in zip(names, topics):
            if not check_topic(rec, available, topic, IMU_TYPE, f"for IMU {name!r}"):
                raise RecordingError(
                    f"{rec.path}: no topic {topic} for IMU {name!r} (recording has: {list_topics(available)})"
                )

    _, by_type = read_topics(
        rec,
        [(t, IMU_LAYOUT) for t in topics],
        {IMU_TYPE: ("angular_velocity", "linear_acceleration")},
        check,
        progress,
    )
    cols = by_type[IMU_TYPE]
    k_count = len(names)
    stats = ReadStats(messages=int(len(cols.topic)))

    invalid = ~cols.valid
    if invalid.any():
        wrong_enc = invalid & ~cols.encap_ok
        per_topic = np.bincount(cols.topic[invalid], minlength=k_count)
        worst = int(np.argmax(per_topic))
        reason = (
            "unsupported CDR encapsulation (only little-endian CDR is read)"
            if wrong_enc.any()
            else "payload does not match the Imu layout"
        )
        stats.notes.append(
            f"{int(invalid.sum())} undecodable messages ({reason}; most on {topics[worst]}: {int(per_topic[worst])})"
        )
    keep = slice(None) if not invalid.any() else cols.valid
    topic = cols.topic[keep].astype(np.int64)
    stamps = cols.stamps[keep]
    gyro_m = cols.fields["angular_velocity"][keep]
    acc_m = cols.fields["linear_acceleration"][keep]

    in_file_order = (topic, stamps, acc_m, gyro_m)
    uniq, inv = np.unique(stamps, return_inverse=True)
    n = len(uniq)
    key = inv.reshape(-1) * k_count + topic
    counts = np.bincount(key, minlength=n * k_count)
    first = None
    if (counts > 1).any():
        _, first = np.unique(key, return_index=True)  # first occurrence in file order
        stats.duplicate_messages = int(len(key) - len(first))
        key, topic, gyro_m, acc_m, inv = key[first], topic[first], gyro_m[first], acc_m[first], inv.reshape(-1)[first]
    inv = inv.reshape(-1)

    fg, fa = np.isfinite(gyro_m), np.isfinite(acc_m)
    finite = fg[:, 0] & fg[:, 1] & fg[:, 2] & fa[:, 0] & fa[:, 1] & fa[:, 2]
    n_nonfinite = int((~finite).sum())
    stats.bad_messages = int(invalid.sum()) + n_nonfinite
    if n_nonfinite:
        per_topic = np.bincount(topic[~finite], minlength=k_count)
        worst = int(np.argmax(per_topic))
        stats.notes.append(f"{n_nonfinite} messages with non-finite values (most on {topics[worst]}: {int(per_topic[worst])})")

    # stamps that do not coincide with the other IMUs': own stamps, paired
    per_imu = np.bincount(topic, minlength=k_count)
    if k_count > 1 and len(key):
        in_sample = np.bincount(inv, minlength=n)
        alone = np.bincount(topic[in_sample[inv] == 1], minlength=k_count)
        frac = np.divide(alone, per_imu, out=np.zeros(k_count), where=per_imu > 0)
        worst = int(np.argmax(frac))
        if frac[worst] > UNMATCHED_LIMIT:
            use = np.zeros(len(in_file_order[0]), dtype=bool)  # first of each (IMU, stamp), finite
            use[slice(None) if first is None else first] = finite
            chosen = np.flatnonzero(use)
            samples, pairing, note = pair_recording(rec.path, names, *(c[chosen] for c in in_file_order),
                                                    reference=reference, unused_rows=unused_rows)
            stats.notes += [f"IMU stamps differ ({topics[worst]}: {100 * frac[worst]:.0f}% of its messages "
                            "at no other IMU's stamp): " + pairing.summary()] + ([note] if note else [])
            for k in np.flatnonzero(per_imu == 0):
                stats.notes.append(f"IMU {names[k]!r}: no messages on {topics[k]}")
            stats.samples = pairing.grid
            incomplete = int((~samples.present.all(axis=1)).sum())
            stats.incomplete_samples = incomplete - int(pairing.unused.sum()) * unused_rows  # not the unused rows
            return samples, stats
    for k in np.flatnonzero(per_imu == 0):
        stats.notes.append(f"IMU {names[k]!r}: no messages on {topics[k]}")

    if n_nonfinite:
        key, inv, acc_m, gyro_m = key[finite], inv[finite], acc_m[finite], gyro_m[finite]
    if len(key) == n * k_count and (key == np.arange(n * k_count)).all():
        accel, gyro = acc_m, gyro_m  # complete and already in (stamp, IMU) order: no scatter
    else:
        accel = np.full((n * k_count, 3), np.nan)
        gyro = np.full((n * k_count, 3), np.nan)
        accel[key] = acc_m
        gyro[key] = gyro_m
    samples = ImuSamples(uniq, accel.reshape(n, k_count, 3), gyro.reshape(n, k_count, 3), names)
    stats.samples = n
    stats.incomplete_samples = int((np.bincount(inv, minlength=n) < k_count).sum())
    return samples, stats


def _stamp_error(path, err: ValueError) -> RecordingError:
    return RecordingError(f"{path}: cannot write: {err}")


def imu_payloads(samples: ImuSamples, description: ArrayDescription,
                 frame_prefix: str = "") -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """Every IMU's raw Imu messages of ``samples``, stamped with its own stamps when ``samples``
    has them (``own_stamps``), else with the samples' stamps (the writer's and the replay's).

    Returns per IMU (names order) (rows (m_k,) of its present samples, stamps (m_k,) int64,
    payloads (m_k, L_k) uint8).  ValueError for a stamp outside ``builtin_interfaces/Time``.
    """
    if samples.own_stamps is None:
        return [(rows, samples.stamps[rows], payload) for rows, payload in raw_imu_payloads(samples, description,
                                                                                            frame_prefix)]
    out = []
    for k, name in enumerate(samples.names):  # one IMU at a time: its own stamps
        one = ImuSamples(samples.own_stamps[:, k], samples.accel[:, k:k + 1], samples.gyro[:, k:k + 1], (name,))
        ((rows, payload),) = raw_imu_payloads(one, description, frame_prefix)
        out.append((rows, one.stamps[rows], payload))
    return out


def _imu_channels(samples: ImuSamples, description: ArrayDescription, topic_prefix: str) -> list[ChannelData]:
    return [ChannelData(imu_topic(name, topic_prefix), IMU_TYPE, stamps, payload)
            for name, (_, stamps, payload) in zip(samples.names, imu_payloads(samples, description))]


def _truth_channels(truth: MotionTruth, frame_id: str, prefix: str) -> list[ChannelData]:
    stamps = np.asarray(truth.stamps, dtype=np.int64)
    omega = np.asarray(truth.omega, dtype=float).reshape(-1, 3)
    omega_dot = np.asarray(truth.omega_dot, dtype=float).reshape(-1, 3)
    force = np.asarray(truth.specific_force, dtype=float).reshape(-1, 3)
    if truth.attitude is not None:
        q = np.asarray(truth.attitude, dtype=float).reshape(-1, 4)
        orientation, orientation_cov = q[:, [1, 2, 3, 0]], None  # [w x y z] -> ROS [x y z w]
    else:
        orientation, orientation_cov = None, NO_ORIENTATION
    imu = encode_imu(
        stamps,
        frame_id,
        angular_velocity=omega,
        linear_acceleration=force,
        orientation=orientation,
        orientation_covariance=orientation_cov,
    )
    accel = encode_accel_with_covariance_stamped(stamps, frame_id, linear=force, angular=omega_dot)
    return [
        ChannelData(f"{prefix}/truth/imu", IMU_TYPE, stamps, imu),
        ChannelData(f"{prefix}/truth/accel", ACCEL_TYPE, stamps, accel),
    ]


def write_imu_recording(
    path: str | os.PathLike,
    samples: ImuSamples,
    description: ArrayDescription,
    *,
    truth: MotionTruth | None = None,
    topic_prefix: str = "/imu_array",
) -> None:
    """Write raw IMU samples (and optionally ground truth) atomically.

    ``path`` ending in ``.mcap`` -> bare MCAP file, else a rosbag2 directory.
    IMUs absent in a sample (non-finite row) are not written for that stamp.
    With ``samples.own_stamps`` every IMU's message carries its own stamp (IMUs
    with their own clocks; read back, they are paired again).
    Message log time = header.stamp.
    """
    unknown = [n for n in samples.names if n not in description.names]
    if unknown:
        raise ValueError(f"IMU(s) {unknown} are not in the array description {description.source}")
    prefix = _prefix(topic_prefix)
    try:
        channels = _imu_channels(samples, description, prefix)
        if truth is not None:
            channels += _truth_channels(truth, description.frame_id, prefix)
    except ValueError as err:
        raise _stamp_error(path, err) from None
    write_recording(path, channels)


@dataclass
class _TopicRows:
    """The first decodable message per stamp of one topic: rows (n,) into the union
    of stamps, fields name -> (n, count)."""

    rows: np.ndarray
    fields: dict[str, np.ndarray]


def _read_motion_topics(
    path, prefix: str, what: str, label: str, imu_fields: Sequence[str], accel_fields: Sequence[str]
) -> tuple[np.ndarray, _TopicRows | None, _TopicRows | None]:
    """Read ``<prefix>/imu`` (Imu) and ``<prefix>/accel`` (AccelWithCovarianceStamped).

    Shared by :func:`read_truth` and :func:`read_fused_recording`.  Returns
    (stamps (N,) int64 ns: sorted union of both topics' decodable stamps, imu,
    accel), imu / accel None when that topic is absent.  RecordingError naming
    ``label`` when both are missing, naming ``what`` when one has another type.
    """
    prefix = _prefix(prefix)
    rec = McapRecording(path)
    t_imu, t_acc = f"{prefix}/imu", f"{prefix}/accel"

    def check(available) -> tuple[bool, bool]:
        has_imu = check_topic(rec, available, t_imu, IMU_TYPE, what)
        has_acc = check_topic(rec, available, t_acc, ACCEL_TYPE, what)
        if not (has_imu or has_acc):
            raise RecordingError(
                f"{rec.path}: {label}: topics {t_imu} and {t_acc} are missing (recording has: {list_topics(available)})"
            )
        return has_imu, has_acc

    present, cols = read_topics(
        rec,
        [(t_imu, IMU_LAYOUT), (t_acc, ACCEL_LAYOUT)],
        {IMU_TYPE: tuple(imu_fields), ACCEL_TYPE: tuple(accel_fields)},
        check,
    )
    found = [cols[name] if has else None for name, has in zip((IMU_TYPE, ACCEL_TYPE), present)]
    parts = [c.stamps[c.valid] for c in found if c is not None]
    stamps = np.unique(np.concatenate(parts)) if parts else np.zeros(0, np.int64)
    out: list[_TopicRows | None] = []
    for c in found:
        if c is None:
            out.append(None)
            continue
        s, first = _first_per_stamp(c.stamps[c.valid])
        out.append(_TopicRows(np.searchsorted(stamps, s), {k: v[c.valid][first] for k, v in c.fields.items()}))
    return stamps, out[0], out[1]


def read_truth(path: str | os.PathLike, *, prefix: str = "/imu_array/truth") -> MotionTruth:
    """Ground truth from ``<prefix>/imu`` and ``<prefix>/accel``.

    Rows are the union of both topics' stamps (sorted); a quantity whose topic
    lacks a stamp is NaN.  attitude (N, 4) [w x y z] if the Imu messages carry
    orientation (orientation_covariance[0] != -1), else None.
    """
    stamps, imu, acc = _read_motion_topics(
        path,
        prefix,
        "(ground truth)",
        "no ground truth",
        ("orientation", "orientation_covariance", "angular_velocity", "linear_acceleration"),
        ("linear", "angular"),
    )
    n = len(stamps)
    omega = np.full((n, 3), np.nan)
    omega_dot = np.full((n, 3), np.nan)
    force = np.full((n, 3), np.nan)
    attitude = None
    if imu is not None:
        rows, f = imu.rows, imu.fields
        omega[rows] = f["angular_velocity"]
        force[rows] = f["linear_acceleration"]
        has_q = f["orientation_covariance"][:, 0] != -1.0
        if has_q.any():
            attitude = np.full((n, 4), np.nan)
            q = f["orientation"][:, [3, 0, 1, 2]]
            attitude[rows[has_q]] = q[has_q]
    if acc is not None:
        omega_dot[acc.rows] = acc.fields["angular"]
        if imu is None:
            force[acc.rows] = acc.fields["linear"]
    return MotionTruth(stamps=stamps, omega=omega, omega_dot=omega_dot, specific_force=force, attitude=attitude)


# --------------------------------------------------------------------------- fused output


def write_fused_recording(
    path: str | os.PathLike, fused: FusedSamples, frame_id: str, *, topic_prefix: str = "/imu_array"
) -> None:
    """Write fusion output to ``<prefix>/fused/imu`` and ``<prefix>/fused/accel`` atomically.

    fused.covariance (N, 9, 9) in parameter order [omega, omega_dot,
    specific_force]; the Imu message carries the omega and specific-force
    3x3 blocks, the Accel message the 6x6 block of [specific_force,
    omega_dot] (ROS order [linear, angular]).  Stamps as in ``fused``.
    """
    prefix = _prefix(topic_prefix)
    stamps = np.asarray(fused.stamps, dtype=np.int64).reshape(-1)
    try:
        imu, acc = fused_payloads(fused, frame_id)
    except ValueError as err:
        raise _stamp_error(path, err) from None
    write_recording(
        path,
        [
            ChannelData(f"{prefix}/fused/imu", IMU_TYPE, stamps, imu),
            ChannelData(f"{prefix}/fused/accel", ACCEL_TYPE, stamps, acc),
        ],
    )


def read_fused_recording(path: str | os.PathLike, *, prefix: str = "/imu_array/fused") -> FusedSamples:
    """Fusion output back from ``<prefix>/imu`` and ``<prefix>/accel``.

    covariance (N, 9, 9) holds only the blocks the messages carry ([omega,
    omega], [omega_dot, omega_dot], [specific_force, specific_force] and the
    specific_force/omega_dot cross blocks); everything else is NaN.
    """
    stamps, imu, acc = _read_motion_topics(
        path,
        prefix,
        "(fused)",
        "no fused output",
        ("angular_velocity", "angular_velocity_covariance", "linear_acceleration", "linear_acceleration_covariance"),
        ("linear", "angular", "covariance"),
    )
    n = len(stamps)
    omega = np.full((n, 3), np.nan)
    omega_dot = np.full((n, 3), np.nan)
    force = np.full((n, 3), np.nan)
    cov = np.full((n, 9, 9), np.nan)
    w, f = slice(0, 3), slice(6, 9)
    if imu is not None:
        rows, col = imu.rows, imu.fields
        omega[rows] = col["angular_velocity"]
        force[rows] = col["linear_acceleration"]
        cov[rows, w, w] = col["angular_velocity_covariance"].reshape(-1, 3, 3)
        cov[rows, f, f] = col["linear_acceleration_covariance"].reshape(-1, 3, 3)
    if acc is not None:
        omega_dot[acc.rows] = acc.fields["angular"]
        if imu is None:
            force[acc.rows] = acc.fields["linear"]
        put_accel_block(cov, acc.rows, acc.fields["covariance"].reshape(-1, 6, 6))
    return FusedSamples(stamps=stamps, omega=omega, omega_dot=omega_dot, specific_force=force, covariance=cov)
