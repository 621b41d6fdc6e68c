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

    python benchmarks/bench_nodes.py [--rates 100,200,400,800,1000,1600,2000] [--duration 10]
                                     [--bisect 2] [--out benchmarks/results/nodes.md]

Helper roles (started by the benchmark itself): ``--role bare-sub`` and ``--role diag``.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import machine_header  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
ARRAY = REPO / "config" / "array32.yaml"
BIN = Path(sys.executable).parent
N_IMUS = 32
CLK_TCK = os.sysconf("SC_CLK_TCK")
LOG_TIME = re.compile(r"\[(\d+\.\d+)\]")


# ====================================================================== helper roles (own processes)


def _topics(n_topics: int) -> list[str]:
    from imu_array_ros.io.rosbag.recording import imu_topic
    from imu_array_ros.model.description import load_description

    names = load_description(ARRAY).names
    return [imu_topic(n) for n in names] if n_topics == N_IMUS else ["/bench/one_topic/data_raw"]


def role_bare_sub(args) -> int:
    """Plain rclpy subscriber: deserializing callbacks (``--raw``: serialized) that count."""
    import rclpy
    from rclpy.experimental import EventsExecutor
    from sensor_msgs.msg import Imu

    from imu_array_ros.nodes.runtime import qos

    topics = _topics(args.topics)
    rclpy.init()
    node = rclpy.create_node("bare_subscriber")
    counts = [0] * len(topics)
    total = [0]
    last = [None]
    q = qos(True, keep_all=True)  # the fusion node's input QoS with reliable:=true

    def make(k):
        def cb(msg):
            counts[k] += 1
            total[0] += 1
            last[0] = msg

        return cb

    for k, topic in enumerate(topics):
        node.create_subscription(Imu, topic, make(k), q, raw=args.raw)
    executor = EventsExecutor()
    executor.add_node(node)
    print("ready", flush=True)
    t_first = t_last = None
    seen = 0
    end = time.monotonic() + args.timeout
    try:
        while time.monotonic() < end and total[0] < args.count:
            executor.spin_once(timeout_sec=0.05)
            if total[0] != seen:
                seen = total[0]
                t_last = time.time_ns()
                if t_first is None:
                    t_first = t_last
    except KeyboardInterrupt:
        pass
    stamp = None
    if last[0] is not None and not args.raw:
        s = last[0].header.stamp
        stamp = s.sec * 1_000_000_000 + s.nanosec
    Path(args.out).write_text(json.dumps({"total": total[0], "per_topic": counts, "t_first_ns": t_first,
                                          "t_last_ns": t_last, "last_stamp_ns": stamp}))
    node.destroy_node()
    rclpy.try_shutdown()
    return 0


def role_pub(args) -> int:
    """Synthetic source: the driver's Imu payloads of ``--bag``, encoded beforehand, published as fast as
    possible (reliable, keep all) on the 32 topics or all on one topic; waits for the acknowledgements."""
    import rclpy
    from rclpy.duration import Duration
    from rclpy.experimental import EventsExecutor
    from sensor_msgs.msg import Imu

    from imu_array_ros.io.messages import raw_imu_payloads
    from imu_array_ros.io.rosbag.recording import read_imu_recording
    from imu_array_ros.model.description import load_description
    from imu_array_ros.nodes.runtime import qos

    desc = load_description(ARRAY)
    samples, _ = read_imu_recording(args.bag, desc)
    per_imu = raw_imu_payloads(samples, desc)
    msgs = [(k, per_imu[k][1][i].tobytes()) for i in range(len(samples)) for k in range(len(per_imu))]
    topics = _topics(args.topics)
    rclpy.init()
    node = rclpy.create_node("bench_publisher")
    q = qos(True, keep_all=True)
    pubs = [node.create_publisher(Imu, t, q) for t in topics]
    executor = EventsExecutor()
    executor.add_node(node)
    while any(p.get_subscription_count() < 1 for p in pubs):
        executor.spin_once(timeout_sec=0.01)
    time.sleep(0.5)  # let the reliable endpoints settle
    t0 = time.time_ns()
    if len(pubs) == 1:
        pub = pubs[0].publish
        for _, data in msgs:
            pub(data)
    else:
        fns = [p.publish for p in pubs]
        for k, data in msgs:
            fns[k](data)
    t1 = time.time_ns()
    acked = all(p.wait_for_all_acked(Duration(seconds=30.0)) for p in pubs)
    t2 = time.time_ns()
    Path(args.out).write_text(json.dumps({"published": len(msgs), "t_start_ns": t0, "t_published_ns": t1,
                                          "t_acked_ns": t2, "acked": acked}))
    node.destroy_node()
    rclpy.try_shutdown()
    return 0


def role_diag(args) -> int:
    """Records every /diagnostics status (with its arrival time) until Ctrl-C."""
    import rclpy
    from diagnostic_msgs.msg import DiagnosticArray
    from rclpy.experimental import EventsExecutor

    rclpy.init()
    node = rclpy.create_node("bench_diag_monitor")
    records = []

    def on_diag(msg):
        now = time.time_ns()
        for s in msg.status:
            records.append({"t_ns": now, "name": s.name, "message": s.message,
                            **{kv.key: kv.value for kv in s.values}})

    node.create_subscription(DiagnosticArray, "/diagnostics", on_diag, 100)
    executor = EventsExecutor()
    executor.add_node(node)
    print("ready", flush=True)
    try:
        while rclpy.ok():
            executor.spin_once(timeout_sec=0.1)
    except KeyboardInterrupt:
        pass
    Path(args.out).write_text(json.dumps(records))
    node.destroy_node()
    rclpy.try_shutdown()
    return 0


# ====================================================================== process handling


_domain_counter = [0]


def next_domain() -> int:
    """A DDS domain of this run's own (30..99: the DDS tests use 100..229)."""
    _domain_counter[0] += 1
    return 30 + (os.getpid() * 7 + _domain_counter[0]) % 70


class Procs:
    """Processes of one run: their own domain, output to files, stopped with SIGINT then killed."""

    def __init__(self, work: Path, tag: str) -> None:
        self.domain = next_domain()
        self.env = dict(os.environ, ROS_DOMAIN_ID=str(self.domain), ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST",
                        PYTHONUNBUFFERED="1", OMP_NUM_THREADS="1", OPENBLAS_NUM_THREADS="1")
        self.dir = work / tag
        self.dir.mkdir(parents=True, exist_ok=True)
        self.procs: dict[str, subprocess.Popen] = {}

    def start(self, name: str, *cmd) -> subprocess.Popen:
        out = open(self.dir / f"{name}.out", "w")
        err = open(self.dir / f"{name}.err", "w")
        p = subprocess.Popen([str(c) for c in cmd], env=self.env, stdout=out, stderr=err, stdin=subprocess.DEVNULL)
        out.close()
        err.close()
        self.procs[name] = p
        return p

    def text(self, name: str, stream: str = "err") -> str:
        try:
            return (self.dir / f"{name}.{stream}").read_text()
        except OSError:
            return ""

    def wait_line(self, name: str, text: str, timeout: float = 30.0) -> None:
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            if text in self.text(name, "out"):
                return
            if self.procs[name].poll() is not None:
                break
            time.sleep(0.05)
        raise RuntimeError(f"{name}: no {text!r} within {timeout} s: {self.text(name)[-2000:]}")

    def wait(self, name: str, timeout: float, unless: str | None = None) -> int | None:
        """Exit status of ``name`` within ``timeout`` (None: still running); gives up early when
        process ``unless`` has ended with an error."""
        end = time.monotonic() + timeout
        p = self.procs[name]
        while time.monotonic() < end:
            if p.poll() is not None:
                return p.returncode
            if unless is not None and self.procs[unless].poll() not in (None, 0):
                return None
            time.sleep(0.05)
        return p.poll()

    def stop(self, name: str, timeout: float = 10.0) -> int:
        p = self.procs[name]
        if p.poll() is None:
            p.send_signal(signal.SIGINT)
            try:
                p.wait(timeout)
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait()
        return p.returncode

    def stop_all(self) -> None:
        for name in list(self.procs):
            self.stop(name)


def proc_cpu_s(pid: int) -> float | None:
    """utime + stime of a process in seconds (None once it is gone)."""
    try:
        with open(f"/proc/{pid}/stat") as fh:
            fields = fh.read().rsplit(")", 1)[1].split()
        return (int(fields[11]) + int(fields[12])) / CLK_TCK
    except (OSError, IndexError):
        return None


def machine_cpu() -> tuple[float, float]:
    """(busy, total) CPU seconds of the whole machine since boot (/proc/stat)."""
    with open("/proc/stat") as fh:
        v = [int(x) for x in fh.readline().split()[1:]]
    total = sum(v[:8])
    idle = v[3] + v[4]
    return (total - idle) / CLK_TCK, total / CLK_TCK


class CpuSampler:
    """Samples the CPU time of some processes and of the machine every ``period`` s (wall clock ns)."""

    def __init__(self, pids: dict[str, int], period: float = 0.05) -> None:
        self.pids = dict(pids)
        self.samples: dict[str, list[tuple[int, float]]] = {k: [] for k in list(pids) + ["_machine"]}
        self._stop = threading.Event()
        self._period = period
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def add(self, name: str, pid: int) -> None:
        self.samples.setdefault(name, [])
        self.pids[name] = pid

    def _run(self) -> None:
        while not self._stop.is_set():
            now = time.time_ns()
            for name, pid in list(self.pids.items()):
                c = proc_cpu_s(pid)
                if c is not None:
                    self.samples[name].append((now, c))
            self.samples["_machine"].append((now, machine_cpu()[0]))
            self._stop.wait(self._period)

    def stop(self) -> None:
        self._stop.set()
        self._thread.join()

    def used(self, name: str, t0_ns: int, t1_ns: int) -> float:
        """CPU seconds used between two wall times (linear interpolation between samples)."""
        import numpy as np

        s = self.samples.get(name) or []
        if len(s) < 2 or t1_ns <= t0_ns:
            return float("nan")
        t = np.array([a for a, _ in s], dtype=float)
        c = np.array([b for _, b in s])
        return float(np.interp(t1_ns, t, c) - np.interp(t0_ns, t, c))

    def share(self, name: str, t0_ns: int, t1_ns: int) -> float:
        """CPU use over the window, as a fraction of one core."""
        return self.used(name, t0_ns, t1_ns) / max((t1_ns - t0_ns) / 1e9, 1e-9)


def log_time(text: str, marker: str) -> float | None:
    """ROS log timestamp (s) of the first line holding ``marker``."""
    for line in text.splitlines():
        if marker in line:
            m = LOG_TIME.search(line)
            if m:
                return float(m.group(1))
    return None


# ====================================================================== recordings


def recording(work: Path, rate: int, duration: float) -> Path:
    out = work / f"rec_{rate}hz"
    if not out.exists():
        exe = BIN / "imu-array"
        t0 = time.perf_counter()
        subprocess.run([exe, "simulate", "--array", ARRAY, "--out", out, "--duration", str(duration),
                        "--rate", str(rate), "--seed", "1", "--start-time", "0", "-q"], check=True,
                       env=dict(os.environ, OMP_NUM_THREADS="1", OPENBLAS_NUM_THREADS="1"))
        print(f"  simulated {rate} Hz x {duration:g} s in {time.perf_counter() - t0:.1f} s", flush=True)
    return out


def driver_cmd(bag: Path, rate: float, *, reliable: bool = True, wait: int = 1, poll: float = 0.0005) -> list:
    return [BIN / "driver_node", "--ros-args", "-p", f"array_config:={ARRAY}", "-p", "mode:=replay",
            "-p", f"bag:={bag}", "-p", f"rate:={float(rate)!r}", "-p", "restamp:=true", "-p", f"reliable:={str(reliable).lower()}",
            "-p", f"wait_for_subscribers:={wait}", "-p", "exit_at_end:=true", "-p", f"poll_period:={float(poll)!r}"]


# ====================================================================== measurements


@dataclass
class Point:
    kind: str  # "driver", "bare", "fusion"
    rate_hz: float  # array sample rate (0: flat out)
    samples: int  # array samples published
    received: int = 0  # messages (bare) or fused samples (fusion)
    expected: int = 0
    msgs_per_s: float = float("nan")  # raw Imu messages/s over the streaming window
    cpu: dict = field(default_factory=dict)  # process -> fraction of one core
    others: float = float("nan")  # CPU of everything else on the machine, cores
    lag_s: float = float("nan")  # last arrival - its stamp
    lat_diag: tuple = ()  # (median p50, median p99, worst p99) over 1 s windows, s
    lat_probe: tuple = ()  # (p50, p99, max) s
    counts: dict = field(default_factory=dict)
    period: float | None = None  # fusion period if not the default
    sustained: bool = False
    note: str = ""

    @property
    def lost(self) -> int:
        return self.expected - self.received


def window_others(cpu: CpuSampler, names, t0: int, t1: int) -> float:
    ours = sum(cpu.used(n, t0, t1) for n in names)
    return (cpu.used("_machine", t0, t1) - ours) / max((t1 - t0) / 1e9, 1e-9)


def measure_driver_alone(work: Path, bag: Path, samples: int) -> Point:
    run = Procs(work, "driver_alone")
    pt = Point("driver", 0, samples, expected=samples * N_IMUS)
    try:
        d = run.start("driver", *driver_cmd(bag, 0.0, reliable=True, wait=0))
        cpu = CpuSampler({"driver": d.pid})
        code = run.wait("driver", 120)
        cpu.stop()
        err = run.text("driver")
        t0, t1 = log_time(err, "replaying"), log_time(err, "replay finished")
        if code != 0 or t0 is None or t1 is None:
            pt.note = f"driver failed (exit {code}): {err[-500:]}"
            return pt
        pt.received = pt.expected
        pt.msgs_per_s = samples * N_IMUS / (t1 - t0)
        a, b = int(t0 * 1e9), int(t1 * 1e9)
        pt.cpu = {"driver": cpu.share("driver", a, b)}
        pt.others = window_others(cpu, ["driver"], a, b)
        pt.sustained = True
        return pt
    finally:
        run.stop_all()


def measure_bare(work: Path, bag: Path, samples: int, rate_hz: float, replay_rate: float, max_lag: float,
                 duration: float) -> Point:
    tag = f"bare_{'flat' if replay_rate == 0 else int(rate_hz)}"
    run = Procs(work, tag)
    pt = Point("bare", 0 if replay_rate == 0 else rate_hz, samples, expected=samples * N_IMUS)
    out = run.dir / "bare.json"
    try:
        s = run.start("bare", sys.executable, Path(__file__).resolve(), "--role", "bare-sub", "--out", out,
                      "--count", pt.expected, "--timeout", duration + 20)
        run.wait_line("bare", "ready")
        d = run.start("driver", *driver_cmd(bag, replay_rate))
        cpu = CpuSampler({"bare": s.pid, "driver": d.pid})
        run.wait("bare", duration + 30, unless="driver")
        run.stop("bare")
        run.wait("driver", 15)
        cpu.stop()
        if not out.exists():
            pt.note = f"bare subscriber wrote nothing: {run.text('bare')[-500:]}"
            return pt
        r = json.loads(out.read_text())
        pt.received = r["total"]
        if r["t_first_ns"] and r["t_last_ns"] and r["t_last_ns"] > r["t_first_ns"]:
            a, b = r["t_first_ns"], r["t_last_ns"]
            pt.msgs_per_s = (r["total"] - 1) / ((b - a) / 1e9)
            pt.cpu = {"driver": cpu.share("driver", a, b), "bare": cpu.share("bare", a, b)}
            pt.others = window_others(cpu, ["driver", "bare"], a, b)
            if r["last_stamp_ns"]:
                pt.lag_s = (b - r["last_stamp_ns"]) / 1e9
        pt.counts = {"min_per_topic": min(r["per_topic"]), "max_per_topic": max(r["per_topic"])}
        keeps_up = replay_rate == 0 or pt.lag_s <= max_lag
        pt.sustained = pt.lost == 0 and keeps_up
        if not keeps_up:
            pt.note = f"fell behind: last message {pt.lag_s:.2f} s after its stamp"
        return pt
    finally:
        run.stop_all()


def measure_synthetic(work: Path, bag: Path, samples: int, topics: int, raw: bool, duration: float) -> Point:
    """Bare subscriber fed flat out by a publisher of payloads encoded beforehand (no driver)."""
    tag = f"synthetic_{topics}topics{'_raw' if raw else ''}"
    run = Procs(work, tag)
    pt = Point("synthetic", 0, samples, expected=samples * N_IMUS)
    out, pub_out = run.dir / "bare.json", run.dir / "pub.json"
    me = Path(__file__).resolve()
    try:
        s = run.start("bare", sys.executable, me, "--role", "bare-sub", "--out", out, "--count", pt.expected,
                      "--timeout", duration * 3 + 30, "--topics", topics, *(["--raw"] if raw else []))
        run.wait_line("bare", "ready")
        p = run.start("pub", sys.executable, me, "--role", "pub", "--out", pub_out, "--bag", bag, "--topics", topics)
        cpu = CpuSampler({"bare": s.pid, "pub": p.pid})
        run.wait("bare", duration * 3 + 40, unless="pub")
        run.stop("bare")
        run.wait("pub", 35)
        cpu.stop()
        if not out.exists():
            pt.note = f"subscriber wrote nothing: {run.text('bare')[-500:]}"
            return pt
        r = json.loads(out.read_text())
        pt.received = r["total"]
        if r["t_first_ns"] and r["t_last_ns"] and r["t_last_ns"] > r["t_first_ns"]:
            a, b = r["t_first_ns"], r["t_last_ns"]
            pt.msgs_per_s = (r["total"] - 1) / ((b - a) / 1e9)
            pt.cpu = {"pub": cpu.share("pub", a, b), "bare": cpu.share("bare", a, b)}
            pt.others = window_others(cpu, ["pub", "bare"], a, b)
        if pub_out.exists():
            w = json.loads(pub_out.read_text())
            pt.counts = {"pub_msgs_per_s": w["published"] / max((w["t_published_ns"] - w["t_start_ns"]) / 1e9, 1e-9)}
        pt.note = f"{topics} topic{'s' if topics > 1 else ''}, " + ("raw (serialized) callbacks" if raw else
                                                                     "deserializing callbacks")
        pt.sustained = pt.lost == 0
        return pt
    finally:
        run.stop_all()


def _diag_latency(records: list, t0: int, t1: int) -> tuple:
    import numpy as np

    p50, p99 = [], []
    for r in records:
        if r["name"].startswith("imu_array_fusion") and t0 + 1e9 <= r["t_ns"] <= t1 + 0.5e9:
            a, b = float(r.get("latency_p50_s", "nan")), float(r.get("latency_p99_s", "nan"))
            if np.isfinite(a) and np.isfinite(b):
                p50.append(a)
                p99.append(b)
    if not p50:
        return ()
    return float(np.median(p50)), float(np.median(p99)), float(np.max(p99))


def measure_fusion(work: Path, bag: Path, samples: int, rate_hz: float, max_lag: float, duration: float,
                   period: float | None = None) -> Point:
    import numpy as np

    tag = f"fusion_{int(rate_hz)}" + (f"_period{period:g}" if period else "")
    run = Procs(work, tag)
    pt = Point("fusion", rate_hz, samples, expected=samples, period=period)
    npz = run.dir / "probe.npz"
    diag_out = run.dir / "diag.json"
    timeout = duration + 20
    try:
        run.start("diag", sys.executable, Path(__file__).resolve(), "--role", "diag", "--out", diag_out)
        extra = ["-p", f"period:={float(period)!r}"] if period else []
        f = run.start("fusion", BIN / "fusion_node", "--ros-args", "-p", f"array_config:={ARRAY}",
                      "-p", "reliable:=true", *extra)
        pr = run.start("probe", sys.executable, "-m", "imu_array_ros.nodes.probe", "--out", npz, "--count", samples,
                       "--timeout", timeout, "--reliable")
        run.wait_line("diag", "ready")
        run.wait_line("probe", "ready")
        d = run.start("driver", *driver_cmd(bag, 1.0))
        cpu = CpuSampler({"driver": d.pid, "fusion": f.pid, "probe": pr.pid})
        run.wait("probe", timeout + 10, unless="driver")
        run.wait("driver", 15)
        time.sleep(1.3)  # one more fusion diagnostics after the last sample: final counts
        cpu.stop()
        run.stop("fusion")
        run.stop("diag")
        run.stop_all()
        if not npz.exists():
            pt.note = f"probe wrote nothing: {run.text('probe')[-500:]}"
            return pt
        got = np.load(npz)
        stamps, arrival = got["stamps"], got["arrival_ns"]
        pt.received = len(np.unique(stamps))
        records = json.loads(diag_out.read_text()) if diag_out.exists() else []
        fus = [r for r in records if r["name"].startswith("imu_array_fusion")]
        if fus:
            last = fus[-1]
            pt.counts = {k: int(float(last[k])) for k in ("messages", "incomplete_samples", "late",
                                                          "overflow_samples", "missing_messages", "fused")
                         if k in last}
        if len(arrival) > 1:
            a, b = int(arrival[0]), int(arrival[-1])
            lat = (arrival - stamps) / 1e9
            pt.lat_probe = (float(np.percentile(lat, 50)), float(np.percentile(lat, 99)), float(lat.max()))
            pt.lag_s = float(lat[-1])
            pt.msgs_per_s = (len(arrival) - 1) * N_IMUS / ((b - a) / 1e9)
            pt.cpu = {n: cpu.share(n, a, b) for n in ("driver", "fusion", "probe")}
            pt.others = window_others(cpu, ["driver", "fusion", "probe"], a, b)
            pt.lat_diag = _diag_latency(records, a, b)
        if len(stamps):
            # samples fused with IMUs missing have a larger CRB than complete ones: where do they fall?
            tr = np.nansum(np.diagonal(got["covariance"], axis1=1, axis2=2)[:, 6:9], axis=1)
            inc = np.flatnonzero(~np.isclose(tr, np.nanmin(tr), rtol=1e-6))
            if len(inc):
                cut = np.flatnonzero(np.diff(inc) > 1)
                starts, ends = np.r_[inc[0], inc[cut + 1]], np.r_[inc[cut], inc[-1]]
                longest = int(np.argmax(ends - starts))
                pt.counts["incomplete_runs"] = len(starts)
                pt.counts["longest_run_samples"] = int(ends[longest] - starts[longest] + 1)
                pt.counts["longest_run_s"] = float((stamps[ends[longest]] - stamps[starts[longest]]) / 1e9)
                pt.counts["longest_run_from_s"] = float((stamps[starts[longest]] - stamps[0]) / 1e9)
        bad = sum(pt.counts.get(k, 0) for k in ("incomplete_samples", "late", "overflow_samples"))
        keeps_up = pt.lag_s <= max_lag
        pt.sustained = pt.lost == 0 and bad == 0 and keeps_up
        notes = []
        if bad:
            notes.append(", ".join(f"{k} {pt.counts[k]}" for k in ("incomplete_samples", "late", "overflow_samples")
                                   if pt.counts.get(k)))
        if not keeps_up:
            notes.append(f"fell behind: last sample {pt.lag_s:.2f} s after its stamp")
        pt.note = "; ".join(notes)
        return pt
    finally:
        run.stop_all()


def in_process_costs(bag: Path) -> list[tuple[str, float, float]]:
    """Per-call CPU costs of the node's work, in this process without DDS: (what, us per call, us per message).

    Best of a few repeats of ``time.process_time`` loops."""
    import numpy as np
    from rclpy.serialization import deserialize_message
    from sensor_msgs.msg import Imu

    from imu_array_ros.estimation.live import LiveFusion
    from imu_array_ros.io.messages import decode_raw_imu, raw_imu_payloads
    from imu_array_ros.io.rosbag.recording import read_imu_recording
    from imu_array_ros.model.description import load_description

    desc = load_description(ARRAY)
    samples, _ = read_imu_recording(bag, desc)

    def timed(fn, reps: int) -> float:
        best_t = float("inf")
        for _ in range(3):
            t0 = time.process_time()
            for _ in range(reps):
                fn()
            best_t = min(best_t, (time.process_time() - t0) / reps)
        return best_t

    out = []
    for n in (1, 10, 100):
        sub = samples.select(slice(0, n))
        t = timed(lambda: raw_imu_payloads(sub, desc), max(20, 400 // n))
        out.append((f"driver: `raw_imu_payloads` (encode) of {n} array sample{'s' if n > 1 else ''} "
                    f"({32 * n} messages)", 1e6 * t, 1e6 * t / (32 * n)))
    per_imu = raw_imu_payloads(samples.select(slice(0, 100)), desc)
    msgs = [(k, per_imu[k][1][i].tobytes()) for i in range(100) for k in range(N_IMUS)]
    one = msgs[0][1]
    t = timed(lambda: deserialize_message(one, Imu), 5000)
    out.append(("bare subscriber: rclpy `deserialize_message(Imu)` of one message", 1e6 * t, 1e6 * t))
    for n in (1, 10, 100):
        payloads = [m for _, m in msgs[:32 * n]]
        index = np.array([k for k, _ in msgs[:32 * n]])
        t = timed(lambda: decode_raw_imu(payloads, index, desc.names), max(20, 400 // n))
        out.append((f"fusion: `decode_raw_imu` of {32 * n} messages", 1e6 * t, 1e6 * t / (32 * n)))
    for n in (1, 10, 100):
        payloads = [m for _, m in msgs[:32 * n]]
        index = np.array([k for k, _ in msgs[:32 * n]])
        live = LiveFusion(desc)
        clock = [10**12]

        def step():  # one fusion-node step: add n array samples, fuse and encode them (fresh stamps each time)
            live.assembler = type(live.assembler)(N_IMUS, timeout_ns=live.assembler.timeout_ns)
            live.add(payloads, index, clock[0])
            live.step(clock[0])
            clock[0] += 10**6

        t = timed(step, max(20, 200 // n))
        out.append((f"fusion: `LiveFusion.add` + `step` of {n} array sample{'s' if n > 1 else ''}",
                    1e6 * t, 1e6 * t / (32 * n)))
    return out


# ====================================================================== report


def _pct(x: float) -> str:
    return "-" if x != x else f"{100 * x:.0f} %"


def _ms(t, i: int) -> str:
    return f"{1e3 * t[i]:.1f}" if t else "-"


def _us_per_msg(p: Point, proc: str) -> str:
    c = p.cpu.get(proc, float("nan"))
    return "-" if c != c or not p.msgs_per_s > 0 else f"{1e6 * c / p.msgs_per_s:.0f}"


def loadavg() -> str:
    return " ".join(Path("/proc/loadavg").read_text().split()[:3])


def describe(pt: Point) -> str:
    return (f"{pt.kind} {'flat out' if pt.rate_hz == 0 else f'{pt.rate_hz:g} Hz'}"
            f"{f' (period {pt.period:g})' if pt.period else ''}: {pt.received}/{pt.expected} received, "
            f"{pt.msgs_per_s:,.0f} msgs/s, cpu " + ", ".join(f"{k} {_pct(v)}" for k, v in pt.cpu.items())
            + (f", probe lat p50/p99 {_ms(pt.lat_probe, 0)}/{_ms(pt.lat_probe, 1)} ms" if pt.lat_probe else "")
            + (f", diag lat p50/p99 {_ms(pt.lat_diag, 0)}/{_ms(pt.lat_diag, 1)} ms" if pt.lat_diag else "")
            + f", others {pt.others:.2f} cores -> {'sustained' if pt.sustained else 'NOT sustained'}"
            + (f" ({pt.note})" if pt.note else ""))


def best(points: list[Point]) -> Point | None:
    ok = [p for p in points if p.sustained and p.rate_hz > 0 and p.period is None]
    return max(ok, key=lambda p: p.rate_hz) if ok else None


def first_failed(points: list[Point]) -> Point | None:
    bad = [p for p in points if not p.sustained and p.rate_hz > 0 and p.period is None]
    return min(bad, key=lambda p: p.rate_hz) if bad else None


def write_report(path: Path, res: dict) -> None:
    a = res["args"]
    drv, bare_flat = res["driver"], res["bare_flat"]
    synth, bare, fusion, extra, costs = res["synthetic"], res["bare"], res["fusion"], res["extra"], res["costs"]
    cores = os.cpu_count()
    text = machine_header("Live nodes over DDS: driver_node -> fusion_node vs a bare rclpy subscriber, 32 IMUs")
    text = text.replace(text[text.index("- command:"):text.index("\n", text.index("- command:"))],
                        f"- command: `{res['command']}`")
    text += (
        f"- load average (1, 5, 15 min) at start: {res['load_start']}; at end: {res['load_end']}; "
        f"whole run {res['minutes']:.1f} min\n"
        "- rclpy (ROS 2 Jazzy, PyPI) with Fast DDS; every node its own process, localhost discovery, "
        "a DDS domain of its own for every measurement\n\n"
        f"Recordings: `imu-array simulate --array config/array32.yaml --duration {a['duration']:g} --rate R --seed 1 "
        "--start-time 0`, one per sample rate R.  Driver: `driver_node mode:=replay rate:=1 restamp:=true "
        "reliable:=true wait_for_subscribers:=1 exit_at_end:=true poll_period:=0.0005` (publishers reliable, keep "
        "last 1000).  Fusion node: `reliable:=true`, the other parameters default (period 0.005 s, sync_timeout "
        "0.05 s, max_batch 1000).  Probe: `python -m imu_array_ros.nodes.probe --reliable --count N`.  Bare "
        "subscriber: a plain rclpy node (own process) subscribing the same 32 `/imu_array/<name>/data_raw` "
        "topics as `sensor_msgs/Imu` with deserializing callbacks that only count, QoS reliable + keep all (the "
        "fusion node's input QoS), spun with `EventsExecutor.spin_once` like the nodes.\n\n"
        "CPU: utime + stime (/proc/<pid>/stat) over the streaming window (first to last message received), in % "
        "of one core; *others* = the rest of the machine's busy CPU in that window (other jobs), in cores "
        f"(the machine has {cores}).  Latency: the stamp is the time the sample fell due at the driver (restamp), "
        "so every latency includes the driver's poll and encode delay; *diag* = the fusion node's /diagnostics "
        "`latency_p50_s` / `latency_p99_s` (fused publish - stamp, 1 s windows; median over the run's windows, "
        "and the worst window's p99); *probe* = probe arrival - stamp over every fused sample of the run (one hop "
        "more).  *Sustained* = nothing lost, every sample fused complete (no incomplete / late / overflow "
        f"samples) and the last sample arrived within {a['max_lag']:g} s of its stamp.\n\n")

    text += ("## Ceilings (same run, flat out: reliable keep-all, nothing can be lost)\n\n"
             "| source -> subscriber | messages/s | array samples/s (/32) | CPU (% of a core) | CPU per message (us) "
             "| others (cores) | lost |\n|---|---|---|---|---|---|---|\n")
    rows = [("`driver_node rate:=0`, no subscriber: the driver's publish ceiling", drv, "driver"),
            ("`driver_node rate:=0` -> bare subscriber (32 topics)", bare_flat, "bare")]
    for p in synth:
        rows.append((f"payloads encoded beforehand, published flat out -> bare subscriber ({p.note})", p, "bare"))
    for name, p, main_proc in rows:
        text += (f"| {name} | {p.msgs_per_s:,.0f} | {p.msgs_per_s / N_IMUS:,.0f} | "
                 + ", ".join(f"{k} {_pct(v)}" for k, v in p.cpu.items())
                 + " | " + ", ".join(f"{k} {_us_per_msg(p, k)}" for k in p.cpu)
                 + f" | {p.others:.2f} | {p.lost} |\n")
    text += "\n(Publisher-side rates of the pre-encoded sources, messages handed to `publish` per second: " + ", ".join(
        f"{p.note.split(',')[0]}{' raw' if 'raw' in p.note else ''}: {p.counts.get('pub_msgs_per_s', float('nan')):,.0f}"
        for p in synth) + ".)\n"

    text += "\n## Bare subscriber, driver at real time (`rate:=1`)\n\n"
    text += ("| sample rate (Hz) | messages published | received | lost | msgs/s | CPU driver | CPU bare sub | "
             "CPU/msg driver, bare (us) | others (cores) | last message lag (ms) | sustained |\n"
             "|---|---|---|---|---|---|---|---|---|---|---|\n")
    for p in sorted(bare, key=lambda p: p.rate_hz):
        text += (f"| {p.rate_hz:g} | {p.expected:,} | {p.received:,} | {p.lost:,} | {p.msgs_per_s:,.0f} | "
                 f"{_pct(p.cpu.get('driver', float('nan')))} | {_pct(p.cpu.get('bare', float('nan')))} | "
                 f"{_us_per_msg(p, 'driver')}, {_us_per_msg(p, 'bare')} | {p.others:.2f} | {1e3 * p.lag_s:.0f} | "
                 f"{'yes' if p.sustained else 'no'}{' (' + p.note + ')' if p.note else ''} |\n")

    text += "\n## driver_node -> fusion_node -> probe, driver at real time (`rate:=1`)\n\n"
    text += ("| sample rate (Hz) | fusion period (s) | samples published | fused received | lost | incomplete / late "
             "| msgs/s in | CPU driver | CPU fusion | CPU probe | CPU/msg driver, fusion (us) | others (cores) | "
             "diag p50 / p99 / worst p99 (ms) | probe p50 / p99 / max (ms) | sustained |\n"
             "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|\n")
    for p in sorted(fusion, key=lambda p: p.rate_hz) + extra:
        c = p.counts
        text += (f"| {p.rate_hz:g} | {p.period or 0.005:g} | {p.expected:,} | {p.received:,} | {p.lost:,} | "
                 f"{c.get('incomplete_samples', '-')} / {c.get('late', '-')} | {p.msgs_per_s:,.0f} | "
                 f"{_pct(p.cpu.get('driver', float('nan')))} | {_pct(p.cpu.get('fusion', float('nan')))} | "
                 f"{_pct(p.cpu.get('probe', float('nan')))} | {_us_per_msg(p, 'driver')}, {_us_per_msg(p, 'fusion')} | "
                 f"{p.others:.2f} | {_ms(p.lat_diag, 0)} / {_ms(p.lat_diag, 1)} / {_ms(p.lat_diag, 2)} | "
                 f"{_ms(p.lat_probe, 0)} / {_ms(p.lat_probe, 1)} / {_ms(p.lat_probe, 2)} | "
                 f"{'yes' if p.sustained else 'no'}{' (' + p.note + ')' if p.note else ''} |\n")

    text += ("\n## Per-call costs of the nodes' work (this process, no DDS; best of 3, CPU time)\n\n"
             "| what | us per call | us per Imu message |\n|---|---|---|\n")
    for what, per_call, per_msg in costs:
        text += f"| {what} | {per_call:,.0f} | {per_msg:.1f} |\n"

    fb, bb = best(fusion), best(bare)
    f_msgs = fb.rate_hz * N_IMUS if fb else 0.0
    b_ladder = bb.rate_hz * N_IMUS if bb else 0.0
    b_flat = bare_flat.msgs_per_s if bare_flat.lost == 0 and bare_flat.received else 0.0
    ceiling = max(b_flat, b_ladder)
    ratio = f_msgs / ceiling if ceiling > 0 else float("nan")
    p200 = next((p for p in fusion if p.rate_hz == 200 and p.period is None), None)
    text += "\n## Result against the targets\n\n"
    text += ("- highest rate driver -> fusion sustained: " + (f"**{fb.rate_hz:g} Hz x 32 IMUs = {f_msgs:,.0f} "
             f"Imu messages/s**" if fb else "**none of the rates tested**")
             + (f" (first rate not sustained: {first_failed(fusion).rate_hz:g} Hz)" if first_failed(fusion) else "")
             + "\n")
    text += (f"- bare subscriber ceiling (same run): **{ceiling:,.0f} messages/s** = the larger of flat out fed by "
             f"the driver ({b_flat:,.0f}) and the highest real-time rate it sustained ("
             + (f"{bb.rate_hz:g} Hz = {b_ladder:,.0f}" if bb else "none") + ")\n")
    text += (f"- fusion / bare ceiling: **{100 * ratio:.0f} %** (target >= 80 %): "
             f"**{'met' if ratio >= 0.8 else 'NOT met'}**\n")
    text += (f"- at least 32 IMUs x 200 Hz without loss: **{'met' if fb and fb.rate_hz >= 200 else 'NOT met'}**\n")
    if p200:
        lat = p200.lat_diag[1] if p200.lat_diag else float("nan")
        worst = p200.lat_probe[1] if p200.lat_probe else float("nan")
        text += (f"- p99 latency < 5 ms at 200 Hz, default parameters: diag p99 {1e3 * lat:.1f} ms (worst window "
                 f"{_ms(p200.lat_diag, 2)} ms), probe p99 {1e3 * worst:.1f} ms: "
                 f"**{'met' if lat < 5e-3 and worst < 5e-3 else 'NOT met'}**\n")
    for p in extra:
        lat = p.lat_diag[1] if p.lat_diag else float("nan")
        worst = p.lat_probe[1] if p.lat_probe else float("nan")
        text += (f"- the same with the fusion node at `period:={p.period:g}`: diag p99 {1e3 * lat:.1f} ms, probe p99 "
                 f"{1e3 * worst:.1f} ms: **{'met' if lat < 5e-3 and worst < 5e-3 else 'NOT met'}**\n")
    text += "\n## What limits the rate\n\n" + analysis(res, fb, bb, ceiling) + "\n"
    path.write_text(text)


def analysis(res: dict, fb: Point | None, bb: Point | None, ceiling: float) -> str:
    """The paragraphs on what limits rate and latency, from this run's numbers."""
    drv, bare_flat, synth, costs = res["driver"], res["bare_flat"], res["synthetic"], res["costs"]
    ncores = os.cpu_count() or 1

    def cost(prefix: str, n: str, per_msg: bool = False) -> float:
        return next((m if per_msg else c) for w, c, m in costs if w.startswith(prefix) and f" of {n} " in w)

    enc1, enc100 = cost("driver", "1"), cost("driver", "100", True)
    deser = next(c for w, c, m in costs if "deserialize" in w)
    dec32 = cost("fusion: `decode", "32")
    step1, step100 = cost("fusion: `Live", "1"), cost("fusion: `Live", "100", True)
    s32 = next((p for p in synth if p.note.startswith("32 topics, deser")), None)
    s1 = next((p for p in synth if p.note.startswith("1 topic")), None)
    sraw = next((p for p in synth if "raw" in p.note), None)
    para = []

    out = [f"**Subscriber side: per message, and mostly rclpy deserialization.**  The bare subscriber's ceiling, "
           f"{ceiling:,.0f} msgs/s = {ceiling / N_IMUS:,.0f} array samples/s, is what rclpy manages when it turns "
           f"every `sensor_msgs/Imu` into Python objects: {deser:.0f} us per message for `deserialize_message` "
           f"alone in process; over DDS, flat out, the subscriber spent {_us_per_msg(bare_flat, 'bare')} us of CPU "
           "per message."]
    if s32 and sraw and s32.msgs_per_s > 0:
        out.append(f"The same messages taken serialized (`raw=True`, as the fusion node takes them) arrived at "
                   f"{sraw.msgs_per_s:,.0f} msgs/s against {s32.msgs_per_s:,.0f} deserialized "
                   f"({sraw.msgs_per_s / s32.msgs_per_s:.1f}x; subscriber CPU {_us_per_msg(sraw, 'bare')} vs "
                   f"{_us_per_msg(s32, 'bare')} us per message).")
    if s32 and s1 and s32.msgs_per_s > 0:
        r = s1.msgs_per_s / s32.msgs_per_s
        if r < 1.1:
            out.append(f"All of them on one topic instead of 32 is not faster ({s1.msgs_per_s:,.0f} vs "
                       f"{s32.msgs_per_s:,.0f} msgs/s, {100 * (r - 1):+.0f} %): the 32 separate topics as such do "
                       "not cap the rate; the number of messages does -- 32 per array sample, every per-message "
                       "cost (deserialization, executor dispatch, DDS) paid 32 times per sample.")
        else:
            out.append(f"All of them on one topic instead of 32: {s1.msgs_per_s:,.0f} vs {s32.msgs_per_s:,.0f} "
                       f"msgs/s ({r:.2f}x): the 32 separate topics cost {100 * (1 - 1 / r):.0f} % of the rate; on top "
                       "of that every per-message cost is paid 32 times per array sample.")
    para.append("  ".join(out))

    out = [f"**Driver side: a fixed encode cost per tick.**  Flat out (`rate:=0`, batches of 200 samples) the "
           f"driver alone publishes {drv.msgs_per_s:,.0f} msgs/s ({_us_per_msg(drv, 'driver')} us of CPU per "
           f"message; encoding a 100-sample batch costs {enc100:.1f} us per message)"
           + (", more than any subscriber here takes." if drv.msgs_per_s > ceiling else ".")]
    out.append(f"At real time each tick holds one or a few samples, and `raw_imu_payloads` encodes them with 32 "
               f"per-IMU `encode_imu` calls: {enc1 / 1e3:.1f} ms per tick whatever the tick holds.  At 200 Hz that "
               f"is {0.2 * enc1 / 1e1:.0f} % of a core for encoding alone, and {enc1 / 1e3:.1f} ms added to every "
               "sample's latency before the first message leaves.")
    para.append("  ".join(out))

    out = [f"**Fusion node: a fixed cost per step.**  One step (`LiveFusion.add` + `step`) of one array sample "
           f"costs {step1 / 1e3:.1f} ms ({dec32 / 1e3:.1f} ms of it in `decode_raw_imu`, whose frame_id check "
           f"loops over the IMUs), against {step100:.1f} us per message in 100-sample batches; with the default "
           f"5 ms period that fixed cost alone is up to {step1 / 5e3 * 100:.0f} % of a core, before the executor's "
           "per-message dispatch of the 32 raw callbacks."]
    if fb:
        out.append(f"At {fb.rate_hz:g} Hz, the highest rate sustained, the driver used "
                   f"{_pct(fb.cpu.get('driver', float('nan')))} and the fusion node "
                   f"{_pct(fb.cpu.get('fusion', float('nan')))} of a core; other jobs {fb.others:.2f} of the "
                   f"{ncores} cores.")
    ff = first_failed(res["fusion"])
    if ff:
        busy = sum(v for v in ff.cpu.values() if v == v) + (ff.others if ff.others == ff.others else 0)
        out.append(f"At {ff.rate_hz:g} Hz, the lowest rate not sustained ({ff.note or 'samples lost'}), the driver "
                   f"used {_pct(ff.cpu.get('driver', float('nan')))}, the fusion node "
                   f"{_pct(ff.cpu.get('fusion', float('nan')))}, the probe {_pct(ff.cpu.get('probe', float('nan')))} "
                   f"and other jobs {ff.others:.2f} cores: {busy:.2f} of {ncores} cores busy"
                   + (", the machine saturated." if busy > 0.9 * ncores else "."))
    degraded = [p for p in res["fusion"] if p.counts.get("incomplete_samples") or p.counts.get("late")]
    if degraded:
        out.append("Past its ceiling the fusion node does not only fall behind, it degrades the output: "
                   + "; ".join(f"at {p.rate_hz:g} Hz {p.counts.get('incomplete_samples', 0):,} of {p.expected:,} "
                               f"samples were fused with IMUs missing and {p.counts.get('late', 0):,} messages "
                               "dropped as late" for p in sorted(degraded, key=lambda p: p.rate_hz))
                   + ".  They come in runs: "
                   + "; ".join(f"at {p.rate_hz:g} Hz {p.counts.get('incomplete_runs', 0)} runs, the longest "
                               f"{p.counts.get('longest_run_samples', 0)} consecutive samples "
                               f"({p.counts.get('longest_run_s', 0) * 1e3:.0f} ms of stream, from "
                               f"{p.counts.get('longest_run_from_s', 0):.2f} s)"
                               for p in sorted(degraded, key=lambda p: p.rate_hz) if "incomplete_runs" in p.counts)
                   + " -- some topics' messages reached the node more than `sync_timeout` (0.05 s) after the "
                   "other IMUs' messages of the same samples, so those samples went without them and the stragglers "
                   "were dropped as late.")
    para.append("  ".join(out))

    p200 = next((p for p in res["fusion"] if p.rate_hz == 200 and p.period is None), None)
    if p200 and p200.lat_diag:
        out = [f"**Latency.**  At 200 Hz the fusion node reports p50 {_ms(p200.lat_diag, 0)} ms and p99 "
               f"{_ms(p200.lat_diag, 1)} ms from stamp to fused publish.  It adds up from the driver's encode per "
               f"tick ({enc1 / 1e3:.1f} ms) plus its poll (<= 0.5 ms), DDS, the fusion node's timer (a sample waits "
               f"up to one `period`, 5 ms by default, so the p99 of that wait alone is ~5 ms) and its step "
               f"({step1 / 1e3:.1f} ms for one sample), all on a machine where other jobs used {p200.others:.2f} "
               "cores."]
        for p in res["extra"]:
            if p.lat_diag:
                out.append(f"With `period:={p.period:g}` the same run gives p50 {_ms(p.lat_diag, 0)} ms and p99 "
                           f"{_ms(p.lat_diag, 1)} ms at a fusion CPU of {_pct(p.cpu.get('fusion', float('nan')))} "
                           f"(vs {_pct(p200.cpu.get('fusion', float('nan')))}): one fixed step cost per period.")
        para.append("  ".join(out))
    return "\n\n".join(para)


# ====================================================================== main


def _point(d: dict) -> Point:
    d = dict(d)
    for k in ("lat_diag", "lat_probe"):
        d[k] = tuple(d.get(k) or ())
    return Point(**d)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--role", choices=("bench", "bare-sub", "diag", "pub"), default="bench", help=argparse.SUPPRESS)
    ap.add_argument("--count", type=int, default=0, help=argparse.SUPPRESS)
    ap.add_argument("--timeout", type=float, default=60.0, help=argparse.SUPPRESS)
    ap.add_argument("--topics", type=int, default=N_IMUS, help=argparse.SUPPRESS)
    ap.add_argument("--raw", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--bag", help=argparse.SUPPRESS)
    ap.add_argument("--rates", default="100,200,400,800,1000,1600,2000",
                    help="array sample rates of the ladders, Hz (comma separated); each ladder stops at its first "
                    "rate not sustained")
    ap.add_argument("--duration", type=float, default=10.0, help="seconds of recording per point (default 10)")
    ap.add_argument("--bisect", type=int, default=2, help="bisection steps between the highest sustained and "
                    "the lowest failed ladder rate (default 2)")
    ap.add_argument("--max-lag", type=float, default=0.5, help="a point is sustained only if its last sample "
                    "arrives within this many seconds of its stamp (default 0.5)")
    ap.add_argument("--latency-periods", default="0.001", help="extra 200 Hz fusion points with these fusion "
                    "node periods (comma separated; empty: none)")
    ap.add_argument("--workdir", help="keep recordings, process logs and points.json here (default: a temp dir, "
                    "removed at the end)")
    ap.add_argument("--render", help="only write the report again from a points.json of an earlier run")
    ap.add_argument("--out", default=str(REPO / "benchmarks" / "results" / "nodes.md"))
    args = ap.parse_args()
    if args.role == "bare-sub":
        raise SystemExit(role_bare_sub(args))
    if args.role == "diag":
        raise SystemExit(role_diag(args))
    if args.role == "pub":
        raise SystemExit(role_pub(args))
    if args.render:
        raw = json.loads(Path(args.render).read_text())
        res = {k: ([_point(d) for d in v] if isinstance(v, list) and v and isinstance(v[0], dict) and "kind" in v[0]
                   else _point(v) if isinstance(v, dict) and "kind" in v else v) for k, v in raw.items()}
        res["costs"] = [tuple(c) for c in res["costs"]]
        write_report(Path(args.out), res)
        print(f"wrote {args.out}")
        return

    command = " ".join(["python", os.path.relpath(__file__, Path.cwd())] + sys.argv[1:])
    t_start = time.perf_counter()
    load_start = loadavg()
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
        print(f"[driver rate 0 -> bare subscriber, {top} Hz recording]", flush=True)
        bare_flat = measure_bare(work, bag, n, top, 0.0, args.max_lag, args.duration)
        print("  " + describe(bare_flat), flush=True)
        synth = []
        for topics, raw in ((N_IMUS, False), (1, False), (N_IMUS, True)):
            print(f"[pre-encoded publisher -> subscriber, {topics} topic(s), {'raw' if raw else 'deserializing'}]",
                  flush=True)
            synth.append(measure_synthetic(work, bag, n, topics, raw, args.duration))
            print("  " + describe(synth[-1]), flush=True)

        bare = ladder("driver -> bare subscriber",
                      lambda bag, n, r: measure_bare(work, bag, n, r, 1.0, args.max_lag, args.duration))
        fusion = ladder("driver -> fusion -> probe",
                        lambda bag, n, r: measure_fusion(work, bag, n, r, args.max_lag, args.duration))
        extra: list[Point] = []
        for per in [float(x) for x in args.latency_periods.split(",") if x.strip()]:
            bag, n = rec(200)
            print(f"[driver -> fusion (period {per:g}) -> probe, 200 Hz]", flush=True)
            extra.append(measure_fusion(work, bag, n, 200, args.max_lag, args.duration, period=per))
            print("  " + describe(extra[-1]), flush=True)

        load_end = loadavg()
        print(f"load average at end: {load_end}", flush=True)
        res = {"args": vars(args), "command": command, "load_start": load_start, "load_end": load_end,
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
