"""Fusing samples and recordings: the fusion ``imu-array fuse``, the fusion node and the Python API share.

A description with sample clocks, or samples whose IMUs carry their own stamps, have *session states*
(clock phases, the board's clock rate, stamp-clock offsets and skews) that no description holds: they are
estimated from the samples themselves first (:func:`~imu_array_ros.timing.session.estimate_session`),
then the samples are fused at every reading's true sample time.

The gyroscopes' turn-on biases are session states too: by default (``bias_tracking``) they are re-measured
on every still interval of the samples (:func:`~imu_array_ros.calibration.bias_tracking.track_biases`) and
the readings are fused with the bias in use at each sample (:func:`prepare_fusion`); before the timing
states, which are then estimated from the corrected readings.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Callable

from imu_array_ros.calibration.bias_tracking import BiasTrack, track_biases
from imu_array_ros.fusion.live import build_fusion
from imu_array_ros.fusion.ml_fusion import FusionStats
from imu_array_ros.fusion.model_fusion import ModelFusion
from imu_array_ros.fusion.stream import fuse_chunked
from imu_array_ros.io.rosbag.recording import read_imu_recording
from imu_array_ros.model.description import ArrayDescription
from imu_array_ros.model.samples import FusedSamples, ImuSamples, ReadStats
from imu_array_ros.model.sensor_model import SensorModel
from imu_array_ros.timing.session import SessionStates, estimate_session, needs_session

__all__ = ["build_fusion", "session_fusion", "prepare_fusion", "PreparedFusion", "session_notes", "fuse", "fuse_recording",
           "FusedRecording"]

Progress = Callable[[int, int], None]


def session_fusion(samples: ImuSamples, array: ArrayDescription | SensorModel) -> tuple[ModelFusion, SessionStates | None]:
    """The fusion of ``samples`` with every term of ``array`` (a description, checked fusable, or a sensor
    model), with this recording's timing session states estimated first when it has any (else None).  The
    gyroscope biases are those of ``array``: :func:`prepare_fusion` tracks them."""
    fusion = _fusion(samples, array)
    return _timed(samples, fusion)


def _fusion(samples: ImuSamples, array: ArrayDescription | SensorModel) -> ModelFusion:
    t0 = int(samples.stamps[0]) if len(samples) else None
    if isinstance(array, ArrayDescription):
        return build_fusion(array, t0_ns=t0)
    if isinstance(array, SensorModel):
        return ModelFusion(array, t0_ns=t0)
    raise TypeError(f"fuse: expected an ArrayDescription or a SensorModel, got {type(array).__name__}")


def _timed(samples: ImuSamples, fusion: ModelFusion) -> tuple[ModelFusion, SessionStates | None]:
    if not len(samples) or not needs_session(samples, fusion.model):
        return fusion, None
    session = estimate_session(samples, fusion.model, t0_ns=fusion.t0_ns)
    timed = ModelFusion(session.model, fusion.config, acc_range=fusion.linear.acc_range,
                        gyro_range=fusion.linear.gyro_range, t0_ns=fusion.t0_ns)
    return timed, session


def session_notes(session: SessionStates | None, biases: BiasTrack | None) -> list[str]:
    """The notes of the session states estimated (gyroscope biases, then timing), one console line each."""
    out = [] if biases is None else list(biases.notes())
    return out + ([] if session is None else [n if n.startswith("session states") else f"session states: {n}"
                                              for n in session.notes])


@dataclass
class PreparedFusion:
    """What fusing ``samples`` needs: the fusion (its model with the timing session states), the samples to
    fuse (the readings with the tracked gyroscope biases applied: :meth:`BiasTrack.correct`; the readings as
    given without tracking or without a still interval), the timing states (None: none to estimate) and the
    bias track (None: tracking off)."""

    fusion: ModelFusion
    samples: ImuSamples
    session: SessionStates | None = None
    biases: BiasTrack | None = None

    def notes(self) -> list[str]:
        """The session states' notes (gyroscope biases, timing), for the console."""
        return session_notes(self.session, self.biases)


def prepare_fusion(samples: ImuSamples, array: ArrayDescription | SensorModel, *,
                   bias_tracking: bool = True) -> PreparedFusion:
    """The fusion of ``samples`` with every term of ``array`` (a description, checked fusable, or a sensor
    model) and this recording's session states: with ``bias_tracking`` the gyroscope biases re-measured on
    every still interval first (:func:`~imu_array_ros.calibration.bias_tracking.track_biases`, applied to the
    readings), then the timing states (:func:`session_fusion`)."""
    fusion = _fusion(samples, array)
    track = None
    if bias_tracking and len(samples):
        track = track_biases(samples, fusion.model, t0_ns=fusion.t0_ns)
        samples = track.correct(samples, fusion.model)
    fusion, session = _timed(samples, fusion)
    return PreparedFusion(fusion, samples, session, track)


def fuse(samples: ImuSamples, array: ArrayDescription | SensorModel, *, progress: Progress | None = None,
         bias_tracking: bool = True) -> tuple[FusedSamples, FusionStats]:
    """ML fusion of ``samples`` (skog2016) with every term of ``array`` (a description, checked fusable,
    or a sensor model): the numbers ``imu-array fuse`` and the fusion node give.  Returns the fused
    samples that were identifiable and the counts; ``progress(done, total)`` per chunk.  Session states
    (the gyroscope biases on every still interval unless ``bias_tracking`` is False, sample-clock phases,
    own-stamp clocks) are estimated from ``samples`` first."""
    prepared = prepare_fusion(samples, array, bias_tracking=bias_tracking)
    return fuse_chunked(prepared.fusion, prepared.samples, progress)


@dataclass
class FusedRecording:
    """A recording read and fused: the samples as fused (the readings with the tracked gyroscope biases
    applied; ``raw`` the readings as read when they differ) and what the reader saw, the fused samples and the
    counts, the fusion (``fusion.model`` carries every term of the description and this recording's timing
    session states), the timing states estimated (None when there were none to estimate) and the gyroscope
    bias track (None: tracking off)."""

    samples: ImuSamples
    read_stats: ReadStats
    fused: FusedSamples
    stats: FusionStats
    fusion: ModelFusion
    session: SessionStates | None = None
    biases: BiasTrack | None = None
    raw: ImuSamples | None = None

    def notes(self) -> list[str]:
        """The session states' notes (gyroscope biases, timing), for the console."""
        return session_notes(self.session, self.biases)


def fuse_recording(recording: str | Path, desc: ArrayDescription, *, read_progress: Progress | None = None,
                   fuse_progress: Progress | None = None, bias_tracking: bool = True) -> FusedRecording:
    """Read ``recording`` (rosbag2 MCAP directory or .mcap file) for the IMUs of ``desc`` and fuse it in
    chunks with every term of ``desc`` (checked fusable first), session states estimated first (the gyroscope
    biases tracked unless ``bias_tracking`` is False: :func:`prepare_fusion`)."""
    build_fusion(desc)  # checked fusable before the recording is read
    samples, read_stats = read_imu_recording(recording, desc, progress=read_progress)
    p = prepare_fusion(samples, desc, bias_tracking=bias_tracking)
    fused, stats = fuse_chunked(p.fusion, p.samples, fuse_progress)
    return FusedRecording(p.samples, read_stats, fused, stats, p.fusion, p.session, p.biases,
                          samples if p.samples is not samples else None)
