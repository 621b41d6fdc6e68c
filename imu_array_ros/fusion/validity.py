"""Valid-axis masks of an array's readings: sums over the valid axes and the patterns they form.

A reading is invalid when missing (NaN) or saturated; an invalid axis gets zero
weight in the fusion (skog2016 Sec. III).  Holds, all batched over samples
without a loop over samples or patterns:

* sums over the valid axes of each sample: :func:`valid_sum` (per-axis terms,
  whole IMUs through one product), :func:`masked_product` (readings minus bias
  times a matrix), :func:`weight_sum` (per-axis weights);
* :class:`Invalid`, the invalid entries of an (n, 3K) array grouped by sample
  and IMU (which samples are saturated or incomplete, which whole IMUs are
  missing, the row of the fusion's dropout table);
* :func:`pattern_summary`: how many distinct patterns of valid axes, and the
  most common one.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from imu_array_ros.fusion.batched_linalg import BLOCK

__all__ = ["valid_sum", "masked_product", "weight_sum", "Invalid", "pattern_summary"]


def valid_sum(valid: np.ndarray, per_imu: np.ndarray, per_axis: np.ndarray) -> np.ndarray:
    """Sum over the valid axes of per-axis terms: (M, 3K) bool -> (M, p).

    ``per_axis`` (3K, p) holds each axis' term, ``per_imu`` (K, p) the sum over
    an IMU's three axes; whole IMUs (the common case) go through the (M, K)
    product, partly valid IMUs (a saturated or missing single axis) add their
    axes one by one.
    """
    m, k = valid.shape[0], per_imu.shape[0]
    v3 = valid.reshape(m, k, 3)
    whole = v3[:, :, 0] & v3[:, :, 1] & v3[:, :, 2]  # (much faster than .all(axis=2))
    out = whole.astype(float) @ per_imu
    part = np.flatnonzero(((v3[:, :, 0] | v3[:, :, 1] | v3[:, :, 2]) & ~whole).any(axis=1))
    if 2 * part.size > m:  # mostly partly valid IMUs (e.g. saturated single axes): axis by axis for all
        return valid.astype(float) @ per_axis
    if part.size:
        out[part] += (v3[part] & ~whole[part, :, None]).reshape(len(part), 3 * k).astype(float) @ per_axis
    return out


def masked_product(y: np.ndarray, invalid: np.ndarray, bias: np.ndarray, mat: np.ndarray,
                   nonfinite: np.ndarray, rows: np.ndarray | None = None, dense: bool = True) -> np.ndarray:
    """``sum over the valid axes a of (y_a - bias_a) mat[a]`` for every sample, or for the samples ``rows``.

    y (n, a) raw readings, invalid (n, a) bool (every non-finite reading is
    invalid), bias (a,), mat (a, p), nonfinite (n,) bool: samples with a
    non-finite reading -> (n, p) or (len(rows), p).  Works through blocks of
    rows in reused buffers (in cache), with ``y`` set to the bias on the invalid
    axes; when ``dense`` (many invalid axes, e.g. saturated gyros) as
    ``(y - bias) * valid`` instead in blocks without non-finite readings (NaN *
    0 is NaN), which is branch-free and faster there.
    """
    n = y.shape[0] if rows is None else len(rows)
    out = np.empty((n, mat.shape[1]))
    shape = (min(n, BLOCK), y.shape[1])
    buf, bad, keep = np.empty(shape), np.empty(shape, dtype=bool), np.empty(shape)
    bias_mat = bias @ mat
    for lo in range(0, n, BLOCK):
        hi = min(lo + BLOCK, n)
        b = buf[:hi - lo]
        if rows is None:
            np.copyto(b, y[lo:hi])
            m = invalid[lo:hi]
            clean = dense and not nonfinite[lo:hi].any()
        else:  # mode="clip": the indices are valid, and "raise" would buffer
            np.take(y, rows[lo:hi], axis=0, out=b, mode="clip")
            m = np.take(invalid, rows[lo:hi], axis=0, out=bad[:hi - lo], mode="clip")
            clean = dense and not nonfinite[rows[lo:hi]].any()
        if clean:
            b -= bias
            np.logical_not(m, out=bad[:hi - lo])
            np.copyto(keep[:hi - lo], bad[:hi - lo])
            b *= keep[:hi - lo]
            np.matmul(b, mat, out=out[lo:hi])
        else:
            np.copyto(b, bias, where=m)
            np.matmul(b, mat, out=out[lo:hi])
            out[lo:hi] -= bias_mat
    return out


def weight_sum(invalid: np.ndarray, per_axis: np.ndarray, rows: np.ndarray) -> np.ndarray:
    """``sum over the valid axes a of per_axis[a]`` for the samples ``rows``: (R, p), invalid (n, a) bool."""
    n = len(rows)
    out = np.empty((n, per_axis.shape[1]))
    shape = (min(n, BLOCK), invalid.shape[1])
    bad, keep = np.empty(shape, dtype=bool), np.empty(shape)
    for lo in range(0, n, BLOCK):
        hi = min(lo + BLOCK, n)
        m = bad[:hi - lo]
        np.take(invalid, rows[lo:hi], axis=0, out=m, mode="clip")
        np.logical_not(m, out=m)
        np.copyto(keep[:hi - lo], m)
        np.matmul(keep[:hi - lo], per_axis, out=out[lo:hi])
    return out


_SPARSE = 0.1  # share of invalid entries up to which Invalid works entry by entry


@dataclass(frozen=True)
class Invalid:
    """The invalid entries of an (n, 3K) array of readings, grouped by sample and IMU.

    rows (R,): sorted samples with an invalid axis; saturated, missing (n,) bool:
    some axis finite but invalid / not finite; per run of invalid axes of one
    IMU in one sample: ``run_pos`` (index into rows), ``run_imu``; ``first_run``
    (R,): each row's first run; ``partial`` (R,) bool: some IMU of that sample
    has only one or two invalid axes (else only whole IMUs are invalid).  With
    more than ``_SPARSE`` of all entries invalid, the runs are not worked out
    (every row counts as ``partial``, ``flat`` is None).
    """

    rows: np.ndarray
    saturated: np.ndarray
    missing: np.ndarray
    run_pos: np.ndarray
    run_imu: np.ndarray
    first_run: np.ndarray
    partial: np.ndarray
    flat: np.ndarray | None  # flat indices of the invalid entries

    @classmethod
    def of(cls, y: np.ndarray, invalid: np.ndarray, like: "Invalid | None" = None) -> "Invalid":
        """From y (n, 3K) raw readings and invalid (n, 3K) bool; works on the (few) invalid entries only.

        ``like``: the analysis of another array with the same invalid entries
        (accelerometers and gyroscopes of dropped IMUs): only the flags are redone.
        """
        n, a = invalid.shape
        if like is None and np.count_nonzero(invalid) > _SPARSE * invalid.size:  # e.g. most gyros saturated
            present = np.isfinite(y)
            rows = np.flatnonzero(invalid.any(axis=1))
            saturated = (present & invalid).any(axis=1)
            missing = ~present.all(axis=1)
            empty = np.empty(0, dtype=np.intp)
            return cls(rows, saturated, missing, empty, empty, np.zeros(len(rows), dtype=np.intp),
                       np.ones(len(rows), dtype=bool), None)
        flat = np.flatnonzero(invalid) if like is None else like.flat
        row = flat // a
        finite = np.isfinite(np.take(y, flat))
        saturated = np.zeros(n, dtype=bool)
        saturated[row[finite]] = True
        missing = np.zeros(n, dtype=bool)
        missing[row[~finite]] = True
        if like is not None:
            return replace(like, saturated=saturated, missing=missing)
        imu = (flat - row * a) // 3
        key = row * (a // 3) + imu  # sorted, like flat
        starts = np.flatnonzero(np.concatenate([[True], key[1:] != key[:-1]]))
        whole = np.diff(np.append(starts, len(key))) == 3
        run_row = row[starts]
        new_row = np.concatenate([[True], run_row[1:] != run_row[:-1]])
        run_pos = np.cumsum(new_row) - 1
        first_run = np.flatnonzero(new_row)
        partial = np.zeros(len(first_run), dtype=bool)
        partial[run_pos[~whole]] = True
        return cls(run_row[first_run], saturated, missing, run_pos, imu[starts], first_run, partial, flat)

    def missing_imus(self, k: int) -> np.ndarray:
        """(R, K) bool: IMUs with invalid axes, per row (all three of them where not ``partial``)."""
        out = np.zeros((len(self.rows), k), dtype=bool)
        out[self.run_pos, self.run_imu] = True
        return out

    def table_index(self, k: int, depth: int) -> np.ndarray:
        """(R,) row of the fusion's dropout table (:func:`~imu_array_ros.fusion.pattern_geometry.dropout_masks`)
        for each sample: 1 + i for IMU i missing, 1 + K + pair index for IMUs i < j (in ``np.triu_indices(K, 1)``
        order); -1 with partly invalid IMUs or more than ``depth`` missing."""
        if self.flat is None:
            return np.full(len(self.rows), -1)
        count = np.diff(np.append(self.first_run, len(self.run_imu)))
        first = self.run_imu[self.first_run]
        last = self.run_imu[self.first_run + count - 1]
        pair = first * (2 * k - first - 1) // 2 + (last - first - 1)
        index = np.where(count == 1, 1 + first, 1 + k + pair)
        return np.where(~self.partial & (count <= depth), index, -1)


def _distinct_rows(valid: np.ndarray) -> tuple[int, int, int]:
    """Distinct rows of ``valid`` (m, a) bool, m >= 1: their number, the most common one's count and a row index of it.

    One sort of the bit-packed rows (no loop over patterns).
    """
    m = len(valid)
    packed = np.packbits(valid, axis=1)
    pad = (-packed.shape[1]) % 8
    if pad:
        packed = np.concatenate([packed, np.zeros((m, pad), np.uint8)], axis=1)
    words = np.ascontiguousarray(packed).view(np.uint64)  # (m, w)
    order = np.lexsort(words.T[::-1])
    sw = words[order]
    first = np.ones(m, dtype=bool)
    first[1:] = (sw[1:] != sw[:-1]).any(axis=1)
    starts = np.flatnonzero(first)
    runs = np.diff(np.append(starts, m))
    top = int(np.argmax(runs))
    return len(starts), int(runs[top]), int(order[starts[top]])


def pattern_summary(valid: np.ndarray, tix: np.ndarray, table_masks: np.ndarray) -> tuple[int, np.ndarray, np.ndarray]:
    """Patterns of valid accelerometer axes and the most common one.

    valid (n, a) bool; tix (n,) the row of ``table_masks`` (P, a) that each
    sample's pattern equals, or -1.  Returns the number of distinct patterns,
    the most common pattern (a,) bool and (n,) bool which samples have it.
    Counting is by table row (``bincount``) plus one sort of the other rows'
    bit-packed patterns (:func:`_distinct_rows`): no loop over patterns.
    """
    in_table = tix >= 0
    counts = np.bincount(tix[in_table], minlength=len(table_masks))
    best = int(np.argmax(counts))
    patterns = int(np.count_nonzero(counts))
    rest = np.flatnonzero(~in_table)
    if rest.size:
        d, run, row = _distinct_rows(valid[rest])
        patterns += d
        if run > counts[best]:
            mask = valid[rest[row]]
            return patterns, mask, (valid == mask).all(axis=1)
    return patterns, table_masks[best], tix == best
