"""The coherent mode test (discovery/coherent.py): a low-frequency board mode spread thinly over many IMUs, too
weak in every channel for the per-channel and pooled scans, is found, located and banded; white noise and rigid
fields give none; a line-only cell group gets the band of its line, not [0, 0]."""

from __future__ import annotations

import numpy as np

from imu_array_ros.discovery.coherent import coherent_scan, field_basis, field_channels
from imu_array_ros.discovery.locate import localize
from imu_array_ros.discovery.modes import detect_modes, mode_segment
from plate_modes import FS, K, N, POS, resonance, rotations, smooth_shape


def _with_mode(rng, amp, f=3.5, bw=1.0):
    """White normalised residuals plus a 1 Hz wide resonance at f, mostly out of plane, amp x shape (noise stds)."""
    rot = rotations(rng)
    r = rng.normal(size=(N, K, 6))
    field = amp * resonance(rng, f, bw)[:, None, None] * smooth_shape()[None, :, None] * np.array([0.2, -0.1, 1.0])
    r[:, :, :3] += np.einsum("kji,nkj->nki", rot, field)                # array frame -> sensor frames
    return r, rot


def test_low_frequency_mode_spread_over_the_array_is_found_coherently():
    """A 3.5 Hz resonance at <= 0.15 noise std per channel over 16 IMUs: no channel nor the pooled mean stands out
    (the scans alone find nothing), the coherent test finds it with its band, on the IMUs of largest amplitude."""
    shape = smooth_shape()
    for seed in range(3):
        rng = np.random.default_rng(seed)
        r, rot = _with_mode(rng, 0.15)
        assert detect_modes(r, FS, positions=POS, heldout=False).modes == []   # scans only (no rotations)
        modes = detect_modes(r, FS, positions=POS, rotations=rot, heldout=False).modes
        assert len(modes) == 1
        m = modes[0]
        assert m.test.startswith("coherent")
        assert m.band_hz[0] <= 3.5 <= m.band_hz[1] and m.band_hz[1] - m.band_hz[0] < 3.0
        assert int(np.argmax(np.abs(shape))) in m.imus
        assert {a for _, a in m.channels} <= {0, 1, 2}                  # accelerometers
        assert np.max(np.abs(shape[m.imus[:3]])) > 0.5                  # the strongest IMUs lead


def test_coherent_test_quiet_on_white_noise_and_rigid_fields():
    """No coherent mode on white residuals, nor from a strong narrowband field affine in position (what the
    motion absorbs: specific force and angular acceleration) seen through anisotropic noise stds and
    rotated sensors: the field basis is orthogonal to it; the family-wise rate of the test on white noise
    stays at its level."""
    rng = np.random.default_rng(7)
    rot = rotations(rng)
    std = rng.uniform(0.01, 0.05, (K, 3))
    basis = field_basis(POS, rot, std)
    assert basis.shape[1] == 3 * 3                                      # x^2, xy, y^2 beyond affine, 3 axes
    # a rigid field (s + C p, every entry a 2 Hz line) in SI, normalised per sensor axis: nothing on the basis
    line = np.sin(2 * np.pi * 2.0 * np.arange(N) / FS)
    s = rng.normal(size=3)
    c = rng.normal(size=(3, 3)) * 50.0
    field = line[:, None, None] * (s[None, None, :] + np.einsum("ij,kj->ki", c, POS)[None])   # (N, K, 3)
    acc = np.einsum("kji,nkj->nki", rot, field) / std
    assert np.max(np.abs(field_channels(acc, basis))) < 1e-8 * np.max(np.abs(acc))
    # the family-wise false-alarm rate on white noise at a loose level
    nper = mode_segment(N, FS)
    alarms = 0
    for _ in range(40):
        v = field_channels(rng.normal(size=(N, K, 3)), basis)
        alarms += bool(coherent_scan(v, FS, nper, 0.2)["cands"])
    assert alarms <= 15                                                 # 8 expected at most; P(> 15) < 1 %
    r = rng.normal(size=(N, K, 6))
    r[:, :, :3] += 3.0 * acc / np.abs(acc).max()
    found = detect_modes(r, FS, positions=POS, rotations=rot, std=np.c_[std, std], heldout=False).modes
    assert not any(m.test.startswith("coherent") for m in found)         # the per-channel scans see the line


def test_line_only_cells_are_banded_by_their_line():
    """Cells significant only by the narrowband line test (no broadband excess: O about E) get the band of the
    bins that test flagged, not the 80 % band of a signed excess that is mostly noise (it was [0, 0])."""
    rng = np.random.default_rng(3)
    n, k = 6000, 4
    t = np.arange(n) / 100.0
    r = 0.985 * rng.normal(size=(n, k, 6))
    r[:, 0, 2] += 0.2 * np.sin(2 * np.pi * 31.0 * t)
    motion = np.column_stack([rng.normal(0, 2.0, (n, 3)), rng.normal(0, 10.0, (n, 3)), rng.normal(0, 3.0, (n, 3))])
    stamps = np.arange(n, dtype=np.int64) * 10_000_000
    loc = localize(r, np.ones_like(r), motion, stamps, [f"imu_{i}" for i in range(k)], modes=False)
    assert loc.line[0, 2] and not np.any(loc.z[0, 2] > loc.z_threshold)
    entries = loc.entries()
    assert entries and all(e["band_hz"] != [0.0, 0.0] for e in entries)
    e = next(e for e in entries if "imu_0" in e["sensors"] and "acc_z" in e["axes"])
    assert e["band_hz"][0] <= 31.0 <= e["band_hz"][1] and e["band_hz"][1] - e["band_hz"][0] < 2.0
