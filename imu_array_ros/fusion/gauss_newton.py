"""Gauss-Newton on the concentrated cost of the ML fusion (skog2016 eq. 10-13), batched over samples.

The cost of omega with phi = [omega_dot, s] concentrated out is the quartic
``J(omega) = q^T F~ q - 2 q^T beta~ + omega^T W_g omega - 2 omega^T g`` in the
quadratic monomials ``q = q(omega)`` (see :mod:`imu_array_ros.fusion.ml_fusion`
for ``F~``, ``beta~``, ``W_g``, ``g``).  :func:`gauss_newton` iterates

    ``omega += (Jq^T F~ Jq + W_g)^{-1} (Jq^T (beta~ - F~ q) + g - W_g omega)``

with ``Jq = dq/domega``, halving the step where the cost goes up, on all
samples at once; samples drop out of the batch as they converge.
"""

from __future__ import annotations

import math

import numpy as np

from imu_array_ros.fusion.batched_linalg import row_times, solve_sym3, take_rows
from imu_array_ros.model.kinematics import quadratic_monomials

__all__ = ["gauss_newton", "gauss_newton_one"]


def gauss_newton(omega0, TF, beta_t, Wg, g, *, max_iterations: int, tolerance: float):
    """Gauss-Newton with step halving on the concentrated cost (skog2016 eq. 12-13).

    Uses that Jq(omega) is linear in omega, so the Gauss-Newton matrix
    ``Jq^T F~ Jq = (q(omega) @ T).reshape(3, 3)`` with T (6 x 9), and
    ``Jq^T v`` has a closed form.  ``TF = [T | F~]`` is (6, 15) shared or
    (n, 6, 15) per sample, so one product gives both T and F~ terms at a
    point; ``Wg`` is (3, 3) shared or (n, 3, 3).  omega0 (n, 3) starting points,
    beta_t (n, 6) ``beta~``, g (n, 3).  Stops a sample when the step is below
    ``tolerance * (1 + |omega|)`` or after ``max_iterations``.
    Returns omega (n, 3), iterations (n,) int32, converged (n,) bool, and the
    final Gauss-Newton matrix ``Jq^T F~ Jq + W_g`` (n, 3, 3).
    """
    n = len(omega0)
    omega = omega0.copy()
    iters = np.zeros(n, dtype=np.int32)
    conv = np.zeros(n, dtype=bool)
    shared = Wg.ndim == 2
    # omega^T Wg omega = q(omega) . wq: the gyro terms fold into beta~ (bt = beta~ - wq / 2), so
    # J = q^T (F~ q - 2 bt) - 2 omega^T g and the Gauss-Newton right-hand side is Jq^T (bt - F~ q) + g
    wf = Wg.reshape(-1, 9)
    wq = np.stack([wf[:, 0], wf[:, 4], wf[:, 8], 2 * wf[:, 1], 2 * wf[:, 2], 2 * wf[:, 5]], axis=1)
    beta_t = beta_t - 0.5 * wq

    def cost(w, q, qf, bt, gg):  # qf = F~ q
        return np.einsum("ni,ni->n", q, qf - 2.0 * bt) - 2.0 * np.einsum("ni,ni->n", w, gg)

    q = quadratic_monomials(omega)
    hf = row_times(q, TF)  # (n, 15): [Jq^T F~ Jq (9) | F~ q (6)] at the current iterate
    c_cur = cost(omega, q, hf[:, 9:], beta_t, g)
    active = None  # None = all samples, else index array
    for it in range(max_iterations):
        if active is None:
            w, qa, hfa, bt, wg, gg, c0, tf = omega, q, hf, beta_t, Wg, g, c_cur, TF
        else:
            if len(active) == 0:
                break
            w, qa, hfa, bt, gg, c0 = omega[active], q[active], hf[active], beta_t[active], g[active], c_cur[active]
            wg = Wg if shared else Wg[active]
            tf = take_rows(TF, active)
        h = hfa[:, :9].reshape(-1, 3, 3) + wg
        step, ok = solve_sym3(h, _jq_transpose_times(w, bt - hfa[:, 9:]) + gg)
        new = w + step
        qn = quadratic_monomials(new)
        hfn = row_times(qn, tf)
        c1 = cost(new, qn, hfn[:, 9:], bt, gg)
        worse = c1 > c0 + 1e-12 * np.abs(c0)
        t = 1.0
        for _ in range(8):  # backtracking: halve the step where the cost went up
            if not worse.any():
                break
            t *= 0.5
            wi = np.flatnonzero(worse)
            cand = w[wi] + t * step[wi]
            qc = quadratic_monomials(cand)
            hfc = row_times(qc, take_rows(tf, wi))
            cc = cost(cand, qc, hfc[:, 9:], bt[wi], gg[wi])
            better = cc <= c0[wi] + 1e-12 * np.abs(c0[wi])
            wb = wi[better]
            new[wb], qn[wb], hfn[wb], c1[wb] = cand[better], qc[better], hfc[better], cc[better]
            worse[wb] = False
        if worse.any():
            new[worse], qn[worse], hfn[worse], c1[worse] = w[worse], qa[worse], hfa[worse], c0[worse]
        size = np.abs(new - w).max(axis=1)
        done = (size <= tolerance * (1.0 + np.abs(new).max(axis=1))) | worse | ~ok
        if active is None:
            omega, q, hf, c_cur = new, qn, hfn, c1
            iters[:] = it + 1
            conv[done & ok] = True
            if done.any():
                active = np.flatnonzero(~done)
        else:
            omega[active], q[active], hf[active], c_cur[active] = new, qn, hfn, c1
            iters[active] = it + 1
            conv[active[done & ok]] = True
            active = active[~done]
    return omega, iters, conv, hf[:, :9].reshape(-1, 3, 3) + Wg


def _jq_transpose_times(w: np.ndarray, v: np.ndarray) -> np.ndarray:
    """(dq/domega)^T v for (n, 3) omega and (n, 6) v, in closed form."""
    x, y, z = w[:, 0], w[:, 1], w[:, 2]
    return np.stack(
        [
            2 * x * v[:, 0] + y * v[:, 3] + z * v[:, 4],
            2 * y * v[:, 1] + x * v[:, 3] + z * v[:, 5],
            2 * z * v[:, 2] + x * v[:, 4] + y * v[:, 5],
        ],
        axis=1,
    )


def gauss_newton_one(omega0, TF, beta_t, Wg, g, *, max_iterations: int, tolerance: float):
    """:func:`gauss_newton` of one sample with a shared geometry, in Python floats.

    The live fusion node fuses a sample as soon as its last message arrives; a batch of one pays numpy's
    fixed cost on every one of the ~60 array operations of an iteration (~0.35 ms a sample for 32 IMUs),
    while the iteration itself is a few hundred floating-point operations.  Same iteration, same stopping
    rule, same step halving; the result equals the batched one to rounding (sums in another order).
    omega0 (1, 3), TF (6, 15), beta_t (1, 6), Wg (3, 3), g (1, 3); returns the same as :func:`gauss_newton`.
    """
    tf = np.asarray(TF, dtype=float).tolist()
    wgm = np.asarray(Wg, dtype=float).reshape(9).tolist()
    wq = (wgm[0], wgm[4], wgm[8], 2 * wgm[1], 2 * wgm[2], 2 * wgm[5])
    bt = [b - 0.5 * v for b, v in zip(np.asarray(beta_t, dtype=float).reshape(6).tolist(), wq)]
    gg = np.asarray(g, dtype=float).reshape(3).tolist()
    cols = list(zip(*tf))  # 15 columns of 6

    def at(w):  # q(w), [Jq^T F~ Jq (9) | F~ q (6)] and the cost at w
        x, y, z = w
        q = (x * x, y * y, z * z, x * y, x * z, y * z)
        hf = [q[0] * c[0] + q[1] * c[1] + q[2] * c[2] + q[3] * c[3] + q[4] * c[4] + q[5] * c[5] for c in cols]
        c = sum(q[i] * (hf[9 + i] - 2.0 * bt[i]) for i in range(6)) - 2.0 * (x * gg[0] + y * gg[1] + z * gg[2])
        return hf, c

    w = np.asarray(omega0, dtype=float).reshape(3).tolist()
    hf, c0 = at(w)
    iters, conv = 0, False
    for it in range(max_iterations):
        h = [hf[i] + wgm[i] for i in range(9)]
        x, y, z = w
        v = [bt[i] - hf[9 + i] for i in range(6)]
        r = (2 * x * v[0] + y * v[3] + z * v[4] + gg[0], 2 * y * v[1] + x * v[3] + z * v[5] + gg[1],
             2 * z * v[2] + x * v[4] + y * v[5] + gg[2])
        step, ok = _solve3(h, r)
        new = [w[i] + step[i] for i in range(3)]
        hfn, c1 = at(new)
        worse = c1 > c0 + 1e-12 * abs(c0)
        t = 1.0
        for _ in range(8):  # backtracking: halve the step where the cost went up
            if not worse:
                break
            t *= 0.5
            cand = [w[i] + t * step[i] for i in range(3)]
            hfc, cc = at(cand)
            if cc <= c0 + 1e-12 * abs(c0):
                new, hfn, c1, worse = cand, hfc, cc, False
        if worse:
            new, hfn, c1 = w, hf, c0
        size = max(abs(new[i] - w[i]) for i in range(3))
        done = size <= tolerance * (1.0 + max(abs(a) for a in new)) or worse or not ok
        w, hf, c0 = new, hfn, c1
        iters = it + 1
        if done:
            conv = ok
            break
    hmat = np.array([hf[i] + wgm[i] for i in range(9)]).reshape(1, 3, 3)
    return np.array([w]), np.array([iters], dtype=np.int32), np.array([conv]), hmat


def _solve3(h, r):
    """Solve the symmetric 3x3 ``h`` (9 floats, row-major) times x = r by cofactors, as
    :func:`~imu_array_ros.fusion.batched_linalg.solve_sym3` does for one matrix: (x, ok)."""
    a, b, c, d, e, f = h[0], h[1], h[2], h[4], h[5], h[8]
    c00, c01, c02 = d * f - e * e, c * e - b * f, b * e - c * d
    c11, c12, c22 = a * f - c * c, b * c - a * e, a * d - b * b
    det = a * c00 + b * c01 + c * c02
    diag = a * d * f
    ok = det > 1e-12 * diag and diag > 0 and math.isfinite(det)
    if not ok:
        return (0.0, 0.0, 0.0), False
    r0, r1, r2 = r
    return ((c00 * r0 + c01 * r1 + c02 * r2) / det, (c01 * r0 + c11 * r1 + c12 * r2) / det,
            (c02 * r0 + c12 * r1 + c22 * r2) / det), True
