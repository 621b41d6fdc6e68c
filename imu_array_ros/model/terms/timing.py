"""Sample time: every reading is the signal at its sensor's true sample time, not at its stamp.

A *timing term* says how far the true sample time of a reading lies from the
array sample's stamp: its ``delay`` (N, K) in seconds (negative: the reading is
older than its stamp) for each sensor.  The model adds up the delays of every
timing term of a chain (and, for IMUs that stamp their own messages, each
message's own stamp minus the array stamp, ``MotionContext.stamp_delays``) into
one delay per reading, Delta, and evaluates the signal at ``stamp + Delta``, in
one stage at the timing terms' place in the chain (:class:`TimingStage`):

* to first order, x + Delta dx/dt, with dx/dt = R^T omega_dot for a gyroscope and
  R^T (ds/dt + dC/dt p) for an accelerometer (the sample's own omega and omega_dot,
  omega_ddot and ds/dt from the motion context).  The sample's own motion in the
  first-order term is what ties the estimate to its stamp: a common shift of every
  delay is then exactly absorbed by the motion, the gauge of time;
* plus, with a ``MotionContext.trajectory`` (the simulator's dense truth, or the
  local cubics through an estimated motion,
  :class:`~imu_array_ros.model.trajectory.MotionTrajectory`), the *remainder* the
  first order leaves out: the exact shift along the trajectory minus the
  trajectory's own first-order shift (second and higher order in the delay;
  held fixed, it depends on no sample's motion).  With the simulator's truth the
  reading is then exactly the motion at its true time (its omega_dot is the
  derivative of its omega); with an estimate it removes the truncation error.

The Jacobians: d y / d theta_j = (dx/dt + the change of the trajectory's rate
between the stamp and the reading's time) * d Delta_j / d theta_j.

Time is relative: a delay common to every sensor of every IMU moves no reading
relative to another and is absorbed by the motion (per sample).  The gauge:
the fused motion refers to the instant the model calls Delta = 0, the array
stamp (for the sample clock, see :mod:`.sample_clock`).
"""

from __future__ import annotations

import numpy as np

from imu_array_ros.model.terms.base import MotionContext, Term

__all__ = ["TimingTerm", "TimingStage", "signal_rate", "exact_shift", "shift_features"]


class TimingTerm(Term):
    """A term that moves the sample time of readings (see module docstring).  Subclasses define
    :meth:`delay` and :meth:`d_delay`; the model applies the sum of the chain's delays once."""

    sensors = ("accelerometer", "gyroscope")
    order = 2
    candidate = False  # the dedicated estimators of :mod:`imu_array_ros.timing` set them up
    linear = False  # the accelerometer's shift needs ds/dt, which is not in the motion
    #: True when :meth:`delay` is the same for both sensors of an IMU (a clock, not a sensor's filter delay):
    #: the stage then computes it once for both
    same_for_sensors = False

    def delay(self, ctx: MotionContext, sensor: str) -> np.ndarray:
        """(N, K) s: true sample time minus stamp of ``sensor``'s readings."""
        raise NotImplementedError

    def d_delay(self, ctx: MotionContext, sensor: str) -> np.ndarray:
        """(N, K, P) d delay / d theta_k."""
        raise NotImplementedError

    # alone (outside a TimingStage) a timing term acts as a first-order shift by its own delay
    def apply(self, x, ctx, sensor):
        return TimingStage([self]).apply(x, ctx, sensor)

    def d_params(self, x, ctx, sensor):
        return TimingStage([self]).d_params_of(self, x, ctx, sensor)

    def d_motion(self, x, ctx, sensor):
        return TimingStage([self]).d_motion(x, ctx, sensor)

    def d_positions(self, x, ctx, sensor):
        return TimingStage([self]).d_positions(x, ctx, sensor)


def signal_rate(ctx: MotionContext, sensor: str) -> np.ndarray:
    """(N, K, 3) dx/dt of the sensor's ideal signal in its (nominal) frame."""
    if sensor == "gyroscope":
        rate = ctx.omega_dot if ctx.omega_rate is None else ctx.omega_rate
        v = np.broadcast_to(rate[:, None, :], (ctx.n, ctx.k, 3))
    else:
        sd = ctx.specific_force_dot if ctx.specific_force_dot is not None else np.zeros_like(ctx.specific_force)
        v = sd[:, None, :] + np.matmul(ctx.lever_dot, ctx.positions.T).transpose(0, 2, 1)  # dC/dt p_k
    return _to_sensor(ctx, v)


def exact_shift(ctx: MotionContext, sensor: str, delta: np.ndarray) -> np.ndarray:
    """(N, K, 3) x(stamp + delta) - x(stamp) of the ideal signal, both read from ``ctx.trajectory``
    (delta (N, K) s): the motion at every reading's own time minus the motion at its stamp."""
    traj = ctx.trajectory
    if hasattr(traj, "shift"):  # a trajectory that evaluates differences directly (the fusion's local cubics)
        if sensor == "gyroscope":
            return _to_sensor(ctx, traj.shift(delta, "omega"))
        ds, omega, omega_dot = traj.shift(delta, "specific_force"), *traj.at_delays(delta)
        omega0, omega_dot0, _ = traj.at_stamps()
        w0, wd0 = omega0[:, None], omega_dot0[:, None]
    else:
        when = ctx.stamps[:, None] + np.round(delta * 1e9).astype(np.int64)
        omega, omega_dot, s = traj(when)  # each (N, K, 3)
        omega0, omega_dot0, s0 = (a[:, 0] for a in traj(ctx.stamps[:, None]))
        if sensor == "gyroscope":
            return _to_sensor(ctx, omega - omega0[:, None])
        ds, w0, wd0 = s - s0[:, None], omega0[:, None], omega_dot0[:, None]
    p = ctx.positions[None]
    lever = _cross(omega, _cross(omega, p)) + _cross(omega_dot, p)
    lever0 = _cross(w0, _cross(w0, p)) + _cross(wd0, p)
    return _to_sensor(ctx, ds + lever - lever0)


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """a x b over the last axis (broadcast), written out (faster than np.cross on small trailing axes)."""
    a0, a1, a2 = a[..., 0], a[..., 1], a[..., 2]
    b0, b1, b2 = b[..., 0], b[..., 1], b[..., 2]
    return np.stack([a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0], axis=-1)


def _lag_rows(a: np.ndarray, rt: np.ndarray, p: np.ndarray) -> np.ndarray:
    """(N, K, 3, 3) R_k^T ((a_n . p_k) I + a_n p_k^T - 2 p_k a_n^T) for a (N, 3), rt (K, 3, 3) R_k^T, p (K, 3)."""
    ap = a @ p.T  # (N, K)
    ra = np.matmul(a, rt.transpose(0, 2, 1)).transpose(1, 0, 2)  # (N, K, 3): R_k^T a_n
    rp = np.matmul(rt, p[..., None])[..., 0]  # (K, 3): R_k^T p_k
    out = ap[..., None, None] * rt[None]
    out += ra[..., :, None] * p[None, :, None, :]
    out -= 2.0 * rp[None, :, :, None] * a[:, None, None, :]
    return out


def _to_sensor(ctx: MotionContext, v: np.ndarray) -> np.ndarray:
    """(N, K, 3) R_k^T v_nk (v_nk^T R_k: one product per IMU)."""
    return np.matmul(v.transpose(1, 0, 2), ctx.rotations).transpose(1, 0, 2)


def _rate_along(ctx: MotionContext, sensor: str, delta: np.ndarray) -> np.ndarray:
    """(N, K, 3) d/d delta of :func:`exact_shift`: the ideal signal's rate of change at stamp + delta."""
    when = ctx.stamps[:, None] + np.round(delta * 1e9).astype(np.int64)
    d_omega, d_omega_dot, d_s = ctx.trajectory.slope_at(when)
    if sensor == "gyroscope":
        v = d_omega
    else:
        omega, _, _ = ctx.trajectory(when)
        p = ctx.positions[None]  # d/dt [w x (w x p) + w_dot x p], written out as cross products
        v = d_s + _cross(d_omega, _cross(omega, p)) + _cross(omega, _cross(d_omega, p)) + _cross(d_omega_dot, p)
    return _to_sensor(ctx, v)


def shift_features(ctx: MotionContext, sensor: str) -> tuple[np.ndarray, np.ndarray | None] | None:
    """The timing stage's shift of ``sensor``'s readings (first order plus the remainder along the context's
    trajectory) as a polynomial in each reading's delay, sum_j delta^j (Lambda_j p_k + e_j) in the array
    frame, j = 1..M, its coefficients per sample shared by every IMU: (low (L, F, N), high (M - L, 6, N) or
    None).  low: orders 1..L, F = 3 (e_j) for a gyroscope, F = 12 for an accelerometer: the symmetric part of
    Lambda_j (its entries 00, 11, 22, 01, 02, 12), w_j with [w_j]x its antisymmetric part, e_j; high: the
    accelerometer's orders above the local polynomials' degree, where Lambda_j is symmetric and e_j = 0 (its
    six entries).  None when the trajectory is not local polynomials (then :meth:`TimingStage.apply`
    evaluates it).

    With the local polynomials' coefficients a_i (omega), b_i (omega_dot), s_i (specific force), i = 0..D,
    the remainder is p(t + delta) - p(t) - delta p'(t) and the first order is delta times the context's
    rates, so: e_1 = the context's rate (omega_rate, else omega_dot; ds/dt) and e_j = a_j or s_j for
    2 <= j <= D; for an accelerometer, C(omega, omega_dot) = [omega]x^2 + [omega_dot]x = omega omega^T -
    |omega|^2 I + [omega_dot]x is quadratic in the coefficients: Lambda_1 = dC/dt of the context, omega
    omega_dot^T + omega_dot omega^T - 2 (omega . omega_dot) I + [omega_ddot]x (the trajectory's own first order
    cancels with the remainder's), Lambda_j = sum_{i+l=j} (a_i a_l^T - (a_i . a_l) I) + [b_j]x for j >= 2
    ([b_j]x for j <= D only)."""
    traj = ctx.trajectory
    if traj is None:
        degree = 1
    elif isinstance(getattr(traj, "coef", None), np.ndarray) and hasattr(traj, "shift"):
        coef = traj.coef  # (N, D+1, 9)
        degree = coef.shape[1] - 1
    else:
        return None
    n = ctx.n
    if sensor == "gyroscope":
        low = np.empty((max(degree, 1), 3, n))
        low[0] = (ctx.omega_dot if ctx.omega_rate is None else ctx.omega_rate).T
        if traj is not None:
            low[1:] = coef[:, 2:, 0:3].transpose(1, 2, 0)
        return low, None
    top = 2 * degree if traj is not None else 1
    low = np.zeros((degree if traj is not None else 1, 12, n))
    high = np.empty((top - len(low), 6, n)) if top > len(low) else None
    w, wd = np.ascontiguousarray(ctx.omega.T), np.ascontiguousarray(ctx.omega_dot.T)
    _symmetric(w, wd, out=low[0, :6])
    if ctx.omega_ddot is not None:
        low[0, 6:9] = ctx.omega_ddot.T
    if ctx.specific_force_dot is not None:
        low[0, 9:] = ctx.specific_force_dot.T
    if traj is None:
        return low, high
    a = np.ascontiguousarray(coef[:, :, 0:3].transpose(1, 2, 0))  # (D+1, 3, N)
    a_r, a_c = a[:, _ROWS], a[:, _COLS]  # (D+1, 6, N): the components each symmetric entry multiplies
    for j in range(2, top + 1):
        q = low[j - 1, :6] if j <= degree else high[j - 1 - len(low)]
        first = True
        for i in range(max(0, j - degree), (j + 1) // 2):  # i < l = j - i: a_i a_l^T + a_l a_i^T
            for x, y in ((a_r[i], a_c[j - i]), (a_r[j - i], a_c[i])):
                if first:
                    np.multiply(x, y, out=q)
                    first = False
                else:
                    q += x * y
        if j % 2 == 0:
            h = j // 2
            if first:
                np.multiply(a_r[h], a_c[h], out=q)
            else:
                q += a_r[h] * a_c[h]
        q[:3] -= q[0] + q[1] + q[2]  # - sum_{i+l=j} (a_i . a_l) I
        if j <= degree:
            low[j - 1, 6:9] = coef[:, j, 3:6].T
            low[j - 1, 9:] = coef[:, j, 6:9].T
    return low, high


#: the entries of a symmetric 3x3 matrix the features hold: (row, column) of 00, 11, 22, 01, 02, 12
_ROWS = np.array([0, 1, 2, 0, 0, 1])
_COLS = np.array([0, 1, 2, 1, 2, 2])


def _symmetric(x: np.ndarray, y: np.ndarray, out: np.ndarray) -> np.ndarray:
    """The six entries of x y^T + y x^T - 2 (x . y) I, x and y (3, N), into ``out`` (6, N)."""
    np.multiply(x[_ROWS], y[_COLS], out=out)
    out += y[_ROWS] * x[_COLS]
    out[:3] -= out[0] + out[1] + out[2]
    return out


def _gemm(a: np.ndarray, b: np.ndarray, out: np.ndarray, accumulate: bool) -> None:
    """out (C-contiguous) = a @ b, or += a @ b: BLAS dgemm accumulating in place (no temporary for the
    product), as out^T = b^T a^T on the Fortran-ordered transposes; numpy's matmul without BLAS access."""
    if _DGEMM is None or not (a.flags.c_contiguous and b.flags.c_contiguous and out.flags.c_contiguous):
        if accumulate:
            out += a @ b
        else:
            np.matmul(a, b, out=out)
        return
    r = _DGEMM(1.0, b.T, a.T, 1.0 if accumulate else 0.0, out.T, overwrite_c=1)
    if not np.shares_memory(r, out):  # BLAS wrote into a copy
        out[...] = r.T


try:  # the BLAS numpy's linear algebra uses (scipy is a dependency); without it, numpy's matmul
    from scipy.linalg.blas import dgemm as _DGEMM
except ImportError:  # pragma: no cover
    _DGEMM = None


def _copied(value: np.ndarray, out: np.ndarray | None) -> np.ndarray:
    if out is None:
        return value
    out[...] = value
    return out


def _feature_basis(sensor: str, rot: np.ndarray, positions: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
    """(low (F, 3K), high (6, 3K) or None): the features of :func:`shift_features` -> every IMU's output (rot_k
    (K, 3, 3) from the array frame): rot_k e for a gyroscope; rot_k (Lambda p_k + e) for an accelerometer."""
    k = len(rot)
    r = rot.transpose(2, 0, 1)  # [i, k, o] = rot[k, o, i]
    if sensor == "gyroscope":
        return r.reshape(3, 3 * k), None
    lam = r[:, None, :, :] * positions.T[None, :, :, None]  # [i, j, k, o] = rot[k, o, i] p[k, j]
    sym = np.stack([lam[i, j] + lam[j, i] if i != j else lam[i, i] for i, j in zip(_ROWS, _COLS)])
    cross = np.stack([lam[2, 1] - lam[1, 2], lam[0, 2] - lam[2, 0], lam[1, 0] - lam[0, 1]])  # rot_k (w x p_k)
    low = np.concatenate([sym, cross, r], axis=0).reshape(12, 3 * k)
    return low, sym.reshape(6, 3 * k)


class TimingStage:
    """The timing terms of one chain applied as one stage: the signal at stamp + the sum of their delays
    (+ the context's stamp delays).  Quacks like a :class:`Term` in the model's chain."""

    name = "timing"
    order = TimingTerm.order

    def __init__(self, terms: list[TimingTerm], *, memo: bool = False) -> None:
        self.terms = list(terms)
        self._memo = {} if memo else None

    def memoised(self) -> "TimingStage":
        """The same stage keeping, for the last context it saw (the same object, the same positions), its
        delays and signal rates, which :meth:`apply`, :meth:`d_params_of`, :meth:`d_motion` and
        :meth:`d_positions` of one linearisation each read (the model's Jacobians): the same values, once."""
        return TimingStage(self.terms, memo=True)

    def _kept(self, ctx: MotionContext, key: tuple, make):
        """``make()``, kept under ``key`` for ``ctx`` in a memoised stage (never modified by its readers)."""
        memo = self._memo
        if memo is None:
            return make()
        if memo.get("ctx") is not ctx or memo.get("positions") is not ctx.positions:
            memo.clear()
            memo.update(ctx=ctx, positions=ctx.positions)  # held: their ids cannot be reused meanwhile
        if key not in memo:
            memo[key] = make()
        return memo[key]

    def delay(self, ctx: MotionContext, sensor: str) -> np.ndarray:
        return self._kept(ctx, ("delay", sensor), lambda: self._delay(ctx, sensor))

    def _delay(self, ctx: MotionContext, sensor: str) -> np.ndarray:
        out = np.zeros((ctx.n, ctx.k)) if ctx.stamp_delays is None else np.array(ctx.stamp_delays, dtype=float)
        for t in self.terms:
            out = out + t.delay(ctx, sensor)
        return out

    def _rate(self, ctx: MotionContext, sensor: str) -> np.ndarray:
        return self._kept(ctx, ("rate", sensor), lambda: signal_rate(ctx, sensor))

    def _rate0(self, ctx: MotionContext, sensor: str, delta: np.ndarray) -> np.ndarray:
        """The trajectory's own rate at the stamps (:func:`_rate_along` at zero delays)."""
        return self._kept(ctx, ("rate0", sensor), lambda: _rate_along(ctx, sensor, np.zeros_like(delta)))

    def delays(self, ctx: MotionContext, sensors=("accelerometer", "gyroscope")) -> dict[str, np.ndarray]:
        """:meth:`delay` of several sensors (each term counted for the sensors it acts on), the delays that are
        the same for both (the clocks', the stamp delays) computed once; the sums in the order of
        :meth:`delay`."""
        base = None if ctx.stamp_delays is None else np.array(ctx.stamp_delays, dtype=float)
        out = {sensor: base for sensor in sensors}
        for t in self.terms:
            on = [sensor for sensor in sensors if sensor in t.sensors]
            shared = t.delay(ctx, on[0]) if on and t.same_for_sensors else None
            for sensor in on:
                v = shared if shared is not None else t.delay(ctx, sensor)
                out[sensor] = v if out[sensor] is None else out[sensor] + v
        return {sensor: np.zeros((ctx.n, ctx.k)) if d is None else np.broadcast_to(d, (ctx.n, ctx.k))
                for sensor, d in out.items()}

    @staticmethod
    def shift_basis(ctx: MotionContext, sensor: str, maps: np.ndarray | None = None):
        """What :meth:`shift` maps the features of :func:`shift_features` with: every IMU's rotation to its
        sensor frame, then ``maps`` (K, 3, 3) (None: none), times its position; per array, not per sample."""
        rot = ctx.rot_t if maps is None else np.matmul(maps, ctx.rot_t)  # (K, 3, 3): array frame -> output
        return _feature_basis(sensor, rot, ctx.positions)

    def shift(self, ctx: MotionContext, sensor: str, maps: np.ndarray | None = None,
              delta: np.ndarray | None = None, *, basis=None, out: np.ndarray | None = None,
              chunk: int = 512) -> np.ndarray:
        """(N, K, 3) what the stage adds to the signal, ``apply(x) - x`` (it does not depend on x), mapped by
        ``maps`` (K, 3, 3), the linear maps that follow the stage in the chain (None: none; ``basis``: their
        :meth:`shift_basis`, when already known).  ``delta``: the stage's delays of ``sensor`` (None:
        computed); ``out``: an (N, K, 3) array to write it into.

        Along the fusion's local cubics (a :class:`~imu_array_ros.model.trajectory.MotionTrajectory`) or without
        a trajectory (first order), the shift is a polynomial in each reading's delay whose coefficients are
        shared by all IMUs (:func:`shift_features`): one matrix product gives every IMU's coefficients in its
        sensor frame, and Horner's rule in the (N, K) delays the shift, in chunks of samples that stay in
        cache.  Equal to :meth:`apply` to rounding.  Along another trajectory (the simulator's truth):
        :meth:`apply`."""
        if delta is None:
            delta = self.delay(ctx, sensor)
        n, k = ctx.n, ctx.k
        if out is None or not out.flags.c_contiguous:
            return _copied(self.shift(ctx, sensor, maps, delta, basis=basis, out=np.empty((n, k, 3)), chunk=chunk),
                           out)
        feats = shift_features(ctx, sensor)
        if feats is None:
            y = self.apply(np.zeros((n, k, 3)), ctx, sensor)
            out[...] = y if maps is None else np.einsum("kij,nkj->nki", maps, y)
            return out
        low, high = feats
        low_basis, high_basis = self.shift_basis(ctx, sensor, maps) if basis is None else basis
        # order j's coefficients of every reading: features (c, F) @ basis (F, 3K), accumulated by Horner's rule
        orders = [(f, low_basis) for f in low] + ([] if high is None else [(f, high_basis) for f in high])
        flat = out.reshape(n, 3 * k)
        step = max(min(chunk, n), 1)
        de = np.empty((step, 3 * k))  # the delays, one per output
        delta = np.asarray(delta, dtype=float)
        for lo in range(0, n, step):
            hi = min(lo + step, n)
            d, y = de[:hi - lo], flat[lo:hi]
            for o in range(3):
                d[:, o::3] = delta[lo:hi]
            for j in range(len(orders) - 1, -1, -1):  # y = (..(u_M d + u_M-1) d + ..) d
                f, b = orders[j]
                _gemm(np.ascontiguousarray(f[:, lo:hi].T), b, y, accumulate=j < len(orders) - 1)
                y *= d
        return out

    def apply(self, x, ctx, sensor):
        delta = self.delay(ctx, sensor)
        first = delta[..., None] * self._rate(ctx, sensor)
        if ctx.trajectory is None:
            return x + first
        return x + first + self.remainder(ctx, sensor, delta)

    def remainder(self, ctx: MotionContext, sensor: str, delta: np.ndarray) -> np.ndarray:
        """(N, K, 3) what the trajectory says the first-order shift leaves out: the exact shift along it minus
        its own first-order shift (second and higher order in the delay; independent of the sample's motion).
        The rates come from :meth:`_rate0` / :meth:`_rate`: kept for d_params_of by a memoised stage.

        Along a trajectory with slopes it reads only the trajectory, the stamps, the delays, the positions and the
        rotations, not the sample's motion: with ``ctx.remainders`` (a dict the caller keeps for contexts of the
        same samples on the same trajectory, e.g. the fitting engine's motion steps on a frozen trajectory) the
        last one computed per sensor is kept there and returned again, the same array, while the delays, the
        positions and the rotations are equal to those it was computed with (compared in full: exact)."""
        held = ctx.remainders
        if held is None or not hasattr(ctx.trajectory, "slope_at"):
            return self._remainder(ctx, sensor, delta)
        entry = held.get(sensor)
        if (entry is not None and entry[0].shape == np.shape(delta) and np.array_equal(entry[0], delta)
                and np.array_equal(entry[1], ctx.positions) and np.array_equal(entry[2], ctx.rotations)):
            return entry[3]
        value = self._remainder(ctx, sensor, delta)
        held[sensor] = (np.array(delta, dtype=float), np.array(ctx.positions), np.array(ctx.rotations), value)
        return value

    def _remainder(self, ctx: MotionContext, sensor: str, delta: np.ndarray) -> np.ndarray:
        if hasattr(ctx.trajectory, "slope_at"):
            rate0 = self._rate0(ctx, sensor, delta)
        else:  # a trajectory without slopes (the simulator's truth): the context's own rates
            rate0 = self._rate(ctx, sensor)
        return exact_shift(ctx, sensor, delta) - delta[..., None] * rate0

    def d_input(self, x, ctx, sensor):
        return None

    def d_params_of(self, term: TimingTerm, x, ctx, sensor):
        """(N, K, 3, P) d apply / d theta_k of one member term: the first-order rate, plus, along a trajectory
        that gives slopes, the change of its rate between the stamp and the reading's own time."""
        rate = self._rate(ctx, sensor)
        if ctx.trajectory is not None and hasattr(ctx.trajectory, "slope_at"):
            delta = self.delay(ctx, sensor)
            rate = rate + self._kept(ctx, ("rate_along", sensor), lambda: _rate_along(ctx, sensor, delta)) \
                - self._rate0(ctx, sensor, delta)
        return rate[..., None] * term.d_delay(ctx, sensor)[:, :, None, :]

    def d_motion(self, x, ctx, sensor):
        out = np.zeros(x.shape + (9,))  # the remainder along a trajectory is held: only the first order moves
        d = self.delay(ctx, sensor)  # (N, K)
        rt = ctx.rot_t
        if sensor == "gyroscope":
            if ctx.omega_rate is None:  # the rate is the sample's own omega_dot
                out[..., 3:6] = d[..., None, None] * rt[None]
            return out
        # d(C_dot p)/d omega = -[w_dot]x[p]x - [w_dot x p]x = (w_dot . p) I + w_dot p^T - 2 p w_dot^T, and
        # d/d omega_dot = -[w x p]x - [w]x[p]x the same with w: R^T of it, (a . p) R^T + (R^T a) p^T - 2 (R^T p) a^T
        out[..., 0:3] = d[..., None, None] * _lag_rows(ctx.omega_dot, rt, ctx.positions)
        out[..., 3:6] = d[..., None, None] * _lag_rows(ctx.omega, rt, ctx.positions)
        return out

    def d_positions(self, x, ctx, sensor):
        if sensor == "gyroscope":
            return None
        d = self.delay(ctx, sensor)
        return d[..., None, None] * np.einsum("kji,njl->nkil", ctx.rotations, ctx.lever_dot)  # d R^T C_dot p / d p
