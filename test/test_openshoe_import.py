"""import_capture on the real MIMU4444BT captures, and verification of the array description.

Data: ``../shared/data/openshoe_mimu4444bt`` relative to the repository root
(see its README).  Tests that need it are skipped when it is absent.

The mapping tests print the measured numbers (run ``pytest -s``) and attach
them with ``record_property`` (``--junitxml``):

(a) static phase — per static pose, the mean specific force of each underside
    IMU mapped to the array frame by its description orientation is compared
    in direction with the mean direction of the four top IMUs.  Raw, the
    underside differs by 4-7 degrees because the accelerometer biases (up to
    0.6 m/s^2, similar in every IMU's *own* frame) flip sign under the
    underside rotation; after removing each IMU's bias (sphere fit over the
    poses) the angle is below 1 degree.  Every other axis permutation is off
    by about 90 degrees or more in some pose.
(b) dynamic phase — gyroscope vectors (unsaturated samples, |omega| > 1 rad/s)
    of each underside IMU mapped to the array frame are compared with the mean
    of the top IMUs: per-axis correlation, relative residual, and the angle
    between the best-fit rotation (Kabsch) and the description's orientation.
"""

from __future__ import annotations

import itertools
from pathlib import Path

import numpy as np
import pytest

from imu_array_ros.model.description import description_from_dict, load_description
from imu_array_ros.errors import CaptureError
from imu_array_ros.io.openshoe.framing import (
    GYRO_SCALE,
    counts_to_si,
    encode_packets,
    packet_length,
    saturation_mask,
    si_saturation_level,
)
from imu_array_ros.io.openshoe.capture import CaptureStats, guess_imu_count, import_capture

REPO = Path(__file__).resolve().parents[1]
DATA = REPO.parent / "shared" / "data" / "openshoe_mimu4444bt"
CONFIG = REPO / "config" / "mimu4444bt_corners.yaml"
CAPTURES = sorted(DATA.glob("exp_*.bin")) if DATA.is_dir() else []
needs_data = pytest.mark.skipif(not CAPTURES, reason=f"real captures not found in {DATA}")

RATE_HZ = 62.5
WINDOW = 62  # ~1 s moving window for static detection

# Nominal underside mapping claimed by the board's host software (README).
UNDERSIDE = np.array([[0, -1, 0], [-1, 0, 0], [0, 0, -1]], float)
ALTERNATIVE = np.array([[0, 1, 0], [1, 0, 0], [0, 0, -1]], float)  # 180 deg about y = x


# --------------------------------------------------------------------------- helpers


def _moving_std(x: np.ndarray, win: int) -> np.ndarray:
    """(N, ...) -> (N-win+1, ...) std over a sliding window, via cumulative sums."""
    c1 = np.concatenate([np.zeros((1,) + x.shape[1:]), np.cumsum(x, axis=0)])
    c2 = np.concatenate([np.zeros((1,) + x.shape[1:]), np.cumsum(x * x, axis=0)])
    m1 = (c1[win:] - c1[:-win]) / win
    m2 = (c2[win:] - c2[:-win]) / win
    return np.sqrt(np.maximum(m2 - m1 * m1, 0.0))


def static_segments(accel: np.ndarray, gyro: np.ndarray, *, min_s: float = 3.0) -> list[tuple[int, int]]:
    """[start, stop) sample ranges where the array rests.

    A 1 s window is static when, averaged over the IMUs, every gyro axis has std
    < 0.01 rad/s and every accelerometer axis std < 0.1 m/s^2 (noise is about
    0.003 rad/s and 0.04 m/s^2); samples covered by static windows form
    segments, kept when longer than ``min_s``.
    """
    gs = _moving_std(gyro, WINDOW).mean(axis=1).max(axis=1)
    as_ = _moving_std(accel - accel.mean(axis=0), WINDOW).mean(axis=1).max(axis=1)
    ok = np.flatnonzero((gs < 0.01) & (as_ < 0.1))
    cover = np.zeros(len(accel) + 1, int)
    np.add.at(cover, ok, 1)
    np.add.at(cover, ok + WINDOW, -1)
    mask = np.cumsum(cover)[:-1] > 0
    edges = np.diff(np.concatenate([[0], mask.astype(int), [0]]))
    starts, stops = np.flatnonzero(edges == 1), np.flatnonzero(edges == -1)
    keep = stops - starts >= min_s * RATE_HZ
    return list(zip(starts[keep].tolist(), stops[keep].tolist()))


def _angle_deg(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    u = u / np.linalg.norm(u, axis=-1, keepdims=True)
    v = v / np.linalg.norm(v, axis=-1, keepdims=True)
    return np.degrees(np.arccos(np.clip((u * v).sum(-1), -1.0, 1.0)))


def _rotation_angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip((np.trace(a.T @ b) - 1) / 2, -1.0, 1.0))))


def _kabsch(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Rotation R minimising sum |R x_i - y_i|^2; x, y (n, 3)."""
    u, _, vt = np.linalg.svd(x.T @ y)
    d = np.sign(np.linalg.det(vt.T @ u.T))
    return vt.T @ np.diag([1.0, 1.0, d]) @ u.T


def _sphere_bias(points: np.ndarray) -> np.ndarray:
    """Centre b of the sphere |p - b| = r through (n, 3) points (linear least squares)."""
    a = np.c_[2 * points, np.ones(len(points))]
    sol = np.linalg.lstsq(a, (points**2).sum(axis=1), rcond=None)[0]
    return sol[:3]


def _signed_permutations() -> list[np.ndarray]:
    """The 24 proper rotations that permute and sign-flip the axes."""
    out = []
    for perm in itertools.permutations(range(3)):
        for signs in itertools.product((1.0, -1.0), repeat=3):
            m = np.zeros((3, 3))
            m[range(3), perm] = signs
            if np.linalg.det(m) > 0:
                out.append(m)
    return out


@pytest.fixture(scope="module")
def description():
    return load_description(CONFIG)


@pytest.fixture(scope="module")
def captures(description):
    return [(path.name, *import_capture(path, description)) for path in CAPTURES]


# --------------------------------------------------------------------------- config file


def test_config_loads_and_matches_readme(description):
    assert description.frame_id == "imu_array"
    assert description.names == tuple(f"imu_{i}" for i in range(1, 9))
    pos = description.positions
    np.testing.assert_allclose(np.abs(pos[:, :2]), 0.00945)
    np.testing.assert_allclose(pos[:, 2], [0.001, -0.001] * 4)
    np.testing.assert_allclose(pos[[0, 1, 4, 5], 1], 0.00945)  # IMUs 1, 2, 5, 6 at +y
    np.testing.assert_allclose(pos[:4, 0], -0.00945)  # IMUs 1-4 at -x
    for k, r in enumerate(description.orientations):
        np.testing.assert_array_equal(r, UNDERSIDE if k % 2 else np.eye(3))
    assert description.gyroscope_range == pytest.approx(np.radians(2000.0))
    assert description.accelerometer_range == pytest.approx(16 * 9.80665)
    # Saturation in SI: accel full scale is the range; gyro full scale is 0.1 % below it.
    acc_level, gyro_level = si_saturation_level()
    assert acc_level == pytest.approx(description.accelerometer_range, rel=1e-4)
    assert gyro_level == pytest.approx(description.gyroscope_range, rel=2e-3)
    assert gyro_level < description.gyroscope_range


# --------------------------------------------------------------------------- import errors (synthetic)


def _desc(k: int):
    eye = np.eye(3).ravel().tolist()
    imus = [{"name": f"imu_{i}", "position": [0.01 * i, 0.02 * (i % 2), 0.0], "orientation": eye} for i in range(k)]
    return description_from_dict(
        {
            "imu_array": {
                "frame_id": "imu_array",
                "accelerometer_noise_std": 0.04,
                "gyroscope_noise_std": 0.003,
                "gyroscope_range": 34.9,
                "accelerometer_range": 156.9,
                "imus": imus,
            }
        }
    )


def _synthetic_capture(tmp_path, k=4, m=300, seed=1):
    rng = np.random.default_rng(seed)
    raw = rng.integers(-32768, 32768, size=(m, k, 6)).astype(np.int16)
    ticks = (np.uint64(4_000_000_000) + np.arange(m, dtype=np.uint64) * 1_024_000) % (1 << 32)
    data = b"\xa0\x28\x00\xc8" + encode_packets(np.arange(m) + 65500, ticks, raw)
    path = tmp_path / "cap.bin"
    path.write_bytes(data + data[4:60])  # plus a partial packet
    return path, raw


def test_import_synthetic_roundtrip(tmp_path):
    path, raw = _synthetic_capture(tmp_path)
    calls = []
    samples, stats = import_capture(path, _desc(4), progress=lambda done, total: calls.append((done, total)))
    assert isinstance(stats, CaptureStats)
    assert samples.names == tuple(f"imu_{i}" for i in range(4))
    acc, gyr = counts_to_si(raw)
    np.testing.assert_array_equal(samples.accel, acc)
    np.testing.assert_array_equal(samples.gyro, gyr)
    assert samples.gyro[0, 0, 0] == raw[0, 0, 3] * GYRO_SCALE
    # 1 024 000 ticks = 16 ms exactly; the 64 MHz counter wraps inside the capture.
    np.testing.assert_array_equal(samples.stamps, np.arange(300) * 16_000_000)
    assert (stats.packets, stats.acks, stats.garbage_bytes, stats.bad_checksums) == (300, 1, 0, 0)
    assert (stats.counter_gaps, stats.counter_backsteps, stats.trailing_bytes) == (0, 0, 56)
    assert stats.interval_ms_min == stats.interval_ms_median == stats.interval_ms_max == 16.0
    assert stats.duration_s == pytest.approx(299 * 0.016)
    np.testing.assert_array_equal(stats.gyro_saturated, saturation_mask(raw)[..., 3:].any(axis=2).sum(axis=0))
    assert calls[-1] == (stats.bytes, stats.bytes)
    assert "300 packets" in stats.summary()


def test_import_start_ns(tmp_path):
    path, _ = _synthetic_capture(tmp_path, m=5)
    samples, _ = import_capture(path, _desc(4), start_ns=1_700_000_000_000_000_000)
    assert samples.stamps[0] == 1_700_000_000_000_000_000


def test_import_missing_and_empty(tmp_path):
    with pytest.raises(CaptureError, match="not found") as err:
        import_capture(tmp_path / "nope.bin", _desc(4))
    assert "nope.bin" in str(err.value) and "\n" not in str(err.value)
    (tmp_path / "empty.bin").write_bytes(b"")
    with pytest.raises(CaptureError, match="empty capture file"):
        import_capture(tmp_path / "empty.bin", _desc(4))
    with pytest.raises(CaptureError, match="directory"):
        import_capture(tmp_path, _desc(4))


def test_import_wrong_imu_count(tmp_path):
    path, _ = _synthetic_capture(tmp_path, k=4)
    expected = r"no valid packet for 5 IMUs .*wrong array description\? \(the capture frames as 4-IMU packets\)"
    with pytest.raises(CaptureError, match=expected) as err:
        import_capture(path, _desc(5))
    assert str(err.value).startswith(str(path)) and "\n" not in str(err.value)
    assert guess_imu_count(path.read_bytes())[0] == 4


def test_import_not_a_capture(tmp_path):
    path = tmp_path / "noise.bin"
    path.write_bytes(np.random.default_rng(3).integers(0, 256, 20_000, dtype=np.uint8).tobytes())
    with pytest.raises(CaptureError, match="no valid packet for 4 IMUs.*not an OpenShoe raw-IMU capture"):
        import_capture(path, _desc(4))


def test_import_mostly_garbage_rejected(tmp_path):
    # A couple of valid packets drowned in noise: not a capture of this array.
    rng = np.random.default_rng(4)
    pkt = encode_packets([1, 2], [0, 1], np.zeros((2, 4, 6), np.int16))
    path = tmp_path / "g.bin"
    path.write_bytes(rng.integers(0, 0xA0, 5000, dtype=np.uint8).tobytes() + pkt)
    with pytest.raises(CaptureError, match="only 2 valid 4-IMU packets"):
        import_capture(path, _desc(4))


# --------------------------------------------------------------------------- real captures


@needs_data
def test_real_captures_import(captures, description):
    for name, samples, stats in captures:
        assert stats.packets == (stats.bytes - 4) // packet_length(8), name
        assert stats.bad_checksums == 0 and stats.garbage_bytes == 0, name
        assert stats.counter_gaps == 0 and stats.counter_backsteps == 0, name
        assert stats.acks == 1, name
        assert stats.trailing_bytes == (stats.bytes - 4) % packet_length(8), name
        assert 15.6 < stats.interval_ms_min and stats.interval_ms_max < 16.05, name
        assert stats.interval_ms_median == pytest.approx(16.0, abs=0.01), name
        assert 590 < stats.duration_s < 640, name
        assert samples.stamps[0] == 0 and np.all(np.diff(samples.stamps) > 0), name
        assert samples.names == description.names
        assert samples.present.all()
        # At rest at the start: specific force magnitude about g in every IMU.
        norm = np.linalg.norm(samples.accel[:100], axis=2).mean(axis=0)
        np.testing.assert_allclose(norm, 9.81, atol=0.6)
        # Hand-twisting saturates gyroscopes (README), accelerometers hardly.
        assert stats.gyro_saturated.sum() > 100, name
    print()
    for name, _, stats in captures:
        print(stats.summary().replace(str(DATA) + "/", ""))


@needs_data
def test_underside_mapping_static(captures, description, record_property):
    """(a) gravity directions in static poses: nominal underside rotation verified."""
    rots = description.orientations
    alternatives = [q for q in _signed_permutations() if not np.allclose(q, UNDERSIDE)]
    lines = []
    for name, samples, _ in captures:
        segs = static_segments(samples.accel, samples.gyro)
        assert len(segs) >= 15, f"{name}: only {len(segs)} static poses found"
        means = np.array([samples.accel[a:b].mean(axis=0) for a, b in segs])  # (P, K, 3) sensor frame
        corrected = means - np.array([_sphere_bias(means[:, k]) for k in range(8)])
        results = {}
        for label, m in (("raw", means), ("bias-removed", corrected)):
            arr = np.einsum("kij,pkj->pki", rots, m)  # (P, K, 3) array frame
            top = arr[:, 0::2] / np.linalg.norm(arr[:, 0::2], axis=-1, keepdims=True)
            ref = top.mean(axis=1)  # (P, 3)
            under = _angle_deg(arr[:, 1::2], ref[:, None])  # (P, 4)
            topang = _angle_deg(arr[:, 0::2], ref[:, None])
            results[label] = (under, topang)
            lines.append(
                f"{name} {label:12s}: {len(segs)} poses; underside angle median {np.median(under):.2f} "
                f"max {under.max():.2f} deg (per IMU 2,4,6,8 max {np.round(under.max(0), 2).tolist()}); "
                f"top IMUs max {topang.max():.2f} deg"
            )
        under_raw, _ = results["raw"]
        under_fix, top_fix = results["bias-removed"]
        assert under_raw.max() < 10.0, name
        assert under_fix.max() < 1.5 and top_fix.max() < 1.5, name
        # Fitted rotation (top mean direction <- underside IMU, bias removed) vs nominal.
        ref = corrected[:, 0::2].mean(axis=1)
        fits = [_rotation_angle_deg(_kabsch(corrected[:, k], ref), UNDERSIDE) for k in (1, 3, 5, 7)]
        assert max(fits) < 1.0, name
        # Every other axis mapping is far off in some pose, for every underside IMU.
        worst_alt = min(_angle_deg(corrected[:, 1::2] @ q.T, ref[:, None]).max(axis=0).min() for q in alternatives)
        alt = _angle_deg(corrected[:, 1::2] @ ALTERNATIVE.T, ref[:, None])
        assert worst_alt > 45.0, name
        assert np.median(alt) > 45.0, name
        lines.append(
            f"{name} best-fit rotation vs nominal (IMU 2,4,6,8): {np.round(fits, 2).tolist()} deg; "
            f"alternative [[0,1,0],[1,0,0],[0,0,-1]] median {np.median(alt):.1f} deg; "
            f"best of 23 other axis mappings still off by >= {worst_alt:.1f} deg in some pose"
        )
    print("\n" + "\n".join(lines))
    record_property("underside_static", "\n".join(lines))


@needs_data
def test_underside_mapping_dynamic(captures, description, record_property):
    """(b) gyroscope vectors while twisting: nominal underside rotation verified."""
    rots = description.orientations
    alternatives = [q for q in _signed_permutations() if not np.allclose(q, UNDERSIDE)]
    _, gyro_level = si_saturation_level()
    lines = []
    for name, samples, _ in captures:
        g = samples.gyro
        unsaturated = (np.abs(g) < gyro_level * (1 - 1e-9)).all(axis=(1, 2))
        arr = np.einsum("kij,nkj->nki", rots, g)
        top = arr[:, 0::2].mean(axis=1)
        sel = unsaturated & (np.linalg.norm(top, axis=1) > 1.0)
        assert sel.sum() > 2000, name
        top = top[sel]
        parts = []
        for k in (1, 3, 5, 7):
            mapped = arr[sel, k]
            corr = min(np.corrcoef(mapped[:, j], top[:, j])[0, 1] for j in range(3))
            rel = float(np.sqrt(((mapped - top) ** 2).sum(1).mean() / (top**2).sum(1).mean()))
            fit = _rotation_angle_deg(_kabsch(g[sel, k], top), UNDERSIDE)
            alt_corr = max(
                min(np.corrcoef((g[sel, k] @ q.T)[:, j], top[:, j])[0, 1] for j in range(3)) for q in alternatives
            )
            assert corr > 0.999 and rel < 0.05 and fit < 1.0, (name, k + 1)
            assert alt_corr < 0.5, (name, k + 1)
            parts.append(
                f"imu_{k + 1}: corr>={corr:.5f} resid {100 * rel:.1f}% fit {fit:.2f} deg alt corr<={alt_corr:.2f}"
            )
        lines.append(f"{name} gyro, {sel.sum()} unsaturated samples with |omega|>1 rad/s: " + "; ".join(parts))
    print("\n" + "\n".join(lines))
    record_property("underside_dynamic", "\n".join(lines))


@needs_data
def test_noise_estimate_matches_config(captures, description, record_property):
    """White-noise std from static segments: first differences / sqrt(2), pooled RMS."""
    acc_d, gyr_d = [], []
    for _, samples, _ in captures:
        for a, b in static_segments(samples.accel, samples.gyro):
            acc_d.append(np.diff(samples.accel[a:b], axis=0))
            gyr_d.append(np.diff(samples.gyro[a:b], axis=0))
    acc_d, gyr_d = np.concatenate(acc_d), np.concatenate(gyr_d)
    acc_imu = acc_d.std(axis=0).mean(axis=1) / np.sqrt(2)  # (K,) per IMU, mean over axes
    gyr_imu = gyr_d.std(axis=0).mean(axis=1) / np.sqrt(2)
    acc_rms = float(np.sqrt((acc_d.var(axis=0)).mean() / 2))
    gyr_rms = float(np.sqrt((gyr_d.var(axis=0)).mean() / 2))
    text = (
        f"static samples {len(acc_d)}: accel noise std pooled RMS {acc_rms:.4f} m/s^2 "
        f"(per IMU {np.round(acc_imu, 4).tolist()}); gyro {gyr_rms:.5f} rad/s = {np.degrees(gyr_rms):.3f} deg/s "
        f"(per IMU {np.round(gyr_imu, 5).tolist()})"
    )
    print("\n" + text)
    record_property("noise", text)
    assert description.accelerometer_noise_std == pytest.approx(acc_rms, rel=0.1)
    assert description.gyroscope_noise_std == pytest.approx(gyr_rms, rel=0.1)
