"""The calibration node's buffer without DDS: raw payloads in, the latest window of array samples out."""

from __future__ import annotations

import threading

import numpy as np
import pytest

from conftest import ARRAY32, REPO
from imu_array_ros.io.messages import raw_imu_payloads
from imu_array_ros.io.rosbag.cdr_columns import encode_imu
from imu_array_ros.io.rosbag.recording import read_imu_recording
from imu_array_ros.io.window import SampleWindow
from imu_array_ros.model.description import load_description

BAG = REPO / "bags" / "twist32_sample"  # 1000 samples at 500 Hz


@pytest.fixture(scope="module")
def recording():
    desc = load_description(ARRAY32)
    samples, _ = read_imu_recording(BAG, desc)
    per_imu = raw_imu_payloads(samples, desc)
    rows = np.concatenate([r for r, _ in per_imu])
    imu = np.concatenate([np.full(len(r), k) for k, (r, _) in enumerate(per_imu)])
    payloads = [bytes(p) for _, pl in per_imu for p in pl]
    # the order a subscriber sees them: by stamp, the IMUs of one sample shuffled
    order = np.lexsort((np.random.default_rng(3).random(len(rows)), rows))
    return desc, samples, [payloads[i] for i in order], imu[order], rows[order]


def _feed(window, recording, chunks, upto=None):
    """Feed the payloads of samples [0, upto) in ``chunks`` pieces, stepping after each (1 ms apart)."""
    desc, samples, payloads, imu, rows = recording
    n = int(np.searchsorted(rows, len(samples) if upto is None else upto))
    cuts = np.linspace(0, n, chunks + 1).astype(int)
    now = 0
    for lo, hi in zip(cuts[:-1], cuts[1:]):
        now += 1_000_000
        window.add(payloads[lo:hi], imu[lo:hi], now)
        window.step(now)
    return now


def _assert_is(window, samples, sl):
    s = window.snapshot()
    stamps, accel, gyro = s.stamps, s.accel, s.gyro
    np.testing.assert_array_equal(stamps, samples.stamps[sl])
    np.testing.assert_array_equal(accel, samples.accel[sl])
    np.testing.assert_array_equal(gyro, samples.gyro[sl])


@pytest.mark.parametrize("chunks", [1, 7, 333])
def test_window_by_count_holds_the_latest_samples(recording, chunks):
    desc, samples, *_ = recording
    window = SampleWindow(desc, window_samples=300)
    now = _feed(window, recording, chunks)
    window.step(now, flush=True)  # the last sample waits for nobody then
    _assert_is(window, samples, slice(-300, None))
    c = window.counts()
    assert c.buffered == len(window) == 300 and c.fill == 1.0 and c.received == len(samples)
    assert c.counts["messages"] == 32 * len(samples) and c.counts["complete_samples"] == len(samples)


@pytest.mark.parametrize("chunks", [3, 250])
def test_window_by_time_grows_and_keeps_the_span(recording, chunks):
    """0.9 s at 500 Hz: 451 samples, more than the initial buffer (256): it grows, order kept."""
    desc, samples, *_ = recording
    window = SampleWindow(desc, window_s=0.9)
    now = _feed(window, recording, chunks)
    window.step(now, flush=True)
    want = samples.stamps >= samples.stamps[-1] - 900_000_000
    _assert_is(window, samples, want)
    c = window.counts()
    assert c.buffered == want.sum() == 451 and c.span_s == pytest.approx(0.9) and c.fill == 1.0


def test_window_filling_up(recording):
    desc, samples, *_ = recording
    window = SampleWindow(desc, window_s=10.0)
    assert window.counts().buffered == 0 and window.counts().fill == 0.0
    s = window.snapshot()
    stamps, accel, gyro = s.stamps, s.accel, s.gyro
    assert stamps.shape == (0,) and accel.shape == gyro.shape == (0, 32, 3)
    now = _feed(window, recording, 5, upto=200)
    window.step(now, flush=True)
    _assert_is(window, samples, slice(0, 200))
    assert window.counts().fill == pytest.approx(199 * 0.002 / 10.0)


def test_snapshot_is_a_consistent_copy_while_the_window_moves(recording):
    """Snapshots from another thread while the executor thread adds: always a contiguous run of
    the recording, oldest first, and never changed afterwards.

    The reader checks each snapshot as it takes it and keeps only the verdicts: holding on to every
    snapshot grew without bound when the feeding thread was slow (24 GB on a loaded 2-core machine)."""
    desc, samples, *_ = recording
    window = SampleWindow(desc, window_samples=250)
    seen, bad, kept, stop = [0], [], [], threading.Event()

    def check(s):
        stamps, accel = s.stamps, s.accel
        if not len(stamps):
            return
        lo = int(np.searchsorted(samples.stamps, stamps[0]))
        if not (np.array_equal(stamps, samples.stamps[lo:lo + len(stamps)])
                and np.array_equal(accel, samples.accel[lo:lo + len(stamps)])):
            bad.append(int(stamps[0]))

    def reader():
        while not stop.is_set():
            s = window.snapshot()
            check(s)
            seen[0] += 1
            if len(kept) < 20 and seen[0] % 5 == 0:
                kept.append(s)  # a few, to check again after the window moved on

    t = threading.Thread(target=reader)
    t.start()
    try:
        _feed(window, recording, 400)
    finally:
        stop.set()
        t.join()
    assert seen[0] > 10
    assert not bad, f"{len(bad)} of {seen[0]} snapshots were not a contiguous run of the recording"
    for s in kept:  # never changed afterwards
        check(s)
    assert not bad
    s = window.snapshot()
    stamps, accel = s.stamps, s.accel
    accel[:] = 0.0
    assert np.isfinite(window.snapshot().accel).all() and window.snapshot().accel.any()


def test_bad_messages_are_counted_and_missing_imus_are_nan(recording):
    desc, samples, payloads, imu, rows = recording
    window = SampleWindow(desc, frame_prefix="", sync_timeout_s=0.01, window_samples=100)
    first = samples.select(slice(0, 1))
    wrong = encode_imu(first.stamps, "someone_else", angular_velocity=[0, 0, 0], linear_acceleration=[0, 0, 9.8])
    nan = encode_imu(first.stamps, desc.names[3], angular_velocity=[np.nan, 0, 0], linear_acceleration=[0, 0, 9.8])
    # samples 0..9 without IMU 5's messages, plus a wrong frame id, a NaN and garbage
    sel = np.flatnonzero((rows < 10) & (imu != 5))
    window.add([payloads[i] for i in sel] + [wrong[0].tobytes(), nan[0].tobytes(), b"\x00\x01"],
               np.r_[imu[sel], 4, 3, 2], 0)
    assert window.step(5_000_000) == 0  # IMU 5 has been silent 5 ms only: the samples wait
    assert window.step(20_000_000) == 10  # silent for the sync timeout: they go without it
    s = window.snapshot()
    accel, gyro = s.accel, s.gyro
    assert np.isnan(accel[:, 5]).all() and np.isnan(gyro[:, 5]).all()
    np.testing.assert_array_equal(np.delete(accel, 5, axis=1), np.delete(samples.accel[:10], 5, axis=1))
    c = window.counts().counts
    assert (c["wrong_frame_id"], c["non_finite"], c["undecodable"]) == (1, 1, 1)
    assert c["incomplete_samples"] == 10 and c["missing_messages"] == 10


def test_window_arguments_are_checked(recording):
    desc = recording[0]
    with pytest.raises(ValueError):
        SampleWindow(desc, window_s=0.0, window_samples=0)
    with pytest.raises(ValueError):
        SampleWindow(desc, window_samples=-1)
