"""The estimated motion near each sample as a function of time: what the fusion, the fitting engine and
the residuals evaluate readings along when they were sampled at other instants than their stamps.

:class:`MotionTrajectory` fits, around every sample n, a cubic polynomial in time to the estimates
[omega, omega_dot, s] of the samples within a window (local polynomial regression, a
Savitzky-Golay filter on the true, possibly irregular, stamps): at least ``2 * MIN_HALF + 1`` samples
and about ``WINDOW_S`` seconds.  Called with int64 ns times ``when`` of shape (N, ...) -- row n near
stamp n -- it returns the motion there from sample n's polynomial, which is what
:attr:`MotionContext.trajectory <imu_array_ros.model.terms.base.MotionContext>` expects.  The timing
stage then shifts every reading by p_n(t + Delta) - p_n(t).

Why this and not the alternatives (measured on 32 IMUs at 500 Hz with time offsets of 1 ms, readings
simulated from the exact motion; NEES of the fused [omega, omega_dot, s], 9 expected):

* first-order shift x + Delta dx/dt with dx/dt from central differences: the neglected
  Delta^2/2 d^2x/dt^2 is several gyroscope sigma on hand motion, and the two-sample slope is noisy
  (sigma / h): NEES 34;
* an interpolating cubic spline through the estimates: no truncation error, but its slope carries the
  estimates' noise over one sample spacing, and more passes feed it back: NEES 15-27 growing with passes;
* the local cubic over a window of ~25 ms: the slope's noise falls as W^(-3/2), its bias (the motion's
  fourth derivative times W^3) stays far below the noise for hand motion up to several Hz.
"""

from __future__ import annotations

import numpy as np

from imu_array_ros.model.samples import FusedSamples

__all__ = ["MotionTrajectory", "timing_context", "fused_timing_context", "WINDOW_S", "MIN_HALF", "DEGREE"]

#: window of the local polynomials, seconds (widened to 2 MIN_HALF + 1 samples at low rates)
WINDOW_S = 0.025
#: fewest samples on each side of the centre
MIN_HALF = 2
#: degree of the local polynomials
DEGREE = 3
#: a step of more than this many median spacings splits the samples into segments no window crosses
GAP = 2.5
#: ridge on the scaled higher coefficients (only matters where a segment is shorter than the degree needs)
RIDGE = 1e-9


class MotionTrajectory:
    """Local cubic fits of an estimated motion around each sample (see module docstring)."""

    def __init__(self, stamps: np.ndarray, motion: np.ndarray) -> None:
        stamps = np.asarray(stamps, dtype=np.int64)
        motion = np.asarray(motion, dtype=float)
        n = len(stamps)
        if n < 2 or np.any(np.diff(stamps) <= 0):
            raise ValueError("a fused trajectory needs at least two samples with strictly increasing stamps")
        self.stamps = stamps
        steps = np.diff(stamps)
        spacing = float(np.median(steps)) * 1e-9
        half = max(MIN_HALF, int(round(0.5 * WINDOW_S / spacing)))
        width = min(2 * half + 1, n)
        degree = min(DEGREE, width - 1)
        # a window never reaches across a gap (more than GAP spacings): segments of consecutive samples
        seg = np.concatenate([[0], np.cumsum(steps > GAP * np.median(steps))])
        first = np.searchsorted(seg, seg, side="left")
        last = np.searchsorted(seg, seg, side="right")  # one past the segment's last sample
        lo = np.clip(np.arange(n) - half, first, np.maximum(last - width, first))  # shifted inside the segment
        idx = np.minimum(lo[:, None] + np.arange(width)[None], n - 1)  # (N, W)
        inside = (lo[:, None] + np.arange(width)[None]) < last[:, None]
        dt = (stamps[idx] - stamps[:, None]) * 1e-9  # (N, W) s, relative to each centre
        scale = max(float(np.abs(np.where(inside, dt, 0.0)).max()), 1e-9)
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
            x = np.matmul(dt[..., None] ** np.arange(c.shape[1]), c)  # (N, K, D+1) @ (N, D+1, 9)
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


def timing_context(stamps: np.ndarray, motion: np.ndarray) -> dict:
    """The motion-context arguments the timing terms read, from an estimated motion (N, 9)
    [omega, omega_dot, s] at ``stamps``: the trajectory and the slopes of the local cubics, ``omega_ddot`` and
    ``specific_force_dot``.  Fewer than two samples: no trajectory, zero slopes."""
    motion = np.asarray(motion, dtype=float)
    if len(stamps) < 2:
        z = np.zeros((len(stamps), 3))
        return dict(trajectory=None, omega_ddot=z, specific_force_dot=z)
    traj = MotionTrajectory(stamps, motion)
    slope = traj.derivative()
    return dict(trajectory=traj, omega_ddot=slope[:, 3:6], specific_force_dot=slope[:, 6:9])


def fused_timing_context(stamps: np.ndarray, motion: np.ndarray) -> dict:
    """:func:`timing_context` for a fused motion, with ``omega_rate``: the gyroscopes' first-order rate taken
    from the slope of the fused angular rate (the gyroscopes' own, far less noisy than the accelerometers'
    omega_dot estimate) plus the constant by which omega_dot differs from it (a rotational
    accelerometer-bias field shifts omega_dot; the fitting engine reads the omega_dot state, so fitted time
    offsets and gyroscope biases are consistent with that constant)."""
    tc = timing_context(stamps, motion)
    if tc["trajectory"] is not None:
        slope = tc["trajectory"].derivative()[:, 0:3]
        tc["omega_rate"] = slope + np.median(np.asarray(motion, dtype=float)[:, 3:6] - slope, axis=0)
    return tc
