"""IMUs with their own stamps: pairing onto a grid offline (io/pairing.py), in recordings, live
(io/live_pairing.py) and in the replay (io/replay.py).

The streams are synthetic: every IMU samples on its own clock (rate off by up to +-200 ppm, start
phase random), stamps its messages with that clock plus a constant offset (up to +-2 ms) and 50 us
of jitter, at 200 Hz.
"""

from __future__ import annotations

import numpy as np
import pytest

from imu_array_ros.errors import RecordingError
from imu_array_ros.io.live_pairing import PairingAssembler
from imu_array_ros.io.messages import decode_raw_imu
from imu_array_ros.io.pairing import (ImuStream, StampClocks, median_period, pair_again, pair_streams,
                                      split_streams)
from imu_array_ros.io.replay import Replay
from imu_array_ros.io.rosbag.cdr_columns import encode_imu
from imu_array_ros.io.rosbag.mcap_writer import ChannelData, write_recording
from imu_array_ros.io.rosbag.recording import (IMU_TYPE, imu_payloads, imu_topic, read_imu_recording,
                                               write_imu_recording)
from imu_array_ros.io.sync import RawIntake
from imu_array_ros.model.layouts import planar_square4
from imu_array_ros.model.samples import ImuSamples

T0 = 1_790_000_000_000_000_000
P = 5_000_000  # 200 Hz


def own_clock_streams(seed=1, k=8, seconds=20.0, skew_ppm=200.0, offset_s=2e-3, jitter_s=50e-6, offsets=None):
    """K streams on own clocks; returns (streams, true sample times (list of (M,) int64))."""
    rng = np.random.default_rng(seed)
    n = int(seconds / (P * 1e-9))
    streams, true = [], []
    for i in range(k):
        skew = 0.0 if i == 0 else rng.uniform(-skew_ppm, skew_ppm)
        off = 0.0 if i == 0 else rng.uniform(-offset_s, offset_s) * 1e9
        if offsets is not None:
            off = offsets[i] * 1e9
        t = T0 + rng.uniform(0, P) + np.arange(n) * P * (1 + skew * 1e-6)
        stamps = (t + off + rng.normal(0, jitter_s * 1e9, n)).astype(np.int64)
        streams.append(ImuStream(stamps, rng.normal(0, 5, (n, 3)), rng.normal(0, 2, (n, 3))))
        true.append(t.astype(np.int64))
    return streams, true


def names_of(k):
    return tuple(f"imu_{i:02d}" for i in range(k))


def one_line(err):
    msg = str(err.value)
    assert msg and "\n" not in msg
    return msg


def drop(stream, index):
    keep = np.setdiff1d(np.arange(len(stream.stamps)), index)
    return ImuStream(stream.stamps[keep], stream.accel[keep], stream.gyro[keep])


# --------------------------------------------------------------------------- offline pairing


def test_own_clocks_pair_onto_the_reference_without_gaps():
    streams, _ = own_clock_streams()
    names = names_of(8)
    samples, stats = pair_streams(streams, names)
    # the grid is the reference's stamps, extended at its ends where the others start earlier or stop later
    ref = streams[0].stamps
    inner = (samples.stamps >= ref[0]) & (samples.stamps <= ref[-1])
    np.testing.assert_array_equal(samples.stamps[inner], ref)
    np.testing.assert_array_equal(samples.own_stamps[inner, 0], ref)
    assert stats.grid == len(samples) and stats.grid_filled == (~inner).sum() <= 2
    present = samples.present
    assert present[inner, 0].all() and not present[~inner, 0].any()
    assert np.diff(samples.stamps).max() < 1.5 * P
    # every paired message is the IMU's own, at its own stamp, within half a period of the grid
    for k, s in enumerate(streams):
        rows = np.flatnonzero(present[:, k])
        pos = np.searchsorted(s.stamps, samples.own_stamps[rows, k])
        np.testing.assert_array_equal(s.stamps[pos], samples.own_stamps[rows, k])
        np.testing.assert_array_equal(s.accel[pos], samples.accel[rows, k])
        np.testing.assert_array_equal(s.gyro[pos], samples.gyro[rows, k])
        assert len(np.unique(pos)) == len(pos)  # each message at most once
        assert stats.paired[k] == len(rows) and stats.paired[k] + stats.unused[k] == len(s.stamps)
    delays = samples.stamp_delays
    assert np.abs(delays[present]).max() <= 0.5 * median_period(streams[3].stamps) * 1e-9 * 1.001
    np.testing.assert_array_equal(samples.own_stamps[~present], np.broadcast_to(samples.stamps[:, None],
                                                                                present.shape)[~present])
    assert np.isnan(samples.accel[~present]).all()
    # missing slots come from the clocks' slips only: under 1 % at +-200 ppm and 50 us jitter
    assert stats.missing.sum() == (~present).sum() and 0 < (~present).mean() < 0.01
    assert stats.paired.sum() / stats.messages.sum() > 0.99
    assert 0.5e-3 < np.nanmedian(stats.median_abs_delay_s) < 1.5e-3
    assert "paired onto the stamps of reference IMU 'imu_00'" in stats.summary() and "\n" not in stats.summary()


def test_common_stamps_pair_to_themselves():
    rng = np.random.default_rng(2)
    stamps = T0 + np.arange(500, dtype=np.int64) * P
    streams = [ImuStream(stamps, rng.normal(size=(500, 3)), rng.normal(size=(500, 3))) for _ in range(4)]
    samples, stats = pair_streams(streams, names_of(4))
    assert samples.present.all() and (samples.stamp_delays == 0).all() and stats.unused.sum() == 0
    np.testing.assert_array_equal(samples.accel[:, 2], streams[2].accel)


def test_reference_by_name_and_grid_given():
    streams, _ = own_clock_streams(seed=3, k=4, seconds=2.0)
    names = names_of(4)
    by_name, stats = pair_streams(streams, names, reference="imu_02")
    ref = streams[2].stamps
    np.testing.assert_array_equal(by_name.stamps[(by_name.stamps >= ref[0]) & (by_name.stamps <= ref[-1])], ref)
    assert stats.reference == "imu_02"
    grid = T0 + np.arange(0, 400, dtype=np.int64) * P
    on_grid, _ = pair_streams(streams, names, grid=grid)
    np.testing.assert_array_equal(on_grid.stamps, grid)  # kept whole


def test_clock_correction_repairs_an_offset_of_several_periods():
    """An IMU 21 ms behind pairs with the wrong samples on its raw stamps; with its clock offset it
    pairs with the samples taken at the same time."""
    streams, true = own_clock_streams(seed=4, k=3, seconds=5.0, jitter_s=20e-6, offsets=[0.0, 0.0, 21e-3])
    names = names_of(3)
    raw, _ = pair_streams(streams, names)
    clocks = StampClocks(offset_s=np.array([0.0, 0.0, -21e-3]), skew_ppm=np.zeros(3), t0_ns=int(raw.stamps[0]))
    fixed, stats = pair_streams(streams, names, clocks=clocks, grid=raw.stamps)

    def true_times(samples, k):
        """(N,) the true sample time of IMU k's message in each grid sample (-1: missing)."""
        out = np.full(len(samples), -1, dtype=np.int64)
        rows = np.flatnonzero(samples.present[:, k])
        out[rows] = true[k][np.searchsorted(streams[k].stamps, samples.own_stamps[rows, k])]
        return out

    for samples in (raw, fixed):
        ref_t, t2 = true_times(samples, 0), true_times(samples, 2)
        both = (ref_t >= 0) & (t2 >= 0)
        err = np.abs(t2 - ref_t)[both] * 1e-9  # how far apart the two readings of one sample were taken
        if samples is raw:
            assert np.median(err) > 18e-3
        else:
            assert err.max() < 3e-3 and both.mean() > 0.95
    assert np.median(np.abs(fixed.stamp_delays[fixed.present[:, 2], 2])) > 18e-3  # own stamps stay uncorrected
    # re-pairing the first pairing with the clocks gives the same on the same grid
    again, _ = pair_again(raw, clocks)
    np.testing.assert_array_equal(again.stamps, raw.stamps)
    both = again.present[:, 2] & fixed.present[:, 2]
    assert both.mean() > 0.95
    np.testing.assert_array_equal(again.own_stamps[both, 2], fixed.own_stamps[both, 2])
    # skew: 300 ppm over 5 s is 1.5 ms; corrected, an IMU with that skew lines up again
    corr = StampClocks(offset_s=np.zeros(3), skew_ppm=np.array([0.0, 300.0, 0.0]), t0_ns=T0)
    t = corr.corrected(1, np.array([T0, T0 + 5_000_000_000]))
    np.testing.assert_array_equal(t - np.array([T0, T0 + 5_000_000_000]), [0, 1_500_000])


def test_reference_dropouts_are_filled_and_the_grid_extended():
    streams, _ = own_clock_streams(seed=5, k=4, seconds=3.0)
    names = names_of(4)
    ref = streams[0]
    cut = drop(ref, np.r_[100:103, len(ref.stamps) - 40:len(ref.stamps)])  # 3 lost, then it stops 0.2 s early
    streams[0] = cut
    samples, stats = pair_streams(streams, names)
    g = samples.stamps
    assert np.diff(g).max() < 1.5 * P and np.diff(g).min() > 0.5 * P  # no gaps
    filled = ~np.isin(g, cut.stamps)
    assert stats.grid_filled == filled.sum() >= 3 + 38
    # the three lost ones: equal steps between the reference's neighbours
    i = np.searchsorted(g, cut.stamps[99])
    np.testing.assert_array_equal(g[i:i + 5], cut.stamps[99] + (cut.stamps[100] - cut.stamps[99]) * np.arange(5) // 4)
    assert not samples.present[filled, 0].any() and samples.present[filled, 1:].mean() > 0.95
    assert stats.missing_tail[0] == filled[-45:].sum() and stats.missing[0] == filled.sum()


def test_an_imu_that_stops_or_starts_late_is_counted_not_refused():
    streams, _ = own_clock_streams(seed=6, k=4, seconds=3.0)
    streams[1] = drop(streams[1], np.arange(400, len(streams[1].stamps)))  # stops after 2 s
    streams[2] = drop(streams[2], np.arange(0, 100))  # starts 0.5 s late
    streams[3] = ImuStream(np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros((0, 3)))  # never speaks
    samples, stats = pair_streams(streams, names_of(4))
    n = len(samples)
    assert 195 <= stats.missing_tail[1] <= 205 and stats.missing_head[1] <= 1
    assert 95 <= stats.missing_head[2] <= 105
    assert stats.missing[3] == n and stats.messages[3] == 0 and not samples.present[:, 3].any()
    assert "missing slots (most on 'imu_03'" in stats.summary()


@pytest.mark.parametrize("what, change, fragment", [
    ("backwards", lambda s: np.r_[s[:300], s[300:] - 400_000_000], "'imu_02': its stamp goes backwards by 0.39"),
    ("jump", lambda s: np.r_[s[:300], s[300:] + 2_000_000_000], "'imu_02': its stamp jumps by 2.00"),
    ("repeat", lambda s: np.r_[s[:300], s[299:-1]], "'imu_02': its stamp repeats a stamp at message 300"),
    ("clock base", lambda s: s - 3600 * 1_000_000_000, "'imu_02': its stamps ("),
])
def test_bad_stamps_are_one_line_errors_naming_the_imu(what, change, fragment):
    streams, _ = own_clock_streams(seed=7, k=3, seconds=3.0)
    s = streams[2]
    streams[2] = ImuStream(change(s.stamps), s.accel, s.gyro)
    with pytest.raises(RecordingError) as err:
        pair_streams(streams, names_of(3))
    msg = one_line(err)
    assert fragment in msg, msg
    assert ("at message 300 of 600" in msg) != (what == "clock base")
    if what == "clock base":
        assert "too far apart to pair" in msg and "'imu_00'" in msg


def test_reference_without_messages_is_an_error():
    streams, _ = own_clock_streams(seed=8, k=3, seconds=1.0)
    streams[0] = drop(streams[0], np.arange(1, len(streams[0].stamps)))
    with pytest.raises(RecordingError) as err:
        pair_streams(streams, names_of(3))
    assert "reference IMU 'imu_00' has 1 message(s)" in one_line(err)


def test_split_streams_inverts_the_pairing_and_unused_rows_keep_every_message():
    streams, _ = own_clock_streams(seed=9, k=4, seconds=5.0)
    names = names_of(4)
    samples, stats = pair_streams(streams, names)
    back = split_streams(samples)
    again, _ = pair_streams(back, names, grid=samples.stamps)
    np.testing.assert_array_equal(again.own_stamps, samples.own_stamps)
    every, _ = pair_streams(streams, names, unused_rows=True)
    assert len(every) == len(samples) + stats.unused.sum() and np.all(np.diff(every.stamps) >= 0)
    for k, s in enumerate(split_streams(every)):
        np.testing.assert_array_equal(s.stamps, streams[k].stamps)
        np.testing.assert_array_equal(s.gyro, streams[k].gyro)


def test_pairing_is_vectorised():
    import time

    streams, _ = own_clock_streams(seed=10, k=32, seconds=60.0)
    t = time.perf_counter()
    samples, stats = pair_streams(streams, names_of(32))
    elapsed = time.perf_counter() - t
    assert stats.messages.sum() == 32 * 12000 and elapsed < 2.0, elapsed  # ~0.2 s on the test machine


# --------------------------------------------------------------------------- recordings


def channels(streams, desc, log_time=None):
    return [ChannelData(imu_topic(name), IMU_TYPE, s.stamps if log_time is None else log_time[k],
                        encode_imu(s.stamps, name, angular_velocity=s.gyro, linear_acceleration=s.accel))
            for k, (name, s) in enumerate(zip(desc.names, streams))]


def test_recording_with_own_stamps_is_paired_and_round_trips(tmp_path):
    desc = planar_square4()
    streams, _ = own_clock_streams(seed=11, k=4, seconds=10.0)
    want, stats = pair_streams(streams, desc.names)
    write_recording(tmp_path / "own.mcap", channels(streams, desc))
    got, rs = read_imu_recording(tmp_path / "own.mcap", desc)
    np.testing.assert_array_equal(got.stamps, want.stamps)
    np.testing.assert_array_equal(got.own_stamps, want.own_stamps)
    np.testing.assert_array_equal(got.accel, want.accel)
    np.testing.assert_array_equal(got.gyro, want.gyro)
    assert rs.samples == len(want) and rs.messages == stats.messages.sum()
    assert rs.incomplete_samples == (~want.present.all(axis=1)).sum()
    note = [n for n in rs.notes if n.startswith("IMU stamps differ")]
    assert len(note) == 1 and stats.summary() in note[0]
    # written back by the writer: each IMU's own stamps again, the same pairing
    write_imu_recording(tmp_path / "again.mcap", got, desc)
    again, _ = read_imu_recording(tmp_path / "again.mcap", desc)
    np.testing.assert_array_equal(again.own_stamps, got.own_stamps)
    np.testing.assert_array_equal(again.accel, got.accel)


def test_common_stamps_read_as_before(tmp_path):
    desc = planar_square4()
    rng = np.random.default_rng(12)
    s = ImuSamples(T0 + np.arange(300, dtype=np.int64) * P, rng.normal(size=(300, 4, 3)), rng.normal(size=(300, 4, 3)),
                   desc.names)
    s.accel[5:8, 2] = np.nan  # dropouts
    write_imu_recording(tmp_path / "r.mcap", s, desc)
    got, rs = read_imu_recording(tmp_path / "r.mcap", desc)
    assert got.own_stamps is None and not any("differ" in n for n in rs.notes)
    np.testing.assert_array_equal(got.stamps, s.stamps)
    np.testing.assert_array_equal(got.gyro[~np.isnan(s.accel).any(axis=2)], s.gyro[~np.isnan(s.accel).any(axis=2)])
    assert rs.incomplete_samples == 3


def test_recording_one_imu_a_microsecond_off_is_paired(tmp_path):
    """Refused before IMUs could have their own stamps ("must carry the same header.stamp")."""
    desc = planar_square4()
    rng = np.random.default_rng(13)
    stamps = T0 + np.arange(60, dtype=np.int64) * P
    streams = [ImuStream(stamps + (1000 if k == 2 else 0), rng.normal(size=(60, 3)), rng.normal(size=(60, 3)))
               for k in range(4)]
    write_recording(tmp_path / "off.mcap", channels(streams, desc))
    got, rs = read_imu_recording(tmp_path / "off.mcap", desc)
    assert len(got) == 60 and got.present.all() and rs.incomplete_samples == 0
    np.testing.assert_array_equal(got.own_stamps[:, 2] - got.stamps, np.full(60, 1000))
    assert any("/imu_array/imu_02/data_raw: 100%" in n for n in rs.notes)


def test_recording_with_bad_own_stamps_names_file_and_imu(tmp_path):
    desc = planar_square4()
    streams, _ = own_clock_streams(seed=14, k=4, seconds=3.0)
    arrival = [s.stamps.copy() for s in streams]  # log time keeps going; the IMU's clock steps back
    s = streams[1]
    streams[1] = ImuStream(np.r_[s.stamps[:200], s.stamps[200:] - 300_000_000], s.accel, s.gyro)
    write_recording(tmp_path / "back.mcap", channels(streams, desc, arrival))
    with pytest.raises(RecordingError) as err:
        read_imu_recording(tmp_path / "back.mcap", desc)
    msg = one_line(err)
    assert str(tmp_path / "back.mcap") in msg and "at message 200 of 599" in msg
    assert "IMU 'imu_01': its stamp goes backwards by 0.29" in msg
    streams, _ = own_clock_streams(seed=14, k=4, seconds=3.0)
    s = streams[3]
    streams[3] = ImuStream(s.stamps - 86400 * 1_000_000_000, s.accel, s.gyro)  # a day off: another clock base
    write_recording(tmp_path / "base.mcap", channels(streams, desc))
    with pytest.raises(RecordingError) as err:
        read_imu_recording(tmp_path / "base.mcap", desc)
    assert "IMU 'imu_03'" in one_line(err) and "too far apart to pair" in str(err.value)


def test_recording_with_own_stamps_counts_bad_and_duplicate_messages(tmp_path):
    desc = planar_square4()
    streams, _ = own_clock_streams(seed=15, k=4, seconds=2.0)
    s = streams[2]
    gyro = s.gyro.copy()
    gyro[50] = np.nan
    stamps = np.r_[s.stamps[:51], s.stamps[50:]]  # message 50 twice: the first (non-finite) one is kept
    streams[2] = ImuStream(stamps, np.r_[s.accel[:51], s.accel[50:]], np.r_[gyro[:51], s.gyro[50:]])
    write_recording(tmp_path / "bad.mcap", channels(streams, desc))
    got, rs = read_imu_recording(tmp_path / "bad.mcap", desc)
    assert rs.duplicate_messages == 1 and rs.bad_messages == 1 and got.own_stamps is not None
    assert s.stamps[50] not in got.own_stamps[got.present[:, 2], 2] and got.present[:, 2].sum() >= len(s.stamps) - 5


# --------------------------------------------------------------------------- live


def feed(asm, streams, true, *, tick=5_000_000, latency=(1e6, 3e6), behind=None, silent_from=None, seed=0,
         pop=True):
    """Messages in arrival order (true sample time + transport latency), a batch per tick; returns
    the samples handed out (flushed at the end)."""
    rng = np.random.default_rng(seed)
    idx = np.concatenate([np.full(len(s.stamps), k) for k, s in enumerate(streams)])
    arr = np.concatenate([t + rng.uniform(*latency, len(t)).astype(np.int64) for t in true])
    for k, lag in (behind or {}).items():
        arr[idx == k] += lag
    for k in range(len(streams)):
        arr[idx == k] = np.maximum.accumulate(arr[idx == k])  # one topic arrives in order
    keep = np.ones(len(idx), bool)
    for k, t_stop in (silent_from or {}).items():
        keep &= ~((idx == k) & (arr > t_stop))
    own = np.concatenate([s.stamps for s in streams])
    acc = np.concatenate([s.accel for s in streams])
    gyr = np.concatenate([s.gyro for s in streams])
    order = np.argsort(arr, kind="stable")
    order = order[keep[order]]
    start = int(arr.min())
    edges = np.searchsorted(arr[order], np.arange(start, int(arr.max()) + 2 * tick, tick))
    out = []
    for i in range(len(edges) - 1):
        sel = order[edges[i]:edges[i + 1]]
        now = start + (i + 1) * tick
        asm.add(idx[sel], own[sel], acc[sel], gyr[sel], now)
        if pop:
            out.append(asm.pop(now))
    out.append(asm.pop(start + len(edges) * tick, flush=True))
    out = [o for o in out if len(o)]
    return ImuSamples(np.concatenate([o.stamps for o in out]), np.concatenate([o.accel for o in out]),
                      np.concatenate([o.gyro for o in out]), names_of(len(streams)),
                      np.concatenate([o.own_stamps for o in out]))


def assert_same(live, offline):
    np.testing.assert_array_equal(live.stamps, offline.stamps)
    np.testing.assert_array_equal(live.own_stamps, offline.own_stamps)
    np.testing.assert_array_equal(live.accel, offline.accel)
    np.testing.assert_array_equal(live.gyro, offline.gyro)


def test_live_pairing_equals_offline_with_skew_jitter_and_an_imu_behind():
    streams, true = own_clock_streams(seed=16, k=8, seconds=10.0)
    offline, stats = pair_streams(streams, names_of(8))
    asm = PairingAssembler(8, timeout_ns=200_000_000)
    live = feed(asm, streams, true, behind={3: 30_000_000})  # IMU 3's messages arrive 30 ms late
    assert_same(live, offline)
    st = asm.stats
    assert st.paired == stats.paired.sum() and st.unused == stats.unused.sum() and st.late == 0
    assert st.missing_messages == stats.missing.sum() and st.overflow_samples == st.overflow_messages == 0
    assert asm.pending == 0
    np.testing.assert_array_equal(asm.periods_ns, [median_period(s.stamps) for s in streams])


def test_live_pairing_goes_on_without_a_silent_imu():
    streams, true = own_clock_streams(seed=17, k=4, seconds=4.0)
    stop = int(true[2][0]) + 2_000_000_000
    asm = PairingAssembler(4, timeout_ns=50_000_000)
    handed_before_flush = []

    class Spy:  # pops as feed does, but remembers how much came out before the final flush
        def __init__(self, inner):
            self.inner = inner

        def add(self, *a):
            return self.inner.add(*a)

        def pop(self, now, flush=False):
            out = self.inner.pop(now, flush=flush)
            if not flush:
                handed_before_flush.append(len(out))
            return out

    live = feed(Spy(asm), streams, true, silent_from={2: stop})
    # IMU 2 went silent after 2 s; the samples after it went out without it, while streaming
    assert sum(handed_before_flush) > len(live) - 30
    after = live.stamps > stop + 10_000_000
    assert after.sum() > 350 and not live.present[after, 2].any() and live.present[after][:, [0, 1, 3]].mean() > 0.98
    assert live.present[live.stamps < stop - 10_000_000, 2].mean() > 0.98


def test_live_pairing_extends_the_grid_while_the_reference_is_silent():
    streams, true = own_clock_streams(seed=18, k=4, seconds=3.0)
    stop = int(true[0][0]) + 1_500_000_000
    asm = PairingAssembler(4, timeout_ns=50_000_000)
    live = feed(asm, streams, true, silent_from={0: stop})
    later = live.stamps > stop + 100_000_000
    assert later.sum() > 250 and not live.present[later, 0].any()
    assert live.present[later][:, 1:].mean() > 0.98 and np.diff(live.stamps).max() < 1.5 * P
    assert asm.stats.grid_filled >= later.sum()
    # offline the grid is extended the same way
    cut = [ImuStream(s.stamps[keep], s.accel[keep], s.gyro[keep])
           for s, keep in zip(streams, [true[0] + 3_000_000 <= stop] + [np.ones(len(t), bool) for t in true[1:]])]
    offline, _ = pair_streams(cut, names_of(4))
    assert np.abs(len(offline) - len(live)) <= 1


def test_live_pairing_counts_bad_messages_and_bounds_memory():
    streams, true = own_clock_streams(seed=19, k=3, seconds=1.0)
    asm = PairingAssembler(3, timeout_ns=10**12, capacity=128)  # never times out: only capacity bounds it
    s = streams[1]
    ok = asm.add([1, 1, 1, 1], s.stamps[[0, 1, 1, 0]], s.accel[:4], s.gyro[:4], 0)
    assert ok.tolist() == [True, True, False, False]
    assert asm.stats.duplicate == 1 and asm.stats.backwards == 1
    live = feed(asm, streams[:1] + [drop(s, [0, 1])] + streams[2:], true[:1] + [true[1][2:]] + true[2:],
                latency=(1e6, 2e6))
    assert asm.stats.overflow_messages == 0 and len(live) == len(streams[0].stamps)
    big = PairingAssembler(3, timeout_ns=10**12, capacity=128)
    feed(big, streams[:1] + [ImuStream(np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros((0, 3)))] + streams[2:],
         true[:1] + [np.zeros(0, np.int64)] + true[2:], pop=False)
    assert big.stats.overflow_messages > 0 and big.pending == 0
    # a message whose grid samples are out already is late
    late_asm = PairingAssembler(2, timeout_ns=0, periods_ns=[P, P])  # no waiting: everything goes at once
    late_asm.add([0, 0, 0, 1, 1], [T0, T0 + P, T0 + 2 * P, T0 + 10_000, T0 + P + 10_000], np.zeros((5, 3)),
                 np.zeros((5, 3)), 0)
    out = late_asm.pop(1)
    assert out.own_stamps[:, 1].tolist() == [T0 + 10_000, T0 + P + 10_000, T0 + 2 * P]  # the last one missing
    assert late_asm.add([1], [T0 + P + 20_000], np.zeros((1, 3)), np.zeros((1, 3)), 2).tolist() == [False]
    assert late_asm.stats.late == 1


def test_live_pairing_with_estimated_clocks():
    streams, true = own_clock_streams(seed=20, k=3, seconds=3.0, jitter_s=20e-6, offsets=[0.0, 0.0, 21e-3])
    clocks = StampClocks(np.array([0.0, 0.0, -21e-3]), np.zeros(3), T0)
    offline, _ = pair_streams(streams, names_of(3), clocks=clocks)
    asm = PairingAssembler(3, timeout_ns=100_000_000, clocks=clocks)
    live = feed(asm, streams, true)
    assert_same(live, offline)


def test_raw_intake_pairs_own_stamps():
    desc = planar_square4()
    streams, _ = own_clock_streams(seed=21, k=4, seconds=1.0)
    intake = RawIntake(desc.names, own_stamps=True, sync_timeout_s=0.05)
    payloads, index = [], []
    for k, (name, s) in enumerate(zip(desc.names, streams)):
        encoded = encode_imu(s.stamps, name, angular_velocity=s.gyro, linear_acceleration=s.accel)
        payloads += [p.tobytes() for p in encoded]
        index += [k] * len(s.stamps)
    order = np.argsort(np.concatenate([s.stamps for s in streams]), kind="stable")
    intake.add([payloads[i] for i in order], np.asarray(index)[order], 0)
    out = intake.assembler.pop(10**9, flush=True)
    want, _ = pair_streams(streams, desc.names)
    np.testing.assert_array_equal(out.own_stamps, want.own_stamps)
    np.testing.assert_array_equal(out.gyro, want.gyro)


# --------------------------------------------------------------------------- replay


def test_replay_keeps_every_message_and_its_own_stamp(tmp_path):
    desc = planar_square4()
    streams, _ = own_clock_streams(seed=22, k=4, seconds=2.0)
    write_recording(tmp_path / "own.mcap", channels(streams, desc))
    rep = Replay(tmp_path / "own.mcap", desc, rate=0, burst=10_000)
    out = rep.due(0)
    per_imu = imu_payloads(out, desc)
    for k, (name, s) in enumerate(zip(desc.names, streams)):  # every message, its own stamp, bit for bit
        rows, stamps, payload = per_imu[k]
        np.testing.assert_array_equal(np.sort(stamps), s.stamps)
        dec = decode_raw_imu([p.tobytes() for p in payload], np.zeros(len(payload), np.int64), [name])
        assert dec.usable.all()
        np.testing.assert_array_equal(dec.stamps, stamps)
        np.testing.assert_array_equal(dec.gyro[np.argsort(stamps)], s.gyro)
    # looping shifts the own stamps with the grid; restamping moves them with their sample
    loop = Replay(tmp_path / "own.mcap", desc, rate=0, burst=len(out), loop=True)
    first, second = loop.due(0), loop.due(0)
    np.testing.assert_array_equal(second.own_stamps[:len(first)] - first.own_stamps,
                                  np.full(first.own_stamps.shape, loop.period_ns))
    re = Replay(tmp_path / "own.mcap", desc, rate=1.0).due(10**9, restamp_ns=5 * 10**18)
    assert re.stamps[0] == 5 * 10**18
    np.testing.assert_array_equal(re.own_stamps - re.stamps[:, None],
                                  out.own_stamps[:len(re)] - out.stamps[:len(re), None])
