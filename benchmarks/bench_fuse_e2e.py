"""End to end: `imu-array fuse` vs rosbags' plain read-and-deserialize, same file, same run.

Recording: 32-IMU array, 60 s at 1 kHz (1.92 M sensor_msgs/Imu messages),
simulated hand twisting.  Baseline: rosbags AnyReader iterating every IMU
message and deserializing it (typestore.deserialize_cdr), nothing else.
Target (issue 2): fuse (read + fuse + write, whole process) >= 3x faster.
Writes benchmarks/results/fuse_e2e.md.

    python -m benchmarks.bench_fuse_e2e [--duration 60] [--workdir DIR]
"""

from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from benchmarks.baselines import rosbags_plain_read
from benchmarks.harness import REPO, RESULTS, machine_header, write_results


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--duration", type=float, default=60.0)
    ap.add_argument("--workdir")
    args = ap.parse_args()
    work = Path(args.workdir or tempfile.mkdtemp(prefix="imu_e2e_"))
    work.mkdir(parents=True, exist_ok=True)
    exe = shutil.which("imu-array") or str(Path(sys.executable).with_name("imu-array"))
    array = REPO / "config" / "array32.yaml"
    rec = work / "twist60"
    env = dict(os.environ, OMP_NUM_THREADS="1", OPENBLAS_NUM_THREADS="1")
    if not rec.exists():
        t0 = time.perf_counter()
        subprocess.run([exe, "simulate", "--array", str(array), "--out", str(rec), "--duration", str(args.duration),
                        "--rate", "1000", "--rms-rate", "900", "-q"], check=True, env=env)
        print(f"simulate: {time.perf_counter() - t0:.1f} s", flush=True)

    t_base, count = rosbags_plain_read(rec)
    print(f"rosbags read+deserialize: {t_base:.2f} s for {count} messages ({1e6 * t_base / count:.1f} us/msg)", flush=True)

    out = work / "fused.mcap"
    t0 = time.perf_counter()
    proc = subprocess.Popen([exe, "fuse", str(rec), "--array", str(array), "--out", str(out), "--force", "-q"], env=env)
    _, status, usage = os.wait4(proc.pid, 0)  # resource usage of this child alone
    t_fuse = time.perf_counter() - t0
    proc.returncode = os.waitstatus_to_exitcode(status)
    if proc.returncode != 0:
        raise SystemExit(f"imu-array fuse failed with exit code {proc.returncode}")
    peak_mb = usage.ru_maxrss / 1024
    ratio = t_base / t_fuse
    print(f"imu-array fuse: {t_fuse:.2f} s (whole process) -> {ratio:.2f}x faster than the plain rosbags read", flush=True)

    text = machine_header("End to end: imu-array fuse vs rosbags plain read")
    text += (
        f"Recording: 32 IMUs, {args.duration:.0f} s at 1 kHz, simulated twisting; {count:,} Imu messages; "
        f"{sum(f.stat().st_size for f in rec.iterdir()) / 1e6:.0f} MB on disk.\n\n"
        "| what | wall time (s) | per IMU message (us) | array samples/s |\n|---|---|---|---|\n"
        f"| rosbags AnyReader read + deserialize (baseline) | {t_base:.2f} | {1e6 * t_base / count:.2f} | {count / 32 / t_base:,.0f} |\n"
        f"| `imu-array fuse` (process start, read, fuse, write) | {t_fuse:.2f} | {1e6 * t_fuse / count:.2f} | {count / 32 / t_fuse:,.0f} |\n\n"
        f"Ratio baseline / fuse: **{ratio:.2f}x** (target >= 3x). Peak RSS of the fuse process: {peak_mb:.0f} MB.\n"
    )
    print(f"wrote {write_results(RESULTS / 'fuse_e2e.md', text)}")
    if not args.workdir:
        shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    main()
