"""Fusing samples and recordings: the fusion ``imu-array fuse``, the fusion node and the Python API share.

A description with sample clocks, or samples whose IMUs carry their own stamps, have *session states*
(clock phases, the board's clock rate, stamp-clock offsets and skews) that no description holds: they are
estimated from the samples themselves first (:func:`~imu_array_ros.timing.session.estimate_session`),
then the samples are fused at every reading's true sample time.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Callable

from imu_array_ros.fusion.live import build_fusion
from imu_array_ros.fusion.ml_fusion import FusionStats
from imu_array_ros.fusion.model_fusion import ModelFusion
from imu_array_ros.fusion.stream import fuse_chunked
from imu_array_ros.io.rosbag.recording import read_imu_recording
from imu_array_ros.model.description import ArrayDescription
from imu_array_ros.model.samples import FusedSamples, ImuSamples, ReadStats
from imu_array_ros.model.sensor_model import SensorModel
from imu_array_ros.timing.session import SessionStates, estimate_session, needs_session

__all__ = ["build_fusion", "session_fusion", "fuse", "fuse_recording", "FusedRecording"]

Progress = Callable[[int, int], None]


def session_fusion(samples: ImuSamples, array: ArrayDescription | SensorModel) -> tuple[ModelFusion, SessionStates | None]:
    """The fusion of ``samples`` with every term of ``array`` (a description, checked fusable, or a sensor
    model), with this recording's session states estimated first when it has any (else None)."""
    if isinstance(array, ArrayDescription):
        fusion = build_fusion(array, t0_ns=int(samples.stamps[0]) if len(samples) else None)
    elif isinstance(array, SensorModel):
        fusion = ModelFusion(array, t0_ns=int(samples.stamps[0]) if len(samples) else None)
    else:
        raise TypeError(f"fuse: expected an ArrayDescription or a SensorModel, got {type(array).__name__}")
    if not len(samples) or not needs_session(samples, fusion.model):
        return fusion, None
    session = estimate_session(samples, fusion.model, t0_ns=fusion.t0_ns)
    timed = ModelFusion(session.model, fusion.config, acc_range=fusion.linear.acc_range,
                        gyro_range=fusion.linear.gyro_range, t0_ns=fusion.t0_ns)
    return timed, session


def fuse(samples: ImuSamples, array: ArrayDescription | SensorModel, *,
         progress: Progress | None = None) -> tuple[FusedSamples, FusionStats]:
    """ML fusion of ``samples`` (skog2016) with every term of ``array`` (a description, checked fusable,
    or a sensor model): the numbers ``imu-array fuse`` and the fusion node give.  Returns the fused
    samples that were identifiable and the counts; ``progress(done, total)`` per chunk.  Session states
    (sample-clock phases, own-stamp clocks) are estimated from ``samples`` first."""
    fusion, _ = session_fusion(samples, array)
    return fuse_chunked(fusion, samples, progress)


@dataclass
class FusedRecording:
    """A recording read and fused: the samples and what the reader saw, the fused samples and the counts,
    the fusion (``fusion.model`` carries every term of the description and this recording's session
    states) and the session states estimated (None when there were none to estimate)."""

    samples: ImuSamples
    read_stats: ReadStats
    fused: FusedSamples
    stats: FusionStats
    fusion: ModelFusion
    session: SessionStates | None = None


def fuse_recording(recording: str | Path, desc: ArrayDescription, *, read_progress: Progress | None = None,
                   fuse_progress: Progress | None = None) -> FusedRecording:
    """Read ``recording`` (rosbag2 MCAP directory or .mcap file) for the IMUs of ``desc`` and fuse it in
    chunks with every term of ``desc`` (checked fusable first), session states estimated first."""
    build_fusion(desc)  # checked fusable before the recording is read
    samples, read_stats = read_imu_recording(recording, desc, progress=read_progress)
    fusion, session = session_fusion(samples, desc)
    fused, stats = fuse_chunked(fusion, samples, fuse_progress)
    return FusedRecording(samples, read_stats, fused, stats, fusion, session)
