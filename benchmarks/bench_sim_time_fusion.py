"""Issue 24 item 6: the fusion node run with ``use_sim_time:=true`` on the replay's /clock, against the same
node without it, over real DDS, N runs each (alternating, so both see the same load).

Each run, in a DDS domain of its own (``ROS_DOMAIN_ID`` base + run, localhost only):

* a probe (:mod:`imu_array_ros.nodes.probe`, reliable keep-all) on the fused topics;
* ``fusion_node -p array_config:=config/array32.yaml`` (and ``-p use_sim_time:=true`` in the sim-time runs);
* once the probe has matched the fusion node's publishers (it prints ``ready``): ``driver_node
  mode:=replay bag:=bags/twist32_sample exit_at_end:=true`` (``publish_clock`` at its default, true).

After the driver logs ``replay finished``, the probe gets up to 10 s more; then every process is
stopped (one run is :func:`benchmarks.bench_default_replay.run_once` with these arguments).  Counted: fused
samples received by the probe (what a subscriber got while the node ran) and the node's own count at exit
(it publishes what it still holds when it exits).

    python -m benchmarks.bench_sim_time_fusion [--runs 3] [--domain 51] [--out benchmarks/results/sim_time_fusion.md]
"""

from __future__ import annotations

import argparse
import datetime
import tempfile
from pathlib import Path

import numpy as np

from benchmarks.bench_default_replay import ARRAY, BAG
from benchmarks.bench_default_replay import run_once as replay_once
from benchmarks.harness import load_average

__all__ = ["run_once", "main"]


def run_once(domain: int, work: Path, n: int, sim_time: bool) -> dict:
    """One run (module docstring): probe count, node count at exit (``fused``)."""
    return replay_once(domain, work, n, fusion_args=["-p", "use_sim_time:=true"] if sim_time else [],
                       driver_args=["-p", "exit_at_end:=true"], probe_ready=True)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="benchmarks.bench_sim_time_fusion")
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--domain", type=int, default=51, help="ROS_DOMAIN_ID of the first run (+1 per run)")
    ap.add_argument("--out", type=Path, default=None, help="results markdown (default: print only)")
    args = ap.parse_args(argv)
    from imu_array_ros.io.rosbag.recording import read_imu_recording
    from imu_array_ros.model.description import load_description

    n = len(read_imu_recording(BAG, load_description(ARRAY))[0])
    load_start = load_average()
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for i in range(args.runs):
            for j, sim in enumerate((False, True)):
                r = run_once(args.domain + 2 * i + j, Path(tmp), n, sim)
                rows.append((i + 1, sim, r))
                print(f"run {i + 1} use_sim_time {sim}: probe {r['probe']}/{n}, node at exit {r['fused']}", flush=True)
    got = {sim: [r["probe"] for _, s, r in rows if s == sim] for sim in (False, True)}
    lines = [
        "# The fusion node with use_sim_time on the replay's /clock (issue 24, item 6)",
        "",
        f"{datetime.date.today().isoformat()}, `python -m benchmarks.bench_sim_time_fusion --runs {args.runs}` "
        "(2-core machine shared with other jobs; load average at the start "
        f"{load_start}, at the end {load_average()}). Default replay of bags/twist32_sample ({n} samples × 32 IMUs) "
        "into fusion_node with and without `use_sim_time:=true`, the probe ready before the replay starts, up "
        "to 10 s after the replay for the rest.",
        "",
        "| run | use_sim_time | fused samples received by the probe | fused by the node by its exit |",
        "|---|---|---|---|",
        *[f"| {i} | {'true' if sim else 'false'} | {r['probe']} / {n} | {r['fused']} |" for i, sim, r in rows],
        "",
        f"Received, worst run: without use_sim_time {min(got[False])} / {n}, with it {min(got[True])} / {n} "
        f"(mean ratio with / without {np.mean(got[True]) / max(np.mean(got[False]), 1):.2f}). What the probe lacks "
        "the node published only when it was stopped.",
        "",
    ]
    text = "\n".join(lines)
    print(text)
    if args.out is not None:
        from imu_array_ros.util.files import atomic_write_text

        atomic_write_text(args.out, text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
