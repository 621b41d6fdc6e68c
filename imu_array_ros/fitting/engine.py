"""Maximum-likelihood fit of sensor-model terms jointly with the motion: the one fitting engine.

Problem
-------
Sample n (n = 1..N) of IMU k reads six axes r = [acc x, y, z, gyro x, y, z]::

    y_nkr = h_kr(x_n, theta_k) + e_nkr,    e_nkr ~ N(0, sigma_kr^2) white,

with h the sensor model (:class:`~imu_array_ros.model.sensor_model.SensorModel`),
x_n = [omega, omega_dot, s] (9) the motion of sample n and theta_k the free
terms' parameters of IMU k (IMU k's parameters move only IMU k's readings).
Saturated and missing axes carry no information and get weight 0, as in the
fusion.  Maximum likelihood of (theta, x_1..x_N) is weighted least squares of
the normalised residuals r = w (y - h), w = 1/sigma (0 on masked axes).

Gauss-Newton with J_x = w dh/dx (per sample) and J_t = w dh/dtheta has
block-arrow normal equations, one 9x9 block per sample coupled only through theta::

    [ A_1            B_1 ] [dx_1 ]   [gx_1]      A_n = J_x^T J_x      (9 x 9)
    [      ...       ... ] [ ... ] = [ ...]      B_n = J_x^T J_t      (9 x dim theta)
    [            A_N B_N ] [dx_N ]   [gx_N]      C   = sum_n J_t^T J_t (block diagonal by IMU)
    [ B_1^T .. B_N^T  C  ] [dth  ]   [ gt ]      g   = J^T r

Eliminating every dx_n (Schur complement), with A_n = L_n L_n^T (Cholesky),
G_n = L_n^-1 B_n and h_n = L_n^-1 gx_n::

    S dth = g_red,     S = C - sum_n G_n^T G_n,     g_red = gt - sum_n G_n^T h_n,
    dx_n = L_n^-T (h_n - G_n dth).

Per chunk of samples the G_n are stacked into one (9 n, dim theta) matrix and
``S -= G^T G`` is one matrix product, so a step costs O(N) in the samples with
no per-sample Python loop; a dim-theta system is solved per step
(Levenberg-Marquardt damping on S's diagonal, accepted when the cost drops).
The initial motion is self-contained: the gyroscopes (and accelerometers)
mapped to the array frame and averaged, refined by the same machinery with no
free parameters (batched 9x9 Gauss-Newton steps).

Cramér-Rao bound
----------------
J^T J is the Fisher information of the joint problem (theta, x_1..x_N); the
information about theta with the motion unknown is its Schur complement, S.
The covariance returned is S^-1 at the estimate (in the gauge chosen below):
the Cramér-Rao bound of the joint problem that carlsson2017 Sec. VI leaves open.

Gauge
-----
Some parameter combinations change no reading when the motion changes with
them: a common shift of every position (s absorbs it: s + C (p + d) = s' + C p
with s' = s + C d), of every time offset (the time base), accelerometer biases
forming a rigid-body field b + c x p_k (s and omega_dot absorb it), a common
gyroscope scale traded against the scale of the positions (omega (1 + e),
omega_dot (1 + e)^2, p / (1 + e)^2), ...  They are found as the null space of
the Jacobi-scaled S (eigenvalues below ``NULL_RTOL``), computed at the
*structural point* (the model with every term but the positions at its identity
value, so that a small known time offset cannot fake information through the
approximation below).  With ``gauge="reference"`` they are fixed by holding
parameters of the reference IMU, tried in the order ``GAUGE_ORDER`` then every
other free term, and, for what is left (e.g. the rotational part of the bias
field), of the other fitted IMUs in turn.  A parameter is held only when that
removes a null direction which also involves other IMUs (a *collective*
direction, a gauge freedom; an unidentifiable parameter of one IMU alone is not
one).  With ``gauge="mean"`` the same directions are instead fixed by keeping
the parameters' component along each of them (in SI units: e.g. the centroid
of the positions, the mean time offset) at its initial value.

Identifiability
---------------
Null directions left after that are not identifiable from the recording.
Motion that is missing (e.g. angular acceleration about x and y when the array
turns about z only) is not exactly missing at the estimated motion: there it is
replaced by the estimate's noise, which fakes a little information.  So the
information F that the motion noise alone produces (S rebuilt from the change
of the parameter Jacobian under one draw of that noise) is compared with S:
directions with more than ``NOISE_SHARE`` of their information from the noise
are not identified either.  Both raise :class:`CalibrationError` naming the
parameters involved and the motion that would identify them (``Term.hint``);
nothing is regularised silently.

Approximation
-------------
The ``time_offset`` term reads the time derivatives omega_ddot and ds/dt of the
motion.  They are recomputed from the current motion estimate at every
iteration (:func:`~imu_array_ros.model.sensor_model.motion_derivative`, as the
simulator does) and held fixed within the iteration, in the Jacobians and in
the cost of the trial step: the dependence of sample n's reading on its
neighbours' motion through those derivatives is neglected (keeps the normal
equations block-arrow), and the iteration converges to the point that is
optimal for the derivatives of its own motion.  The effect is second order in
the offset (milliseconds) times the noise of the motion estimate.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable, Sequence

import numpy as np
import scipy.linalg

from imu_array_ros.errors import CalibrationError
from imu_array_ros.fitting.motion_models import RigidMotion
from imu_array_ros.model.reference import imu_indexes, reference_index
from imu_array_ros.model.samples import ImuSamples
from imu_array_ros.model.sensor_model import SensorModel, motion_context, motion_derivative
from imu_array_ros.model.terms import REGISTRY, term_names

__all__ = ["FitResult", "ScoreBlocks", "fit_terms", "fit_motion", "score_blocks", "check_terms", "GAUGE_ORDER"]

#: terms whose reference-IMU parameters are tried first to fix a gauge freedom (frame-defining ones)
GAUGE_ORDER = ("position", "accelerometer_misalignment", "accelerometer_gain", "accelerometer_bias", "time_offset")
#: eigenvalue of the Jacobi-scaled Fisher information, relative to its largest, below which a direction is null
NULL_RTOL = 1e-10
#: a null direction is a gauge freedom when at least this share of it lies outside the reference IMU
COLLECTIVE_SHARE = 0.1
#: smallest eigenvalue of a sample's scaled motion information (A_n) for its motion to count as identified
MOTION_RTOL = 1e-10
#: working memory per chunk of samples (Jacobians and the stacked G of the Schur complement)
CHUNK_BYTES = 64 << 20
#: motion-only Gauss-Newton iterations for the initial motion
MOTION_ITERATIONS = 30
#: a direction is not identified when the noise of the motion estimate alone would give it this share of its information
NOISE_SHARE = 0.25
#: samples the noise information is estimated on (evenly spaced)
NOISE_SAMPLES = 1000


@dataclass
class FitResult:
    """What :func:`fit_terms` estimated (SI units).

    model: the input model with the estimate written into the free terms;
    free: the fitted terms; imus: names of the IMUs whose parameters were fitted;
    parameter_names (M,): "imu_03 accelerometer.gain[1]", fitted IMUs x free
    terms' parameters, IMU-major; theta (M,); covariance (M, M): the Cramér-Rao
    bound at the estimate in the chosen gauge (zero rows for held parameters);
    std: term -> (K, P) standard deviations, NaN where not fitted or held;
    held: names of the parameters held to fix the gauge; gauge: one line per
    fixed gauge direction; gauge_directions (M, q): orthonormal basis (SI
    units) of the gauge freedoms, to first order theta + gauge_directions @ c
    predicts the same readings for any c (the motion changing with it);
    loglik_before/after: log-likelihood at the initial parameters (motion
    fitted to them) and at the estimate; nis_before/after:
    sum of squared normalised residuals / degrees of freedom (valid axes -
    9 samples_used - estimated parameters), ~1 for a correct model;
    iterations, converged; samples_used (samples_dropped: no motion information);
    motion (N, 9) [omega, omega_dot, s] in the array frame (NaN where dropped);
    residuals (N, K, 6) normalised (y - h) / sigma, NaN on masked axes and dropped samples.
    """

    model: SensorModel
    free: tuple[str, ...]
    imus: tuple[str, ...]
    parameter_names: list[str]
    theta: np.ndarray
    covariance: np.ndarray
    std: dict[str, np.ndarray]
    held: list[str]
    gauge: list[str]
    gauge_directions: np.ndarray = field(repr=False)
    loglik_before: float
    loglik_after: float
    nis_before: float
    nis_after: float
    iterations: int
    converged: bool
    samples_used: int
    samples_dropped: int
    dof: int
    motion: np.ndarray = field(repr=False)
    residuals: np.ndarray = field(repr=False)


def fit_terms(samples: ImuSamples, model: SensorModel, free: Sequence[str], *, imus=None, reference=None,
              gauge: str = "reference", motion0=None, max_iterations: int = 50, tolerance: float = 1e-3,
              progress: Callable[[int, float], None] | None = None, motion_model=None, sigma=None,
              only: dict | None = None) -> FitResult:
    """Maximum likelihood of the ``free`` terms' parameters jointly with every sample's motion.

    samples: the readings (:class:`~imu_array_ros.model.samples.ImuSamples`: stamps (N,) int64 ns,
    accel, gyro (N, K, 3) in the sensor frames; NaN: missing; clipped readings are masked by
    ``model.valid``);
    model: the initial values of every term (the non-free terms are held);
    free: registry names of the terms to fit; imus: names or indexes of the
    IMUs whose parameters are fitted (default all; the others are held);
    reference: IMU (name or index, among ``imus``) whose parameters fix the
    gauge (default the first fitted IMU); gauge: "reference" (hold the
    reference's parameters, see the module docstring) or "mean" (keep the
    parameters' component along every gauge freedom, e.g. the centroid of the
    positions, at its initial value);
    motion0: (N, 9) initial [omega, omega_dot, s] (default: from the readings);
    tolerance: converged when every parameter step is below ``tolerance``
    standard deviations and the RMS motion step below ``tolerance`` of its own;
    progress(iteration, cost): called once per iteration, cost = sum of
    squared normalised residuals / 2;
    motion_model: how each sample's motion is parametrised
    (:mod:`~imu_array_ros.fitting.motion_models`; default
    :class:`~imu_array_ros.fitting.motion_models.RigidMotion`, any motion;
    :class:`~imu_array_ros.fitting.motion_models.StaticMotion` for poses at
    rest on gravity of known magnitude); sigma: (N, K, 6) standard deviations
    of the readings [acc, gyro] replacing the model's noise figures (e.g. of
    averages over still intervals, or robust reweighting); only: term -> IMUs
    (names or indexes) where that free term is fitted, the term held on the
    other IMUs of ``imus`` (e.g. the findings of mismatch discovery: one term
    on one IMU, another on another; default every free term on every fitted
    IMU; with ``only``, a gauge freedom left is fixed by holding parameters as
    with gauge="reference", whatever ``gauge`` says).  Raises
    :class:`CalibrationError` (one line) when the problem cannot be solved or
    identified.
    """
    free = check_terms(free)
    if gauge not in ("reference", "mean"):
        raise CalibrationError(f"gauge must be 'reference' or 'mean', got {gauge!r}")
    fit = imu_indexes(model.names, imus, "imus")
    ref = _reference(model, fit, reference)
    prob = _Problem(samples, model, free, fit, motion_model=motion_model, sigma=sigma)
    motion = prob.initial_motion(model) if motion0 is None else prob.check_motion(motion0)
    motion, lin = prob.fit_motion(model, motion)
    motion = prob.drop(~lin.ok, motion)
    prob.check_dof(prob.m)
    lin = prob.linearize(model, motion)  # with the free parameters, at the initial point
    gauge_fix = _Gauge.find(prob, model, motion, lin, ref, gauge, _fixed(prob, model, only))
    dof = prob.check_dof(gauge_fix.rank)
    before = lin.cost
    model, motion, lin, iterations, converged = _optimise(prob, model, motion, lin, gauge_fix, max_iterations,
                                                          tolerance, progress)
    return _result(prob, model, motion, lin, gauge_fix, before, dof, iterations, converged)


def fit_motion(samples: ImuSamples, model: SensorModel, motion0=None, *, motion_model=None,
               sigma=None) -> tuple[np.ndarray, float, np.ndarray]:
    """The ML motion of every sample with every term of ``model`` held (the engine's batched
    Gauss-Newton on each sample's motion coordinates, exact for the non-linear terms the fusion only
    compensates).  motion_model, sigma: as for :func:`fit_terms`.

    Returns (motion (N, 9) [omega, omega_dot, s], log-likelihood over the valid axes, normalised
    residuals (N, K, 6), NaN on masked axes).  A sample whose motion is not identified keeps a
    ridge-regularised estimate."""
    prob = _Problem(samples, model, ("position",), np.arange(model.n_imus), motion_model=motion_model,
                    sigma=sigma)
    motion = prob.initial_motion(model) if motion0 is None else prob.check_motion(motion0)
    motion, lin = prob.fit_motion(model, motion)
    return prob.expand(motion), _loglik(prob, lin.cost), np.where(prob.valid, lin.r, np.nan)


@dataclass
class ScoreBlocks:
    """Score and Fisher information of candidate terms, per time block and IMU, with the motion profiled out.

    terms: the candidate terms; offsets: term -> first column in the per-IMU
    parameter vector (P = sum of the terms' sizes); g (B, K, P): score
    d loglik / d theta_k summed over block b (each IMU's parameters alone,
    every other held); S (B, K, P, P): the information of IMU k's parameters
    in block b with every sample's motion profiled out (the per-IMU diagonal
    block of the engine's Schur complement; block sums add up to it);
    counts (B,) samples per block; residuals (N, K, 6) normalised, NaN on
    masked axes and on samples that do not identify their motion; expected (N,
    K, 6): E[r^2] = 1 - leverage of each valid axis (leverage: what the fitted
    motion absorbs, 9 per sample), NaN where masked; cost: sum r^2 / 2;
    loglik: log-likelihood of the valid axes; valid_axes: their number.
    """

    terms: tuple[str, ...]
    offsets: dict[str, int]
    g: np.ndarray
    S: np.ndarray
    counts: np.ndarray
    residuals: np.ndarray = field(repr=False)
    expected: np.ndarray = field(repr=False)
    cost: float = 0.0
    loglik: float = 0.0
    valid_axes: int = 0

    def columns(self, term: str) -> slice:
        return slice(self.offsets[term], self.offsets[term] + REGISTRY[term].dim())


def score_blocks(samples: ImuSamples, model: SensorModel, terms: Sequence[str], motion, blocks, *,
                 sigma=None) -> ScoreBlocks:
    """Score test ingredients of every term in ``terms`` on every IMU at (model, motion), by time block.

    ``motion`` (N, 9): the ML motion for ``model`` (:func:`fit_motion`);
    blocks (N,) non-decreasing block index 0..B-1 of every sample (contiguous
    blocks).  For the parameters theta_k of one IMU, g_k = J_t,k^T r -
    sum_n G_n,k^T h_n and S_kk = C_kk - sum_n G_n,k^T G_n,k (module docstring)
    are the score and information of the one-step Gauss-Newton fit of theta_k
    with every sample's motion re-estimated: g^T S^-1 g is the Rao score
    statistic of adding the term to that IMU (chi-square under the model) and
    g^T S^-1 g / 2 the log-likelihood it gains to first order.  Per block, so
    that held-out blocks and a block-robust (sandwich) variance can be formed.
    """
    terms = check_terms(terms)
    k = model.n_imus
    prob = _Problem(samples, model, terms, np.arange(k), sigma=sigma)
    blocks = np.asarray(blocks, dtype=np.int64).reshape(-1)
    if blocks.shape != (prob.n,) or blocks.min() < 0 or np.any(np.diff(blocks) < 0):
        raise CalibrationError("blocks must give a non-decreasing block index >= 0 for every sample")
    z = prob.check_motion(motion)
    derivs = prob.derivatives(z)
    nb, p = int(blocks[-1]) + 1, prob.p
    g, S = np.zeros((nb, k, p)), np.zeros((nb, k, p, p))
    res, expected = np.full_like(prob.y, np.nan), np.full_like(prob.y, np.nan)
    cost = 0.0
    mask = np.zeros(prob.y.shape, dtype=bool)
    edges = np.flatnonzero(np.diff(blocks)) + 1
    for b, (lo0, hi0) in zip(blocks[np.r_[0, edges]], zip(np.r_[0, edges], np.r_[edges, prob.n])):
        for lo in range(lo0, hi0, prob.chunk):
            hi = min(lo + prob.chunk, hi0)
            jac = model.jacobians(prob.context(model, z, derivs, lo, hi), terms)
            linv, ok = _factor(_gram(prob.motion_jacobian(jac.motion, prob.w[lo:hi], z, slice(lo, hi))))
            w = prob.w[lo:hi] * ok[:, None, None]  # a sample that does not identify its motion tells nothing
            r = w * (prob.y[lo:hi] - jac.predicted)
            jx = prob.motion_jacobian(jac.motion, w, z, slice(lo, hi))
            h = np.einsum("nij,nkrj,nkr->ni", linv, jx, r, optimize=True)
            jt = prob.parameter_jacobian(jac, w)
            jk = _per_imu(jt)
            mk = np.matmul(jx, linv.transpose(0, 2, 1)[:, None])  # (n, K, 6, 9): rows (L^-1 phi)^T
            gk = np.matmul(mk.transpose(0, 1, 3, 2), jt)  # (n, K, 9, P) G_n,k
            gs = gk.transpose(1, 0, 2, 3).reshape(k, -1, p)
            S[b] += np.matmul(jk.transpose(0, 2, 1), jk) - np.matmul(gs.transpose(0, 2, 1), gs)
            g[b] += (np.matmul(jk.transpose(0, 2, 1), r.transpose(1, 0, 2).reshape(k, -1, 1))[..., 0]
                     - np.einsum("nkip,ni->kp", gk, h))
            valid = prob.valid[lo:hi] & ok[:, None, None]
            mask[lo:hi] = valid
            res[lo:hi] = np.where(valid, r, np.nan)
            expected[lo:hi] = np.where(valid, 1.0 - np.sum(mk * mk, axis=3), np.nan)
            cost += 0.5 * float(np.sum(r * r))
    loglik = float(-cost + np.sum(np.log(prob.w[mask])) - 0.5 * int(mask.sum()) * np.log(2 * np.pi))
    offsets = {t: int(o) for t, o in zip(terms, np.cumsum([0] + prob.sizes[:-1]))}
    return ScoreBlocks(terms, offsets, g, S, np.bincount(blocks, minlength=nb), res, expected, cost, loglik,
                       int(mask.sum()))


# --------------------------------------------------------------------------- input checks


def check_terms(free: Sequence[str]) -> tuple[str, ...]:
    """``free`` as a tuple of known registry names without repeats; CalibrationError otherwise."""
    if isinstance(free, str):
        free = [free]
    out = tuple(dict.fromkeys(free))
    if not out:
        raise CalibrationError(f"no free terms to fit: name at least one term (known: {', '.join(term_names())})")
    unknown = [n for n in out if n not in REGISTRY]
    if unknown:
        raise CalibrationError(f"unknown term {unknown[0]!r} in free (known: {', '.join(term_names())})")
    return out


def _fixed(prob: "_Problem", model: SensorModel, only: dict | None) -> np.ndarray:
    """(M,) True for the parameters ``only`` holds (its term not fitted on that IMU)."""
    fixed = np.zeros(prob.m, dtype=bool)
    if not only:
        return fixed
    unknown = [t for t in only if t not in prob.free]
    if unknown:
        raise CalibrationError(f"only: term {unknown[0]!r} is not among the free terms ({', '.join(prob.free)})")
    offsets = dict(zip(prob.free, np.cumsum([0] + prob.sizes[:-1])))
    for t, imus in only.items():
        on = set(imu_indexes(model.names, imus, f"only[{t!r}]").tolist())
        for j, k in enumerate(prob.fit):
            if k not in on:
                lo = j * prob.p + offsets[t]
                fixed[lo:lo + REGISTRY[t].dim()] = True
    if fixed.all():
        raise CalibrationError("only: no parameter left to fit")
    return fixed


def _reference(model: SensorModel, fit: np.ndarray, reference) -> int:
    """Position of the reference IMU within the fitted ones (:func:`~imu_array_ros.model.reference.reference_index`)."""
    return int(np.flatnonzero(fit == reference_index(model.names, reference, among=fit))[0])


# --------------------------------------------------------------------------- the problem and its linearisation


@dataclass
class _Linearization:
    """The Gauss-Newton system at one point (theta, x), Schur-complemented.

    cost: sum r^2 / 2; S (M, M), g (M,): reduced information and right-hand
    side over every candidate parameter; cdiag (M,): diag(C) (information of
    each parameter with the motion known); linv (N, 9, 9): L_n^-1; h (N, 9):
    L_n^-1 gx_n; ok (N,): A_n positive definite (the sample identifies its
    motion); r (N, K, 6) normalised residuals (0 on masked axes); derivs: the
    motion derivatives held fixed in it.
    """

    cost: float
    S: np.ndarray
    g: np.ndarray
    cdiag: np.ndarray
    linv: np.ndarray
    h: np.ndarray
    ok: np.ndarray
    r: np.ndarray
    derivs: tuple


class _Problem:
    """Readings, weights and the parameter layout: fitted IMUs x free terms' parameters, IMU-major."""

    def __init__(self, samples: ImuSamples, model: SensorModel, free: tuple[str, ...], fit: np.ndarray, *,
                 motion_model=None, sigma=None):
        stamps = samples.stamps
        n, k = len(stamps), model.n_imus
        if tuple(samples.names) != tuple(model.names):
            raise CalibrationError(f"the samples are of IMUs {', '.join(samples.names[:4])}..., the model of "
                                   f"{', '.join(model.names[:4])}...")
        if n < 3:
            raise CalibrationError(f"too few samples: {n} (the motion of every sample is unknown; record longer)")
        self.model0 = model
        self.stamps, self.free, self.fit = stamps, free, fit
        self.cols = slice(None) if len(fit) == k else fit  # the fitted IMUs, a view when all are
        self.t0_ns = int(stamps[0])
        self.raw = samples.readings
        valid = samples.valid(model)
        if not valid.any():
            raise CalibrationError("no valid samples: every reading is missing or saturated")
        self.y = np.where(valid, self.raw, 0.0)
        if sigma is None:
            self.w = valid / model.std[None]
        else:
            sigma = np.broadcast_to(np.asarray(sigma, dtype=float), (n, k, 6))
            if not np.all(np.isfinite(sigma[valid]) & (sigma[valid] > 0)):
                raise CalibrationError("sigma must be positive and finite on every valid reading")
            self.w = np.where(valid, 1.0 / np.where(valid, sigma, 1.0), 0.0)
        self.valid = valid
        self.mm = RigidMotion() if motion_model is None else motion_model
        self.dm = self.mm.dim
        self.used = np.ones(n, dtype=bool)
        self.sizes = [REGISTRY[t].dim() for t in free]
        self.p = sum(self.sizes)
        self.needs_derivatives = "time_offset" in free or not model.terms["time_offset"].is_identity
        if self.needs_derivatives and np.any(np.diff(stamps) <= 0):
            raise CalibrationError("stamps must increase strictly (time offsets need the motion's time derivatives)")
        per_sample = 8 * (4 * 6 * k * (9 + self.p) + 2 * self.dm * self.m + 20 * 81)
        self.chunk = int(np.clip(CHUNK_BYTES // per_sample, 16, n))

    # ---- layout
    @property
    def n(self) -> int:
        return len(self.stamps)

    @property
    def m(self) -> int:
        return len(self.fit) * self.p

    def n_used(self) -> int:
        return int(self.used.sum())

    def n_valid(self) -> int:
        return int(self.valid[self.used].sum())

    def values(self, model: SensorModel) -> np.ndarray:
        """(K_fit, P) the free parameters of the fitted IMUs."""
        return np.concatenate([model.terms[t].values[self.fit] for t in self.free], axis=1)

    def with_values(self, model: SensorModel, theta: np.ndarray) -> SensorModel:
        theta = theta.reshape(len(self.fit), self.p)
        new, col = {}, 0
        for t, size in zip(self.free, self.sizes):
            v = model.terms[t].values.copy()
            v[self.fit] = theta[:, col:col + size]
            new[t] = v
            col += size
        return model.with_terms(**new)

    def parameter_names(self) -> list[str]:
        per_imu = [name for t in self.free for name in REGISTRY[t].parameter_names()]
        return [f"{self.model0.names[k]} {name}" for k in self.fit for name in per_imu]

    def column_terms(self) -> list[str]:
        """(M,) the term of every parameter."""
        return [t for _ in self.fit for t, size in zip(self.free, self.sizes) for _ in range(size)]

    def drop(self, bad: np.ndarray, motion: np.ndarray) -> np.ndarray:
        """Samples whose motion is not identified leave the problem (weight 0); their motion is
        interpolated from the others (it enters the time derivatives of the neighbours)."""
        self.used &= ~bad
        self.w[bad] = 0.0
        if not self.used.any():
            raise CalibrationError("no valid samples: no sample has enough valid axes to determine its motion")
        if not bad.any():
            return motion
        t, used = self.stamps - self.t0_ns, np.flatnonzero(self.used)
        return np.stack([np.interp(t, t[used], motion[used, i]) for i in range(motion.shape[1])], axis=1)

    def check_dof(self, parameters: int) -> int:
        """Degrees of freedom left (valid axes - motion coordinates - parameters); CalibrationError if none."""
        dof = self.n_valid() - self.dm * self.n_used() - parameters
        if dof <= 0:
            raise CalibrationError(f"too few samples: {self.n_used()} usable samples cannot determine their motion "
                                   f"and {parameters} parameters (no degrees of freedom left); record longer")
        return dof

    def check_motion(self, motion0) -> np.ndarray:
        """The motion model's coordinates of an (N, 9) initial motion [omega, omega_dot, s]."""
        motion = np.array(motion0, dtype=float)
        if motion.shape != (self.n, 9) or not np.isfinite(motion).all():
            raise CalibrationError(f"motion0 must be finite with shape {(self.n, 9)}, got {motion.shape}")
        return self.mm.initial(motion)

    def expand(self, z: np.ndarray, sel=slice(None)) -> np.ndarray:
        """(n, 9) motion [omega, omega_dot, s] of the samples ``sel`` from their coordinates ``z[sel]``."""
        return self.mm.expand(z[sel], sel)

    def motion_jacobian(self, jac_motion: np.ndarray, w: np.ndarray, z: np.ndarray, sel) -> np.ndarray:
        """(n, K, 6, dm) weighted d y / d z from the model's (n, K, 6, 9) d y / d x."""
        jx = jac_motion * w[..., None]
        d = self.mm.jacobian(z[sel], sel)
        return jx if d is None else np.matmul(jx, d[:, None])

    # ---- evaluation
    def chunks(self):
        for lo in range(0, self.n, self.chunk):
            yield lo, min(lo + self.chunk, self.n)

    def derivatives(self, motion: np.ndarray) -> tuple:
        """(omega_ddot, specific_force_dot) of the whole recording, or (None, None) when no term reads them."""
        if not self.needs_derivatives:
            return None, None
        x = self.expand(motion)
        return motion_derivative(self.stamps, x[:, 3:6]), motion_derivative(self.stamps, x[:, 6:9])

    def context(self, model: SensorModel, motion: np.ndarray, derivs: tuple, lo: int, hi: int):
        return self.context_at(model, motion, derivs, slice(lo, hi))

    def context_at(self, model: SensorModel, motion: np.ndarray, derivs: tuple, sel):
        """The motion context of the samples ``sel`` (slice or indexes); ``motion`` and ``derivs`` whole."""
        cut = lambda a: None if a is None else a[sel]  # noqa: E731
        x = self.expand(motion, sel)
        return motion_context(self.stamps[sel], x[:, 0:3], x[:, 3:6], x[:, 6:9],
                              model.rotations, t0_ns=self.t0_ns, omega_ddot=cut(derivs[0]),
                              specific_force_dot=cut(derivs[1]))

    def residuals(self, model: SensorModel, motion: np.ndarray, derivs: tuple) -> np.ndarray:
        """(N, K, 6) normalised residuals w (y - h), 0 on masked axes, with the motion derivatives ``derivs``."""
        out = np.empty_like(self.y)
        for lo, hi in self.chunks():
            acc, gyr = model.predict(self.context(model, motion, derivs, lo, hi))
            out[lo:hi] = self.w[lo:hi] * (self.y[lo:hi] - np.concatenate([acc, gyr], axis=2))
        return out

    def linearize(self, model: SensorModel, motion: np.ndarray, *, free: bool = True) -> _Linearization:
        """The Schur-complemented Gauss-Newton system at (model, motion); ``free=False``: motion only."""
        m = self.m if free else 0
        kf, p = len(self.fit), self.p
        S, g = np.zeros((m, m)), np.zeros(m)
        cblocks, gt = np.zeros((kf, p, p)), np.zeros((kf, p))
        linv, h = np.empty((self.n, self.dm, self.dm)), np.empty((self.n, self.dm))
        ok, r_all = np.empty(self.n, dtype=bool), np.empty_like(self.y)
        derivs = self.derivatives(motion)
        for lo, hi in self.chunks():
            jac = model.jacobians(self.context(model, motion, derivs, lo, hi), self.free if m else ())
            w = self.w[lo:hi]
            r = w * (self.y[lo:hi] - jac.predicted)
            jx = self.motion_jacobian(jac.motion, w, motion, slice(lo, hi))  # (n, K, 6, dm)
            linv[lo:hi], ok[lo:hi] = _factor(_gram(jx))
            h[lo:hi] = np.einsum("nij,nkrj,nkr->ni", linv[lo:hi], jx, r, optimize=True)
            r_all[lo:hi] = r
            if m:
                jt = self.parameter_jacobian(jac, w)
                _accumulate_c(cblocks, gt, jt, r[:, self.cols])
                gmat = _stacked_g(jx[:, self.cols], linv[lo:hi], jt)  # (9 n, M)
                S -= gmat.T @ gmat
                g -= gmat.T @ h[lo:hi].reshape(-1)
        if m:
            S += scipy.linalg.block_diag(*cblocks)
            g += gt.reshape(-1)
        cdiag = np.einsum("kpp->kp", cblocks).reshape(-1)[:m]
        return _Linearization(0.5 * float(np.sum(r_all * r_all)), S, g, cdiag, linv, h, ok, r_all, derivs)

    def parameter_jacobian(self, jac, w: np.ndarray) -> np.ndarray:
        """(n, K_fit, 6, P) weighted d y / d theta of the fitted IMUs, free terms concatenated."""
        jt = [jac.params[t] for t in self.free]
        jt = jt[0] if len(jt) == 1 else np.concatenate(jt, axis=3)
        return jt[:, self.cols] * w[:, self.cols, :, None]

    def noise_information(self, model: SensorModel, motion: np.ndarray, lin: _Linearization) -> np.ndarray:
        """(M, M) information the motion estimate's own noise would fake: S built (Schur complement and all)
        from dJ_n, the change of the parameter Jacobian when x_n moves by one draw of its noise, N(0, A_n^-1).

        Central difference at x_n +- delta_n (fixed seed), on at most ``NOISE_SAMPLES`` evenly spaced
        used samples, scaled to all of them.
        """
        used = np.flatnonzero(self.used)
        pick = used[::max(1, len(used) // NOISE_SAMPLES)]
        delta = np.einsum("nji,nj->ni", lin.linv[pick],
                          np.random.default_rng(0).normal(size=(len(pick), self.dm)))
        kf, p = len(self.fit), self.p
        info, blocks = np.zeros((self.m, self.m)), np.zeros((kf, p, p))
        for lo in range(0, len(pick), self.chunk):
            sel, d = pick[lo:lo + self.chunk], delta[lo:lo + self.chunk]
            w = self.w[sel]
            jac = []
            for sign in (1.0, -1.0):
                moved = motion.copy()
                moved[sel] += sign * d
                jac.append(model.jacobians(self.context_at(model, moved, lin.derivs, sel), self.free))
            djt = 0.5 * (self.parameter_jacobian(jac[0], w) - self.parameter_jacobian(jac[1], w))
            jx = self.motion_jacobian(0.5 * (jac[0].motion + jac[1].motion)[:, self.cols], w[:, self.cols], motion, sel)
            dk = _per_imu(djt)
            blocks += np.matmul(dk.transpose(0, 2, 1), dk)
            gmat = _stacked_g(jx, lin.linv[sel], djt)
            info -= gmat.T @ gmat
        return (info + scipy.linalg.block_diag(*blocks)) * (len(used) / len(pick))

    def motion_step(self, model: SensorModel, motion: np.ndarray, lin: _Linearization,
                    dtheta: np.ndarray | None) -> np.ndarray:
        """dx_n = L_n^-T (h_n - G_n dtheta) (back-substitution), (N, 9); G_n recomputed chunk by chunk."""
        v = lin.h.copy()
        if dtheta is not None and np.any(dtheta):
            dt = dtheta.reshape(len(self.fit), self.p)
            for lo, hi in self.chunks():
                jac = model.jacobians(self.context(model, motion, lin.derivs, lo, hi), self.free)
                w = self.w[lo:hi]
                u = np.einsum("nkrp,kp->nkr", self.parameter_jacobian(jac, w), dt)  # J_t dtheta per IMU
                jx = self.motion_jacobian(jac.motion[:, self.cols], w[:, self.cols], motion, slice(lo, hi))
                bdt = np.einsum("nkri,nkr->ni", jx, u)
                v[lo:hi] -= np.einsum("nij,nj->ni", lin.linv[lo:hi], bdt)
        return np.einsum("nji,nj->ni", lin.linv, v)

    # ---- the motion alone
    def initial_motion(self, model: SensorModel) -> np.ndarray:
        """Readings mapped to the array frame and averaged (clipped readings included: a lower bound is a
        better start than nothing); omega_dot by differentiating omega.  Refined by :meth:`fit_motion`."""
        def average(y, std):
            wt = np.isfinite(y) / std[None] ** 2  # (N, K, 3)
            rot = model.rotations
            mat = np.einsum("kia,nka,kja->nij", rot, wt, rot)
            rhs = np.einsum("kia,nka->ni", rot, wt * np.nan_to_num(y))
            mat += 1e-12 * np.trace(mat, axis1=1, axis2=2)[:, None, None] * np.eye(3) + 1e-300 * np.eye(3)
            return np.linalg.solve(mat, rhs[..., None])[..., 0]
        omega = average(self.raw[..., 3:], model.gyro_std)
        s = average(self.raw[..., :3], model.acc_std)
        return self.mm.initial(np.concatenate([omega, motion_derivative(self.stamps, omega), s], axis=1))

    def fit_motion(self, model: SensorModel, motion: np.ndarray, tolerance: float = 1e-4):
        """Motion-only Gauss-Newton for fixed parameters (batched 9x9 steps), step halving per sample.

        Returns the motion and the motion-only linearisation at it (whose ``ok`` flags the samples that
        identify their motion)."""
        for _ in range(MOTION_ITERATIONS):
            lin = self.linearize(model, motion, free=False)
            if not lin.ok.any() or np.mean(np.sum(lin.h[lin.ok] ** 2, axis=1)) < tolerance ** 2:
                return motion, lin
            step = self.motion_step(model, motion, lin, None)
            cost0 = 0.5 * np.sum(lin.r ** 2, axis=(1, 2))
            t, todo = 1.0, np.ones(self.n, dtype=bool)
            new = motion.copy()
            for _ in range(10):  # halve the step where a sample's cost went up
                trial = np.where(todo[:, None], motion + t * step, new)
                cost = 0.5 * np.sum(self.residuals(model, trial, lin.derivs) ** 2, axis=(1, 2))
                better = todo & (cost <= cost0)
                new[better] = trial[better]
                todo &= ~better
                if not todo.any():
                    break
                t *= 0.5
            motion = new
        return motion, self.linearize(model, motion, free=False)


def _gram(jx: np.ndarray) -> np.ndarray:
    """(n, K, 6, d) -> A_n = J_x^T J_x (n, d, d)."""
    j = jx.reshape(len(jx), -1, jx.shape[-1])
    return np.matmul(j.transpose(0, 2, 1), j)


def _factor(a: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """L^-1 of A = L L^T for each (n, 9, 9) matrix, and ok (n,): numerically positive definite.

    Jacobi-scaled first (A = D An D); where An's smallest eigenvalue is below
    ``MOTION_RTOL`` the sample does not identify its motion: ok is False and a
    ridge keeps the factor finite (such samples are dropped after the initial
    motion fit, weight 0).
    """
    d = np.sqrt(np.einsum("nii->ni", a))
    d = np.where(d > 0, d, 1.0)
    an = a / (d[:, :, None] * d[:, None, :])
    ok = np.linalg.eigvalsh(an)[:, 0] > MOTION_RTOL
    an[~ok] += np.eye(a.shape[-1])
    lower = np.linalg.cholesky(an)
    return np.linalg.inv(lower) / d[:, None, :], ok


def _per_imu(jt: np.ndarray) -> np.ndarray:
    """(n, K_fit, 6, P) -> (K_fit, 6 n, P): each IMU's rows over the chunk's samples."""
    return jt.transpose(1, 0, 2, 3).reshape(jt.shape[1], -1, jt.shape[3])


def _accumulate_c(cblocks: np.ndarray, gt: np.ndarray, jt: np.ndarray, r: np.ndarray) -> None:
    """C_k += J_t,k^T J_t,k and gt_k += J_t,k^T r_k over the chunk; jt (n, K_fit, 6, P), r (n, K_fit, 6)."""
    jk = _per_imu(jt)
    cblocks += np.matmul(jk.transpose(0, 2, 1), jk)
    gt += np.matmul(jk.transpose(0, 2, 1), r.transpose(1, 0, 2).reshape(len(jk), -1, 1))[..., 0]


def _stacked_g(jx: np.ndarray, linv: np.ndarray, jt: np.ndarray) -> np.ndarray:
    """G_n = L_n^-1 B_n stacked over the chunk: (9 n, K_fit P).

    B_n is block-structured by IMU (B_n,k = J_x,k^T J_t,k): with M_n,k = J_x,k L_n^-T (6 x 9),
    G_n,k = M_n,k^T J_t,k, one batched product over (n, k).
    """
    n, kf, _, p = jt.shape
    d = jx.shape[-1]
    mk = np.matmul(jx, linv.transpose(0, 2, 1)[:, None])  # (n, K_fit, 6, d)
    gk = np.matmul(mk.transpose(0, 1, 3, 2), jt)  # (n, K_fit, d, P)
    return gk.transpose(0, 2, 1, 3).reshape(d * n, kf * p)


# --------------------------------------------------------------------------- gauge


@dataclass
class _Gauge:
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
    def find(cls, prob: _Problem, model: SensorModel, motion: np.ndarray, lin: _Linearization, ref: int,
             mode: str, fixed: np.ndarray | None = None) -> "_Gauge":
        """Null space of the scaled S at the structural point, holds, then the check that what is left is
        identified by the motion itself (:func:`_check_excitation`); CalibrationError if anything is not.
        ``fixed`` (M,): parameters held from the start (``only``), outside every search."""
        structural = _structural(model)
        if structural is not model:
            lin = prob.linearize(structural, motion)
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
            raise CalibrationError(_unidentifiable_message(rest, names, prob.column_terms()))
        directions = np.linalg.qr(null / scale[:, None])[0]  # gauge freedoms in SI units
        if mode == "reference" or not held or not act.all():
            keep = act.copy()
            keep[held] = False
            gauge = cls(keep, None, held, [f"{names[i]} held" for i in held], directions, ~act)
        else:
            basis = scipy.linalg.null_space(directions.T)
            gauge = cls(np.ones(prob.m, dtype=bool), basis, [],
                        [f"{_combination(d, names)} kept at its initial value" for d in directions.T], directions)
        _check_excitation(prob, structural, motion, lin, gauge, scale)
        return gauge


def _check_excitation(prob: _Problem, model: SensorModel, motion: np.ndarray, lin: _Linearization, gauge: _Gauge,
                      scale: np.ndarray) -> None:
    """CalibrationError for directions whose information comes mostly from the noise of the motion estimate.

    At the estimated motion, motion that is really absent (e.g. the angular
    acceleration about x and y when the array turns about z only) is replaced
    by its estimation noise, which fakes a little information about the
    parameters it would excite: S is not singular there.  F, the information
    that noise alone produces (:meth:`_Problem.noise_information`), is compared
    with S in the gauge-fixed space: directions with v^T F v > NOISE_SHARE v^T S v
    (generalised eigenvalues of (F, S)) are not identified by the recording.
    """
    s_z = gauge.reduce(lin.S, lin.g)[0]
    f_z = gauge.reduce(prob.noise_information(model, motion, lin), lin.g)[0]
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
        raise CalibrationError(_unidentifiable_message(rest, prob.parameter_names(), prob.column_terms()))


def _structural(model: SensorModel) -> SensorModel:
    """The model with every term but the positions at its identity value (``model`` itself if it is so)."""
    reset = {n: t.default_values(model.n_imus) for n, t in model.terms.items() if n != "position" and not t.is_identity}
    return model.with_terms(**reset) if reset else model


def _hold_gauge(null: np.ndarray, prob: _Problem, ref: int) -> tuple[list[int], np.ndarray]:
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
    offsets = dict(zip(prob.free, np.cumsum([0] + prob.sizes[:-1])))
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


def _unidentifiable_message(rest: np.ndarray, names: list[str], terms: list[str], top: int = 6) -> str:
    """One line naming the parameters in the unidentifiable directions and the motion that would help."""
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


# --------------------------------------------------------------------------- optimisation


def _optimise(prob: _Problem, model: SensorModel, motion: np.ndarray, lin: _Linearization, gauge: _Gauge,
              max_iterations: int, tolerance: float, progress):
    """Levenberg-Marquardt on the reduced system; returns (model, motion, lin, iterations, converged)."""
    lam, iterations, converged = 0.0, 0, False
    for _ in range(max_iterations):
        if progress is not None:
            progress(iterations, lin.cost)
        s_z, g_z = gauge.reduce(lin.S, lin.g)
        cov_z = _inverse(s_z)
        step_z = cov_z @ g_z
        motion_rms = np.sqrt(np.mean(np.sum(lin.h[prob.used] ** 2, axis=1)))
        if np.max(np.abs(step_z) / np.sqrt(np.diag(cov_z)), initial=0.0) < tolerance and motion_rms < tolerance:
            converged = True
            break
        while True:
            dz = step_z if lam == 0 else _solve_damped(s_z, g_z, lam)
            dtheta = gauge.expand(dz)
            new_model = prob.with_values(model, prob.values(model).reshape(-1) + dtheta)
            new_motion = motion + prob.motion_step(model, motion, lin, dtheta)
            r = prob.residuals(new_model, new_motion, lin.derivs)  # the derivatives held, as in the step
            cost = 0.5 * float(np.sum(r * r))
            if cost <= lin.cost:
                lam = lam / 10 if lam > 1e-6 else 0.0
                break
            lam = max(1e-4, 10 * lam)
            if lam > 1e8:  # no step lowers the cost: stalled short of the tolerance
                return model, motion, lin, iterations, False
        model, motion = new_model, new_motion
        iterations += 1
        lin = prob.linearize(model, motion)
    return model, motion, lin, iterations, converged


def _inverse(s: np.ndarray) -> np.ndarray:
    """Inverse of a symmetric positive definite matrix, Jacobi-scaled Cholesky."""
    if s.size == 0:
        return s.copy()
    d = np.sqrt(np.diag(s))
    d = np.where(d > 0, d, 1.0)
    try:
        factor = scipy.linalg.cho_factor(s / np.outer(d, d))
    except np.linalg.LinAlgError:
        raise CalibrationError("the free parameters are not identifiable at the current estimate "
                               "(Fisher information singular); record more varied motion") from None
    return scipy.linalg.cho_solve(factor, np.eye(len(s))) / np.outer(d, d)


def _solve_damped(s: np.ndarray, g: np.ndarray, lam: float) -> np.ndarray:
    return np.linalg.solve(s + lam * np.diag(np.diag(s)), g)


# --------------------------------------------------------------------------- result


def _loglik(prob: _Problem, cost: float) -> float:
    """log p(y) at a point with cost sum r^2 / 2, over the valid axes of the samples used."""
    mask = prob.valid & prob.used[:, None, None]
    return float(-cost + np.sum(np.log(prob.w[mask])) - 0.5 * int(mask.sum()) * np.log(2 * np.pi))


def _result(prob: _Problem, model: SensorModel, motion: np.ndarray, lin: _Linearization, gauge: _Gauge,
            before: float, dof: int, iterations: int, converged: bool) -> FitResult:
    s_z, _ = gauge.reduce(lin.S, lin.g)
    cov = gauge.expand_covariance(_inverse(s_z))
    std_flat = np.sqrt(np.clip(np.diag(cov), 0.0, None)).reshape(len(prob.fit), prob.p)
    std_flat[np.unravel_index(np.array(gauge.held, dtype=int), std_flat.shape)] = np.nan
    if gauge.fixed is not None:
        std_flat.reshape(-1)[gauge.fixed] = np.nan
    std, col = {}, 0
    for t, size in zip(prob.free, prob.sizes):
        full = np.full((model.n_imus, size), np.nan)
        full[prob.fit] = std_flat[:, col:col + size]
        std[t] = full
        col += size
    names = prob.parameter_names()
    mask = ~(prob.valid & prob.used[:, None, None])
    residuals = np.where(mask, np.nan, lin.r)
    motion = np.where(prob.used[:, None], prob.expand(motion), np.nan)
    return FitResult(model=model, free=prob.free, imus=tuple(model.names[k] for k in prob.fit),
                     parameter_names=names, theta=prob.values(model).reshape(-1), covariance=cov, std=std,
                     held=[names[i] for i in gauge.held], gauge=gauge.lines, gauge_directions=gauge.directions,
                     loglik_before=_loglik(prob, before), loglik_after=_loglik(prob, lin.cost),
                     nis_before=2 * before / dof, nis_after=2 * lin.cost / dof, iterations=iterations,
                     converged=converged, samples_used=prob.n_used(), samples_dropped=prob.n - prob.n_used(),
                     dof=dof, motion=motion, residuals=residuals)
