"""Recordings in and out: simulate one, import an OpenShoe capture, read one for an array."""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np

from imu_array_ros.errors import ConfigError, ImuArrayError
from imu_array_ros.io.openshoe.capture import CaptureStats, import_capture
from imu_array_ros.io.rosbag.recording import read_imu_recording
from imu_array_ros.model.description import ArrayDescription
from imu_array_ros.model.samples import ImuSamples, MotionTruth
from imu_array_ros.model.sensor_model import SensorModel
from imu_array_ros.simulation.icosahedron import FACES, simulate_icosahedron
from imu_array_ros.simulation.perturb import DEFAULT_ERROR_SCALES, perturb
from imu_array_ros.simulation.simulator import simulate_random, simulate_twist
from imu_array_ros.workflows.arrays import check_fusable

__all__ = ["read_imu_recording", "import_openshoe", "simulate", "Simulated", "MOTIONS", "icosahedron_seconds"]

#: what :func:`simulate` can simulate
MOTIONS = ("twist", "random", "icosahedron")


def import_openshoe(capture: str | Path, desc: ArrayDescription, *, start_ns: int | None = None,
                    progress: Callable[[int, int], None] | None = None) -> tuple[ImuSamples, CaptureStats]:
    """An OpenShoe raw serial capture as samples of ``desc`` (IMU order = capture order).  ``start_ns``:
    stamp of the first packet, ns since the epoch; default: the last packet is stamped with the capture
    file's modification time (the capture ended when the file was last written)."""
    samples, stats = import_capture(capture, desc, progress=progress, start_ns=0 if start_ns is None else start_ns)
    if start_ns is None and len(samples):
        end_ns = os.stat(capture).st_mtime_ns
        samples.stamps = samples.stamps + max(end_ns - int(samples.stamps[-1]), 0)
    return samples, stats


@dataclass
class Simulated:
    """A simulated recording: the readings, the true motion, and the description of the true sensors."""

    samples: ImuSamples
    truth: MotionTruth
    true_description: ArrayDescription


def icosahedron_seconds(still_s: float, transition_s: float, twist_s: float) -> float:
    """Length of the icosahedron session (nilsson2014): 20 rests, 19 transitions, then twisting."""
    return FACES * still_s + (FACES - 1) * transition_s + twist_s


def simulate(desc: ArrayDescription, *, motion: str = "twist", duration: float = 5.0, rate: float = 1000.0,
             rms_rate: float = 600.0, angular_accel: float = 2000.0, still_seconds: float = 3.0,
             transition_seconds: float = 2.0, tilt_std_deg: float = 1.0, twist_seconds: float = 0.0, seed: int = 0,
             start_ns: int = 0, true_desc: ArrayDescription | None = None, error_seed: int | None = None,
             position_error_std: float | None = None) -> Simulated:
    """Simulate a recording of ``desc`` (checked fusable) measured by the sensors of ``true_desc`` (default:
    ``desc``), with seeded errors (positions, gains, biases, angles) when ``error_seed`` is given.

    motion: "twist" (hand twisting; rms_rate deg/s), "random" (independent samples, |omega| = rms_rate
    deg/s, |omega_dot| = angular_accel deg/s^2) or "icosahedron" (nilsson2014's static session: 20 rests of
    ``still_seconds`` tilted by ``tilt_std_deg`` per axis, ``transition_seconds`` between, then
    ``twist_seconds`` of twisting; ``duration`` is ignored, see :func:`icosahedron_seconds`)."""
    if motion not in MOTIONS:
        raise ImuArrayError(f"motion must be one of {', '.join(MOTIONS)}, not {motion!r}")
    check_fusable(desc)
    true_desc = desc if true_desc is None else true_desc
    if true_desc.names != desc.names:
        raise ConfigError(f"{true_desc.source}: IMU names differ from {desc.source}")
    rng = np.random.default_rng(seed)
    true_model = SensorModel.from_description(true_desc)  # every term of the true description
    if error_seed is not None:
        scales = dict(DEFAULT_ERROR_SCALES)
        if position_error_std is not None:
            scales["position"] = position_error_std
        true_model = perturb(true_model, np.random.default_rng(error_seed), scales)
        true_desc = true_model.to_description(true_desc, names=[n for n in scales if scales[n]])
    if motion == "twist":
        samples, truth = simulate_twist(true_model, duration, rate, rng, rms_rate=np.deg2rad(rms_rate),
                                        start_ns=start_ns)
    elif motion == "icosahedron":
        samples, truth, _ = simulate_icosahedron(true_model, rng, rate_hz=rate, still_s=still_seconds,
                                                 transition_s=transition_seconds,
                                                 tilt_std=float(np.deg2rad(tilt_std_deg)), twist_s=twist_seconds,
                                                 rms_rate=float(np.deg2rad(rms_rate)), start_ns=start_ns)
    else:
        n = int(round(duration * rate))
        samples, truth = simulate_random(true_model, n, np.deg2rad(rms_rate), np.deg2rad(angular_accel), rng,
                                         rate_hz=rate, start_ns=start_ns)
    return Simulated(samples, truth, true_desc)
