"""Board modes on a small planar grid for the mode-search tests (test_discovery_modes_low, test_discovery_bank):
the grid, random IMU orientations, a resonance's waveform and a smooth plate shape no rigid motion absorbs."""

from __future__ import annotations

import numpy as np
from scipy.signal import lfilter

__all__ = ["FS", "N", "POS", "K", "rotations", "resonance", "smooth_shape"]

FS, N = 50.0, 2000
_G = np.linspace(-0.01, 0.01, 4)
POS = np.array([[x, y, 0.0] for x in _G for y in _G])               # a 4 x 4 planar grid, 2 cm
K = len(POS)


def rotations(rng, k=K):
    """k random proper rotations (IMU orientations)."""
    q, _ = np.linalg.qr(rng.normal(size=(k, 3, 3)))
    return q * np.sign(np.linalg.det(q))[:, None, None]


def resonance(rng, f, bw, n=N):
    """n samples at FS of a unit-variance second-order resonance at f (Hz), about bw (Hz) wide."""
    r = np.exp(-np.pi * bw / FS)
    x = lfilter([1.0], [1.0, -2 * r * np.cos(2 * np.pi * f / FS), r * r], rng.normal(size=n + 1000))[1000:]
    return x / x.std()


def smooth_shape():
    """A quadratic plate shape over the grid with its affine part removed (what no rigid motion absorbs)."""
    q = (POS - POS.mean(axis=0)) / 0.01
    shape = q[:, 0] ** 2 + 0.5 * q[:, 0] * q[:, 1] - 0.7 * q[:, 1] ** 2
    aff = np.c_[np.ones(K), q[:, :2]]
    shape = shape - aff @ np.linalg.lstsq(aff, shape, rcond=None)[0]
    return shape / np.abs(shape).max()
