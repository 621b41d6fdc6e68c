"""Identifiability: the information the noise of the motion estimate alone would fake, the check that the
recording identifies the gauge-fixed parameters beyond it, and the one-line message naming what it cannot
identify (theory: :mod:`imu_array_ros.fitting`, section Identifiability)."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
import scipy.linalg

from imu_array_ros.errors import CalibrationError
from imu_array_ros.fitting.problem import Linearization, Problem
from imu_array_ros.fitting.schur import per_imu, stacked_g
from imu_array_ros.model.sensor_model import SensorModel
from imu_array_ros.model.terms import REGISTRY

if TYPE_CHECKING:
    from imu_array_ros.fitting.gauge import Gauge

__all__ = ["NOISE_SHARE", "NOISE_SAMPLES", "noise_information", "check_noise_share", "unidentifiable_message"]

#: a direction is not identified when the noise of the motion estimate alone would give it this share of its information
NOISE_SHARE = 0.25
#: samples the noise information is estimated on (evenly spaced)
NOISE_SAMPLES = 1000


def noise_information(prob: Problem, model: SensorModel, motion: np.ndarray, lin: Linearization) -> np.ndarray:
    """(M, M) information the motion estimate's own noise would fake: S built (Schur complement and all)
    from dJ_n, the change of the parameter Jacobian when x_n moves by one draw of its noise, N(0, A_n^-1).

    Central difference at x_n +- delta_n (fixed seed), on at most ``NOISE_SAMPLES`` evenly spaced
    used samples, scaled to all of them.
    """
    used = np.flatnonzero(prob.used)
    pick = used[::max(1, len(used) // NOISE_SAMPLES)]
    delta = np.einsum("nji,nj->ni", lin.linv[pick],
                      np.random.default_rng(0).normal(size=(len(pick), prob.dm)))
    kf, p = len(prob.fit), prob.p
    info, blocks = np.zeros((prob.m, prob.m)), np.zeros((kf, p, p))
    for lo in range(0, len(pick), prob.chunk):
        sel, d = pick[lo:lo + prob.chunk], delta[lo:lo + prob.chunk]
        w = prob.w[sel]
        jac = []
        for sign in (1.0, -1.0):
            moved = motion.copy()
            moved[sel] += sign * d
            jac.append(model.jacobians(prob.context_at(model, moved, lin.derivs, sel), prob.free))
        djt = 0.5 * (prob.parameter_jacobian(jac[0], w) - prob.parameter_jacobian(jac[1], w))
        cols = prob.rates(model, prob.context_at(model, motion, lin.derivs, sel))
        jx = prob.motion_jacobian(0.5 * (jac[0].motion + jac[1].motion)[:, prob.cols], w[:, prob.cols], motion, sel,
                                  None if cols is None else cols[:, prob.cols])
        dk = per_imu(djt)
        blocks += np.matmul(dk.transpose(0, 2, 1), dk)
        gmat = stacked_g(jx, lin.linv[sel], djt)
        info -= gmat.T @ gmat
    return (info + scipy.linalg.block_diag(*blocks)) * (len(used) / len(pick))


def check_noise_share(prob: Problem, model: SensorModel, motion: np.ndarray, lin: Linearization, gauge: Gauge,
                      scale: np.ndarray) -> None:
    """CalibrationError for directions whose information comes mostly from the noise of the motion estimate.

    At the estimated motion, motion that is really absent (e.g. the angular
    acceleration about x and y when the array turns about z only) is replaced
    by its estimation noise, which fakes a little information about the
    parameters it would excite: S is not singular there.  F, the information
    that noise alone produces (:func:`noise_information`), is compared
    with S in the gauge-fixed space: directions with v^T F v > NOISE_SHARE v^T S v
    (generalised eigenvalues of (F, S)) are not identified by the recording.
    ``scale`` (M,): the Jacobi scaling of the parameters the gauge was found in.
    """
    s_z = gauge.reduce(lin.S, lin.g)[0]
    f_z = gauge.reduce(noise_information(prob, model, motion, lin), lin.g)[0]
    if not f_z.any():
        return  # no free parameter's Jacobian depends on the motion (biases, ...)
    try:
        share, vec = scipy.linalg.eigh(f_z, s_z)
    except np.linalg.LinAlgError:
        raise CalibrationError("the free parameters are not identifiable from this recording "
                               "(Fisher information singular); record more varied motion") from None
    bad = share > NOISE_SHARE
    if bad.any():
        rest = np.linalg.qr(scale[:, None] * np.stack([gauge.expand(v) for v in vec[:, bad].T], axis=1))[0]
        raise CalibrationError(unidentifiable_message(rest, prob.parameter_names(), prob.column_terms()))


def unidentifiable_message(rest: np.ndarray, names: list[str], terms: list[str], top: int = 6) -> str:
    """One line naming the parameters in the unidentifiable directions and the motion that would help.

    rest (M, q): the directions not identified; names, terms (M,): each parameter's name and term."""
    weight = np.sum(rest ** 2, axis=1)
    idx = np.flatnonzero(weight > 1e-3 * weight.max())
    idx = idx[np.argsort(-weight[idx], kind="stable")]
    shown = ", ".join(names[i] for i in idx[:top]) + (f" and {len(idx) - top} more" if len(idx) > top else "")
    hints = [REGISTRY[t].hint for t in dict.fromkeys(terms[i] for i in idx) if REGISTRY[t].hint]
    q = rest.shape[1]
    what = "1 combination" if q == 1 else f"{q} combinations"
    advice = "; ".join(dict.fromkeys(hints)) or "record more varied motion"
    return (f"the recording cannot identify {what} of the free parameters, involving {shown} "
            f"(missing motion? {advice})")
