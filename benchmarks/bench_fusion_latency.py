"""Fused-output latency of fusion_node at 32 IMUs x 200 Hz against the bare-subscriber ceiling, same run (issue 24).

Three processes per measurement, each in its own interpreter, in a DDS domain of the measurement's own
(localhost only):

* ``pub``: a driver-like publisher: 32 ``/imu_array/<name>/data_raw`` topics of config/array32.yaml, reliable
  (keep last 1000, the driver's ``reliable:=true``), one array sample every 1/rate s on an absolute schedule; the
  payloads are encoded beforehand (bags/twist32_sample, looped) and each tick's 32 messages get the wall time at
  the start of that tick's publishing as their ``header.stamp`` (restamping: stamp = publish time);
* ``fusion_node`` (``reliable:=true``, other parameters default), only in the fused modes;
* ``sub``: one rclpy subscriber (serialized callbacks, ``EventsExecutor.spin_once`` as the nodes) that notes
  ``arrival - header.stamp`` (wall clock, same machine) of every message: of ``/imu_array/fused/imu`` (the
  fused modes), or of the 32 raw topics (``bare``: the ceiling -- a sample's latency is the arrival of its last
  IMU message, the earliest a fusion could start; every message's is kept too).

Modes: ``bare``; ``event`` (this checkout's fusion_node); ``old`` (``--old PATH``: the fusion_node of another
checkout, e.g. ``git worktree add /tmp/old <commit>``, run from there with the same interpreter).  The modes are
measured in turn, ``--repeats`` times round, so a change of the machine's load hits them alike; the first
``--warmup`` s of each are left out.  CPU per message: the fusion node's utime + stime (/proc) over the
measured window / the raw messages published in it.

    python -m benchmarks.bench_fusion_latency [--old /tmp/h1-old] [--duration 12] [--repeats 3]
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from benchmarks.harness import REPO, RESULTS, load_average, machine_header, write_results

ARRAY = REPO / "config" / "array32.yaml"
BAG = REPO / "bags" / "twist32_sample"
FUSED = "/imu_array/fused/imu"
CLK_TCK = os.sysconf("SC_CLK_TCK")


# --------------------------------------------------------------------------- roles (own processes)

def _stamp(payload: bytes) -> int:
    return int.from_bytes(payload[4:8], "little", signed=True) * 1_000_000_000 + int.from_bytes(payload[8:12], "little")


def role_pub(args) -> int:
    import rclpy
    from sensor_msgs.msg import Imu

    from imu_array_ros.io.messages import raw_imu_payloads
    from imu_array_ros.io.rosbag.recording import imu_topic, read_imu_recording
    from imu_array_ros.model.description import load_description
    from imu_array_ros.nodes.runtime import qos

    desc = load_description(ARRAY)
    samples, _ = read_imu_recording(BAG, desc)
    per_imu = raw_imu_payloads(samples, desc)
    k = len(per_imu)
    rows = [[None] * k for _ in range(len(samples))]
    for i, (r, pl) in enumerate(per_imu):
        for row, p in zip(r, pl):
            rows[row][i] = bytearray(p.tobytes())
    rclpy.init()
    node = rclpy.create_node("bench_latency_publisher")
    pubs = [node.create_publisher(Imu, imu_topic(n), qos(True)) for n in desc.names]
    t_wait = time.monotonic() + 60
    while any(p.get_subscription_count() < 1 for p in pubs) and time.monotonic() < t_wait:
        time.sleep(0.02)
    time.sleep(1.0)  # let the reliable endpoints settle
    period = 1e9 / args.rate
    n_ticks = int(round(args.duration * args.rate))
    ticks = np.zeros(n_ticks, dtype=np.int64)
    start = time.monotonic_ns() + 10_000_000
    print(f"start {time.time_ns() + 10_000_000}", flush=True)
    for t in range(n_ticks):
        due = start + int(t * period)
        delay = (due - time.monotonic_ns()) / 1e9
        if delay > 0:
            time.sleep(delay)
        now = time.time_ns()
        sec, nsec = divmod(now, 1_000_000_000)
        head = sec.to_bytes(4, "little", signed=True) + nsec.to_bytes(4, "little")
        row = rows[t % len(rows)]
        for i in range(k):
            buf = row[i]
            buf[4:12] = head
            pubs[i].publish(bytes(buf))
        ticks[t] = now
    Path(args.out).write_text(json.dumps({"ticks_ns": ticks.tolist(), "n_imus": k}))
    time.sleep(1.0)  # let the last messages go out before the publisher leaves
    node.destroy_node()
    rclpy.try_shutdown()
    return 0


def role_sub(args) -> int:
    import rclpy
    from rclpy.executors import ExternalShutdownException
    from rclpy.experimental import EventsExecutor
    from sensor_msgs.msg import Imu

    from imu_array_ros.io.rosbag.recording import imu_topic
    from imu_array_ros.model.description import load_description
    from imu_array_ros.nodes.runtime import qos

    rclpy.init()
    node = rclpy.create_node("bench_latency_subscriber")
    topics = [FUSED] if args.fused else [imu_topic(n) for n in load_description(ARRAY).names]
    stamps: list[int] = []
    arrivals: list[int] = []

    def cb(payload: bytes) -> None:
        arrivals.append(time.time_ns())
        stamps.append(_stamp(payload))

    for t in topics:
        node.create_subscription(Imu, t, cb, qos(True, keep_all=True), raw=True)
    executor = EventsExecutor()
    executor.add_node(node)
    stop = []
    signal.signal(signal.SIGINT, lambda *_: stop.append(1))
    print("ready", flush=True)
    try:
        while not stop:
            executor.spin_once(timeout_sec=0.05)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    np.savez(args.out, stamps=np.array(stamps, np.int64), arrivals=np.array(arrivals, np.int64))
    node.destroy_node()
    rclpy.try_shutdown()
    return 0


# --------------------------------------------------------------------------- one measurement

def _cpu_s(pid: int) -> float:
    with open(f"/proc/{pid}/stat") as fh:
        f = fh.read().rsplit(")", 1)[1].split()
    return (int(f[11]) + int(f[12])) / CLK_TCK


def _machine_busy() -> float:
    with open("/proc/stat") as fh:
        v = [int(x) for x in fh.readline().split()[1:]]
    return (sum(v[:8]) - v[3] - v[4]) / CLK_TCK


def measure(mode: str, args, work: Path, domain: int) -> dict:
    env = dict(os.environ, ROS_DOMAIN_ID=str(domain), ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST",
               PYTHONUNBUFFERED="1", OMP_NUM_THREADS="1", OPENBLAS_NUM_THREADS="1")
    d = work / f"{mode}_{domain}_{time.time_ns()}"
    d.mkdir(parents=True)
    procs: dict[str, subprocess.Popen] = {}

    def start(name, cmd, cwd=REPO, extra_env=None):
        e = dict(env, **(extra_env or {}))
        procs[name] = subprocess.Popen([str(c) for c in cmd], cwd=cwd, env=e, stdin=subprocess.DEVNULL,
                                       stdout=open(d / f"{name}.out", "w"), stderr=open(d / f"{name}.err", "w"))
        return procs[name]

    me = [sys.executable, "-m", "benchmarks.bench_fusion_latency"]
    try:
        if mode != "bare":
            tree = REPO if mode == "event" else Path(args.old)
            start("fusion", [sys.executable, "-m", "imu_array_ros.nodes.fusion_node", "--ros-args",
                             "-p", f"array_config:={ARRAY}", "-p", "reliable:=true",
                             *[a for kv in (args.param or []) if mode == "event" for a in ("-p", kv)]], cwd=tree,
                  extra_env={"PYTHONPATH": str(tree)})
        start("sub", me + ["sub", "--out", d / "sub.npz"] + (["--fused"] if mode != "bare" else []))
        for _ in range(600):
            if "ready" in (d / "sub.out").read_text():
                break
            time.sleep(0.05)
        if mode != "bare":
            for _ in range(600):
                if "fusing" in (d / "fusion.err").read_text():
                    break
                if procs["fusion"].poll() is not None:
                    raise RuntimeError(f"fusion_node ended: {(d / 'fusion.err').read_text()[-2000:]}")
                time.sleep(0.05)
        pub = start("pub", me + ["pub", "--out", d / "pub.json", "--rate", args.rate, "--duration", args.duration])
        t0 = None
        while t0 is None and pub.poll() is None:
            text = (d / "pub.out").read_text()
            if "start " in text:
                t0 = int(text.split("start ")[1].split()[0])
            time.sleep(0.01)
        cpu = {}
        if t0 is not None:
            for label, at in (("a", t0 + args.warmup * 1e9), ("b", t0 + (args.duration - 1.0) * 1e9)):
                time.sleep(max(0.0, (at - time.time_ns()) / 1e9))
                cpu[label] = (time.time_ns(), _cpu_s(procs["fusion"].pid) if "fusion" in procs else float("nan"),
                              _machine_busy(), os.getloadavg()[0])
        pub.wait(args.duration + 60)
        time.sleep(1.0)
        ticks = np.array(json.loads((d / "pub.json").read_text())["ticks_ns"], np.int64) \
            if (d / "pub.json").exists() else None
    finally:
        for name in ("pub", "sub", "fusion"):
            p = procs.get(name)
            if p is not None and p.poll() is None:
                p.send_signal(signal.SIGINT)
                try:
                    p.wait(20)
                except subprocess.TimeoutExpired:
                    p.kill()
                    p.wait()
    if ticks is None:
        raise RuntimeError(f"{mode}: the publisher failed: {(d / 'pub.err').read_text()[-2000:]}")
    got = np.load(d / "sub.npz")
    return {"mode": mode, "dir": str(d), "ticks": ticks, "stamps": got["stamps"], "arrivals": got["arrivals"],
            "cpu": cpu, "t0": t0}


# --------------------------------------------------------------------------- numbers

N_IMUS = 32


def latencies(m: dict, warmup_s: float) -> dict:
    """Per-sample latencies (ms) of one measurement after the warm-up, and the counts."""
    ticks, stamps, arr = m["ticks"], m["stamps"], m["arrivals"]
    lo = ticks[0] + int(warmup_s * 1e9)
    keep = stamps >= lo
    out = {"published_samples": int((ticks >= lo).sum())}
    if m["mode"] == "bare":
        # a sample's ceiling: the arrival of its last IMU message
        st, inv = np.unique(stamps[keep], return_inverse=True)
        last = np.full(len(st), np.iinfo(np.int64).min)
        np.maximum.at(last, inv, arr[keep])
        count = np.bincount(inv, minlength=len(st))
        out["lat_ms"] = (last - st)[count == N_IMUS] / 1e6
        out["lat_msg_ms"] = (arr[keep] - stamps[keep]) / 1e6
        out["received_samples"] = int((count == N_IMUS).sum())
    else:
        out["lat_ms"] = (arr[keep] - stamps[keep]) / 1e6
        out["received_samples"] = int(keep.sum())
    cpu = m["cpu"]
    if "a" in cpu and "b" in cpu:
        (ta, ca, ma, la), (tb, cb, mb, lb) = cpu["a"], cpu["b"]
        msgs = int(((ticks >= ta) & (ticks < tb)).sum()) * N_IMUS
        out["cpu_us_per_msg"] = (cb - ca) / msgs * 1e6 if msgs else float("nan")
        out["cpu_share"] = (cb - ca) / ((tb - ta) / 1e9)
        out["machine_busy_cores"] = (mb - ma) / ((tb - ta) / 1e9)
        out["load1"] = (la, lb)
    return out


def _q(x, q):
    return float(np.percentile(x, q)) if len(x) else float("nan")


def report(results: list[dict], args, started: str, load_start: str, load_end: str, cmd: str) -> str:
    modes = [m for m in ("bare", "event", "old") if any(r["mode"] == m for r in results)]
    names = {"bare": "bare subscriber (ceiling: last IMU message of a sample)",
             "event": "fusion_node, event-driven (this commit)", "old": f"fusion_node of `{args.old}` (the baseline)"}
    lines = [machine_header("Fused-output latency at 32 IMUs x 200 Hz vs the bare-subscriber ceiling", date=started,
                            cmd=cmd, extra=[f"load average (1, 5, 15 min) at start: {load_start}; at end: {load_end}",
                                            f"{args.repeats} rounds of {args.duration:g} s per mode, modes in turn, "
                                            f"first {args.warmup:g} s of each left out; rate {args.rate:g} Hz"]),
             "Latency = arrival at a subscriber process - `header.stamp` (the publisher's wall time when it "
             "started publishing the sample's 32 messages).  Fused: `/imu_array/fused/imu`, two hops "
             "(publisher -> fusion_node -> subscriber).  Ceiling: the same publisher, the subscriber on the 32 raw "
             "topics, a sample's latency = arrival of its last message (one hop).  CPU per message: fusion_node "
             "utime + stime over the measured window / raw messages published in it.  *Machine busy*: all "
             "processes, in cores (2).\n",
             "## Pooled over the rounds\n",
             "| mode | samples received / published | p50 (ms) | p95 (ms) | p99 (ms) | max (ms) | p99 / ceiling p99 "
             "| fusion CPU per message (us) | fusion CPU (% of a core) | machine busy (cores) |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    pooled = {}
    for mode in modes:
        rs = [r for r in results if r["mode"] == mode]
        lat = np.concatenate([r["lat_ms"] for r in rs])
        pooled[mode] = lat
        cpu = [r.get("cpu_us_per_msg", float("nan")) for r in rs]
        share = [r.get("cpu_share", float("nan")) for r in rs]
        busy = [r.get("machine_busy_cores", float("nan")) for r in rs]
        ceiling = _q(pooled["bare"], 99) if "bare" in pooled else float("nan")
        ratio = "" if mode == "bare" else f"{_q(lat, 99) / ceiling:.2f}"
        cpu_txt = "" if mode == "bare" else f"{np.nanmean(cpu):.1f}"
        share_txt = "" if mode == "bare" else f"{100 * np.nanmean(share):.0f} %"
        lines.append(f"| {names[mode]} | {sum(r['received_samples'] for r in rs):,} / "
                     f"{sum(r['published_samples'] for r in rs):,} | {_q(lat, 50):.2f} | {_q(lat, 95):.2f} | "
                     f"{_q(lat, 99):.2f} | {lat.max() if len(lat) else float('nan'):.1f} | {ratio} | {cpu_txt} | "
                     f"{share_txt} | {np.nanmean(busy):.2f} |")
    if "bare" in modes:
        msg = np.concatenate([r["lat_msg_ms"] for r in results if r["mode"] == "bare"])
        lines.append(f"\nBare subscriber, every raw message (not only a sample's last): p50 {_q(msg, 50):.2f} ms, "
                     f"p95 {_q(msg, 95):.2f} ms, p99 {_q(msg, 99):.2f} ms.\n")
    lines += ["## Every round\n", "| round | mode | samples received / published | p50 (ms) | p95 (ms) | p99 (ms) | "
              "fusion CPU per message (us) | load (1 min) at start, end of window | machine busy (cores) |",
              "|---|---|---|---|---|---|---|---|---|"]
    for r in results:
        la = r.get("load1", (float("nan"), float("nan")))
        lines.append(f"| {r['round']} | {r['mode']} | {r['received_samples']:,} / {r['published_samples']:,} | "
                     f"{_q(r['lat_ms'], 50):.2f} | {_q(r['lat_ms'], 95):.2f} | {_q(r['lat_ms'], 99):.2f} | "
                     f"{'' if r['mode'] == 'bare' else format(r.get('cpu_us_per_msg', float('nan')), '.1f')} | "
                     f"{la[0]:.2f}, {la[1]:.2f} | {r.get('machine_busy_cores', float('nan')):.2f} |")
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("role", nargs="?", choices=("run", "pub", "sub"), default="run")
    ap.add_argument("--out", help="pub/sub: the record written; run: the results file")
    ap.add_argument("--fused", action="store_true", help="sub: the fused topic (else the 32 raw topics)")
    ap.add_argument("--rate", type=float, default=200.0, help="array samples per second")
    ap.add_argument("--duration", type=float, default=12.0, help="seconds of publishing per measurement")
    ap.add_argument("--warmup", type=float, default=2.0, help="seconds left out at the start of each")
    ap.add_argument("--repeats", type=int, default=3, help="rounds over the modes")
    ap.add_argument("--param", action="append", help="NAME:=VALUE given to the event mode's fusion_node too")
    ap.add_argument("--modes", default="bare,event,old", help="modes measured, in this order each round")
    ap.add_argument("--old", help="a checkout whose fusion_node is measured too (mode 'old')")
    ap.add_argument("--domain", type=int, default=45, help="DDS domain of the first measurement (then +1 each, "
                    "wrapping within 10)")
    ap.add_argument("--workdir", default="/tmp/bench_fusion_latency")
    args = ap.parse_args(argv)
    if args.role == "pub":
        return role_pub(args)
    if args.role == "sub":
        return role_sub(args)
    from benchmarks.harness import command

    cmd = command(argv if argv is None else [sys.argv[0], *argv])
    started = datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%d %H:%M UTC")
    load_start = load_average()
    work = Path(args.workdir)
    modes = [m for m in args.modes.split(",") if m != "old" or args.old]
    results = []
    n = 0
    for rnd in range(1, args.repeats + 1):
        for mode in modes:
            m = measure(mode, args, work, args.domain + n % 10)
            n += 1
            r = latencies(m, args.warmup)
            r.update(mode=mode, round=rnd)
            results.append(r)
            print(f"round {rnd} {mode}: {r['received_samples']}/{r['published_samples']} samples, p50 "
                  f"{_q(r['lat_ms'], 50):.2f} p99 {_q(r['lat_ms'], 99):.2f} ms, CPU/msg "
                  f"{r.get('cpu_us_per_msg', float('nan')):.1f} us, load {os.getloadavg()[0]:.2f}", flush=True)
    text = report(results, args, started, load_start, load_average(), cmd)
    out = write_results(Path(args.out) if args.out else RESULTS / "fusion_latency.md", text)
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
