"""Which samples a calibration uses: the one sample-selection module.

Every calibration that uses the array's motion (geometry, the moving stage of
``calibrate all``, the Bayesian positions) selects its samples here; the still
poses of the static calibrations come from :mod:`.still`.

* :func:`check_samples`: a window a calibration can use at all (samples present,
  stamps strictly increasing, the model's IMUs);
* :func:`select_rotating`: complete samples (every reading present and not
  saturated) whose fused motion identifies itself and rotates:
  ||C_n||_F >= ``min_excitation`` (C_n = [omega]x^2 + [omega_dot]x, the lever-arm
  matrix that makes the positions visible, :func:`lever_matrices`) and >=
  ``NOISE_FACTOR`` times what the fused motion's own noise gives it (at rest the
  fused omega_dot is noise).  With ``gyroscopes=True`` the rotation is also
  tested with the gyroscopes alone (the time derivative of the fused omega): the
  fused omega_dot comes from the accelerometers, and with uncalibrated
  accelerometer biases a still array shows tens of rad/s^2 there (the
  MIMU4444BT captures: ~14 rad/s^2 at rest), so static poses would pass as
  rotation;
* :func:`require_rotation`: CalibrationError naming the missing motion when the
  selected samples cannot determine the positions (too few, or every sample
  turning about one axis, or omega parallel to omega_dot);
* :func:`spread_evenly`: ``n`` of the selected samples, evenly spread in time.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from imu_array_ros.errors import CalibrationError
from imu_array_ros.fusion.model_fusion import ModelFusion
from imu_array_ros.model.kinematics import skew
from imu_array_ros.model.samples import ImuSamples
from imu_array_ros.model.sensor_model import SensorModel

__all__ = ["Selection", "check_samples", "lever_matrices", "select_rotating", "require_rotation", "spread_evenly",
           "MIN_SAMPLES", "MIN_EXCITATION", "NOISE_FACTOR", "EXCITATION_RTOL", "PARALLEL_SIN"]

#: fewest samples with rotation that can determine the positions
MIN_SAMPLES = 3
#: default lowest ||[omega]x^2 + [omega_dot]x||_F (rad/s^2) for a sample to be used
MIN_EXCITATION = 1.0
#: a sample's ||C_n|| must exceed this many times the part the noise of its fused motion explains
NOISE_FACTOR = 3.0
#: smallest eigenvalue of sum C_n^T C_n relative to its largest below which a direction counts as not
#: excited: its positions would be >= 18x less certain than the best-determined direction's, and at the
#: fused motion the noise of the omega_dot estimate alone gives ~1e-3 (a turn about one fixed axis
#: measured 5.6e-4; a simulated hand twist 0.06)
EXCITATION_RTOL = 3e-3
#: |sin| of the angle between omega and omega_dot below which they count as parallel
PARALLEL_SIN = 0.02


@dataclass
class Selection:
    """The samples a calibration uses: used (N,) bool; dropped: reason -> count of the samples left out;
    motion (N, 9) [omega, omega_dot, s] fused for the complete samples (NaN elsewhere)."""

    used: np.ndarray
    dropped: dict[str, int]
    motion: np.ndarray

    @property
    def n_used(self) -> int:
        return int(self.used.sum())

    def dropped_text(self) -> str:
        """'12 missing or saturated, 3 little rotation' (empty when nothing was dropped)."""
        return ", ".join(f"{v} {k.replace('_', ' ')}" for k, v in self.dropped.items() if v)


def check_samples(samples: ImuSamples, model: SensorModel) -> ImuSamples:
    """``samples`` when a calibration can use them: non-empty, of the model's IMUs, strictly increasing stamps."""
    if tuple(samples.names) != tuple(model.names):
        raise CalibrationError(f"the samples are of IMUs {', '.join(samples.names[:4])}..., the model of "
                               f"{', '.join(model.names[:4])}...")
    if len(samples) == 0:
        raise CalibrationError("no samples in the window: record (or buffer) some motion first")
    if np.any(np.diff(samples.stamps) <= 0):
        raise CalibrationError("stamps must increase strictly")
    return samples


def lever_matrices(motion: np.ndarray) -> np.ndarray:
    """(N, 3, 3) C_n = [omega]x^2 + [omega_dot]x from (N, 9) motion [omega, omega_dot, ...]."""
    w = skew(motion[:, 0:3])
    return w @ w + skew(motion[:, 3:6])


def select_rotating(samples: ImuSamples, model: SensorModel, min_excitation: float = MIN_EXCITATION, *,
                    gyroscopes: bool = False) -> Selection:
    """The complete samples that rotate (module docstring); ``gyroscopes``: also by the gyroscopes alone."""
    stamps = samples.stamps
    n = len(stamps)
    complete = samples.valid(model).all(axis=(1, 2))
    motion = np.full((n, 9), np.nan)
    fused_ok = np.zeros(n, dtype=bool)
    noise = np.zeros(n)
    if complete.any():
        idx = np.flatnonzero(complete)
        fused, _ = ModelFusion(model).fuse(samples.select(idx))
        rows = idx[np.searchsorted(stamps[idx], fused.stamps)]
        motion[rows] = np.concatenate([fused.omega, fused.omega_dot, fused.specific_force], axis=1)
        fused_ok[rows] = True
        # the part of ||C_n|| the estimate's own noise makes (||[d omega_dot]x||_F = sqrt(2) |d omega_dot|,
        # d([w]x^2) ~ 2 |w| |d omega|): a still array's fused omega_dot is noise, not rotation
        cov = fused.covariance
        var_w, var_wd = np.einsum("nii->n", cov[:, 0:3, 0:3]), np.einsum("nii->n", cov[:, 3:6, 3:6])
        noise[rows] = np.sqrt(2 * var_wd + 4 * np.sum(fused.omega ** 2, axis=1) * var_w)
    excitation = np.linalg.norm(lever_matrices(np.nan_to_num(motion)), axis=(1, 2))
    low = fused_ok & (excitation < np.maximum(float(min_excitation), NOISE_FACTOR * noise))
    used = fused_ok & ~low
    dropped = {"missing_or_saturated": int((~complete).sum()), "motion_not_identified": int((complete & ~fused_ok).sum()),
               "little_rotation": int(low.sum())}
    if gyroscopes and n >= 2:
        still = used & ~_rotating_by_gyroscopes(stamps, motion[:, 0:3], model, float(min_excitation))
        used = used & ~still
        dropped["still_by_gyroscopes"] = int(still.sum())
    return Selection(used, dropped, motion)


def _rotating_by_gyroscopes(stamps: np.ndarray, omega: np.ndarray, model: SensorModel, threshold: float) -> np.ndarray:
    """(N,) ||[omega]x^2 + [d omega/dt]x||_F >= threshold and >= NOISE_FACTOR times what the gyroscope noise
    gives it, with d omega/dt the central difference of the fused omega (NaN: not rotating)."""
    seconds = (stamps - stamps[0]) * 1e-9
    with np.errstate(invalid="ignore"):
        omega_dot = np.gradient(omega, seconds, axis=0)
    excitation = np.linalg.norm(lever_matrices(np.concatenate([omega, omega_dot], axis=1)), axis=(1, 2))
    # what the gyroscopes' noise alone gives ||[d omega/dt]x||_F: sqrt(sum_j var_j) / dt for the
    # central difference of the fused omega (per-axis variance var_j = 1 / sum_k sigma_kj^-2)
    dt = float(np.median(np.diff(seconds)))
    noise = np.sqrt(np.sum(1.0 / np.sum(model.gyro_std ** -2.0, axis=0))) / dt if dt > 0 else np.inf
    return excitation >= max(threshold, NOISE_FACTOR * noise)  # NaN compares False: not rotating


def require_rotation(selection: Selection) -> None:
    """CalibrationError naming the missing motion when the used samples cannot determine the positions."""
    motion, n_used, n_total = selection.motion[selection.used], selection.n_used, len(selection.used)
    why = selection.dropped_text()
    if n_used < MIN_SAMPLES:
        raise CalibrationError(
            f"too few samples with rotation: {n_used} of {n_total} usable (need at least {MIN_SAMPLES}"
            f"{'; dropped: ' + why if why else ''}); twist the array by hand about at least two axes for a few seconds")
    c = lever_matrices(motion)
    info = np.einsum("nji,njk->ik", c, c)
    lam, vec = np.linalg.eigh(info)
    if lam[0] > EXCITATION_RTOL * lam[-1]:
        return
    axis = vec[:, 0] * np.sign(vec[np.argmax(np.abs(vec[:, 0])), 0])
    axis_text = "[" + " ".join(f"{a:.2f}" for a in np.round(axis, 2) + 0.0) + "]"  # + 0.0: no "-0.00"
    w, wd = motion[:, 0:3], motion[:, 3:6]
    nw, nwd = np.linalg.norm(w, axis=1), np.linalg.norm(wd, axis=1)
    sin = np.linalg.norm(np.cross(w, wd), axis=1) / np.maximum(nw * nwd, 1e-300)
    parallel = np.all((sin < PARALLEL_SIN) | (nwd < 1e-9 * np.maximum(nw ** 2, 1e-300)))
    sv = np.linalg.svd(w / np.maximum(nw, 1e-300)[:, None], compute_uv=False)
    one_axis = sv[1] < 0.1 * sv[0]  # omega's direction hardly changes (measured 0.05 for one fixed axis)
    if one_axis:
        what = f"the array turned about one axis only ({axis_text} in the array frame)"
    elif parallel:
        what = "omega and omega_dot are parallel in every sample"
    else:
        what = "the motion does not excite every direction"
    raise CalibrationError(f"{what}: the positions along {axis_text} cannot be determined; "
                           "rotate about at least two axes, with angular acceleration")


def spread_evenly(selection: Selection, n: int | None) -> np.ndarray:
    """Indexes of ``n`` of the used samples, evenly spread in time (None: all of them)."""
    idx = np.flatnonzero(selection.used)
    if n is not None and len(idx) > n:
        idx = idx[np.round(np.linspace(0, len(idx) - 1, n)).astype(int)]
    return idx
