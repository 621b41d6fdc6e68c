"""The estimated motion near each sample as a function of time: what the fusion, the fitting engine and
the residuals evaluate readings along when they were sampled at other instants than their stamps.

:class:`MotionTrajectory` fits, around every sample n, a polynomial in time to the estimates
[omega, omega_dot, s] of the samples within a window (local polynomial regression, a
Savitzky-Golay filter on the true, possibly irregular, stamps): at least ``2 * MIN_HALF + 1`` samples
and about a window's seconds.  The fusion's are cubics over ``WINDOW_S``, the fitting engine's quartics over
``ENGINE_WINDOW_S`` (below).  Called with int64 ns times ``when`` of shape (N, ...) -- row n near
stamp n -- it returns the motion there from sample n's polynomial, which is what
:attr:`MotionContext.trajectory <imu_array_ros.model.terms.base.MotionContext>` expects.  The timing
stage then shifts every reading by p_n(t + Delta) - p_n(t).

The fusion's cubics, and why not the alternatives (measured on 32 IMUs at 500 Hz with time offsets of 1 ms,
readings simulated from the exact motion; NEES of the fused [omega, omega_dot, s], 9 expected):

* first-order shift x + Delta dx/dt with dx/dt from central differences: the neglected
  Delta^2/2 d^2x/dt^2 is several gyroscope sigma on hand motion, and the two-sample slope is noisy
  (sigma / h): NEES 34;
* an interpolating cubic spline through the estimates: no truncation error, but its slope carries the
  estimates' noise over one sample spacing, and more passes feed it back: NEES 15-27 growing with passes;
* the local cubic over a window of ~25 ms: the slope's noise falls as W^(-3/2), its bias (the motion's
  fourth derivative times W^3) stays far below the noise for hand motion up to several Hz.  Quartics
  instead (``ENGINE_DEGREE``, either window) raise that NEES on hand twisting by 1-2.5 % (9.02 -> 9.12 at
  500 Hz, 9.17 -> 9.39 at 250 Hz, 9.04 -> 9.11 at 62.5 Hz; 3-6 seeds), so the fusion keeps the cubics.

The fitting engine's quartics: a cubic's second- and third-order coefficients, which carry a reading's shift
beyond first order (Delta^2 a_2 + Delta^3 a_3), are biased by the motion's fourth derivative times the window
squared.  On the 0.3 s transitions of a simulated icosahedron session that put the fitted time offsets off: at
62.5 Hz (the window widened to 5 samples, 64 ms) the accelerometers' common delay ~40 us early and the moved
gyroscopes' offsets ~1.5 of their std too large, still 11-13 us at 250-500 Hz (24 ms).  A quartic is exact to
the fourth degree.  Its window: below ~140 Hz the 5 samples it interpolates (a reading's delay is small
against the spacing there, so the estimates' noise barely enters), above about ``ENGINE_WINDOW_S`` = 35 ms,
wider than the cubics' so that its higher coefficients are no noisier (a quartic over 25 ms, 5 samples at
200 Hz with time offsets of ~2 ms, left a fit's NIS at 1.32: test_fit_terms' Monte Carlo).  With the true terms
held its fitted offsets match those along the exact motion at 62.5, 200 and 500 Hz (docs/timing.md).
"""

from __future__ import annotations

import threading
from contextlib import contextmanager

import numpy as np
from numpy.lib.stride_tricks import sliding_window_view

from imu_array_ros.model.samples import FusedSamples

__all__ = ["MotionTrajectory", "timing_context", "fused_timing_context", "shared_fits", "LocalFits", "fit_weights",
           "solve_spd", "WINDOW_S", "MIN_HALF", "DEGREE", "ENGINE_DEGREE", "ENGINE_WINDOW_S"]

#: window of the fusion's local cubics, seconds (widened to 2 MIN_HALF + 1 samples at low rates)
WINDOW_S = 0.025
#: fewest samples on each side of the centre
MIN_HALF = 2
#: degree of the fusion's local polynomials (cubics)
DEGREE = 3
#: degree of the fitting engine's local polynomials (quartics; see the module docstring)
ENGINE_DEGREE = 4
#: window of the fitting engine's local quartics, seconds (at least 2 MIN_HALF + 1 samples)
ENGINE_WINDOW_S = 0.035
#: a step of more than this many median spacings splits the samples into segments no window crosses
GAP = 2.5
#: ridge on the scaled higher coefficients (only matters where a segment is shorter than the degree needs)
RIDGE = 1e-9


def _windows(stamps: np.ndarray, degree: int = DEGREE, window_s: float = WINDOW_S):
    """The samples each local polynomial is fitted to: (idx (N, W) their indexes, inside (N, W) False where a
    window reaches past its segment's end, dt (N, W) s relative to each centre, scale (s) of the scaled time,
    degree)."""
    n = len(stamps)
    steps = np.diff(stamps)
    spacing = float(np.median(steps)) * 1e-9
    half = max(MIN_HALF, int(round(0.5 * window_s / spacing)))
    width = min(2 * half + 1, n)
    degree = min(degree, width - 1)
    # a window never reaches across a gap (more than GAP spacings): segments of consecutive samples
    seg = np.concatenate([[0], np.cumsum(steps > GAP * np.median(steps))])
    first = np.searchsorted(seg, seg, side="left")
    last = np.searchsorted(seg, seg, side="right")  # one past the segment's last sample
    lo = np.clip(np.arange(n) - half, first, np.maximum(last - width, first))  # shifted inside the segment
    idx = np.minimum(lo[:, None] + np.arange(width)[None], n - 1)  # (N, W)
    inside = (lo[:, None] + np.arange(width)[None]) < last[:, None]
    dt = (stamps[idx] - stamps[:, None]) * 1e-9  # (N, W) s, relative to each centre
    scale = max(float(np.abs(np.where(inside, dt, 0.0)).max()), 1e-9)
    return idx, inside, dt, scale, degree


def solve_spd(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """x with a x = b for every row: a (N, d, d) symmetric positive definite (d small), b (N, d, c); a Cholesky
    factorisation and two substitutions written out over all N rows at once (no per-row LAPACK call)."""
    n, d = a.shape[:2]
    a = np.ascontiguousarray(a.transpose(1, 2, 0))  # (d, d, N): every entry a contiguous row
    x = np.ascontiguousarray(b.transpose(1, 2, 0))  # (d, c, N), solved in place
    low = np.empty((d, d, n))  # L[i, j] over the rows (lower triangle used)
    inv = np.empty((d, n))  # 1 / L[j, j]
    for j in range(d):
        s = a[j, j].copy()
        for m in range(j):
            s -= low[j, m] * low[j, m]
        np.sqrt(s, out=s)
        np.divide(1.0, s, out=inv[j])
        low[j, j] = s
        for i in range(j + 1, d):
            t = low[i, j]
            t[...] = a[i, j]
            for m in range(j):
                t -= low[i, m] * low[j, m]
            t *= inv[j]
    for i in range(d):  # L z = b
        for m in range(i):
            x[i] -= low[i, m] * x[m]
        x[i] *= inv[i]
    for i in range(d - 1, -1, -1):  # L^T x = z
        for m in range(i + 1, d):
            x[i] -= low[m, i] * x[m]
        x[i] *= inv[i]
    return np.ascontiguousarray(x.transpose(2, 0, 1))


class LocalFits:
    """The local polynomials' least-squares fits at given stamps, solved for every sample at once
    (:func:`solve_spd`): :meth:`coefficients` of any motion at those stamps.  They depend on the stamps only.

    On a regular grid most windows have the same offsets: those share one set of weights, solved once, and
    their coefficients are one matrix product over the windows of the motion (no gathered copy)."""

    def __init__(self, stamps: np.ndarray, degree: int = DEGREE, window_s: float = WINDOW_S) -> None:
        idx, inside, dt, scale, degree = _windows(stamps, degree, window_s)
        n, width = idx.shape
        rel = stamps[idx] - stamps[:, None]
        same = inside.all(axis=1) & (rel == rel[n // 2]).all(axis=1)
        # runs of consecutive samples with the shared weights whose windows start at consecutive samples
        start = idx[:, 0]
        cut = np.flatnonzero(~same[1:] | ~same[:-1] | (np.diff(start) != 1)) + 1
        self.runs = [(int(a), int(b)) for a, b in zip(np.r_[0, cut], np.r_[cut, n]) if same[a] and b - a > 1]
        shared = np.zeros(n, dtype=bool)
        for a, b in self.runs:
            shared[a:b] = True
        self.rest = np.flatnonzero(~shared)
        rows = self.rest if not self.runs else np.r_[self.runs[0][0], self.rest]
        tau = np.where(inside[rows], dt[rows] / scale, 0.0)
        pt = np.empty((len(rows), degree + 1, width))  # the scaled powers, transposed
        pt[:, 0] = inside[rows]
        pt[:, 1] = tau
        for d in range(2, degree + 1):
            np.multiply(pt[:, d - 1], tau, out=pt[:, d])
        gram = np.matmul(pt, pt.transpose(0, 2, 1))
        gram += RIDGE * np.diag((np.arange(degree + 1) > 0).astype(float))[None]
        solved = solve_spd(gram, pt)
        solved /= (scale ** np.arange(degree + 1))[None, :, None]  # per second^d
        self.shared_t = np.ascontiguousarray(solved[0].T) if self.runs else None  # (W, D+1)
        self.weights = solved[1:] if self.runs else solved  # (R, D+1, W) of the other samples
        self.idx, self.start, self.n, self.shape = idx[self.rest], start, n, (degree + 1, width)

    def coefficients(self, motion: np.ndarray) -> np.ndarray:
        """(N, D+1, C) per second^d: the local polynomials through ``motion`` (N, C) at these stamps."""
        motion = np.asarray(motion, dtype=float)
        out = np.empty((self.n, self.shape[0], motion.shape[1]))
        if self.runs:
            windows = sliding_window_view(motion, self.shape[1], axis=0)  # (N - W + 1, C, W), no copy
            for a, b in self.runs:
                s = int(self.start[a])
                out[a:b] = np.matmul(windows[s:s + b - a], self.shared_t).transpose(0, 2, 1)
        if len(self.rest):
            out[self.rest] = np.matmul(self.weights, motion[self.idx])
        return out


def fit_weights(stamps: np.ndarray, degree: int = DEGREE, window_s: float = WINDOW_S) -> tuple[np.ndarray, np.ndarray]:
    """(idx (N, W), weights (N, D+1, W)): the local polynomials' coefficients (per second^d) are
    ``weights @ motion[idx]`` (:class:`LocalFits`, every sample's weights written out)."""
    fits = LocalFits(np.asarray(stamps, dtype=np.int64), degree, window_s)
    idx, _, _, _, _ = _windows(np.asarray(stamps, dtype=np.int64), degree, window_s)
    weights = np.empty((fits.n,) + fits.shape)
    for a, b in fits.runs:
        weights[a:b] = fits.shared_t.T
    weights[fits.rest] = fits.weights
    return idx, weights


_SHARED = threading.local()


@contextmanager
def shared_fits():
    """Within the context (in this thread), local cubics fitted with ``solver="cholesky"`` to the same stamps
    share their :class:`LocalFits`: the fusion's compensation passes fit new estimates at the same stamps.
    They are dropped on leaving."""
    outer = getattr(_SHARED, "slot", None)
    _SHARED.slot = {}
    try:
        yield
    finally:
        _SHARED.slot = outer


def _fits_of(stamps: np.ndarray, degree: int, window_s: float) -> LocalFits:
    slot = getattr(_SHARED, "slot", None)
    if slot is None:
        return LocalFits(stamps, degree, window_s)
    held = slot.get("stamps")
    if (held is None or slot.get("shape") != (degree, window_s) or len(held) != len(stamps)
            or not np.array_equal(held, stamps)):
        slot["fits"] = LocalFits(stamps, degree, window_s)
        slot["stamps"], slot["shape"] = stamps.copy(), (degree, window_s)
    return slot["fits"]


class MotionTrajectory:
    """Local polynomial fits of an estimated motion around each sample (see module docstring)."""

    def __init__(self, stamps: np.ndarray, motion: np.ndarray, *, solver: str = "lapack",
                 degree: int = DEGREE, window_s: float = WINDOW_S) -> None:
        """``solver``: how each sample's normal equations are solved -- "lapack" (one LAPACK solve per sample, the
        fitting engine's numbers) or "cholesky" (:class:`LocalFits`: every sample's at once, the same fit to
        rounding, many times faster, and shared by fits at the same stamps inside :func:`shared_fits`; what
        the fusion uses).  ``degree``: of the polynomials (at most the window's samples - 1): ``DEGREE`` (cubics,
        the fusion's) or ``ENGINE_DEGREE`` (quartics, the fitting engine's); ``window_s``: their window, s (at
        least ``2 * MIN_HALF + 1`` samples): ``WINDOW_S`` (the fusion's) or ``ENGINE_WINDOW_S`` (the engine's)."""
        stamps = np.asarray(stamps, dtype=np.int64)
        motion = np.asarray(motion, dtype=float)
        n = len(stamps)
        if n < 2 or np.any(np.diff(stamps) <= 0):
            raise ValueError("a fused trajectory needs at least two samples with strictly increasing stamps")
        if solver not in ("lapack", "cholesky"):
            raise ValueError(f"solver must be 'lapack' or 'cholesky', got {solver!r}")
        self.stamps = stamps
        if solver == "cholesky":
            self.coef = _fits_of(stamps, degree, window_s).coefficients(motion)  # (N, D+1, 9) per second^d
            return
        idx, inside, dt, scale, degree = _windows(stamps, degree, window_s)
        powers = (dt / scale)[..., None] ** np.arange(degree + 1) * inside[..., None]  # (N, W, D+1), scaled
        gram = np.einsum("nwi,nwj->nij", powers, powers)
        # short segments: a small ridge on the higher coefficients gives the lower-degree fit (a lone sample:
        # its value, slope 0)
        gram += RIDGE * np.diag((np.arange(degree + 1) > 0).astype(float))[None]
        rhs = np.einsum("nwi,nwc->nic", powers, motion[idx])
        coef = np.linalg.solve(gram, rhs)  # (N, D+1, 9) in scaled time
        self.coef = coef / (scale ** np.arange(degree + 1))[None, :, None]  # per second^d

    @classmethod
    def of(cls, fused: FusedSamples) -> "MotionTrajectory":
        return cls(fused.stamps, np.concatenate([fused.omega, fused.omega_dot, fused.specific_force], axis=1))

    def rows(self, sel) -> "MotionTrajectory":
        """The trajectory of the samples ``sel`` (a slice or indexes) only: for a chunk's context."""
        out = object.__new__(MotionTrajectory)
        out.stamps, out.coef = self.stamps[sel], self.coef[sel]
        return out

    def derivative(self) -> np.ndarray:
        """(N, 9) d/dt of [omega, omega_dot, s] at every fused sample (the local cubics' slopes): omega's
        from the gyroscope-dominated omega estimates, omega_ddot and ds/dt for the first-order Jacobians."""
        return self.coef[:, 1, :] if self.coef.shape[1] > 1 else np.zeros(self.coef.shape[::2])

    def slope_at(self, when_ns: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """d/dt of the motion at ``when_ns`` (as :meth:`__call__`): the exact derivative of what it returns."""
        return self._evaluate(when_ns, 1)

    def __call__(self, when_ns: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Motion at ``when_ns`` (N, ...) int64, row n from sample n's polynomial; each (N, ..., 3)."""
        return self._evaluate(when_ns, 0)

    _COLUMNS = {"omega": slice(0, 3), "omega_dot": slice(3, 6), "specific_force": slice(6, 9)}

    def shift(self, delta: np.ndarray, part: str) -> np.ndarray:
        """(N, K, 3) p_n(t_n + delta) - p_n(t_n) of one part ("omega", "omega_dot", "specific_force") at delays
        ``delta`` (N, K) s: Horner without the constant term."""
        c = self.coef[:, 1:, self._COLUMNS[part]]  # (N, D, 3)
        x = c[:, None, -1]
        for d in range(c.shape[1] - 2, -1, -1):
            x = x * delta[..., None] + c[:, None, d]
        return x * delta[..., None]

    def at_delays(self, delta: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(omega, omega_dot) at t_n + delta (N, K) s, each (N, K, 3)."""
        c = self.coef[:, :, 0:6]
        x = c[:, None, -1]
        for d in range(c.shape[1] - 2, -1, -1):
            x = x * delta[..., None] + c[:, None, d]
        return x[..., 0:3], x[..., 3:6]

    def at_stamps(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The motion at every sample's own stamp (each (N, 3)): the local cubics' constant terms."""
        c = self.coef[:, 0, :]
        return c[:, 0:3], c[:, 3:6], c[:, 6:9]

    def _evaluate(self, when_ns, order: int):
        when = np.asarray(when_ns, dtype=np.int64)
        if when.ndim == 2:  # the common case, (N, K): one batched product
            dt = (when - self.stamps[:, None]) * 1e-9
            c = self.coef
            if order:
                c = c[:, 1:] * np.arange(1, c.shape[1])[None, :, None]
            powers = np.empty(dt.shape + (c.shape[1],))  # dt^d by products (a power ** is ~20x slower)
            powers[..., :1] = 1.0
            for d in range(1, c.shape[1]):
                np.multiply(powers[..., d - 1], dt, out=powers[..., d])
            x = np.matmul(powers, c)  # (N, K, D+1) @ (N, D+1, 9)
            return x[..., 0:3], x[..., 3:6], x[..., 6:9]
        if when.shape[:1] != self.stamps.shape:
            raise ValueError(f"times must have one row per fused sample ({len(self.stamps)}), got {when.shape}")
        dt = ((when - self.stamps.reshape((-1,) + (1,) * (when.ndim - 1))) * 1e-9)[..., None]
        c = self.coef
        if order:  # the derivative's coefficients: d * c_d
            c = c[:, 1:] * np.arange(1, c.shape[1])[None, :, None] if c.shape[1] > 1 else np.zeros_like(c)
        coef = c.reshape((len(c),) + (1,) * (when.ndim - 1) + c.shape[1:])
        x = coef[..., -1, :]
        for d in range(c.shape[1] - 2, -1, -1):  # Horner
            x = x * dt + coef[..., d, :]
        return x[..., 0:3], x[..., 3:6], x[..., 6:9]


def timing_context(stamps: np.ndarray, motion: np.ndarray, *, solver: str = "lapack", degree: int = DEGREE,
                   window_s: float = WINDOW_S) -> dict:
    """The motion-context arguments the timing terms read, from an estimated motion (N, 9)
    [omega, omega_dot, s] at ``stamps``: the trajectory and the slopes of the local polynomials, ``omega_ddot`` and
    ``specific_force_dot``.  Fewer than two samples: no trajectory, zero slopes.  ``solver``, ``degree``,
    ``window_s``: see :class:`MotionTrajectory` (the fitting engine passes "lapack", ``ENGINE_DEGREE`` and
    ``ENGINE_WINDOW_S``)."""
    motion = np.asarray(motion, dtype=float)
    if len(stamps) < 2:
        z = np.zeros((len(stamps), 3))
        return dict(trajectory=None, omega_ddot=z, specific_force_dot=z)
    traj = MotionTrajectory(stamps, motion, solver=solver, degree=degree, window_s=window_s)
    slope = traj.derivative()
    return dict(trajectory=traj, omega_ddot=slope[:, 3:6], specific_force_dot=slope[:, 6:9])


def fused_timing_context(stamps: np.ndarray, motion: np.ndarray) -> dict:
    """:func:`timing_context` for a fused motion, with ``omega_rate``: the gyroscopes' first-order rate taken
    from the slope of the fused angular rate (the gyroscopes' own, far less noisy than the accelerometers'
    omega_dot estimate) plus the constant by which omega_dot differs from it (a rotational
    accelerometer-bias field shifts omega_dot; the fitting engine reads the omega_dot state, so fitted time
    offsets and gyroscope biases are consistent with that constant).  The local cubics are solved all at once
    (``solver="cholesky"``): the fusion fits them in every pass."""
    tc = timing_context(stamps, motion, solver="cholesky")
    if tc["trajectory"] is not None:
        slope = tc["trajectory"].derivative()[:, 0:3]
        tc["omega_rate"] = slope + np.median(np.asarray(motion, dtype=float)[:, 3:6] - slope, axis=0)
    return tc
