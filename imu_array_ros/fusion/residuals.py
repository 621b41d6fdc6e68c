"""How well a model explains a recording: normalised residuals (NIS).

For every fused sample the model (:class:`~imu_array_ros.model.sensor_model.SensorModel`,
every term) predicts each valid sensor axis from the ML estimate
theta_hat = [omega, omega_dot, s] (skog2016 eq. 5).  The normalised
squared residual of axis a is ``z^2 = (y_a - h_a(theta_hat))^2 / sigma_a^2``.  If
the model is right, its expected value is ``1 - leverage_a`` with
``leverage_a = phi_a^T Cov(theta_hat) phi_a / sigma_a^2`` (phi_a the axis' row
of the model's motion Jacobian, Phi of eq. 15, and Cov the CRB), so that the per-sample NIS
``sum_a z^2`` has expected value ``m - 9`` for m valid axes.  The report
gives ``ratio = sum z^2 / sum E[z^2]`` by IMU and axis, separately for still
and moving samples: 1 means the model explains the data to the noise level,
100 means residuals ten times the noise.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from imu_array_ros.model.trajectory import fused_timing_context
from imu_array_ros.model.sensor_model import SensorModel, motion_context
from imu_array_ros.model.samples import FusedSamples, ImuSamples

__all__ = ["ResidualReport", "normalized_residuals", "AXES"]

AXES = ("acc_x", "acc_y", "acc_z", "gyr_x", "gyr_y", "gyr_z")


@dataclass
class ResidualReport:
    """Sums of z^2 and of its expectation, per regime ('still', 'moving'), (K, 6) each.

    ``samples`` counts fused samples per regime; ``nis``/``nis_expected`` are
    the per-sample totals (N,) for all fused samples; ``moving`` (N,) bool.
    """

    names: tuple[str, ...]
    observed: dict[str, np.ndarray]
    expected: dict[str, np.ndarray]
    samples: dict[str, int]
    nis: np.ndarray
    nis_expected: np.ndarray
    moving: np.ndarray

    def ratio(self, regime: str) -> np.ndarray:
        """(K, 6) observed / expected; NaN where no valid axis was seen."""
        with np.errstate(invalid="ignore", divide="ignore"):
            return self.observed[regime] / self.expected[regime]

    def table(self, regime: str) -> str:
        """Markdown table of the ratio by IMU (rows) and axis (columns)."""
        r = self.ratio(regime)
        head = "| IMU | " + " | ".join(AXES) + " |\n|---|" + "---|" * len(AXES) + "\n"
        rows = "".join(
            f"| {n} | " + " | ".join("—" if not np.isfinite(v) else f"{v:.3g}" for v in row) + " |\n"
            for n, row in zip(self.names, r)
        )
        return head + rows

    def summary(self) -> dict:
        """Ratios by regime: all axes, accelerometers, gyroscopes, by IMU, by axis, worst five."""
        out = {}
        for regime in ("still", "moving"):
            o, e = self.observed[regime], self.expected[regime]
            out[regime] = {
                "samples": self.samples[regime],
                "ratio_all": _ratio(o, e),
                "ratio_accelerometers": _ratio(o[:, :3], e[:, :3]),
                "ratio_gyroscopes": _ratio(o[:, 3:], e[:, 3:]),
                "by_imu": {n: _ratio(o[i], e[i]) for i, n in enumerate(self.names)},
                "by_axis": {a: _ratio(o[:, j], e[:, j]) for j, a in enumerate(AXES)},
                "worst": _worst(self.ratio(regime), self.names),
            }
        return out


def _ratio(observed: np.ndarray, expected: np.ndarray) -> float:
    e = float(expected.sum())
    return float(observed.sum()) / e if e > 0 else float("nan")


def _worst(r: np.ndarray, names) -> list:
    flat = np.where(np.isfinite(r), r, -np.inf).ravel()
    order = np.argsort(flat)[::-1][:5]
    return [(names[i // 6], AXES[i % 6], float(flat[i])) for i in order if np.isfinite(flat[i])]


def normalized_residuals(samples: ImuSamples, model: SensorModel, fused: FusedSamples, *,
                         still_threshold: float = 0.2, chunk: int = 4096) -> ResidualReport:
    """Residual analysis of ``samples`` against ``model`` at the fused estimates.

    ``still_threshold`` (rad/s): a sample is 'still' when |omega_hat| is below it.
    Only samples present in ``fused`` are used (matched by stamp).  Bias drifts
    count from the samples' first stamp.
    """
    idx = np.searchsorted(samples.stamps, fused.stamps)
    if np.any(idx >= len(samples)) or np.any(samples.stamps[np.clip(idx, 0, len(samples) - 1)] != fused.stamps):
        raise ValueError("fused stamps are not a subset of the samples' stamps")
    k = model.n_imus
    obs = {r: np.zeros((k, 6)) for r in ("still", "moving")}
    exp = {r: np.zeros((k, 6)) for r in ("still", "moving")}
    nis = np.zeros(len(fused))
    nis_exp = np.zeros(len(fused))
    moving = np.linalg.norm(fused.omega, axis=1) >= still_threshold
    sig2 = model.std ** 2  # (K, 6)
    t0 = int(samples.stamps[0]) if len(samples) else None
    # time derivatives of the estimate over the whole recording (not per chunk)
    ctx_all = motion_context(fused.stamps, fused.omega, fused.omega_dot, fused.specific_force, model.rotations,
                             t0_ns=t0, derivatives=True)
    # readings away from their stamps are predicted along the fused trajectory, as the fusion compensates them
    delays = samples.stamp_delays
    timed = model.timed or delays is not None
    tc = fused_timing_context(fused.stamps, np.concatenate([fused.omega, fused.omega_dot, fused.specific_force],
                                                           axis=1)) if timed else None
    for lo in range(0, len(fused), chunk):
        hi = min(lo + chunk, len(fused))
        sel = idx[lo:hi]
        if tc is None:
            extra = dict(omega_ddot=ctx_all.omega_ddot[lo:hi], specific_force_dot=ctx_all.specific_force_dot[lo:hi])
        else:
            extra = dict(omega_ddot=tc["omega_ddot"][lo:hi], specific_force_dot=tc["specific_force_dot"][lo:hi],
                         omega_rate=tc["omega_rate"][lo:hi], trajectory=tc["trajectory"].rows(slice(lo, hi)),
                         stamp_delays=None if delays is None else delays[sel])
        ctx = motion_context(fused.stamps[lo:hi], fused.omega[lo:hi], fused.omega_dot[lo:hi],
                             fused.specific_force[lo:hi], model.rotations, t0_ns=t0, **extra)
        jac = model.jacobians(ctx)
        ya, yg = samples.accel[sel], samples.gyro[sel]
        valid = model.valid(ya, yg)
        res = np.concatenate([ya, yg], axis=2) - jac.predicted
        z2 = np.where(valid, np.nan_to_num(res) ** 2 / sig2, 0.0)
        rows = jac.motion  # (n, K, 6, 9)
        # leverage of each reading: row C row^T (a matmul: a three-operand einsum runs as a naive loop)
        lev = np.einsum("nkai,nkai->nka", rows @ fused.covariance[lo:hi, None], rows) / sig2
        e = np.where(valid, 1.0 - lev, 0.0)
        nis[lo:hi] = z2.sum(axis=(1, 2))
        nis_exp[lo:hi] = e.sum(axis=(1, 2))
        mv = moving[lo:hi]
        for regime, m in (("moving", mv), ("still", ~mv)):
            obs[regime] += z2[m].sum(axis=0)
            exp[regime] += e[m].sum(axis=0)
    return ResidualReport(
        names=model.names, observed=obs, expected=exp,
        samples={"still": int(np.count_nonzero(~moving)), "moving": int(np.count_nonzero(moving))},
        nis=nis, nis_expected=nis_exp, moving=moving,
    )
