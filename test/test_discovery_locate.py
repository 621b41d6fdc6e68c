"""Localising the residual excess: cells, regimes, spectra, time spans and the rigid-body test."""

from __future__ import annotations

import json

import numpy as np
import pytest

from imu_array_ros.discovery.excess import REGIMES
from imu_array_ros.discovery.locate import localize
from imu_array_ros.discovery.rigid import rigid_body_test
from imu_array_ros.discovery.spectra import relative_psd

N, K, FS = 4000, 8, 100.0
NAMES = [f"imu_{i}" for i in range(K)]
STAMPS = np.arange(N, dtype=np.int64) * 10_000_000 + 1_700_000_000 * 10**9
T = np.arange(N) / FS


def random_motion(rng, n=N):
    """Independent omega, omega_dot and s, mostly moving."""
    return np.column_stack([rng.normal(0, 2.0, (n, 3)), rng.normal(0, 10.0, (n, 3)),
                            rng.normal(0, 3.0, (n, 3)) + [0.0, 0.0, 9.81]])


def random_rotations(rng, k):
    q, _ = np.linalg.qr(rng.normal(size=(k, 3, 3)))
    return q * np.sign(np.linalg.det(q))[:, None, None]


@pytest.fixture
def white():
    rng = np.random.default_rng(7)
    return rng.normal(size=(N, K, 6)), np.ones((N, K, 6)), random_motion(rng)


def test_white_noise_has_no_finding(white):
    r, e, m = white
    loc = localize(r, e, m, STAMPS, NAMES)
    assert not loc.significant.any()
    assert loc.entries() == []
    assert loc.spans == []
    assert np.allclose(loc.ratio, 1.0, atol=0.1)
    # relative PSD: white unit noise ~ 1 at every frequency, DC and Nyquist included
    assert loc.psd.shape == (K, 6, len(loc.freqs)) and loc.freqs[-1] == pytest.approx(FS / 2)
    mean_f = loc.psd.mean(axis=(0, 1))
    assert np.all(np.abs(mean_f - 1.0) < 0.1)
    assert set(loc.regime_ratio) == set(REGIMES) and loc.regime_samples["near_saturation"] == 0
    json.dumps(loc.to_dict(spectra=True))


def test_sinusoid_located_in_sensor_axis_and_band(white):
    r, e, m = white
    r = r.copy()
    r[:, 2, 2] += 0.8 * np.sin(2 * np.pi * 30.0 * T)
    r[:, 7, 2] += 0.8 * np.sin(2 * np.pi * 30.0 * T + 1.0)
    loc = localize(r, e, m, STAMPS, NAMES)
    assert set(zip(*np.nonzero(loc.significant))) == {(2, 2), (7, 2)}
    entries = loc.entries()
    assert len(entries) >= 1
    assert all(set(x) - {"mode"} == {"sensors", "sensor_shares", "axes", "regime", "band_hz", "share_of_excess"} for x in entries)
    sensors = {s for x in entries for s in x["sensors"]}
    assert sensors == {"imu_2", "imu_7"}
    for x in entries:
        assert x["axes"] == ["acc_z"]
        lo, hi = x["band_hz"]
        assert lo <= 30.0 <= hi and hi - lo < 10.0
        assert x["regime"] == "all"  # a vibration independent of the motion belongs to no regime
    assert sum(x["share_of_excess"] for x in entries) > 0.5
    assert [x["share_of_excess"] for x in entries] == sorted((x["share_of_excess"] for x in entries), reverse=True)
    # the excess is confined to the PSD near 30 Hz
    peak = loc.freqs[np.argmax(loc.psd[2, 2])]
    assert abs(peak - 30.0) < 1.0
    json.dumps(loc.to_dict())


def test_excess_at_high_rate_is_fast_rotation(white):
    r, e, m = white
    r = r.copy()
    wn = np.linalg.norm(m[:, :3], axis=1)
    fast = wn > np.percentile(wn, 85)
    r[fast, 1, 3] *= 3.0
    loc = localize(r, e, m, STAMPS, NAMES)
    entries = loc.entries()
    assert len(entries) == 1
    assert entries[0]["sensors"] == ["imu_1"] and entries[0]["axes"] == ["gyr_x"]
    assert entries[0]["regime"] == "fast_rotation"
    assert loc.regime_ratio["fast_rotation"][1, 3] > 2 * loc.regime_ratio["moving"][1, 3] > 2.0


def test_time_span_of_a_burst(white):
    r, e, m = white
    r = r.copy()
    burst = (T >= 12.0) & (T < 15.0)
    r[burst] *= 1.5
    loc = localize(r, e, m, STAMPS, NAMES)
    assert loc.spans == [(12.0, 15.0)]
    assert loc.window_ratio.shape == (40,) and loc.window_ratio_by_imu.shape == (40, K)
    assert np.all(loc.window_ratio_by_imu[12:15] > 1.5)


def test_masks_and_edge_cases(white):
    r, e, m = white
    r, e, m = r.copy(), e.copy(), m.copy()
    r[:, 4] = np.nan                     # IMU 4 missing throughout
    e[:, 4] = np.nan
    r[100:200] = np.nan                  # dropped samples
    e[100:200] = np.nan
    m[100:200] = np.nan
    sat = np.zeros((N, K, 6), bool)
    sat[::3, 0, 0] = True
    loc = localize(r, e, m, STAMPS, NAMES, near_saturation=sat)
    assert np.all(np.isnan(loc.ratio[4])) and not loc.significant[4].any()
    assert loc.entries() == []
    assert loc.regime_samples["near_saturation"] == np.count_nonzero(sat[:, 0, 0] & np.isfinite(r[:, 0, 0]))
    assert np.all(np.isfinite(loc.psd[[0, 1, 2, 3, 5, 6, 7]]))
    d = loc.to_dict(spectra=True)
    json.dumps(d, allow_nan=False)
    # everything masked: NaN ratios, no crash
    nan = np.full((N, K, 6), np.nan)
    loc = localize(nan, nan, m, STAMPS, NAMES)
    assert np.all(np.isnan(loc.ratio)) and loc.entries() == []
    json.dumps(loc.to_dict(spectra=True), allow_nan=False)
    # short recording: no spectra, band [0, 0]
    rs = r[:40].copy()
    rs[:, 3, 5] += 4.0
    loc = localize(rs, e[:40], m[:40], STAMPS[:40], NAMES)
    assert len(loc.freqs) == 0 and loc.psd.shape == (K, 6, 0)
    ent = loc.entries()
    assert len(ent) == 1 and ent[0]["band_hz"] == [0.0, 0.0] and ent[0]["sensors"] == ["imu_3"]


def test_relative_psd_convention():
    rng = np.random.default_rng(3)
    x = rng.normal(0, 2.0, (20000, 2))
    x[::4, 1] = np.nan                   # 25 % masked: rescaled by the valid fraction
    f, p = relative_psd(x, 50.0)
    assert p.shape == (2, len(f))
    assert np.allclose(p.mean(axis=1), 4.0, rtol=0.05)
    assert abs(p[0, 0] - 4.0) < 1.5 and abs(p[0, -1] - 4.0) < 1.5


@pytest.fixture
def rigid_setup():
    rng = np.random.default_rng(11)
    k, n = 8, 3000
    rot = random_rotations(rng, k)
    pos = rng.uniform(-0.05, 0.05, (k, 3))
    std = rng.uniform(0.01, 0.05, (k, 3))
    s = rng.normal(0, 0.05, (n, 3))
    c = rng.normal(0, 1.0, (n, 3, 3))
    field = s[:, None, :] + np.einsum("nij,kj->nki", c, pos)         # affine in position, array frame, m/s^2
    sensor = np.einsum("kji,nkj->nki", rot, field)                    # R_k^T e
    r = sensor / std + rng.normal(size=(n, k, 3))
    return rng, rot, pos, std, r


def test_rigid_affine_field_is_rigid(rigid_setup):
    rng, rot, pos, std, r = rigid_setup
    test = rigid_body_test(r, rot, pos, std)
    assert test.ratio == pytest.approx(1.0, abs=0.05)
    assert test.samples == len(r) and np.all(test.dof == 3 * 8 - 12)
    # the same through localize (acc residuals huge per cell, but affine)
    n = len(r)
    res = np.concatenate([r, rng.normal(size=(n, 8, 3))], axis=2)
    m = random_motion(rng, n)
    loc = localize(res, np.ones_like(res), m, STAMPS[:n], NAMES, rotations=rot, positions=pos, acc_std=std)
    assert loc.rigid_ratio == pytest.approx(1.0, abs=0.05)
    assert np.all(loc.rigid_by_imu < 0.3)


def test_rigid_offset_imu_is_found(rigid_setup):
    rng, rot, pos, std, r = rigid_setup
    r = r.copy()
    r[:, 5] += np.array([10.0, -8.0, 6.0])     # IMU 5 offset (sigma units): not an affine field
    r[::7, 2] = np.nan                          # IMU 2 partly missing: per-sample weights
    r[::11, :4] = np.nan                        # only 4 accelerometers left: sample skipped
    test = rigid_body_test(r, rot, pos, std)
    assert test.ratio > 5.0
    assert int(np.argmax(test.by_imu)) == 5 and test.by_imu[5] > 0.3
    assert np.nansum(test.by_imu) == pytest.approx(1.0)
    assert np.all(np.isnan(test.statistic[::11])) and np.all(test.dof[::11] == 0)
    assert set(np.unique(test.dof[test.dof > 0])) == {12.0, 9.0}


def test_rigid_planar_array_drops_unidentifiable_directions(rigid_setup):
    rng, rot, pos, std, r = rigid_setup
    pos = pos.copy()
    pos[:, 2] = 0.0                             # coplanar: C[:, 2] unidentifiable
    n = len(r)
    s = rng.normal(0, 0.05, (n, 3))
    c = rng.normal(0, 1.0, (n, 3, 3))
    field = s[:, None, :] + np.einsum("nij,kj->nki", c, pos)
    r = np.einsum("kji,nkj->nki", rot, field) / std + rng.normal(size=(n, 8, 3))
    test = rigid_body_test(r, rot, pos, std)
    assert np.all(test.dof == 3 * 8 - 9)
    assert test.ratio == pytest.approx(1.0, abs=0.05)
