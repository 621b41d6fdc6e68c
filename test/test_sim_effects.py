"""Effects outside the model's term library: board vibration mode and coloured noise."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from scipy.signal import hilbert, welch
from scipy.spatial.transform import Rotation

from imu_array_ros.model.description import load_description
from imu_array_ros.model.sensor_model import SensorModel
from imu_array_ros.model.samples import ImuSamples
from imu_array_ros.simulation.effects import EFFECTS, add_colored_noise, add_vibration, narrowband_process
from imu_array_ros.simulation.simulator import simulate_twist

from conftest import REPO

RATE = 200.0
DIRECTION = np.array([1.0, 2.0, 2.0]) / 3.0


@pytest.fixture(scope="module")
def model() -> SensorModel:
    """The MIMU4444BT corner array, with imu_3 turned by a random (non-symmetric) rotation,
    so that using R instead of R^T (or ignoring it) is visible."""
    m = SensorModel.from_description(load_description(REPO / "config" / "mimu4444bt_corners.yaml"))
    rot = m.rotations.copy()
    rot[2] = Rotation.random(random_state=7).as_matrix()
    assert not np.allclose(rot[2], rot[2].T)
    return dataclasses.replace(m, rotations=rot)


@pytest.fixture(scope="module")
def recording(model) -> ImuSamples:
    samples, _ = simulate_twist(model, 10.0, RATE, np.random.default_rng(4242))
    return samples


def _copy(s: ImuSamples) -> ImuSamples:
    return ImuSamples(s.stamps.copy(), s.accel.copy(), s.gyro.copy(), s.names)


def test_effects_registry():
    assert EFFECTS == {"vibration": add_vibration, "colored_noise": add_colored_noise}


def test_vibration_only_listed_accelerometers(model, recording):
    before = _copy(recording)
    out = add_vibration(recording, model, sensors=["imu_1", 2, "imu_8"], frequency_hz=23.0, amplitude=0.3,
                        direction=DIRECTION, rng=np.random.default_rng(1))
    diff = out.accel - recording.accel
    changed = np.abs(diff).max(axis=(0, 2)) > 0
    assert changed.tolist() == [True, False, True, False, False, False, False, True]
    np.testing.assert_array_equal(out.gyro, recording.gyro)
    np.testing.assert_array_equal(out.stamps, recording.stamps)
    # the input is untouched, and the output does not share its arrays
    for a, b in ((recording.accel, before.accel), (recording.gyro, before.gyro), (recording.stamps, before.stamps)):
        np.testing.assert_array_equal(a, b)
    assert not np.shares_memory(out.accel, recording.accel) and not np.shares_memory(out.gyro, recording.gyro)


def test_vibration_spectrum_rms_and_direction(model, recording):
    f0, amp, bw = 23.0, 0.3, 0.5
    sensors = ["imu_2", "imu_3", "imu_5"]
    out = add_vibration(recording, model, sensors=sensors, frequency_hz=f0, amplitude=amp, direction=DIRECTION,
                        rng=np.random.default_rng(2), bandwidth_hz=bw)
    k = [recording.names.index(s) for s in sensors]
    added = out.accel[:, k] - recording.accel[:, k]                       # (N, 3, 3) sensor frames
    in_array = np.einsum("kij,nkj->nki", model.rotations[k], added)       # R_k a: back to the array frame
    along = in_array @ DIRECTION                                           # (N, 3)
    off = in_array - along[..., None] * DIRECTION
    assert np.abs(off).max() < 1e-9 * np.abs(along).max()
    # the same mode, in phase, at every listed IMU
    np.testing.assert_allclose(along[:, 1:], along[:, :1].repeat(2, axis=1), atol=1e-12)
    x = along[:, 0]
    assert abs(np.sqrt(np.mean(x**2)) / amp - 1.0) < 0.1
    f, p = welch(x, RATE, nperseg=1024)
    assert abs(f[np.argmax(p)] - f0) <= bw
    near = np.abs(f - f0) <= 5 * bw
    assert p[near].sum() / p.sum() > 0.8


def test_vibration_linewidth():
    """The envelope's autocorrelation decays as exp(-pi B |tau|): a Lorentzian of full width B."""
    rate, n, f0, bw = 100.0, 40000, 23.0, 0.5
    stamps = np.round(np.arange(n) * 1e9 / rate).astype(np.int64)
    x = narrowband_process(stamps, f0, bw, np.random.default_rng(3))
    assert abs(np.sqrt(np.mean(x**2)) - 1.0) < 1e-12
    t = np.arange(n) / rate
    h = hilbert(x) * np.exp(-2j * np.pi * f0 * t)
    lag = int(round(rate / (np.pi * bw)))
    c = abs(np.vdot(h[:-lag], h[lag:]) / np.vdot(h, h))
    assert abs(c - np.exp(-1.0)) < 0.1


def test_vibration_keeps_nan_and_clips(model, recording):
    s = _copy(recording)
    s.accel[100:110, 0] = np.nan
    s.accel[200:300, 0, 2] = model.acc_clip  # clipped readings stay within the clip level
    out = add_vibration(s, model, sensors="imu_1", frequency_hz=10.0, amplitude=5.0, rng=np.random.default_rng(5))
    assert np.isnan(out.accel[100:110, 0]).all()
    assert np.isfinite(out.accel[:100, 0]).all()
    assert np.all(np.abs(out.accel[np.isfinite(out.accel)]) <= model.acc_clip)
    assert np.mean(out.accel[200:300, 0, 2] == model.acc_clip) > 0.3  # those pushed outwards clip again
    assert np.isnan(s.accel[100:110, 0]).all() and np.all(s.accel[200:300, 0, 2] == model.acc_clip)


def test_vibration_rejects_bad_arguments(model, recording):
    kw = dict(frequency_hz=10.0, amplitude=0.1, rng=np.random.default_rng(0))
    with pytest.raises(ValueError, match="unknown IMU"):
        add_vibration(recording, model, sensors=["imu_9"], **kw)
    with pytest.raises(ValueError, match="Nyquist"):
        add_vibration(recording, model, sensors=[0], **{**kw, "frequency_hz": 150.0})
    with pytest.raises(ValueError, match="direction"):
        add_vibration(recording, model, sensors=[0], direction=(0, 0, 0), **kw)


@pytest.mark.parametrize("kind", ["accelerometer", "gyroscope"])
def test_colored_noise(model, recording, kind):
    tau, ratio = 0.05, 2.0
    before = _copy(recording)
    out = add_colored_noise(recording, model, sensor="imu_4", correlation_time_s=tau, std_ratio=ratio,
                            sensor_kind=kind, rng=np.random.default_rng(6))
    k = 3
    acc = kind == "accelerometer"
    this, other = (out.accel, out.gyro) if acc else (out.gyro, out.accel)
    this_in, other_in = (recording.accel, recording.gyro) if acc else (recording.gyro, recording.accel)
    np.testing.assert_array_equal(other, other_in)
    changed = np.abs(this - this_in).max(axis=(0, 2)) > 0
    assert changed.tolist() == [i == k for i in range(8)]
    np.testing.assert_array_equal(recording.accel, before.accel)
    np.testing.assert_array_equal(recording.gyro, before.gyro)

    e = this[:, k] - this_in[:, k]                                         # (N, 3)
    std = (model.acc_std if acc else model.gyro_std)[k]
    assert np.all(np.abs(e.std(axis=0) / (ratio * std) - 1.0) < 0.1)
    e = e - e.mean(axis=0)
    lag1 = (e[1:] * e[:-1]).sum(axis=0) / (e * e).sum(axis=0)
    np.testing.assert_allclose(lag1, np.exp(-1.0 / RATE / tau), atol=0.03)


def test_colored_noise_keeps_nan(model, recording):
    s = _copy(recording)
    s.gyro[50:60, 1] = np.nan
    out = add_colored_noise(s, model, sensor=1, correlation_time_s=0.1, sensor_kind="gyroscope",
                            rng=np.random.default_rng(8))
    assert np.isnan(out.gyro[50:60, 1]).all()
    assert np.isfinite(out.gyro[:50, 1]).all() and np.isfinite(out.gyro[60:, 1]).all()
    with pytest.raises(ValueError, match="sensor_kind"):
        add_colored_noise(s, model, sensor=1, correlation_time_s=0.1, sensor_kind="magnetometer",
                          rng=np.random.default_rng(8))


def test_effects_handle_gaps_in_the_stamps(model, recording):
    """Dropped samples: the processes stay on the time grid (the lag-1 pairs across the gap are skipped)."""
    keep = np.ones(len(recording), dtype=bool)
    keep[500:700] = False
    s = recording.select(keep)
    out = add_colored_noise(s, model, sensor=0, correlation_time_s=0.05, rng=np.random.default_rng(9))
    e = out.accel[:, 0] - s.accel[:, 0]
    contiguous = np.diff(s.stamps) == np.median(np.diff(s.stamps))
    e = e - e.mean(axis=0)
    lag1 = (e[1:] * e[:-1])[contiguous].sum(axis=0) / (e[1:] ** 2)[contiguous].sum(axis=0)
    np.testing.assert_allclose(lag1, np.exp(-1.0 / RATE / 0.05), atol=0.04)
