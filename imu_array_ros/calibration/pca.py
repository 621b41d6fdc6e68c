"""Closed-form multi-position calibration by principal component analysis (rupniewski, Algorithm 2).

Model (rupniewski eq. 1-3): m single-axis sensors read the projections of one vector quantity v_j
(|v_j| = c, eq. 2) at n positions, ``m_ij = a_i^T v_j (+ beta_i) + noise``.  ``readings`` here is the
paper's matrix **m** transposed: (n poses, m sensors).

Unbiased case -- exactly Algorithm 2:

1. truncated SVD of rank d (eq. 13-15): **m** ~ e b with e = u (m x d, orthonormal columns) and
   b = s w^T (d x n).  (The paper's text gives u in R^{n x d} and w in R^{m x d} after eq. 13; with
   **m** in R^{m x n} the two are swapped: u is m x d, w is n x d, as eq. 15 and step 4 need.)
2. the least-squares symmetric g of c^2 = b_j^T g b_j (eq. 7, Remark 3): d(d+1)/2 unknowns, hence
   n >= d(d+1)/2 poses (eq. 16);
3. g = q^T lambda q (eq. 8), which must be positive definite: otherwise the poses are (nearly)
   coplanar or the noise too large for them, and a :class:`~imu_array_ros.errors.CalibrationError` is raised;
4. v_hat = lambda^(1/2) q b (eq. 10), a_hat = lambda^(-1/2) q e^T (eq. 11).

a_hat^T v_hat is the rank-d truncation of the readings; (a_hat, v_hat) equal (a, v) up to one
orthogonal matrix multiplying both from the left (Remark 1), reflections included.

Biased case (accelerometers under gravity: a still measurement does not remove their biases) --
our extension.  r_j = A^T v_j + beta lies in a d-dimensional *affine* subspace of R^m, so:

1. centred PCA (Pearson's planes of closest fit pass through the centroid): r_bar = mean_j r_j,
   truncated SVD of rank d of r_j - r_bar gives an orthonormal E (m x d) and coordinates
   x_j = E^T (r_j - r_bar) (d); noiseless, r_j = r_bar + E x_j exactly and v_j = A' (x_j - x0) for
   some invertible A' (d x d) and centre x0 (d).  This is the Eckart-Young optimum over affine
   d-dimensional subspaces, and unlike a rank-(d+1) linear fit it needs no separate "constant
   direction": it works for beta = 0 and for m = d (one triad: an ellipsoid fit);
2. |v_j|^2 = c^2 says that the x_j lie on the ellipsoid (x - x0)^T G (x - x0) = c^2 (G = A'^T A'), i.e. on
   the quadric x^T G x + 2 h^T x + k = 0 (h = -G x0, k = x0^T G x0 - c^2).  Its coefficients
   theta = (G, h, k) are linear in the data but defined only up to a common factor (k absorbs c^2), so
   they are the *homogeneous* least-squares solution: the right singular vector of the smallest singular
   value of the n x (d(d+1)/2 + d + 1) design matrix [x_j^T G x_j terms, 2 x_j, 1] (coordinates scaled to
   unit RMS).  A fit of x^T G x + 2 h^T x + kappa = c^2 with kappa free is rank deficient (the scale
   of (G, h, kappa - c^2) is free): noiseless it has a null space, noisy it is ill-posed.  The
   d(d+1)/2 + d + 1 coefficients up to scale are d(d+3)/2 unknowns: n >= d(d+3)/2 = 9 poses for d = 3
   (an ellipsoid through 9 generic points is unique; nilsson2014 counts 9 parameters per triad, too);
3. the scale is fixed by c: x0 = -G^-1 h, rho = h^T G^-1 h - k, G' = G c^2 / rho (any common factor of
   theta cancels).  G' must be positive definite (else the quadric is no ellipsoid: poses degenerate or
   noise too large);
4. G' = q^T lambda q, A' = lambda^(1/2) q (eq. 8-9), v_j = A' (x_j - x0), a = lambda^(-1/2) q E^T
   (eq. 11 with e = E), beta = r_bar + E x0.

The rank-d reconstruction a^T v + beta is then the centred rank-d truncation; ``residual_rms`` is its RMS
misfit.  Like eq. 7, the quadric is fitted to noisy coordinates (errors in variables), so g and G carry a
relative bias of O(sigma^2 / c^2 per axis) -- small against the O(sigma / (c sqrt n)) scatter unless n is
huge (``benchmarks/results/rupniewski_fig34.md`` for Algorithm 2, ``test_pca_array_noisy`` for the biased fit).

Arrays (:func:`pca_array`): the 3K accelerometer axes of K IMUs are m = 3K sensors with v_j = s_j, the
specific force of pose j in the array frame.  The block of IMU k of a^T is T_k = M_k Rbar_k^T with
M_k = K_k L_k (I + [xi_k]x) (nilsson2014 eq. 1-2: gain, unit lower-triangular non-orthogonality,
first-order misalignment; the chain of :mod:`imu_array_ros.model.sensor_model`) and Rbar_k the nominal
sensor -> array rotation.  PCA gives T_hat_k = T_k Omega^T, s_hat = Omega s for an unknown orthogonal
Omega.  xi_ref = 0 defines the array frame, i.e. M_ref = T_hat_ref Omega Rbar_ref is lower triangular with
positive diagonal: the LQ decomposition T_hat_ref Rbar_ref = L Q gives Omega = Rbar_ref Q^T Rbar_ref^T
(unique, reflection included).  Then M_k = T_hat_k Omega Rbar_k for every IMU, and
M_k = K L (I + [xi]x) is solved exactly in closed form, row by row (row 0 of M_k is k_x times row 0 of
I + [xi]x: xi_y, xi_z; the 2 x 2 system of row 1 gives (KL)_10, (KL)_11 and then xi_x; then
KL = M_k (I + [xi]x)^-1) -- no iteration needed.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from imu_array_ros.errors import CalibrationError
from imu_array_ros.model.constants import STANDARD_GRAVITY
from imu_array_ros.model.reference import reference_index
from imu_array_ros.model.terms.triad import triads_in_reference_frame

__all__ = ["PcaResult", "ArrayPca", "ARRAY_TERMS", "pca_calibrate", "pca_array", "calibration_error",
           "upper_triangular_form"]

#: the terms :func:`pca_array` estimates (registry names), in the order of the chain's factors K L (I + [xi]x) + b
ARRAY_TERMS = ("accelerometer_gain", "accelerometer_nonorthogonality", "accelerometer_misalignment",
               "accelerometer_bias")

#: relative size below which a singular value / triangular pivot counts as zero (exact degeneracy)
_RANK_TOL = 1e-10


@dataclass(frozen=True)
class PcaResult:
    """Result of :func:`pca_calibrate` (leading batch axes ``...`` when the readings had them).

    a (..., d, m): sensitivity vectors a_i as columns; v (..., d, n): the vector quantity of every pose;
    bias (..., m): zeros when unbiased; singular_values (..., min(n, m)) of the readings (of the centred
    readings when biased); residual_rms: RMS of readings - (v^T a + bias), the rank-d (affine when
    biased) reconstruction's misfit.  Defined up to an orthogonal matrix multiplying a and v (Remark 1).
    """

    a: np.ndarray
    v: np.ndarray
    bias: np.ndarray
    magnitude: float
    dim: int
    biased: bool
    singular_values: np.ndarray
    residual_rms: float | np.ndarray

    def predict(self) -> np.ndarray:
        """The reconstructed readings (..., n, m) = v^T a + bias."""
        return np.swapaxes(self.v, -1, -2) @ self.a + self.bias[..., None, :]


@dataclass(frozen=True)
class ArrayPca:
    """Result of :func:`pca_array`.

    values: term name (:data:`ARRAY_TERMS`) -> (K, 3), skipped IMUs at identity and the reference's
    misalignment 0; specific_force (P, 3): every pose in the array frame (NaN for poses not used);
    reference: the reference IMU's name; skipped: IMUs without readings; poses (P,): True for the
    poses used (no missing reading of a kept IMU); pca: the :class:`PcaResult` of the kept IMUs' 3K'
    axes (columns in IMU order, x y z); seconds: wall time.
    """

    values: dict[str, np.ndarray]
    specific_force: np.ndarray
    reference: str
    skipped: tuple[str, ...]
    poses: np.ndarray
    pca: PcaResult
    seconds: float

    def calibrated(self, model):
        """``model`` (a :class:`~imu_array_ros.model.sensor_model.SensorModel`) with these values set."""
        return model.with_terms(**self.values)


# --------------------------------------------------------------------------- helpers (batched)


def _quadratic_design(x: np.ndarray) -> np.ndarray:
    """(B, n, d) -> (B, n, d(d+1)/2): x^T g x = row . (upper triangle of g), off-diagonals doubled."""
    i, j = np.triu_indices(x.shape[-1])
    return x[..., i] * x[..., j] * np.where(i == j, 1.0, 2.0)


def _symmetric(theta: np.ndarray, d: int) -> np.ndarray:
    """(B, d(d+1)/2) upper triangles -> (B, d, d) symmetric matrices."""
    i, j = np.triu_indices(d)
    g = np.zeros(theta.shape[:-1] + (d, d))
    g[..., i, j] = theta
    g[..., j, i] = theta
    return g


def _lstsq(design: np.ndarray, rhs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Batched least squares by QR: (B, n, p), (B, n) -> solutions (B, p), rank deficient (B,)."""
    q, r = np.linalg.qr(design)
    piv = np.abs(np.diagonal(r, axis1=-2, axis2=-1))
    bad = piv.min(axis=-1) <= _RANK_TOL * piv.max(axis=-1)
    r = np.where(bad[:, None, None], np.eye(r.shape[-1]), r)
    rhs_q = np.einsum("bnp,bn->bp", q, rhs)
    return np.linalg.solve(r, rhs_q[..., None])[..., 0], bad


def _raise_failures(failures: list[tuple[np.ndarray, str]], batch: int) -> None:
    for bad, message in failures:
        count = int(np.count_nonzero(bad))
        if count:
            prefix = f"{count} of {batch} reading sets: " if batch > 1 else ""
            raise CalibrationError(prefix + message)


# --------------------------------------------------------------------------- PCA calibration


def pca_calibrate(readings, magnitude: float, *, dim: int = 3, biased: bool = False) -> PcaResult:
    """Sensitivity vectors and poses from ``readings`` (n poses, m sensors) of a vector of known
    ``magnitude`` (rupniewski Algorithm 2; ``biased``: the affine extension of the module docstring).

    Leading batch axes (..., n, m) are calibrated independently (one batched SVD / QR / eigh), e.g. for
    Monte Carlo.  Raises :class:`~imu_array_ros.errors.CalibrationError` for too few poses
    (n < d(d+1)/2, biased n < d(d+3)/2), non-finite readings, degenerate poses or an indefinite g.
    """
    x = np.asarray(readings, dtype=float)
    d = int(dim)
    c = float(magnitude)
    if x.ndim < 2:
        raise CalibrationError(f"readings must be (n poses, m sensors), got shape {x.shape}")
    n, m = x.shape[-2:]
    if d < 1:
        raise CalibrationError(f"dim must be >= 1, got {dim}")
    if not (np.isfinite(c) and c > 0):
        raise CalibrationError(f"the magnitude must be finite and > 0, got {magnitude}")
    if biased:
        need = d * (d + 3) // 2
        if n < need:
            raise CalibrationError(f"{n} poses < d(d+3)/2 = {need} needed for a biased PCA calibration with d = {d} "
                                   f"(an ellipsoid of {need} parameters in R^{d})")
    elif n < d * (d + 1) // 2:
        raise CalibrationError(f"{n} poses < d(d+1)/2 = {d * (d + 1) // 2} needed for d = {d} (rupniewski eq. 16)")
    if m < d:
        raise CalibrationError(f"{m} sensors < d = {d}: their readings cannot span {d} dimensions")
    if not np.all(np.isfinite(x)):
        raise CalibrationError(f"{np.count_nonzero(~np.isfinite(x))} readings are not finite")
    lead = x.shape[:-2]
    x = x.reshape((-1, n, m))
    batch = x.shape[0]

    centre = x.mean(axis=1) if biased else np.zeros((batch, m))
    w, s, vh = np.linalg.svd(x - centre[:, None, :] if biased else x, full_matrices=False)
    flat = s[:, d - 1] <= _RANK_TOL * s[:, 0]
    e_t = vh[:, :d, :]                                  # e^T (B, d, m)
    coords = w[:, :, :d] * s[:, None, :d]               # b^T (eq. 15) or x_j (B, n, d)
    scale = np.sqrt(np.sum(s[:, :d] ** 2, axis=-1) / n)  # RMS |coords_j|: a dimensionless least-squares problem
    scale = np.where(scale > 0, scale, 1.0)
    xs = coords / scale[:, None, None]
    p = d * (d + 1) // 2
    if biased:                                          # homogeneous: x~^T G x~ + 2 h^T x~ + k = 0
        design = np.concatenate([_quadratic_design(xs), 2.0 * xs, np.ones((batch, n, 1))], axis=-1)
        _, sd, vd = np.linalg.svd(design, full_matrices=True)     # vd (B, 10, 10) also when n = 9
        theta = vd[:, -1, :]
        deficient = sd[:, design.shape[-1] - 2] <= _RANK_TOL * sd[:, 0]
    else:                                               # c^2 = b_j^T g b_j (eq. 7) as b~_j^T g~ b~_j = 1
        theta, deficient = _lstsq(_quadratic_design(xs), np.ones((batch, n)))
    g = _symmetric(theta[:, :p], d)
    lam, vec = np.linalg.eigh(g)                        # g = vec diag(lam) vec^T: q = vec^T (eq. 8)
    if biased:
        h, k = theta[:, p:p + d], theta[:, -1]
        tiny = np.abs(lam) <= _RANK_TOL * np.abs(lam).max(axis=-1, keepdims=True)
        lam_safe = np.where(tiny, 1.0, lam)
        ginv_h = np.einsum("bij,bj,bkj,bk->bi", vec, 1.0 / lam_safe, vec, h)
        rho = np.einsum("bi,bi->b", h, ginv_h) - k
        rho = np.where(rho == 0, np.nan, rho)
        lam = lam / rho[:, None]                        # G' of step 3 (in the scaled coordinates, c = 1)
        centre_x = -ginv_h * scale[:, None]             # x0
        deficient |= tiny.any(axis=-1)
    else:
        centre_x = np.zeros((batch, d))
    indefinite = ~(lam.min(axis=-1) > 0) & ~deficient & ~flat
    lam = np.where(lam > 0, lam, np.nan) * (c / scale[:, None]) ** 2
    q = np.swapaxes(vec, -1, -2)
    root = np.sqrt(lam)
    v = root[:, :, None] * (q @ np.swapaxes(coords - centre_x[:, None, :], -1, -2))   # eq. 10
    a = (q @ e_t) / root[:, :, None]                                                   # eq. 11
    bias = centre + np.einsum("bdm,bd->bm", e_t, centre_x) if biased else np.zeros((batch, m))
    rms = np.sqrt(np.sum(s[:, d:] ** 2, axis=-1) / (n * m))

    what = "the quadric of |v_j| = c (module docstring, step 2)" if biased else "g of rupniewski eq. 7"
    _raise_failures([
        (flat, f"the readings span fewer than {d} dimensions (singular values "
               f"{', '.join(f'{val:.3g}' for val in s[np.argmax(flat), :d + 1])}, ...): the poses are coplanar "
               f"or the sensors' axes do not span {d} dimensions"),
        (deficient & ~flat, f"the poses do not determine {what} (rupniewski Remark 1): too few distinct poses or "
                            "poses on a common quadric"),
        (indefinite, ("the fitted quadric is not an ellipsoid (eigenvalues of G/rho not all > 0)" if biased else
                      "g of rupniewski eq. 7 is not positive definite") +
                     f": the {n} poses are (nearly) coplanar or the noise is too large for them"),
    ], batch)
    one = lambda arr, k: arr.reshape(lead + arr.shape[1:]) if k else arr[0]  # noqa: E731
    keep = len(lead) > 0
    return PcaResult(a=one(a, keep), v=one(v, keep), bias=one(bias, keep), magnitude=c, dim=d, biased=bool(biased),
                     singular_values=one(s, keep), residual_rms=(rms.reshape(lead) if keep else float(rms[0])))


def upper_triangular_form(a: np.ndarray) -> np.ndarray:
    """h a with h orthogonal and h a upper triangular with positive diagonal (rupniewski Sec. IV); (..., d, m)."""
    q, r = np.linalg.qr(np.asarray(a, dtype=float))
    sign = np.sign(np.diagonal(r, axis1=-2, axis2=-1))
    return r * np.where(sign == 0, 1.0, sign)[..., :, None]


def calibration_error(a: np.ndarray, a_hat: np.ndarray) -> np.ndarray:
    """rupniewski eq. 19: ||h a - k a_hat||_F with both in :func:`upper_triangular_form`; (..., d, m) -> (...)."""
    return np.linalg.norm(upper_triangular_form(a) - upper_triangular_form(a_hat), axis=(-2, -1))


# --------------------------------------------------------------------------- arrays of accelerometer triads


def pca_array(accel, model, *, reference: int | str = 0, gravity: float = STANDARD_GRAVITY,
              biased: bool = True) -> ArrayPca:
    """Accelerometer gain, non-orthogonality, misalignment and bias of every IMU, closed form, from
    ``accel`` (P, K, 3): per-pose averaged readings at rest (own sensor frames) of ``model``'s K IMUs.

    ``reference`` (index or name) defines the array frame (its misalignment is 0); ``gravity`` is |s| at
    rest; ``biased=False`` assumes bias-free readings (bias 0, 6 poses suffice).  An IMU with an axis
    that reads NaN in every pose is skipped (identity values, named in ``skipped``); a pose with any
    other missing reading is not used.  The values replace (not add to) the model's current ones.
    """
    t0 = time.perf_counter()
    accel = np.asarray(accel, dtype=float)
    k = model.n_imus
    names = tuple(model.names)
    if accel.ndim != 3 or accel.shape[1:] != (k, 3):
        raise CalibrationError(f"accelerometer readings must be (poses, {k}, 3) for this array, got {accel.shape}")
    ref = reference_index(names, reference)
    finite = np.isfinite(accel)
    dead = ~finite.any(axis=0).all(axis=-1)
    if dead[ref]:
        raise CalibrationError(f"the reference IMU {names[ref]} has an axis without readings in every pose")
    kept = np.flatnonzero(~dead)
    poses = finite[:, kept].all(axis=(1, 2))
    used, total = int(poses.sum()), len(accel)
    need = 9 if biased else 6
    if used < need:
        dropped = f" ({total - used} of {total} with a missing reading)" if used < total else ""
        raise CalibrationError(f"{used} poses{dropped} < {need} needed for the {'biased' if biased else 'unbiased'} "
                               "PCA calibration of the accelerometers")
    readings = accel[poses][:, kept].reshape(used, 3 * len(kept))
    pca = pca_calibrate(readings, gravity, dim=3, biased=biased)

    rot = np.asarray(model.rotations, dtype=float)[kept]
    r = int(np.searchsorted(kept, ref))
    t_hat = pca.a.reshape(3, len(kept), 3).transpose(1, 2, 0)     # T_hat_k: row i = a_(3k+i)^T
    omega, gain, l, xi = triads_in_reference_frame(t_hat, rot, r)
    bad = np.flatnonzero(~(gain > 0).all(axis=-1))
    if len(bad):
        raise CalibrationError(f"IMU {names[kept[bad[0]]]}: estimated accelerometer gains {np.round(gain[bad[0]], 4)} "
                               "are not all > 0: its nominal orientation in the description is wrong")

    values = {"accelerometer_gain": np.ones((k, 3)), "accelerometer_nonorthogonality": np.zeros((k, 3)),
              "accelerometer_misalignment": np.zeros((k, 3)), "accelerometer_bias": np.zeros((k, 3))}
    for name, val in zip(ARRAY_TERMS, (gain, l, xi, pca.bias.reshape(len(kept), 3))):
        values[name][kept] = val
    force = np.full((total, 3), np.nan)
    force[poses] = (omega.T @ pca.v).T
    return ArrayPca(values=values, specific_force=force, reference=names[ref],
                    skipped=tuple(names[i] for i in np.flatnonzero(dead)), poses=poses, pca=pca,
                    seconds=time.perf_counter() - t0)
