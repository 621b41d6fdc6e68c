"""Where the residuals exceed the noise: by sensor, axis, motion regime, time, frequency and geometry.

:func:`localize` takes the normalised residuals ``r = (y - h(theta_hat)) / sigma`` of a
fitted model, (N, K, 6) for N samples, K IMUs and the axes
:data:`~imu_array_ros.fusion.residuals.AXES` (NaN = masked), and their expectation under
the model ``E[r^2] = 1 - leverage``; every statistic compares an observed sum
``O = sum r^2`` with its expected value ``E = sum E[r^2]`` over a set of readings.
The statistics, one module each:

* ratio, z and significance of a cell (IMU k, axis a), the split by **regime** of the
  fitted motion and by **time**: :mod:`~imu_array_ros.discovery.excess`;
* by **frequency** (relative PSD, the band of a finding, the narrowband line test):
  :mod:`~imu_array_ros.discovery.spectra`;
* **narrowband modes** shared across the array (frequency, band, mode shape, when present,
  held-out empirical model): :mod:`~imu_array_ros.discovery.modes`;
* by **geometry** (rigid-body test of the accelerometer residual field):
  :mod:`~imu_array_ros.discovery.rigid`.

:meth:`Localization.entries` groups the significant cells into findings (see there).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from imu_array_ros.discovery.excess import (
    REGIMES,
    excess_ratio,
    excess_z,
    is_significant,
    merge_spans,
    regime_masks,
    regime_sums,
    window_sums,
)
from imu_array_ros.discovery.rigid import RigidTest, rigid_body_test
from imu_array_ros.discovery.modes import ModeSearch, detect_modes
from imu_array_ros.discovery.spectra import imu_spectra, line_bins, narrowest_band
from imu_array_ros.fusion.residuals import AXES
from imu_array_ros.util.jsontools import json_safe

__all__ = ["Localization", "localize"]

#: a regime needs this fraction of the samples to be reported for a finding
MIN_REGIME_FRACTION = 0.05
#: a regime is named only when its excess per expected unit is this many times that of the other samples
REGIME_CONTRAST = 2.0


@dataclass
class Localization:
    """Where the residual exceeds the noise (statistics: the modules named in the module docstring).

    names: K IMU names.  observed, expected, ratio, z, significant: (K, 6) over all
    samples.  regime_observed / regime_expected / regime_ratio: regime -> (K, 6);
    regime_samples: regime -> number of samples; n_samples: samples with any valid
    reading.  windows (W,) s since the first stamp (window starts), window_ratio (W,),
    window_ratio_by_imu (W, K), spans: [(t0, t1)] s of merged significant windows.
    freqs (F,) Hz and psd (K, 6, F): relative PSD (white noise of variance v -> v);
    floor (K, 6): the white level (mean E[r^2]).  rigid: :class:`RigidTest` or None.
    line (K, 6): cells significant by the narrowband line test (included in ``significant``); line_bins
    (K, 6, F): the bins that test flagged.
    modes: the :class:`~imu_array_ros.discovery.modes.ModeSearch` (None when not run).
    """

    names: tuple[str, ...]
    observed: np.ndarray
    expected: np.ndarray
    ratio: np.ndarray
    z: np.ndarray
    significant: np.ndarray
    regime_observed: dict[str, np.ndarray]
    regime_expected: dict[str, np.ndarray]
    regime_ratio: dict[str, np.ndarray]
    regime_samples: dict[str, int]
    n_samples: int
    windows: np.ndarray
    window_ratio: np.ndarray
    window_ratio_by_imu: np.ndarray
    spans: list[tuple[float, float]]
    freqs: np.ndarray
    psd: np.ndarray
    floor: np.ndarray
    rigid: RigidTest | None = None
    window_s: float = 1.0
    z_threshold: float = 5.0
    rate_hz: float = float("nan")
    line: np.ndarray | None = None
    modes: ModeSearch | None = None
    line_bins: np.ndarray | None = None
    _groups: list | None = field(default=None, repr=False)

    # ---- conveniences
    @property
    def rigid_ratio(self) -> float:
        """Non-affine accelerometer field ratio (NaN when the rigid test was skipped)."""
        return self.rigid.ratio if self.rigid is not None else float("nan")

    @property
    def rigid_by_imu(self) -> np.ndarray:
        """(K,) share of the non-affine sum of squares per IMU (NaN when skipped)."""
        return self.rigid.by_imu if self.rigid is not None else np.full(len(self.names), np.nan)

    def _cells(self, cells) -> np.ndarray:
        """(K, 6) bool from a (K, 6) mask or an iterable of (k, a) pairs."""
        arr = np.asarray(cells)
        if arr.dtype == bool and arr.shape == self.ratio.shape:
            return arr
        mask = np.zeros(self.ratio.shape, dtype=bool)
        for k, a in cells:
            mask[int(k), int(a)] = True
        return mask

    def band_hz(self, cells) -> list[float]:
        """[lo, hi] Hz: narrowest band holding >= 80 % of the summed excess PSD of ``cells``
        ((k, a) pairs or a (K, 6) mask); [0, 0] without spectra or without excess.  Cells significant by the
        line test only (no broadband excess): the span of their flagged bins (the signed excess of a line far
        below the noise is mostly noise, and its 80 % band anywhere, DC included)."""
        if len(self.freqs) == 0:
            return [0.0, 0.0]
        m = self._cells(cells)
        if self.line_bins is not None and self.line is not None:
            broadband = is_significant(self.observed, self.expected, self.z_threshold)
            hits = np.flatnonzero(self.line_bins[m].any(axis=0)) if not broadband[m].any() else []
            if len(hits):
                half = 0.5 * (self.freqs[1] - self.freqs[0])
                return [max(0.0, float(self.freqs[hits[0]] - half)), float(self.freqs[hits[-1]] + half)]
        excess = np.nansum(np.where(m[..., None], self.psd - self.floor[..., None], 0.0), axis=(0, 1))
        return narrowest_band(self.freqs, excess)

    def _band_excess(self, imus, axes, band) -> dict | None:
        """IMU -> its excess PSD summed over ``axes`` and the bins of ``band`` (None without spectra): where a
        narrowband mismatch is, the broadband sums are mostly noise."""
        if len(self.freqs) == 0:
            return None
        half = 0.5 * (self.freqs[1] - self.freqs[0]) if len(self.freqs) > 1 else 0.0
        sel = (self.freqs >= band[0] - half) & (self.freqs <= band[1] + half)
        ex = self.psd[:, axes][:, :, sel] - self.floor[:, axes, None]
        return {i: float(np.nansum(ex[i])) for i in imus}

    def regime_of(self, cells) -> str:
        """The regime where the ratio of ``cells`` is largest among regimes with >= 5 % of the samples."""
        m = self._cells(cells)
        best, best_ratio = "moving", -np.inf
        for regime in REGIMES:
            if self.regime_samples[regime] < MIN_REGIME_FRACTION * max(self.n_samples, 1):
                continue
            r = excess_ratio(self.regime_observed[regime][m].sum(), self.regime_expected[regime][m].sum())
            if np.isfinite(r) and r > best_ratio:
                best, best_ratio = regime, float(r)
        if np.isfinite(best_ratio):  # "all" unless the excess per expected unit is twice that of the other samples
            obs = self.observed[m].sum() - self.regime_observed[best][m].sum()
            exp = self.expected[m].sum() - self.regime_expected[best][m].sum()
            rest = excess_ratio(obs, exp)
            if np.isfinite(rest) and best_ratio - 1.0 < REGIME_CONTRAST * (rest - 1.0):
                return "all"
        return best

    # ---- findings
    def _findings(self) -> list[dict]:
        """Significant cells grouped (see :meth:`entries`), unsorted, with their cell masks."""
        if self._groups is not None:
            return self._groups
        cands = []
        for k in range(len(self.names)):
            for block in (range(0, 3), range(3, 6)):
                axes = tuple(a for a in block if self.significant[k, a])
                if axes:
                    cands.append({"imus": [k], "axes": axes, "band": self.band_hz([(k, a) for a in axes])})
        groups = []
        for axes in sorted({c["axes"] for c in cands}):
            same = sorted((c for c in cands if c["axes"] == axes), key=lambda c: c["band"][0])
            cur = None
            for c in same:  # merge the IMUs whose bands overlap
                if cur is not None and c["band"][0] <= cur["band"][1]:
                    cur["imus"] += c["imus"]
                    cur["band"] = [cur["band"][0], max(cur["band"][1], c["band"][1])]
                else:
                    cur = {"imus": list(c["imus"]), "axes": axes, "band": list(c["band"])}
                    groups.append(cur)
        exc = self.observed - self.expected
        total = float(np.nansum(np.clip(exc, 0.0, None)))
        out = []
        for g in groups:
            mask = np.zeros(self.ratio.shape, dtype=bool)
            mask[np.ix_(sorted(g["imus"]), list(g["axes"]))] = True
            share = float(np.nansum(exc[mask])) / total if total > 0 else 0.0
            per = self._band_excess(g["imus"], list(g["axes"]), self.band_hz(mask))
            if per is None:
                per = {i: float(np.nansum(exc[i, list(g["axes"])])) for i in g["imus"]}
            imus = sorted(per, key=lambda i: (-per[i], i))  # the IMU carrying most of the excess first
            denom = sum(max(v, 0.0) for v in per.values())
            out.append({"mask": mask, "sensors": [self.names[i] for i in imus],
                        "sensor_shares": [max(per[i], 0.0) / denom if denom > 0 else 0.0 for i in imus],
                        "axes": [AXES[a] for a in g["axes"]], "regime": self.regime_of(mask),
                        "band_hz": self.band_hz(mask), "share_of_excess": share})
        self._groups = out
        return out

    def entries(self, max_entries: int = 10) -> list[dict]:
        """Findings, largest share first: dicts with keys sensors, axes, regime, band_hz, share_of_excess.

        Grouping: the significant cells of one IMU and one sensor (accelerometer
        axes, gyroscope axes) form a candidate; candidates with the same axis set
        whose frequency bands overlap are merged into one finding listing several
        IMUs (e.g. acc_z of imu_02 and imu_07, both at 30 Hz).  Per finding, over
        all its cells: regime = the regime of largest ratio among those with >= 5 %
        of the samples (note: for an excess that does not depend on the motion this
        is whichever regime is largest by chance); band_hz = :meth:`band_hz`;
        share_of_excess = its O - E over the total positive excess of all cells;
        sensors ordered by their own excess power in the finding's axes and band, largest first,
        with sensor_shares (their shares of it): a mismatch on a few IMUs leaks
        into the others through the fitted motion (which averages over all IMUs),
        so the IMUs that carry it come first, the leaks after.

        Narrowband modes (:meth:`mode_entries`, key "mode" with their detail) are
        entries too, on top of the ``max_entries`` largest groups; a group whose
        cells are all a mode's and whose band overlaps the mode's is that mode.
        """
        groups = self._findings()
        modes = self.mode_entries()
        mode_cells = [{(k, a) for k, a in zip(*np.nonzero(m["mask"]))} for m in modes]
        kept = []
        for g in groups:  # a broadband group inside a mode's cells and band is that mode
            cells = {(k, a) for k, a in zip(*np.nonzero(g["mask"]))}
            if not any(cells <= mc and g["band_hz"][0] <= m["band_hz"][1] and m["band_hz"][0] <= g["band_hz"][1]
                       for m, mc in zip(modes, mode_cells)):
                kept.append(g)
        rows = sorted(kept, key=lambda g: -g["share_of_excess"])[:max_entries]  # the modes come on top of these
        rows = sorted(rows + modes, key=lambda g: -g["share_of_excess"])
        out = []
        for g in rows:
            e = {"sensors": list(g["sensors"]), "sensor_shares": [float(v) for v in g["sensor_shares"]],
                 "axes": list(g["axes"]), "regime": g["regime"],
                 "band_hz": [float(g["band_hz"][0]), float(g["band_hz"][1])],
                 "share_of_excess": float(g["share_of_excess"])}
            if "mode" in g:
                e["mode"] = g["mode"]
            out.append(e)
        return out

    def mode_entries(self) -> list[dict]:
        """The narrowband modes as entries (:meth:`entries`' keys plus "mode": the mode's detail and "mask");
        share_of_excess: the positive O - E of the mode's cells over the total positive excess (as a group's)."""
        if self.modes is None:
            return []
        exc = self.observed - self.expected
        total = float(np.nansum(np.clip(exc, 0.0, None)))
        out = []
        for m in self.modes.modes:
            e = m.entry(self.names)
            mask = np.zeros(self.ratio.shape, dtype=bool)
            for k, a in m.channels:
                mask[k, a] = True
            e["mask"] = mask
            e["share_of_excess"] = max(float(np.nansum(exc[mask])), 0.0) / total if total > 0 else 0.0
            out.append(e)
        return out

    def to_dict(self, *, spectra: bool = False, max_entries: int = 10) -> dict:
        """JSON-serialisable summary (plain floats and lists, None for NaN); ``spectra`` adds freqs and psd."""
        names = list(self.names)
        total_o, total_e = float(np.nansum(self.observed)), float(np.nansum(self.expected))
        out = {
            "names": names, "axes": list(AXES), "n_samples": self.n_samples, "rate_hz": self.rate_hz,
            "z_threshold": self.z_threshold,
            "ratio_all": float(excess_ratio(total_o, total_e)), "z_all": float(excess_z(total_o, total_e)),
            "ratio": self.ratio, "z": self.z, "observed": self.observed, "expected": self.expected,
            "significant": [[names[k], AXES[a]] for k, a in zip(*np.nonzero(self.significant))],
            "regime_ratio": {r: self.regime_ratio[r] for r in REGIMES},
            "regime_samples": {r: int(self.regime_samples[r]) for r in REGIMES},
            "window_s": self.window_s, "windows": self.windows, "window_ratio": self.window_ratio,
            "window_ratio_by_imu": self.window_ratio_by_imu, "spans": [list(s) for s in self.spans],
            "rigid": self.rigid.to_dict(names) if self.rigid is not None else None,
            "entries": self.entries(max_entries),
            "modes": None if self.modes is None else {
                **self.modes.summary(), "found": [m.to_dict(names) for m in self.modes.modes],
                "motion_lines": [m.to_dict(names) for m in self.modes.motion_lines]},
        }
        if spectra:
            out["freqs"] = self.freqs
            out["psd"] = self.psd
            out["floor"] = self.floor
        return json_safe(out)


def localize(residuals: np.ndarray, expected: np.ndarray, motion: np.ndarray, stamps: np.ndarray, names, *,
             near_saturation: np.ndarray | None = None, rotations: np.ndarray | None = None,
             positions: np.ndarray | None = None, acc_std: np.ndarray | None = None,
             still_threshold: float = 0.2, window_s: float = 1.0, gravity: float = 9.80665,
             z_threshold: float = 5.0, std: np.ndarray | None = None, modes: bool = True) -> Localization:
    """Locate the residual excess of a fitted recording.

    residuals, expected: (N, K, 6) normalised residuals and E[r^2] = 1 - leverage
    (NaN where masked; a reading counts when both are finite).  motion (N, 9) =
    [omega rad/s, omega_dot rad/s^2, s m/s^2] in the array frame (NaN rows:
    dropped samples).  stamps (N,) int64 ns.  names: K IMU names.
    near_saturation: (N, K, 6) bool or None.  rotations (K, 3, 3) sensor -> array,
    positions (K, 3) m and acc_std (K, 3) m/s^2 enable the rigid-body test.
    still_threshold rad/s; window_s s; gravity m/s^2; z_threshold: see
    :mod:`~imu_array_ros.discovery.excess`.  std (K, 6) noise stds (else acc_std for the
    accelerometers): mode amplitudes in SI units.  modes: run the narrowband mode search
    (:func:`~imu_array_ros.discovery.modes.detect_modes`).
    """
    r = np.asarray(residuals, dtype=float)
    e = np.asarray(expected, dtype=float)
    if r.ndim != 3 or r.shape[2] != 6 or e.shape != r.shape:
        raise ValueError(f"residuals and expected must both be (N, K, 6), got {r.shape} and {e.shape}")
    n, k = r.shape[:2]
    names = tuple(str(x) for x in names)
    if len(names) != k:
        raise ValueError(f"{len(names)} names for {k} IMUs")
    motion = np.asarray(motion, dtype=float).reshape(n, 9)
    stamps = np.asarray(stamps, dtype=np.int64).reshape(n)
    valid = np.isfinite(r) & np.isfinite(e)
    r2 = np.where(valid, r, 0.0) ** 2
    ev = np.where(valid, e, 0.0)
    o_all, e_all = r2.sum(axis=0), ev.sum(axis=0)

    # ---- regimes
    masks = regime_masks(motion, still_threshold, gravity)
    reg_o, reg_e, reg_n = regime_sums(r2, ev, valid, masks, near_saturation)

    # ---- time windows
    t = (stamps - stamps[0]) * 1e-9 if n else np.zeros(0)
    starts, o_w, e_w, o_wk, e_wk = window_sums(t, r2, ev, window_s)
    spans = merge_spans(starts, is_significant(o_w, e_w, z_threshold), window_s)

    # ---- spectra (per IMU: bounded memory)
    dt = np.diff(t)
    fs = 1.0 / float(np.median(dt)) if len(dt) and np.median(dt) > 0 else float("nan")
    freqs, psd = imu_spectra(r, valid, fs)
    nv = valid.sum(axis=0)
    floor = excess_ratio(e_all, nv)
    bins = line_bins(psd, floor, n)
    line = bins.any(axis=-1)
    significant = is_significant(o_all, e_all, z_threshold) | line
    search = None
    if modes:
        if std is None and acc_std is not None:
            std = np.concatenate([np.asarray(acc_std, dtype=float).reshape(k, 3), np.full((k, 3), np.nan)], axis=1)
        search = detect_modes(r, fs, valid=valid, positions=positions, rotations=rotations, std=std,
                              still=masks["still"], motion=motion)

    # ---- rigid body
    rigid = None
    if rotations is not None and positions is not None and acc_std is not None and k >= 5:
        rigid = rigid_body_test(np.where(valid[:, :, :3], r[:, :, :3], np.nan), rotations, positions, acc_std)

    return Localization(
        names=names, observed=o_all, expected=e_all, ratio=excess_ratio(o_all, e_all), z=excess_z(o_all, e_all),
        significant=significant, line=line, line_bins=bins,
        regime_observed=reg_o, regime_expected=reg_e,
        regime_ratio={regime: excess_ratio(reg_o[regime], reg_e[regime]) for regime in REGIMES},
        regime_samples={regime: reg_n[regime] for regime in REGIMES},
        n_samples=int(np.count_nonzero(valid.any(axis=(1, 2)))),
        windows=starts, window_ratio=excess_ratio(o_w, e_w), window_ratio_by_imu=excess_ratio(o_wk, e_wk), spans=spans,
        freqs=freqs, psd=psd, floor=floor, rigid=rigid, window_s=float(window_s), z_threshold=float(z_threshold),
        rate_hz=fs, modes=search,
    )
