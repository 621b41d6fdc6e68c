"""Recording I/O speed: read_imu_recording vs rosbags' plain read-and-deserialize, same file, same run.

Recording: 32-IMU array (grid_array32), 60 s at 1 kHz, simulated hand twisting
with ground truth (1.92 M sensor_msgs/Imu messages + 120 k truth messages),
written by write_imu_recording (timed).  Baseline (a): rosbags AnyReader
iterating every IMU message and deserializing it (typestore.deserialize_cdr),
nothing else.  (b): read_imu_recording (decode + align into ImuSamples).
Also compares chunk compressions (zstd / lz4 / none) for read speed and size.
Writes benchmarks/results/recording_io.md.

    python benchmarks/bench_recording_io.py [--duration 60] [--workdir DIR] [--repeat 3]
"""

from __future__ import annotations

import argparse
import os
import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from _common import machine_header, rosbags_plain_read  # noqa: E402

from imu_array_ros.io.rosbag import mcap_format, mcap_writer  # noqa: E402
from imu_array_ros.model.layouts import grid_array32  # noqa: E402
from imu_array_ros.io.rosbag.recording import _imu_channels, read_imu_recording, write_imu_recording  # noqa: E402
from imu_array_ros.simulation.simulator import simulate_twist  # noqa: E402

RESULTS = Path(__file__).resolve().parent / "results" / "recording_io.md"


def best_of(fn, repeat: int) -> tuple[float, list[float], object, float]:
    """(best wall s, all wall s, last result, best CPU s of this process incl. helper threads)."""
    times, cpu, result = [], [], None
    for _ in range(repeat):
        c0, t0 = time.process_time(), time.perf_counter()
        result = fn()
        times.append(time.perf_counter() - t0)
        cpu.append(time.process_time() - c0)
    return min(times), times, result, min(cpu)


def du(path: Path) -> int:
    if path.is_file():
        return path.stat().st_size
    return sum(p.stat().st_size for p in path.rglob("*") if p.is_file())


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--duration", type=float, default=60.0, help="seconds of 1 kHz data (default 60)")
    ap.add_argument("--workdir", help="where to put the recordings (default: a temp dir, removed)")
    ap.add_argument("--repeat", type=int, default=3, help="runs of our reader/writer (best is reported)")
    ap.add_argument("--no-results", action="store_true", help="do not write benchmarks/results/recording_io.md")
    args = ap.parse_args()

    work = Path(args.workdir) if args.workdir else Path(tempfile.mkdtemp(prefix="imu_rec_io_"))
    work.mkdir(parents=True, exist_ok=True)
    try:
        desc = grid_array32()
        rng = np.random.default_rng(2016)
        t0 = time.perf_counter()
        samples, truth = simulate_twist(desc, args.duration, 1000.0, rng)
        print(f"simulate: {time.perf_counter() - t0:.1f} s", flush=True)
        n_imu_msgs = int(samples.present.sum())
        rec = work / "twist"

        def write():
            write_imu_recording(rec, samples, desc, truth=truth)

        t_write, write_runs, _, _ = best_of(write, args.repeat)
        size = du(rec)
        print(f"write_imu_recording: {t_write:.2f} s (runs {', '.join(f'{t:.2f}' for t in write_runs)}), "
              f"{n_imu_msgs + 2 * len(truth.stamps)} messages, {size / 1e6:.0f} MB", flush=True)

        t_ours, ours_runs, (back, stats), cpu_ours = best_of(lambda: read_imu_recording(rec, desc), args.repeat)
        assert stats.messages == n_imu_msgs and stats.bad_messages == 0, stats
        assert np.array_equal(back.accel, samples.accel) and np.array_equal(back.gyro, samples.gyro)
        print(f"read_imu_recording: {t_ours:.2f} s (runs {', '.join(f'{t:.2f}' for t in ours_runs)}), "
              f"{n_imu_msgs / t_ours / 1e6:.2f} M msgs/s", flush=True)

        t_rb, n_rb = rosbags_plain_read(rec)
        assert n_rb == n_imu_msgs
        print(f"rosbags AnyReader + deserialize_cdr: {t_rb:.1f} s, {n_rb / t_rb / 1e3:.0f} k msgs/s "
              f"({1e6 * t_rb / n_rb:.1f} µs/msg)", flush=True)
        ratio = t_rb / t_ours
        print(f"ratio rosbags / ours: {ratio:.1f}x", flush=True)

        # chunk compression: read speed and size of the same IMU messages
        channels = _imu_channels(samples, desc, "/imu_array")
        comp_rows = []
        for comp in ("zstd", "lz4", "none"):
            path = work / f"imu_{comp}.mcap"
            t_w, _, _, _ = best_of(lambda: mcap_writer.write_recording(path, channels, compression=comp), 1)
            t_r, _, _, c_r = best_of(lambda: read_imu_recording(path, desc), args.repeat)
            comp_rows.append((comp, t_w, t_r, c_r, path.stat().st_size))
            print(f"  {comp:5s}: write {t_w:.2f} s, read {t_r:.2f} s wall / {c_r:.2f} s CPU, "
                  f"{path.stat().st_size / 1e6:.0f} MB", flush=True)
            path.unlink()
    finally:
        if not args.workdir:
            shutil.rmtree(work, ignore_errors=True)

    if args.no_results:
        return
    n_samples = len(samples)
    load = os.getloadavg()
    text = machine_header("Recording I/O: read_imu_recording vs rosbags")
    text += (
        f"Recording: {len(desc.imus)} IMUs, {args.duration:g} s at 1 kHz = {n_samples} array samples, "
        f"{n_imu_msgs} sensor_msgs/Imu messages (+ {2 * len(truth.stamps)} truth messages), "
        f"rosbag2 directory, MCAP chunk compression {mcap_format.DEFAULT_COMPRESSION}, "
        f"{mcap_format.DEFAULT_CHUNK_SIZE >> 20} MiB chunks, {size / 1e6:.0f} MB.  "
        f"Load average at the end: {load[0]:.2f} (other jobs may share the machine; ours: best of {args.repeat}).\n\n"
        "| step | time | throughput |\n|---|---:|---:|\n"
        f"| rosbags AnyReader + `deserialize_cdr` of every IMU message | {t_rb:.2f} s | "
        f"{n_rb / t_rb / 1e3:.0f} k msgs/s ({1e6 * t_rb / n_rb:.1f} µs/msg, {n_samples / t_rb:.0f} array samples/s) |\n"
        f"| `read_imu_recording` (decode + align into ImuSamples; {cpu_ours:.2f} s CPU incl. its "
        f"decompression thread) | {t_ours:.2f} s | "
        f"{n_imu_msgs / t_ours / 1e6:.2f} M msgs/s ({n_samples / t_ours / 1e3:.0f} k array samples/s) |\n"
        f"| **ratio** rosbags / ours | **{ratio:.1f}x** | |\n"
        f"| `write_imu_recording` (encode + write, incl. truth) | {t_write:.2f} s | "
        f"{(n_imu_msgs + 2 * len(truth.stamps)) / t_write / 1e6:.2f} M msgs/s |\n\n"
        f"Runs: read {', '.join(f'{t:.2f}' for t in ours_runs)} s; write {', '.join(f'{t:.2f}' for t in write_runs)} s.\n\n"
        f"Chunk compression (IMU topics only, bare .mcap, same messages; zstd level {mcap_format.ZSTD_LEVEL}; "
        "decompression runs in a helper thread, so CPU shows its cost better than wall time):\n\n"
        "| compression | write | read_imu_recording wall | read CPU | size |\n|---|---:|---:|---:|---:|\n"
        + "".join(f"| {c} | {w:.2f} s | {r:.2f} s | {cr:.2f} s | {s / 1e6:.0f} MB |\n" for c, w, r, cr, s in comp_rows)
    )
    RESULTS.parent.mkdir(parents=True, exist_ok=True)
    RESULTS.write_text(text, encoding="utf-8")
    print(f"wrote {RESULTS}")


if __name__ == "__main__":
    main()
