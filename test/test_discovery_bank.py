"""The template-bank mode test (discovery/bank.py): a board mode spread thinly over the array at moderate SNR is
found and located; its family-wise false-alarm rate on white noise is near its level (binomial bounds); one
IMU's coloured noise (coherent across the field channels over a broad band) gives no mode."""

from __future__ import annotations

import numpy as np
from scipy.signal import lfilter

from imu_array_ros.discovery.bank import bank_scan
from imu_array_ros.discovery.coherent import field_basis, field_channels
from imu_array_ros.discovery.modes import detect_modes
from imu_array_ros.discovery.spectra import merge_windows
from plate_modes import FS, K, N, POS, resonance, rotations, smooth_shape


def test_bank_finds_a_moderate_mode_spread_over_the_array():
    """An 8 Hz resonance 0.3 Hz wide at 0.15 noise std per channel at most over 16 IMUs: the bank finds it in its
    band, and the mode search with it locates it on the IMUs of largest amplitude."""
    shape = smooth_shape()
    for seed in range(2):
        rng = np.random.default_rng(seed)
        rot = rotations(rng)
        r = rng.normal(size=(N, K, 6))
        field = 0.15 * resonance(rng, 8.0, 0.3)[:, None, None] * shape[None, :, None] * np.array([0.2, -0.1, 1.0])
        r[:, :, :3] += np.einsum("kji,nkj->nki", rot, field)
        bank = bank_scan(field_channels(r, field_basis(POS, rot)), FS, 0.01 / 3)
        assert bank is not None and bank["cands"]
        p, lo, hi, _, _ = bank["cands"][0]
        assert lo <= 8.0 <= hi and hi - lo < 4.0 and p < 1e-4
        modes = detect_modes(r, FS, positions=POS, rotations=rot, heldout=False, coherent="bank").modes
        assert len(modes) == 1 and modes[0].test.startswith("coherent bank")
        assert modes[0].band_hz[0] <= 8.0 <= modes[0].band_hz[1]
        assert np.max(np.abs(shape[modes[0].imus[:3]])) > 0.5


def test_bank_family_wise_rate_on_white_noise_is_near_its_level():
    """200 white recordings of 3 field channels (768 samples): the bank at level 0.1 fires on at most 32 (P < 1 %
    at a true rate of 0.1) and on at least 2: conservative (Bonferroni over the 4 widths, a Gumbel tail; 5 of 200
    at this seed), not blind."""
    rng = np.random.default_rng(11)
    alarms = sum(bool(bank_scan(rng.normal(size=(768, 3)), 100.0, 0.1)["cands"]) for _ in range(200))
    assert 2 <= alarms <= 32


def test_bank_quiet_on_one_imus_coloured_noise():
    """One IMU's first-order Gauss-Markov noise (1.5 noise stds, 0.2 s) projects on several field channels at
    once, coherent over a broad band: the local level absorbs it, no mode at 0.01."""
    for seed in range(3):
        rng = np.random.default_rng([seed, 5])
        rot = rotations(rng)
        r = rng.normal(size=(N, K, 3))
        a = np.exp(-1.0 / (0.2 * FS))
        r[:, 0] += 1.5 * lfilter([np.sqrt(1 - a * a)], [1.0, -a], rng.normal(size=(N, 3)), axis=0)
        assert bank_scan(field_channels(r, field_basis(POS, rot)), FS, 0.01)["cands"] == []


def test_merge_windows_joins_touching_and_overlapping_windows_keeping_the_smallest_p():
    # (p, lo, hi, peak, width), given out of order
    cands = [(0.05, 23, 30, 28, 8),     # overlaps the next: the union 20..30, p 0.02's fields
             (0.001, 13, 15, 14, 3),    # touches 10..12: the union 10..15 with its own (smaller) p, peak and width
             (0.02, 20, 25, 22, 6),
             (0.01, 10, 12, 11, 3),
             (0.3, 32, 33, 32, 2),      # one empty bin after 30: separate when only touching counts
             (0.5, 40, 50, 45, 11),
             (0.1, 42, 44, 43, 3),      # inside 40..50: hi stays 50, the smaller p's fields
             (0.1, 45, 46, 46, 2),      # tie on p: the first (lower start) is kept
             (0.2, 54, 55, 54, 2)]      # three empty bins after 50: separate even with max_gap 2
    assert merge_windows(cands, 0) == [(0.001, 10, 15, 14, 3), (0.02, 20, 30, 22, 6), (0.3, 32, 33, 32, 2),
                                       (0.1, 40, 50, 43, 3), (0.2, 54, 55, 54, 2)]
    assert merge_windows(cands, 2) == [(0.001, 10, 15, 14, 3), (0.02, 20, 33, 22, 6), (0.1, 40, 50, 43, 3),
                                       (0.2, 54, 55, 54, 2)]
    assert merge_windows(cands[:1], 2) == cands[:1] and merge_windows([], 0) == []
