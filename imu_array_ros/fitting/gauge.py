"""Gauge fixing: the null space of the Fisher information at the structural point, the parameters held
to fix the gauge freedoms (``gauge="reference"``) or the subspace keeping their component at its initial
value (``gauge="mean"``) (theory: :mod:`imu_array_ros.fitting`, section Gauge)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.linalg

from imu_array_ros.errors import CalibrationError
from imu_array_ros.fitting.identifiability import check_noise_share, unidentifiable_message
from imu_array_ros.fitting.problem import Linearization, Problem
from imu_array_ros.model.sensor_model import SensorModel
from imu_array_ros.model.terms import REGISTRY, term_names

__all__ = ["Gauge", "GAUGE_ORDER", "NULL_RTOL", "COLLECTIVE_SHARE"]

#: terms whose reference-IMU parameters are tried first to fix a gauge freedom (frame-defining ones)
GAUGE_ORDER = ("position", "accelerometer_misalignment", "accelerometer_gain", "accelerometer_bias", "time_offset")
#: eigenvalue of the Jacobi-scaled Fisher information, relative to its largest, below which a direction is null
NULL_RTOL = 1e-10
#: a null direction is a gauge freedom when at least this share of it lies outside the reference IMU
COLLECTIVE_SHARE = 0.1


@dataclass
class Gauge:
    """How the gauge is fixed: the estimated subspace dtheta = Z z of the candidate parameters.

    keep (M,) bool (reference mode: the parameters not held) or basis (M, R)
    (mean mode: orthonormal complement of the gauge directions); held: indexes
    of held parameters; lines: one description per fixed direction;
    directions (M, q): orthonormal basis of the gauge freedoms, SI units.
    """

    keep: np.ndarray
    basis: np.ndarray | None
    held: list[int]
    lines: list[str]
    directions: np.ndarray
    fixed: np.ndarray | None = None

    @property
    def rank(self) -> int:
        return int(self.keep.sum()) if self.basis is None else self.basis.shape[1]

    def reduce(self, S: np.ndarray, g: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        if self.basis is None:
            return S[np.ix_(self.keep, self.keep)], g[self.keep]
        return self.basis.T @ S @ self.basis, self.basis.T @ g

    def expand(self, z: np.ndarray) -> np.ndarray:
        if self.basis is None:
            out = np.zeros(len(self.keep))
            out[self.keep] = z
            return out
        return self.basis @ z

    def expand_covariance(self, cov_z: np.ndarray) -> np.ndarray:
        if self.basis is None:
            out = np.zeros((len(self.keep),) * 2)
            out[np.ix_(self.keep, self.keep)] = cov_z
            return out
        return self.basis @ cov_z @ self.basis.T

    @classmethod
    def find(cls, prob: Problem, model: SensorModel, motion: np.ndarray, lin: Linearization, ref: int,
             mode: str, fixed: np.ndarray | None = None) -> Gauge:
        """Null space of the scaled S at the structural point, holds, then the check that what is left is
        identified by the motion itself (:func:`~imu_array_ros.fitting.identifiability.check_noise_share`);
        CalibrationError if anything is not.  ``fixed`` (M,): parameters held from the start (``only``),
        outside every search."""
        structural = _structural(model)
        if structural is not model or prob.needs_derivatives:
            lin = prob.linearize(structural, motion, gauge_point=True)
        scale = np.sqrt(lin.cdiag)
        scale = np.where(scale > 0, scale, 1.0)
        act = np.ones(prob.m, dtype=bool) if fixed is None else ~fixed
        lam, vec = np.linalg.eigh((lin.S / np.outer(scale, scale))[np.ix_(act, act)])
        small = lam <= NULL_RTOL * max(lam.max(), 0.0)
        null = np.zeros((prob.m, int(small.sum())))
        null[act] = vec[:, small]
        names = prob.parameter_names()
        held, rest = _hold_gauge(null, prob, ref)
        if rest.shape[1]:
            raise CalibrationError(unidentifiable_message(rest, names, prob.column_terms()))
        directions = np.linalg.qr(null / scale[:, None])[0]  # gauge freedoms in SI units
        if mode == "reference" or not held or not act.all():
            keep = act.copy()
            keep[held] = False
            gauge = cls(keep, None, held, [f"{names[i]} held" for i in held], directions, ~act)
        else:
            basis = scipy.linalg.null_space(directions.T)
            gauge = cls(np.ones(prob.m, dtype=bool), basis, [],
                        [f"{_combination(d, names)} kept at its initial value" for d in directions.T], directions)
        check_noise_share(prob, structural, motion, lin, gauge, scale)
        return gauge


#: terms kept at their values at the structural point: the geometry, and the sample clocks (at their identity
#: value a clock has no period and its rate no effect)
STRUCTURAL = ("position", "sample_clock", "gyroscope_sample_clock", "accelerometer_sample_clock")


def _structural(model: SensorModel) -> SensorModel:
    """The model with every term but the ``STRUCTURAL`` ones at its identity value (``model`` itself if it is so)."""
    reset = {n: t.default_values(model.n_imus) for n, t in model.terms.items()
             if n not in STRUCTURAL and not t.is_identity}
    return model.with_terms(**reset) if reset else model


def _hold_gauge(null: np.ndarray, prob: Problem, ref: int) -> tuple[list[int], np.ndarray]:
    """Hold parameters that remove a collective null direction: the reference IMU's first, then the
    other fitted IMUs' in turn, each IMU's in gauge order.

    ``null`` (M, q) orthonormal basis of the null space (scaled coordinates).
    The null space left after holding set H is {v in null : v_H = 0}, so
    holding parameter i removes a direction iff row i of the basis is not
    zero.  It is held only if the null direction closest to it (the projection
    of e_i) lies for at least ``COLLECTIVE_SHARE`` outside i's IMU: a gauge
    freedom moves every IMU, an unidentifiable parameter of one IMU is not one.
    Returns the held indexes and an orthonormal basis of what is left.
    """
    offsets = prob.offsets
    order = [t for t in GAUGE_ORDER if t in prob.free]
    order += [t for t in term_names() if t in prob.free and t not in order]
    held = []
    for k in [ref] + [k for k in range(len(prob.fit)) if k != ref]:
        own = np.zeros(prob.m, dtype=bool)
        own[k * prob.p:(k + 1) * prob.p] = True
        for i in (k * prob.p + offsets[t] + j for t in order for j in range(REGISTRY[t].dim())):
            if null.shape[1] == 0:
                return held, null
            row = null[i]
            if np.linalg.norm(row) < 1e-6:
                continue  # holding it removes no null direction
            u = null @ row  # the null direction closest to parameter i
            if np.sum(u[~own] ** 2) < COLLECTIVE_SHARE * np.sum(u ** 2):
                continue  # confined to one IMU: unidentifiable, not a gauge freedom
            held.append(i)
            null = null @ np.linalg.svd(row[None], full_matrices=True)[2][1:].T
    return held, null


def _combination(direction: np.ndarray, names: list[str], top: int = 4) -> str:
    """'imu_00 position[0] + imu_01 position[0] + ... (32 parameters)' for a direction vector."""
    mags = np.abs(direction)
    idx = np.flatnonzero(mags > 1e-3 * mags.max())
    idx = idx[np.argsort(-mags[idx], kind="stable")]
    parts = " ".join(f"{'+' if direction[i] >= 0 else '-'} {names[i]}" for i in idx[:top]).lstrip("+ ")
    more = f" ... ({len(idx)} parameters)" if len(idx) > top else ""
    return f"the combination {parts}{more}"


