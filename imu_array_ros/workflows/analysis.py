"""How well a model explains a recording, and what it leaves out: residuals and mismatch discovery."""

from __future__ import annotations

from typing import Callable, Sequence

import numpy as np

from imu_array_ros.discovery.discover import Discovery, DiscoveryOptions
from imu_array_ros.discovery.discover import discover as run_discovery
from imu_array_ros.fitting.reading_rates import rates_scope
from imu_array_ros.fusion.residuals import ResidualReport, normalized_residuals
from imu_array_ros.fusion.stream import fuse_chunked
from imu_array_ros.model.description import ArrayDescription
from imu_array_ros.model.samples import FusedSamples, ImuSamples
from imu_array_ros.simulation.simulator import simulate_same_motion
from imu_array_ros.workflows.arrays import as_model
from imu_array_ros.fusion.model_fusion import ModelFusion
from imu_array_ros.workflows.fusion import prepare_fusion

__all__ = ["residuals", "discover", "DiscoveryOptions"]


def residuals(samples: ImuSamples, desc: ArrayDescription, *, fused: FusedSamples | None = None,
              fusion: ModelFusion | None = None, compare_simulated: bool = False, seed: int = 0,
              still_threshold: float = 0.2, bias_tracking: bool = True,
              progress: Callable[[int, int], None] | None = None) -> dict[str, ResidualReport]:
    """Normalised residuals of ``samples`` under every term of ``desc`` at the fused motion (``fused``:
    already fused by ``fusion``, whose model then holds the recording's session states; default: both made
    here, :func:`~imu_array_ros.workflows.fusion.session_fusion`).  ``{"recording": report}``; with
    ``compare_simulated`` also ``"simulated_same_motion"``: a simulated recording of the same fused motion
    (seeded), with the same readings missing, analysed the same way -- what the model alone would give.
    The NIS is always against the description's white-noise figures.  Without ``fusion``, the gyroscope biases
    are tracked on the still intervals (``bias_tracking``, as ``imu-array fuse``); a ``fusion`` given comes with
    ``samples`` as it fused them (:attr:`FusedRecording.samples`)."""
    if fusion is None:  # drifts and clocks count from the first stamp
        prepared = prepare_fusion(samples, desc, bias_tracking=bias_tracking)
        fusion, samples = prepared.fusion, prepared.samples
    if fused is None:
        fused, _ = fuse_chunked(fusion, samples, progress)
    model = fusion.model
    reports = {"recording": normalized_residuals(samples, model, fused, still_threshold=still_threshold)}
    if compare_simulated:
        sim = simulate_same_motion(fused, model, np.random.default_rng(seed), like=samples)
        sim_fused, _ = fuse_chunked(fusion, sim, progress)
        reports["simulated_same_motion"] = normalized_residuals(sim, model, sim_fused, still_threshold=still_threshold)
    return reports


def discover(samples: ImuSamples, desc: ArrayDescription, *, options: DiscoveryOptions | None = None,
             sim: ImuSamples | None = None, validate: Sequence[tuple[str, ImuSamples]] = (),
             progress: Callable[[str], None] | None = None) -> Discovery:
    """Mismatch discovery (:func:`imu_array_ros.discovery.discover.discover`) on ``samples`` under every term
    of ``desc``; ``sim``: the user's own simulation of the same run; ``validate``: (label, samples) of other
    recordings to score the findings on.  ``findings_calibration(result, samples)`` turns the findings into a
    calibration to install.  Its fits carry each sample's reading rates when the chips' sample clocks are known and
    the recording wants them (:mod:`imu_array_ros.fitting.reading_rates`; discovery's timing stage decides, and
    the decision holds for this call only)."""
    with rates_scope():
        return run_discovery(samples, as_model(desc), options=options, sim=sim, validate=validate, progress=progress)


