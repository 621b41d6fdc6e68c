"""The fitting problem: readings, weights, the parameter layout (fitted IMUs x free terms' parameters,
IMU-major) and the Schur-complemented Gauss-Newton system at a point, with the motion-only fit (theory
and notation: :mod:`imu_array_ros.fitting`)."""

from __future__ import annotations

import contextlib
import contextvars
from dataclasses import dataclass
from typing import Sequence

import numpy as np
import scipy.linalg

from imu_array_ros.errors import CalibrationError
from imu_array_ros.fitting.motion_models import RigidMotion
from imu_array_ros.fitting.reading_rates import RATES, chip_clock, rate_columns, rates_on
from imu_array_ros.fitting.schur import accumulate_c, factor, gram, stacked_g
from imu_array_ros.model.samples import ImuSamples
from imu_array_ros.model.sensor_model import SensorModel, motion_context, motion_derivative
from imu_array_ros.model import trajectory
from imu_array_ros.model.terms import REGISTRY, term_names
from imu_array_ros.model.terms.timing import TimingTerm
from imu_array_ros.util.names import did_you_mean

__all__ = ["Problem", "Linearization", "check_terms", "keep_schur", "CHUNK_BYTES", "KEEP_G_BYTES", "MOTION_ITERATIONS"]

#: working memory per chunk of samples (Jacobians and the stacked G of the Schur complement)
CHUNK_BYTES = 64 << 20
#: motion-only Gauss-Newton iterations for the initial motion
MOTION_ITERATIONS = 30
#: the largest stacked G (N x 9 x M floats) a linearisation keeps for the motion steps that follow it
#: (:func:`keep_schur`); above it the steps recompute it chunk by chunk as without
KEEP_G_BYTES = 512 << 20
_KEEP_G = contextvars.ContextVar("keep_schur", default=False)


@contextlib.contextmanager
def keep_schur(on: bool = True):
    """Inside (also as a decorator): a problem made without an explicit ``keep_g`` keeps each linearisation's
    G_n = L_n^-1 B_n (:attr:`Linearization.G`, at most ``KEEP_G_BYTES``), so the Levenberg-Marquardt motion
    steps that follow read it instead of a Jacobian pass over every sample of their own (with timing terms as
    costly as the linearisation).  The same step to rounding, not bit-identical (the products are associated
    differently), which is why it is off by default: the calibrations' results stay bit-identical; discovery
    turns it on."""
    token = _KEEP_G.set(bool(on))
    try:
        yield
    finally:
        _KEEP_G.reset(token)


def check_terms(free: Sequence[str]) -> tuple[str, ...]:
    """``free`` as a tuple of known registry names without repeats; CalibrationError otherwise."""
    if isinstance(free, str):
        free = [free]
    out = tuple(dict.fromkeys(free))
    if not out:
        raise CalibrationError(f"no free terms to fit: name at least one term (known: {', '.join(term_names())})")
    unknown = [n for n in out if n not in REGISTRY]
    if unknown:
        near = did_you_mean(unknown[0], term_names())
        raise CalibrationError(f"unknown term {unknown[0]!r}{f'; did you mean {near!r}?' if near else ''} "
                               f"(known: {', '.join(term_names())})")
    return out


@dataclass
class Linearization:
    """The Gauss-Newton system at one point (theta, x), Schur-complemented.

    cost: sum r^2 / 2; S (M, M), g (M,): reduced information and right-hand
    side over every candidate parameter; cdiag (M,): diag(C) (information of
    each parameter with the motion known); linv (N, 9, 9): L_n^-1; h (N, 9):
    L_n^-1 gx_n; ok (N,): A_n positive definite (the sample identifies its
    motion); r (N, K, 6) normalised residuals (0 on masked axes); derivs: the
    motion derivatives held fixed in it; G (N, 9, M): G_n = L_n^-1 B_n when the problem keeps it
    (:func:`keep_schur`), else None; exact (N,): the motion step is the exact Gauss-Newton one (ok, or ok
    but for coordinates no reading informs, which are held: :func:`~imu_array_ros.fitting.schur.factor`).
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
    G: np.ndarray | None = None
    exact: np.ndarray | None = None


class Problem:
    """Readings, weights and the parameter layout: fitted IMUs x free terms' parameters, IMU-major."""

    def __init__(self, samples: ImuSamples, model: SensorModel, free: tuple[str, ...], fit: np.ndarray, *,
                 motion_model=None, sigma=None, t0_ns: int | None = None, keep_g: bool | None = None):
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
        self.t0_ns = int(stamps[0]) if t0_ns is None else int(t0_ns)  # drifts and sample clocks count from it
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
        # each sample's reading rates as motion coordinates after the motion model's (reading_rates)
        self.clock = chip_clock(model) if motion_model is None and rates_on() else None
        self.dm = self.mm.dim + (RATES if self.clock else 0)
        self.used = np.ones(n, dtype=bool)
        self.sizes = [REGISTRY[t].dim() for t in free]
        self.p = sum(self.sizes)
        self.stamp_delays = samples.stamp_delays
        self.needs_derivatives = (model.timed or self.stamp_delays is not None
                                  or any(isinstance(REGISTRY[t], type) and issubclass(REGISTRY[t], TimingTerm)
                                         for t in free))
        if self.needs_derivatives and np.any(np.diff(stamps) <= 0):
            raise CalibrationError("stamps must increase strictly (time offsets need the motion's time derivatives)")
        per_sample = 8 * (4 * 6 * k * (9 + self.p) + 2 * self.dm * self.m + 20 * 81)
        self.chunk = int(np.clip(CHUNK_BYTES // per_sample, 16, n))
        self.keep_g = _KEEP_G.get() if keep_g is None else bool(keep_g)  # Linearization.G (keep_schur)

    # ---- layout
    @property
    def n(self) -> int:
        return len(self.stamps)

    @property
    def m(self) -> int:
        return len(self.fit) * self.p

    @property
    def offsets(self) -> dict[str, int]:
        """term -> its first column in the per-IMU parameter vector (P columns)."""
        return {t: int(o) for t, o in zip(self.free, np.cumsum([0] + self.sizes[:-1]))}

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

    def loglik(self, cost: float, mask: np.ndarray | None = None) -> float:
        """log p(y) at a point with cost sum r^2 / 2, over the valid axes ``mask`` (N, K, 6) (default those of
        the samples used)."""
        if mask is None:
            mask = self.valid & self.used[:, None, None]
        return float(-cost + np.sum(np.log(self.w[mask])) - 0.5 * int(mask.sum()) * np.log(2 * np.pi))

    def check_dof(self, parameters: int) -> int:
        """Degrees of freedom left (valid axes - motion coordinates - parameters); CalibrationError if none."""
        dof = self.n_valid() - self.dm * self.n_used() - parameters
        if dof <= 0:
            raise CalibrationError(f"too few samples: {self.n_used()} usable samples cannot determine their motion "
                                   f"and {parameters} parameters (no degrees of freedom left); record longer")
        return dof

    def check_motion(self, motion0, model: SensorModel | None = None) -> np.ndarray:
        """The motion model's coordinates of an (N, 9) initial motion [omega, omega_dot, s]; with reading rates,
        each sample's rates are the least-squares ones given that motion under ``model`` (default: the
        problem's), as at the joint optimum (they enter linearly)."""
        motion = np.array(motion0, dtype=float)
        if motion.shape != (self.n, 9) or not np.isfinite(motion).all():
            raise CalibrationError(f"motion0 must be finite with shape {(self.n, 9)}, got {motion.shape}")
        return self.with_rates(self.mm.initial(motion), self.model0 if model is None else model)

    def with_rates(self, z: np.ndarray, model: SensorModel) -> np.ndarray:
        """Motion coordinates ``z`` of the motion model, with the reading rates appended (least squares given
        the motion) when the problem carries them."""
        if not self.clock:
            return z
        z = np.concatenate([z, np.zeros((len(z), RATES))], axis=1)
        derivs = self.derivatives(z)
        for lo, hi in self.chunks():
            ctx = self.context(model, z, derivs, lo, hi)
            acc, gyr = model.predict(ctx)
            w = self.w[lo:hi]
            r = (w * (self.y[lo:hi] - np.concatenate([acc, gyr], axis=2))).reshape(hi - lo, -1)
            c = (rate_columns(model, ctx, self.clock) * w[..., None]).reshape(hi - lo, -1, RATES)
            ctc = np.matmul(c.transpose(0, 2, 1), c)
            ctc += 1e-12 * np.trace(ctc, axis1=1, axis2=2)[:, None, None] * np.eye(RATES) + 1e-300 * np.eye(RATES)
            z[lo:hi, -RATES:] = np.linalg.solve(ctc, np.matmul(c.transpose(0, 2, 1), r[..., None]))[..., 0]
        return z

    def expand(self, z: np.ndarray, sel=slice(None)) -> np.ndarray:
        """(n, 9) motion [omega, omega_dot, s] of the samples ``sel`` from their coordinates ``z[sel]``."""
        zs = z[sel]
        return self.mm.expand(zs[:, :self.mm.dim] if self.clock else zs, sel)

    def rates(self, model: SensorModel, ctx) -> np.ndarray | None:
        """(n, K, 6, RATES) d y / d (reading rates) of the samples of ``ctx`` (unweighted), None without them."""
        return rate_columns(model, ctx, self.clock) if self.clock else None

    def rate_shift(self, cols: np.ndarray | None, z: np.ndarray, sel) -> np.ndarray | float:
        """(n, K, 6) what the reading rates add to the predictions of the samples ``sel`` (0 without them)."""
        if cols is None:
            return 0.0
        return np.matmul(cols, z[sel][:, None, -RATES:, None])[..., 0]

    def motion_jacobian(self, jac_motion: np.ndarray, w: np.ndarray, z: np.ndarray, sel,
                        cols: np.ndarray | None = None) -> np.ndarray:
        """(n, K, 6, dm) weighted d y / d z from the model's (n, K, 6, 9) d y / d x and, with reading rates, their
        columns ``cols`` (:meth:`rates`, the same IMUs as ``jac_motion``)."""
        zs = z[sel]
        d = self.mm.jacobian(zs[:, :self.mm.dim] if self.clock else zs, sel)
        if d is None and self.clock:  # written into one array (no concatenated copy): the same values
            jx = np.empty(jac_motion.shape[:3] + (self.dm,))
            np.multiply(jac_motion, w[..., None], out=jx[..., :jac_motion.shape[3]])
            np.multiply(cols, w[..., None], out=jx[..., jac_motion.shape[3]:])
            return jx
        jx = jac_motion * w[..., None]
        jx = jx if d is None else np.matmul(jx, d[:, None])
        if self.clock:
            jx = np.concatenate([jx, cols * w[..., None]], axis=3)
        return jx

    # ---- evaluation
    def chunks(self):
        for lo in range(0, self.n, self.chunk):
            yield lo, min(lo + self.chunk, self.n)

    def freeze(self, motion: np.ndarray | None) -> None:
        """Hold the timing context of ``motion`` (None: release it) until the next freeze: the timing
        terms then see one fixed trajectory, so the problem does not move under the optimiser (``frozen_motion``:
        the motion it was built from)."""
        self.frozen, self.frozen_motion, self.remainders = None, None, {}
        if motion is not None and self.needs_derivatives:
            self.frozen, self.frozen_motion = self.derivatives(motion), motion

    def derivatives(self, motion: np.ndarray) -> tuple:
        """(omega_ddot, specific_force_dot, omega_rate, trajectory) of the whole recording: the local
        quartics through the motion (:func:`~imu_array_ros.model.trajectory.timing_context` with
        ``ENGINE_DEGREE`` and ``ENGINE_WINDOW_S``), or those
        held by :meth:`freeze`; all None when no timing term reads them."""
        if not self.needs_derivatives:
            return None, None, None, None
        if getattr(self, "frozen", None) is not None:
            return self.frozen
        tc = trajectory.timing_context(self.stamps, self.expand(motion), degree=trajectory.ENGINE_DEGREE,
                                       window_s=trajectory.ENGINE_WINDOW_S)
        return tc["omega_ddot"], tc["specific_force_dot"], None, tc["trajectory"]

    def context(self, model: SensorModel, motion: np.ndarray, derivs: tuple, lo: int, hi: int):
        return self.context_at(model, motion, derivs, slice(lo, hi))

    def context_at(self, model: SensorModel, motion: np.ndarray, derivs: tuple, sel):
        """The motion context of the samples ``sel`` (slice or indexes); ``motion`` and ``derivs`` whole."""
        cut = lambda a: None if a is None else a[sel]  # noqa: E731
        x = self.expand(motion, sel)
        traj = None if derivs[3] is None else derivs[3].rows(sel)
        ctx = motion_context(self.stamps[sel], x[:, 0:3], x[:, 3:6], x[:, 6:9],
                             model.rotations, t0_ns=self.t0_ns, omega_ddot=cut(derivs[0]),
                             specific_force_dot=cut(derivs[1]), stamp_delays=cut(self.stamp_delays),
                             omega_rate=cut(derivs[2]), trajectory=traj)
        frozen = getattr(self, "frozen", None)
        if traj is not None and frozen is not None and derivs[3] is frozen[3]:
            # on the frozen trajectory the timing remainders do not depend on the motion: a chunk's kept until the
            # next freeze (TimingStage.remainder checks the delays, positions and rotations they were made with);
            # some samples' (residuals_at) are read from their chunks' (computed per sample: the same values)
            ctx.remainders = self.remainders.setdefault((sel.start, sel.stop, sel.step), {}) \
                if isinstance(sel, slice) else self.remainder_rows(sel)
        return ctx

    def remainder_rows(self, idx: np.ndarray) -> dict:
        """The timing remainders kept for the chunks (:meth:`chunks`) of the sorted samples ``idx``, their rows
        only, per sensor for which every chunk holds one made with the same positions and rotations (as
        :meth:`~imu_array_ros.model.terms.timing.TimingStage.remainder` keeps them); a new dict."""
        out, starts = {}, np.unique(idx // self.chunk) * self.chunk
        entries = [self.remainders.get((int(lo), min(int(lo) + self.chunk, self.n), None), {}) for lo in starts]
        for sensor in ("accelerometer", "gyroscope"):
            parts = [e.get(sensor) for e in entries]
            if any(p is None for p in parts) or not all(np.array_equal(p[1], parts[0][1])
                                                        and np.array_equal(p[2], parts[0][2]) for p in parts):
                continue
            which = np.searchsorted(starts, idx, side="right") - 1  # each sample's chunk among ``starts``
            delta, value = np.empty((len(idx),) + parts[0][0].shape[1:]), np.empty((len(idx),) + parts[0][3].shape[1:])
            for j, (lo, p) in enumerate(zip(starts, parts)):
                rows = which == j
                delta[rows], value[rows] = p[0][idx[rows] - lo], p[3][idx[rows] - lo]
            out[sensor] = (delta, parts[0][1], parts[0][2], value)
        return out

    def residuals(self, model: SensorModel, motion: np.ndarray, derivs: tuple) -> np.ndarray:
        """(N, K, 6) normalised residuals w (y - h), 0 on masked axes, with the motion derivatives ``derivs``."""
        out = np.empty_like(self.y)
        for lo, hi in self.chunks():
            out[lo:hi] = self._residuals_of(model, motion, derivs, slice(lo, hi))
        return out

    def residuals_at(self, model: SensorModel, motion: np.ndarray, derivs: tuple, idx: np.ndarray) -> np.ndarray:
        """(n, K, 6) :meth:`residuals` of the samples ``idx`` only (sorted indexes; ``motion`` and ``derivs``
        whole): with the derivatives held, a sample's residual reads its own motion alone."""
        out = np.empty((len(idx),) + self.y.shape[1:])
        for lo in range(0, len(idx), self.chunk):
            sel = idx[lo:lo + self.chunk]
            out[lo:lo + len(sel)] = self._residuals_of(model, motion, derivs, sel)
        return out

    def _residuals_of(self, model: SensorModel, motion: np.ndarray, derivs: tuple, sel) -> np.ndarray:
        """w (y - h) of the samples ``sel`` (a slice or indexes), as :meth:`residuals` and :meth:`residuals_at`."""
        ctx = self.context_at(model, motion, derivs, sel)
        acc, gyr = model.predict(ctx)
        shift = self.rate_shift(self.rates(model, ctx), motion, sel)
        return self.w[sel] * (self.y[sel] - np.concatenate([acc, gyr], axis=2) - shift)

    def linearize(self, model: SensorModel, motion: np.ndarray, *, free: bool = True,
                  gauge_point: bool = False) -> Linearization:
        """The Schur-complemented Gauss-Newton system at (model, motion); ``free=False``: motion only;
        ``gauge_point``: with the timing terms' first-order shift on the motion's own omega_dot and no
        trajectory, the model in which a common time shift of every reading is exactly absorbed by the
        motion (where the gauge freedoms are found)."""
        m = self.m if free else 0
        kf, p = len(self.fit), self.p
        S, g = np.zeros((m, m)), np.zeros(m)
        cblocks, gt = np.zeros((kf, p, p)), np.zeros((kf, p))
        linv, h = np.empty((self.n, self.dm, self.dm)), np.empty((self.n, self.dm))
        ok, exact, r_all = np.empty(self.n, dtype=bool), np.empty(self.n, dtype=bool), np.empty_like(self.y)
        keep = m and self.keep_g and not gauge_point and 8 * self.n * self.dm * m <= KEEP_G_BYTES
        g_all = np.empty((self.n, self.dm, m)) if keep else None
        derivs = self.derivatives(motion)
        if gauge_point:
            derivs = (derivs[0], derivs[1], None, None)
        for lo, hi in self.chunks():
            ctx = self.context(model, motion, derivs, lo, hi)
            jac = model.jacobians(ctx, self.free if m else ())
            w = self.w[lo:hi]
            cols = self.rates(model, ctx)
            r = w * (self.y[lo:hi] - jac.predicted - self.rate_shift(cols, motion, slice(lo, hi)))
            jx = self.motion_jacobian(jac.motion, w, motion, slice(lo, hi), cols)  # (n, K, 6, dm)
            linv[lo:hi], ok[lo:hi], exact[lo:hi] = factor(gram(jx))
            h[lo:hi] = np.einsum("nij,nkrj,nkr->ni", linv[lo:hi], jx, r, optimize=True)
            r_all[lo:hi] = r
            if m:
                jt = self.parameter_jacobian(jac, w)
                accumulate_c(cblocks, gt, jt, r[:, self.cols])
                gmat = stacked_g(jx[:, self.cols], linv[lo:hi], jt, out=g_all[lo:hi] if keep else None)  # (dm n, M)
                S -= gmat.T @ gmat
                g -= gmat.T @ h[lo:hi].reshape(-1)
        if m:
            S += scipy.linalg.block_diag(*cblocks)
            g += gt.reshape(-1)
        cdiag = np.einsum("kpp->kp", cblocks).reshape(-1)[:m]
        return Linearization(0.5 * float(np.sum(r_all * r_all)), S, g, cdiag, linv, h, ok, r_all, derivs, g_all,
                             exact)

    def parameter_jacobian(self, jac, w: np.ndarray) -> np.ndarray:
        """(n, K_fit, 6, P) weighted d y / d theta of the fitted IMUs, free terms concatenated."""
        wc = w[:, self.cols, :, None]
        if len(self.free) == 1:
            return jac.params[self.free[0]][:, self.cols] * wc
        first = jac.params[self.free[0]][:, self.cols]
        out = np.empty(first.shape[:3] + (self.p,))  # each term's weighted columns in place: no concatenated copy
        for t, o, size in zip(self.free, np.cumsum([0] + self.sizes[:-1]), self.sizes):
            np.multiply(jac.params[t][:, self.cols], wc, out=out[..., o:o + size])
        return out

    def motion_step(self, model: SensorModel, motion: np.ndarray, lin: Linearization,
                    dtheta: np.ndarray | None) -> np.ndarray:
        """dx_n = L_n^-T (h_n - G_n dtheta) (back-substitution), (N, 9); G_n from ``lin`` when it kept it
        (:func:`keep_schur`), else recomputed chunk by chunk."""
        v = lin.h.copy()
        if dtheta is not None and np.any(dtheta) and lin.G is not None:
            v -= np.matmul(lin.G, dtheta)
        elif dtheta is not None and np.any(dtheta):
            dt = dtheta.reshape(len(self.fit), self.p)
            for lo, hi in self.chunks():
                ctx = self.context(model, motion, lin.derivs, lo, hi)
                jac = model.jacobians(ctx, self.free)
                w = self.w[lo:hi]
                u = np.einsum("nkrp,kp->nkr", self.parameter_jacobian(jac, w), dt)  # J_t dtheta per IMU
                cols = self.rates(model, ctx)
                jx = self.motion_jacobian(jac.motion[:, self.cols], w[:, self.cols], motion, slice(lo, hi),
                                          None if cols is None else cols[:, self.cols])
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
        z = self.mm.initial(np.concatenate([omega, motion_derivative(self.stamps, omega), s], axis=1))
        return np.concatenate([z, np.zeros((len(z), RATES))], axis=1) if self.clock else z

    def fit_motion(self, model: SensorModel, motion: np.ndarray, tolerance: float = 1e-4,
                   lin: Linearization | None = None, *, iterations: int = MOTION_ITERATIONS,
                   last_lin: bool = True):
        """Motion-only Gauss-Newton for fixed parameters (batched 9x9 steps), step halving per sample, until the
        mean squared whitened step of the samples whose step is exact (:attr:`Linearization.exact`) is below
        ``tolerance`` squared, at most ``iterations`` steps; ``lin``: the motion-only linearisation at
        ``motion`` when the caller has it.

        Returns the motion and the motion-only linearisation at it (whose ``ok`` flags the samples that
        identify their motion); ``last_lin`` False: None in its place when the steps ran out (a caller that
        linearises at the motion anyway, on another trajectory: one pass over every sample less)."""
        for i in range(iterations):
            lin = self.linearize(model, motion, free=False) if i or lin is None else lin
            if not lin.exact.any() or np.mean(np.sum(lin.h[lin.exact] ** 2, axis=1)) < tolerance ** 2:
                return motion, lin
            step = self.motion_step(model, motion, lin, None)
            cost0 = 0.5 * np.sum(lin.r ** 2, axis=(1, 2))
            t, todo = 1.0, np.ones(self.n, dtype=bool)
            new = motion.copy()
            for k in range(10):  # halve the step where a sample's cost went up (then only those samples evaluated)
                trial = np.where(todo[:, None], motion + t * step, new)
                if k == 0:
                    cost = 0.5 * np.sum(self.residuals(model, trial, lin.derivs) ** 2, axis=(1, 2))
                else:
                    idx = np.flatnonzero(todo)
                    cost = np.full(self.n, np.inf)
                    cost[idx] = 0.5 * np.sum(self.residuals_at(model, trial, lin.derivs, idx) ** 2, axis=(1, 2))
                better = todo & (cost <= cost0)
                new[better] = trial[better]
                todo &= ~better
                if not todo.any():
                    break
                t *= 0.5
            motion = new
        return motion, self.linearize(model, motion, free=False) if last_lin else None
