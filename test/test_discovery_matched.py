"""The matched-resonance mode test (discovery/matched.py) and the smooth field basis: a low-frequency resonance on
the 8-corner layout that the Welch coherent test misses is found by detect_modes; the scan keeps its family-wise
level on white noise; one IMU's coloured noise gives no mode; the thickness quadratics leave the basis."""

from __future__ import annotations

import numpy as np
import pytest

from imu_array_ros.discovery.modes import detect_modes
from imu_array_ros.model.sensor_model import SensorModel
from imu_array_ros.simulation.effects import narrowband_process
from imu_array_ros.simulation.suites import array_description

FS, SECONDS = 62.5, 25.0


@pytest.fixture(scope="module")
def corners():
    return SensorModel.from_description(array_description("corners8"))


def _residuals(model, seed, amp, f=4.0, bw=1.8):
    """White normalised residuals of the corner layout plus a resonance at f (Hz, bw wide) along ~z with a saddle
    shape (x y plus a uniform part, as the suite draws them), amp noise stds at the largest IMU."""
    rng = np.random.default_rng(seed)
    n = int(SECONDS * FS)
    stamps = (np.arange(n) * 1e9 / FS).astype(np.int64)
    p = model.positions - model.positions.mean(axis=0)
    shape = p[:, 0] * p[:, 1] / np.max(np.abs(p[:, 0] * p[:, 1])) - 0.3
    shape /= np.max(np.abs(shape))
    d = np.array([0.1, 0.25, 1.0]) / np.linalg.norm([0.1, 0.25, 1.0])
    x = narrowband_process(stamps, f, bw, rng)
    field = amp * x[:, None, None] * shape[None, :, None] * d                      # (N, K, 3) array frame
    r = rng.normal(size=(n, len(p), 6))
    r[:, :, :3] += np.einsum("kji,nkj->nki", model.rotations, field)              # sensor frames
    return r, shape


def test_low_frequency_resonance_on_the_corner_layout_is_found(corners):
    """4 Hz, 1.8 Hz wide, 25 s at 62.5 Hz on the 8 corner IMUs (the generalisation suite's missed 'vibration 5' of
    seed 283334, evidence 233) at 0.22 noise std: found at its frequency on a largest-amplitude IMU in 3 of 3
    draws (the code before matched.py and the smooth basis, 683064b, found 1 of the 3; 3 of 3 from 0.3)."""
    for seed in range(3):
        r, shape = _residuals(corners, seed, 0.22)
        modes = detect_modes(r, FS, positions=corners.positions, rotations=corners.rotations, heldout=False).modes
        at_f = [m for m in modes if m.band_hz[0] <= 4.0 <= m.band_hz[1]]
        assert at_f, f"seed {seed}: no mode at 4 Hz ({[(m.frequency_hz, m.band_hz) for m in modes]})"
        lead = set(np.flatnonzero(np.abs(shape) > 0.999).tolist())
        assert lead & set(at_f[0].imus)
        assert len(modes) == 1


def test_matched_scan_keeps_its_family_wise_level_on_white_noise(corners):
    """40 white recordings at alpha 0.25: at most 18 with a candidate (binomial 99.9 % bound: a law that were not
    family-wise, a count of correlated templates, would alarm on nearly all)."""
    from imu_array_ros.discovery.coherent import field_basis
    from imu_array_ros.discovery.matched import matched_scan

    basis = field_basis(corners.positions, corners.rotations, min_scale=0.25)
    rng = np.random.default_rng(5)
    alarms = sum(bool(matched_scan(rng.normal(size=(1024, 24)), basis, FS, 0.25)["cands"]) for _ in range(40))
    assert alarms <= 18


def test_one_imus_coloured_noise_gives_no_mode(corners):
    """One IMU's accelerometers with first-order Gauss-Markov noise 3 x the white noise (0.3 s): broadband,
    coloured on one IMU, coherent across the field channels it projects on; no matched candidate at 0.01."""
    from scipy.signal import lfilter

    from imu_array_ros.discovery.coherent import field_basis
    from imu_array_ros.discovery.matched import matched_scan

    basis = field_basis(corners.positions, corners.rotations, min_scale=0.25)
    n = int(SECONDS * FS)
    a = np.exp(-1.0 / (0.3 * FS))
    for seed in range(4):
        rng = np.random.default_rng([seed, 9])
        acc = rng.normal(size=(n, 8, 3))
        acc[:, seed % 8] += 3.0 * np.sqrt(1 - a * a) * lfilter([1.0], [1.0, -a], rng.normal(size=(n, 3)), axis=0)
        assert matched_scan(acc.reshape(n, 24), basis, FS, 0.01)["cands"] == []


def test_field_basis_keeps_the_quadratics_a_smooth_mode_can_excite(corners):
    """The corner layout (IMUs stacked 2 mm apart across 19 mm): 9 quadratic field directions, 3 of them (the
    in-plane saddle along each axis) at least 0.25 of the largest; a planar grid loses none."""
    from imu_array_ros.discovery.coherent import field_basis

    assert field_basis(corners.positions, corners.rotations).shape[1] == 9
    b = field_basis(corners.positions, corners.rotations, min_scale=0.25)
    assert b.shape == (24, 3)
    assert np.allclose(b.T @ b, np.eye(3))
    grid = SensorModel.from_description(array_description("planar4"))
    assert field_basis(grid.positions, grid.rotations, min_scale=0.25).shape[1] == \
        field_basis(grid.positions, grid.rotations).shape[1]
