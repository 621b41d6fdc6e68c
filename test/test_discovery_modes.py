"""Narrowband modes of the residual across the array: no false mode on nulls, located with its shape, reported."""

from __future__ import annotations

import json

import numpy as np
from scipy.signal import lfilter

from imu_array_ros.discovery.locate import localize
from imu_array_ros.discovery.modes import detect_modes

FS, N, K = 200.0, 4000, 8
STAMPS = np.arange(N, dtype=np.int64) * 5_000_000
T = np.arange(N) / FS


def _positions(rng, k=K):
    p = rng.uniform(-0.02, 0.02, (k, 3))
    p[:, 2] = 0.0
    return p


def _mode_signal(rng, f, bw=0.0):
    if bw <= 0:
        return np.sin(2 * np.pi * f * T + rng.uniform(0, 2 * np.pi))
    r = np.exp(-np.pi * bw / FS)
    x = lfilter([1.0], [1.0, -2 * r * np.cos(2 * np.pi * f / FS), r * r], rng.normal(size=N + 1000))[1000:]
    return x / x.std()


def test_no_mode_on_white_or_coloured_residuals():
    """Nulls (a few seeds here; >= 50 in benchmarks/discovery_modes.py): white residuals and residuals with a
    broadband misfit (AR(1) coloured noise and a random walk on some channels) give no mode."""
    for seed in range(4):
        rng = np.random.default_rng([seed, 41])
        r = rng.normal(size=(N, K, 6))
        assert detect_modes(r, FS, heldout=False).modes == []
        c = r.copy()
        a = rng.uniform(0.9, 0.995)
        c[:, :3] += 2.0 * lfilter([np.sqrt(1 - a * a)], [1.0, -a], rng.normal(size=(N, 3, 6)), axis=0)
        c[:, 5] += np.cumsum(rng.normal(size=(N, 6)), axis=0) / 20.0
        assert detect_modes(c, FS, heldout=False).modes == []


def test_mode_located_with_its_shape_band_and_model():
    """A mode on random IMUs with random signed gains, at a random frequency up to 0.95 Nyquist, 0.3 noise std
    at its strongest channel: found, band holding f, strongest IMU first among its IMUs, standing-wave phases
    (0 or pi), and the held-out empirical model lowers the residual of its channels."""
    for seed in range(3):
        rng = np.random.default_rng([seed, 42])
        f = float(np.exp(rng.uniform(np.log(1.0), np.log(0.95 * FS / 2))))
        imus = rng.choice(K, size=4, replace=False)
        gains = rng.choice([-1, 1], 4) * rng.uniform(0.5, 1.0, 4)
        gains[0] = 1.0
        r = rng.normal(size=(N, K, 6))
        x = _mode_signal(rng, f, bw=0.3 * seed)
        r[:, imus, 2] += 0.3 * gains[None] * x[:, None]
        found = detect_modes(r, FS, positions=_positions(rng)).modes
        assert len(found) == 1, (seed, f, [m.frequency_hz for m in found])
        m = found[0]
        df = 1.0
        assert m.band_hz[0] - df <= f <= m.band_hz[1] + df
        assert set(m.imus) <= set(imus.tolist()) and int(imus[0]) in m.imus
        assert m.axes == [2]
        ph = np.array([m.phase[k, 2] for k in m.imus])
        assert np.all(np.minimum(np.abs(ph), np.abs(np.abs(ph) - np.pi)) < 0.5)
        same = [np.sign(gains[list(imus).index(k)]) == np.sign(gains[list(imus).index(m.imus[0])]) for k in m.imus]
        assert all((abs(p) < 0.5) == s for p, s in zip(ph, same))
        assert m.model["improves_heldout"] and m.model["ratio_after_before"] < 0.99
        assert m.presence["fraction_present"] > 0.5


def test_shape_distance_from_centre_and_regime():
    """A mode growing with distance from the centre is described so; present only while still -> regime still."""
    rng = np.random.default_rng(43)
    pos = _positions(rng)
    d = np.linalg.norm(pos - pos.mean(axis=0), axis=1)
    still = np.zeros(N, dtype=bool)
    still[: N // 2] = True
    r = rng.normal(size=(N, K, 6))
    x = _mode_signal(rng, 37.0) * still
    r[:, :, 2] += 0.5 * (d / d.max())[None] * x[:, None]
    m = detect_modes(r, FS, positions=pos, still=still).modes[0]
    assert m.shape["best"] == "distance from centre", m.shape
    assert m.presence["regime"] == "still" and 0.3 < m.presence["fraction_present"] < 0.7


def test_line_that_follows_the_motion_is_not_a_mode():
    """A gain misfit under a hand-twisting-like motion (sinusoids at random frequencies) leaves residual lines at
    the motion's frequencies: set aside as motion lines (the relation holds outside their bands), no mode."""
    rng = np.random.default_rng(44)
    f = rng.uniform(0.8, 3.0, 3)
    omega = sum(3.0 * np.sin(2 * np.pi * fi * T + rng.uniform(0, 6)) for fi in f)
    motion = np.zeros((N, 9))
    motion[:, 2] = omega
    motion[:, 8] = 9.81
    r = rng.normal(size=(N, K, 6))
    r[:, 3, 5] += 0.01 * omega / 0.001  # a 1 % gyroscope gain error on imu 3 (noise 0.001 rad/s)
    s = detect_modes(r, FS, positions=_positions(rng), motion=motion, heldout=False)
    assert s.modes == [] and len(s.motion_lines) >= 1
    assert all(min(abs(m.frequency_hz - f)) < 0.5 for m in s.motion_lines)


def test_localize_reports_the_mode_as_an_entry(tmp_path):
    """localize: the mode is an entry (IMUs, axes, band, regime) with its detail under "mode"; JSON-safe; the
    plot is written."""
    from imu_array_ros.discovery import plots

    rng = np.random.default_rng(45)
    pos = _positions(rng)
    r = rng.normal(size=(N, K, 6))
    r[:, [1, 6], 0] += 0.4 * _mode_signal(rng, 61.0)[:, None] * np.array([1.0, -0.7])
    motion = np.column_stack([rng.normal(0, 2.0, (N, 3)), rng.normal(0, 10.0, (N, 3)), rng.normal(0, 3.0, (N, 3))])
    names = [f"imu_{i}" for i in range(K)]
    loc = localize(r, np.ones_like(r), motion, STAMPS, names, positions=pos, rotations=np.tile(np.eye(3), (K, 1, 1)),
                   acc_std=np.full((K, 3), 0.04))
    modes = [e for e in loc.entries() if "mode" in e]
    assert len(modes) == 1
    e = modes[0]
    assert e["sensors"][0] == "imu_1" and set(e["sensors"]) == {"imu_1", "imu_6"} and e["axes"] == ["acc_x"]
    assert e["band_hz"][0] <= 61.0 <= e["band_hz"][1]
    assert {(k, a) for k, a in loc.modes.modes[0].channels} == {(1, 0), (6, 0)}
    json.dumps(loc.to_dict())
    s = loc.modes
    plots.plot_mode(e["mode"], names, pos, s.freqs, s.pooled, s.pooled_threshold, tmp_path / "mode.png")
    assert (tmp_path / "mode.png").read_bytes()[:4] == b"\x89PNG"
