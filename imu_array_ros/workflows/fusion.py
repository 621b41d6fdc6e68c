"""Fusing samples and recordings: the fusion ``imu-array fuse``, the fusion node and the Python API share."""

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

__all__ = ["build_fusion", "fuse", "fuse_recording", "FusedRecording"]

Progress = Callable[[int, int], None]


def fuse(samples: ImuSamples, array: ArrayDescription | SensorModel, *,
         progress: Progress | None = None) -> tuple[FusedSamples, FusionStats]:
    """ML fusion of ``samples`` (skog2016) with every term of ``array`` (a description, checked fusable,
    or a sensor model): the numbers ``imu-array fuse`` and the fusion node give.  Returns the fused
    samples that were identifiable and the counts; ``progress(done, total)`` per chunk."""
    if isinstance(array, ArrayDescription):
        fusion = build_fusion(array)
    elif isinstance(array, SensorModel):
        fusion = ModelFusion(array)
    else:
        raise TypeError(f"fuse: expected an ArrayDescription or a SensorModel, got {type(array).__name__}")
    return fuse_chunked(fusion, samples, progress)


@dataclass
class FusedRecording:
    """A recording read and fused: the samples and what the reader saw, the fused samples and the counts,
    and the fusion (``fusion.model`` carries every term of the description)."""

    samples: ImuSamples
    read_stats: ReadStats
    fused: FusedSamples
    stats: FusionStats
    fusion: ModelFusion


def fuse_recording(recording: str | Path, desc: ArrayDescription, *, read_progress: Progress | None = None,
                   fuse_progress: Progress | None = None) -> FusedRecording:
    """Read ``recording`` (rosbag2 MCAP directory or .mcap file) for the IMUs of ``desc`` and fuse it in
    chunks with every term of ``desc`` (checked fusable first)."""
    fusion = build_fusion(desc)
    samples, read_stats = read_imu_recording(recording, desc, progress=read_progress)
    fused, stats = fuse_chunked(fusion, samples, fuse_progress)
    return FusedRecording(samples, read_stats, fused, stats, fusion)
