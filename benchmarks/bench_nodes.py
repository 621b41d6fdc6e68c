"""Live nodes over real DDS: driver_node -> fusion_node -> probe vs a bare rclpy subscriber, same run.

Issue 7 evidence.  32-IMU array (config/array32.yaml), recordings simulated with
``imu-array simulate`` at each sample rate tested, replayed by ``driver_node``
(``mode:=replay restamp:=true reliable:=true``), every process on its own, each
run in a DDS domain of its own (``ROS_DOMAIN_ID``, ``ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST``).

Measured, in one run:

* driver alone (no subscriber, ``rate:=0``): its publish ceiling (messages/s);
* bare subscriber: a plain rclpy node of its own process subscribing the 32
  ``/imu_array/<name>/data_raw`` topics with deserializing callbacks that only
  count, the fusion node's reliable input QoS (reliable, keep all), spun by
  ``EventsExecutor.spin_once`` as the nodes are; fed by the driver flat out
  (``rate:=0``, flow-controlled) and at real time (``rate:=1``) up the ladder of
  sample rates; its ceiling = messages/s received with nothing lost;
* driver -> fusion_node -> probe at real time up the same ladder: fused samples
  received vs published, CPU of each process (/proc/<pid>/stat) over the
  streaming window, latency fused publish - stamp (the fusion node's own
  /diagnostics, per 1 s window) and probe arrival - stamp (every sample; one
  more hop).  The stamp is the time the sample fell due at the driver
  (``restamp``), so both include the driver's poll delay (<= ``poll_period``).

A point *sustains* its rate when every message / fused sample arrived, the
fusion node fused every sample complete (no incomplete, late or overflow
samples) and the stream kept up (the last sample arrived within --max-lag of
its stamp).  The highest sustained rate of the ladder is refined by bisection.

    python -m benchmarks.bench_nodes [--rates 100,200,400,800,1000,1600,2000] [--duration 10]
                                     [--bisect 2] [--out benchmarks/results/nodes.md]

The parts live in :mod:`benchmarks.nodes`: the processes and commands (``procs``), the helper roles started in
processes of their own (``roles``), the CPU sampler (``cpu``), the measurements (``measure``), the in-process
costs (``costs``) and the results file (``report``).
"""

from __future__ import annotations

import argparse
import datetime
import json
import shutil
import tempfile
import time
from pathlib import Path

from benchmarks.harness import RESULTS, command, commit, load_average
from benchmarks.nodes.costs import in_process_costs
from benchmarks.nodes.measure import Point, measure_bare, measure_driver_alone, measure_fusion, measure_synthetic
from benchmarks.nodes.procs import N_IMUS, recording
from benchmarks.nodes.report import best, describe, first_failed, write_report


def _point(d: dict) -> Point:
    d = dict(d)
    for k in ("lat_diag", "lat_probe"):
        d[k] = tuple(d.get(k) or ())
    return Point(**d)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--rates", default="100,200,400,800,1000,1600,2000",
                    help="array sample rates of the ladders, Hz (comma separated); each ladder stops at its first "
                    "rate not sustained")
    ap.add_argument("--duration", type=float, default=10.0, help="seconds of recording per point (default 10)")
    ap.add_argument("--bisect", type=int, default=2, help="bisection steps between the highest sustained and "
                    "the lowest failed ladder rate (default 2)")
    ap.add_argument("--max-lag", type=float, default=0.5, help="a point is sustained only if its last sample "
                    "arrives within this many seconds of its stamp (default 0.5)")
    ap.add_argument("--warmup", type=float, default=2.0, help="seconds at the start of each fusion point left out "
                    "of the steady-state figures (reported on their own; default 2)")
    ap.add_argument("--flat-rate", type=int, default=500, help="recording (Hz x --duration) replayed flat out for "
                    "the ceilings (default 500: 160,000 messages with 10 s)")
    ap.add_argument("--drains", type=int, default=3, help="repeats of each queue-drain measurement; the best is "
                    "reported (default 3)")
    ap.add_argument("--latency-periods", default="0.001", help="extra 200 Hz fusion points with these fusion "
                    "node periods (comma separated; empty: none)")
    ap.add_argument("--workdir", help="keep recordings, process logs and points.json here (default: a temp dir, "
                    "removed at the end)")
    ap.add_argument("--render", help="only write the report again from a points.json of an earlier run")
    ap.add_argument("--out", default=str(RESULTS / "nodes.md"))
    args = ap.parse_args()
    if args.render:
        raw = json.loads(Path(args.render).read_text())
        res = {k: ([_point(d) for d in v] if isinstance(v, list) and v and isinstance(v[0], dict) and "kind" in v[0]
                   else _point(v) if isinstance(v, dict) and "kind" in v else v) for k, v in raw.items()}
        res["costs"] = [tuple(c) for c in res["costs"]]
        if not res.get("date"):  # runs before the date was saved: when points.json was written
            res["date"] = datetime.datetime.fromtimestamp(Path(args.render).stat().st_mtime, datetime.timezone.utc
                                                          ).strftime("%Y-%m-%d %H:%M UTC")
        res["rendered"] = datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%d %H:%M UTC")
        write_report(Path(args.out), res)
        print(f"wrote {args.out}")
        return

    cmd, code = command(), commit()
    t_start = time.perf_counter()
    date = datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%d %H:%M UTC")
    load_start = load_average()
    print(f"load average at start: {load_start}", flush=True)
    work = Path(args.workdir or tempfile.mkdtemp(prefix="imu_bench_nodes_"))
    work.mkdir(parents=True, exist_ok=True)
    rates = sorted({int(r) for r in args.rates.split(",") if r.strip()})
    recs: dict[int, Path] = {}

    def rec(rate: int) -> tuple[Path, int]:
        if rate not in recs:
            recs[rate] = recording(work, rate, args.duration)
        return recs[rate], int(round(rate * args.duration))

    def ladder(kind: str, measure) -> list[Point]:
        points: list[Point] = []
        for r in rates:
            bag, n = rec(r)
            print(f"[{kind}, {r} Hz, driver at real time]", flush=True)
            points.append(measure(bag, n, r))
            print("  " + describe(points[-1]), flush=True)
            if not points[-1].sustained:
                break
        lo, hi = best(points), first_failed(points)
        if lo and hi:
            a, b = lo.rate_hz, hi.rate_hz
            for _ in range(args.bisect):
                mid = int(round((a + b) / 2 / 10) * 10)
                if mid <= a or mid >= b:
                    break
                bag, n = rec(mid)
                print(f"[{kind}, {mid} Hz, bisection]", flush=True)
                points.append(measure(bag, n, mid))
                print("  " + describe(points[-1]), flush=True)
                a, b = (mid, b) if points[-1].sustained else (a, mid)
        return points

    try:
        top = rates[-1]
        bag, n = rec(top)
        print("[in-process costs]", flush=True)
        costs = in_process_costs(bag)
        for what, c, m in costs:
            print(f"  {what}: {c:,.0f} us per call, {m:.1f} us per message", flush=True)
        print(f"[driver alone, rate 0, {top} Hz recording]", flush=True)
        drv = measure_driver_alone(work, bag, n)
        print("  " + describe(drv), flush=True)
        flat_bag, flat_n = rec(args.flat_rate)  # flat out: 32 x flat_rate x duration messages
        print(f"[driver rate 0 -> bare subscriber, {args.flat_rate} Hz recording]", flush=True)
        bare_flat = measure_bare(work, flat_bag, flat_n, args.flat_rate, 0.0, args.max_lag, args.duration)
        print("  " + describe(bare_flat), flush=True)
        synth = []
        for topics, raw in ((N_IMUS, False), (1, False), (0, False), (N_IMUS, True)):
            print(f"[queues filled, then drained: {topics or 'one array message per sample, 1'} topic(s), "
                  f"{'raw' if raw else 'deserializing'}]", flush=True)
            tries = []
            for _ in range(args.drains):
                tries.append(measure_synthetic(work, bag, topics, raw))
                print("  " + describe(tries[-1]), flush=True)
            best_try = max(tries, key=lambda p: p.counts.get("messages_per_s", 0.0))
            best_try.counts["tries_msgs_per_s"] = [round(p.counts.get("messages_per_s", 0.0)) for p in tries]
            synth.append(best_try)

        bare = ladder("driver -> bare subscriber",
                      lambda bag, n, r: measure_bare(work, bag, n, r, 1.0, args.max_lag, args.duration))
        fusion = ladder("driver -> fusion -> probe",
                        lambda bag, n, r: measure_fusion(work, bag, n, r, args.max_lag, args.duration,
                                                         warmup=args.warmup))
        extra: list[Point] = []
        for per in [float(x) for x in args.latency_periods.split(",") if x.strip()]:
            bag, n = rec(200)
            print(f"[driver -> fusion (period {per:g}) -> probe, 200 Hz]", flush=True)
            extra.append(measure_fusion(work, bag, n, 200, args.max_lag, args.duration, period=per,
                                        warmup=args.warmup))
            print("  " + describe(extra[-1]), flush=True)

        load_end = load_average()
        print(f"load average at end: {load_end}", flush=True)
        res = {"args": vars(args), "command": cmd, "commit": code, "date": date, "load_start": load_start,
               "load_end": load_end,
               "minutes": (time.perf_counter() - t_start) / 60, "driver": drv, "bare_flat": bare_flat,
               "synthetic": synth, "bare": bare, "fusion": fusion, "extra": extra, "costs": costs}
        (work / "points.json").write_text(json.dumps(
            {k: ([p.__dict__ for p in v] if isinstance(v, list) and v and isinstance(v[0], Point)
                 else v.__dict__ if isinstance(v, Point) else v) for k, v in res.items()}, default=str, indent=1))
        write_report(Path(args.out), res)
        print(f"wrote {args.out}")
    finally:
        if not args.workdir:
            shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    main()
