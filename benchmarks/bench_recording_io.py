"""Recording I/O speed: read_imu_recording vs rosbags' plain read-and-deserialize, same file, same run;
and the reader's container layer before / after moving it onto the ``mcap`` library, same run.

Recording: 32-IMU array (grid_array32), 60 s at 1 kHz, simulated hand twisting
with ground truth (1.92 M sensor_msgs/Imu messages + 120 k truth messages),
written by write_imu_recording (timed).  Baseline (a): rosbags AnyReader
iterating every IMU message and deserializing it (typestore.deserialize_cdr),
nothing else.  (b): read_imu_recording (decode + align into ImuSamples).
Also compares chunk compressions (zstd / lz4 / none) for read speed and size.

Before / after (issue 5 section 2): the package at ``--old-rev`` (default
5d79859, the hand-written container layer) is extracted with ``git archive``
into a temporary directory; read_imu_recording of that old package and of
the working tree read the same 32-IMU, 1 kHz, ``--ab-duration`` s (default 20)
bare .mcap files (lz4 and zstd chunks), one child interpreter per variant,
reading in turn (old, new, new, old, ...) ``--ab-reads`` times each after a
warm-up read; the paired new/old ratios cancel the drift of a shared machine.
Both must return the same arrays (checked by hash).

Writes benchmarks/results/recording_io.md.

    python -m benchmarks.bench_recording_io [--duration 60] [--workdir DIR] [--repeat 3]
                                            [--ab-duration 20] [--ab-reads 20] [--old-rev 5d79859]
"""

from __future__ import annotations

import argparse
import io
import json
import os
import shutil
import statistics
import subprocess
import sys
import tarfile
import tempfile
import time
from pathlib import Path

import numpy as np

from benchmarks.baselines import rosbags_plain_read
from benchmarks.harness import REPO, RESULTS, machine_header, timed, write_results
from imu_array_ros.io.rosbag import mcap_format, mcap_writer
from imu_array_ros.io.rosbag.cdr_columns import encode_imu
from imu_array_ros.io.rosbag.recording import (
    IMU_TYPE,
    NO_ORIENTATION,
    imu_topic,
    read_imu_recording,
    write_imu_recording,
)
from imu_array_ros.model.layouts import grid_array32
from imu_array_ros.simulation.simulator import simulate_twist

OUT = RESULTS / "recording_io.md"


# --------------------------------------------------------------------------- before / after, child processes


#: A child interpreter: argv = root, recording; PYTHONPATH = root (see :class:`Child`), so it imports
#: imu_array_ros from ``root`` (the old package extracted from git, or the working tree); for every
#: line on stdin it times one read_imu_recording and prints one JSON line.
CHILD = r"""
import hashlib, json, sys, time
from pathlib import Path
root, path = sys.argv[1], sys.argv[2]
import imu_array_ros
from imu_array_ros.io.rosbag.recording import read_imu_recording
from imu_array_ros.model.layouts import grid_array32
assert Path(imu_array_ros.__file__).resolve().is_relative_to(Path(root).resolve()), imu_array_ros.__file__
desc = grid_array32()
for _ in sys.stdin:
    c0, t0 = time.process_time(), time.perf_counter()
    samples, stats = read_imu_recording(path, desc)
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    h = hashlib.sha1(samples.stamps.tobytes())
    h.update(samples.accel.tobytes())
    h.update(samples.gyro.tobytes())
    del samples
    print(json.dumps({"wall": wall, "cpu": cpu, "messages": stats.messages, "digest": h.hexdigest(),
                      "package": str(Path(imu_array_ros.__file__).parent)}), flush=True)
"""


def imu_channels(samples, desc) -> list[mcap_writer.ChannelData]:
    """The IMU topics of ``samples`` as write_imu_recording writes them (public API only)."""
    gyro_cov = np.diag(np.full(3, float(desc.gyroscope_noise_std) ** 2)).reshape(9)
    acc_cov = np.diag(np.full(3, float(desc.accelerometer_noise_std) ** 2)).reshape(9)
    out = []
    for k, name in enumerate(samples.names):
        rows = samples.present[:, k]
        payload = encode_imu(samples.stamps[rows], name, angular_velocity=samples.gyro[rows, k],
                             linear_acceleration=samples.accel[rows, k], angular_velocity_covariance=gyro_cov,
                             linear_acceleration_covariance=acc_cov, orientation_covariance=NO_ORIENTATION)
        out.append(mcap_writer.ChannelData(imu_topic(name), IMU_TYPE, samples.stamps[rows], payload))
    return out


def extract_old(rev: str, into: Path) -> Path:
    """``git archive`` the imu_array_ros package of ``rev`` into ``into``; returns the import root."""
    blob = subprocess.run(["git", "-C", str(REPO), "archive", "--format=tar", rev, "imu_array_ros"],
                          check=True, capture_output=True).stdout
    with tarfile.open(fileobj=io.BytesIO(blob)) as tar:
        tar.extractall(into, filter="data")
    return into


class Child:
    """A child interpreter reading the recording on request (see :data:`CHILD`)."""

    def __init__(self, root: Path, path: Path) -> None:
        env = {**{k: v for k, v in os.environ.items() if k != "PYTHONPATH"}, "PYTHONPATH": str(root)}
        self.proc = subprocess.Popen([sys.executable, "-c", CHILD, str(root), str(path)], stdin=subprocess.PIPE,
                                     stdout=subprocess.PIPE, text=True, cwd=path.parent, env=env)

    def read(self) -> dict:
        self.proc.stdin.write("go\n")
        self.proc.stdin.flush()
        line = self.proc.stdout.readline()
        if not line:
            raise RuntimeError(f"benchmark child failed (exit {self.proc.wait()})")
        return json.loads(line)

    def close(self) -> None:
        self.proc.stdin.close()
        self.proc.wait()


def before_after(work: Path, desc, samples, rev: str, reads: int) -> list[dict]:
    """Old (``rev``) vs new read_imu_recording on lz4 and zstd files of ``samples``; one row per compression.

    One child interpreter per variant; after one warm-up read each, the two read
    in turn (old, new, new, old, ...), so every new read has an old one next to it
    in time: their ratio is what a busy machine's drift cancels out of.
    """
    old_root = extract_old(rev, work / "old_package")
    channels = imu_channels(samples, desc)
    rows = []
    for comp in ("lz4", "zstd"):
        path = work / f"ab_{comp}.mcap"
        mcap_writer.write_recording(path, channels, compression=comp)
        kids = {"old": Child(old_root, path), "new": Child(REPO, path)}
        try:
            first = {v: kids[v].read() for v in kids}  # warm-up, not timed
            print(f"  {comp}: old package {first['old']['package']}, new {first['new']['package']}", flush=True)
            assert first["old"]["digest"] == first["new"]["digest"], "old and new read different arrays"
            wall = {"old": [], "new": []}
            cpu = {"old": [], "new": []}
            for i in range(reads):
                for v in (("old", "new") if i % 2 == 0 else ("new", "old")):
                    got = kids[v].read()
                    assert got["digest"] == first[v]["digest"]
                    wall[v].append(got["wall"])
                    cpu[v].append(got["cpu"])
        finally:
            for kid in kids.values():
                kid.close()
        messages = first["new"]["messages"]
        us = {v: [1e6 * t / messages for t in wall[v]] for v in wall}
        pair = sorted(n / o for n, o in zip(wall["new"], wall["old"]))
        q = lambda f: pair[min(len(pair) - 1, int(f * len(pair)))]  # noqa: E731
        row = {"compression": comp, "messages": messages, "size": path.stat().st_size, "reads": reads,
               "min": {v: min(us[v]) for v in us}, "median": {v: statistics.median(us[v]) for v in us},
               "max": {v: max(us[v]) for v in us},
               "cpu_median": {v: 1e6 * statistics.median(cpu[v]) / messages for v in cpu},
               "ratio_median": statistics.median(pair), "ratio_q25": q(0.25), "ratio_q75": q(0.75)}
        rows.append(row)
        print(f"  {comp}: old min/median {row['min']['old']:.3f}/{row['median']['old']:.3f} µs/msg, "
              f"new {row['min']['new']:.3f}/{row['median']['new']:.3f} µs/msg, "
              f"paired new/old median {row['ratio_median']:.3f} (quartiles {row['ratio_q25']:.3f}-{row['ratio_q75']:.3f})",
              flush=True)
        path.unlink()
    return rows


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
    ap.add_argument("--ab-duration", type=float, default=20.0, help="seconds of the before/after recording")
    ap.add_argument("--ab-reads", type=int, default=20, help="timed reads per variant and compression")
    ap.add_argument("--old-rev", default="5d79859", help="git revision with the hand-written container layer")
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

        w = timed(write, args.repeat)
        t_write, write_runs = w.best, w.wall
        size = du(rec)
        print(f"write_imu_recording: {t_write:.2f} s (runs {', '.join(f'{t:.2f}' for t in write_runs)}), "
              f"{n_imu_msgs + 2 * len(truth.stamps)} messages, {size / 1e6:.0f} MB", flush=True)

        r = timed(lambda: read_imu_recording(rec, desc), args.repeat)  # CPU includes the helper threads
        t_ours, ours_runs, (back, stats), cpu_ours = r.best, r.wall, r.result, r.best_cpu
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
        channels = imu_channels(samples, desc)
        comp_rows = []
        for comp in ("zstd", "lz4", "none"):
            path = work / f"imu_{comp}.mcap"
            t_w = timed(lambda: mcap_writer.write_recording(path, channels, compression=comp), 1).best
            r = timed(lambda: read_imu_recording(path, desc), args.repeat)
            t_r, c_r = r.best, r.best_cpu
            comp_rows.append((comp, t_w, t_r, c_r, path.stat().st_size))
            print(f"  {comp:5s}: write {t_w:.2f} s, read {t_r:.2f} s wall / {c_r:.2f} s CPU, "
                  f"{path.stat().st_size / 1e6:.0f} MB", flush=True)
            path.unlink()

        print(f"before / after ({args.old_rev} vs working tree), {args.ab_duration:g} s:", flush=True)
        ab_samples = samples.select(slice(0, int(round(args.ab_duration * 1000))))
        ab_rows = before_after(work, desc, ab_samples, args.old_rev, args.ab_reads)
        ab_load = os.getloadavg()[0]
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
        + f"\nContainer layer before / after (issue 5 section 2): `read_imu_recording` of the package at "
        f"`{args.old_rev}` (hand-written file scanning, record parsing, chunk reading, decompression) vs the "
        "working tree (`mcap` library: `SeekingReader.get_summary`, `Chunk.read`, "
        "`get_chunk_data_stream(validate_crc=True)`, plus the summary and data-section CRCs; numpy message "
        "location and columnar CDR decode unchanged).  Same bare .mcap file for both, "
        f"{len(desc.imus)} IMUs, {args.ab_duration:g} s at 1 kHz; one child interpreter per variant, reading in "
        f"turn (old, new, new, old, ...) {args.ab_reads} times each after a warm-up read; both return identical "
        "arrays (hash).  µs per IMU message, wall; the paired ratio divides each new read by the old read next "
        "to it in time:\n\n"
        "| chunks | messages | old min | old median | new min | new median | new / old, paired median "
        "(quartiles) | CPU median old / new |\n|---|---:|---:|---:|---:|---:|---:|---:|\n"
        + "".join(
            f"| {r['compression']} ({r['size'] / 1e6:.0f} MB) | {r['messages']} | {r['min']['old']:.3f} | "
            f"{r['median']['old']:.3f} | {r['min']['new']:.3f} | {r['median']['new']:.3f} | "
            f"**{r['ratio_median']:.3f}** ({r['ratio_q25']:.3f}-{r['ratio_q75']:.3f}) | "
            f"{r['cpu_median']['old']:.3f} / {r['cpu_median']['new']:.3f} |\n"
            for r in ab_rows
        )
        + "\nRange of single reads (µs/msg): "
        + "; ".join(
            f"{r['compression']} old {r['min']['old']:.3f}-{r['max']['old']:.3f}, new {r['min']['new']:.3f}-{r['max']['new']:.3f}"
            for r in ab_rows
        )
        + f".  Load average after the before/after runs: {ab_load:.2f}.\n"
    )
    print(f"wrote {write_results(OUT, text)}")


if __name__ == "__main__":
    main()
