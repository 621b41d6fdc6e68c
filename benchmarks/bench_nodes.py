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
import datetime
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
    """The 32 raw topics, or one topic (``n_topics`` 1: all Imu messages; 0: one array message per sample)."""
    from imu_array_ros.io.rosbag.recording import imu_topic
    from imu_array_ros.model.description import load_description

    names = load_description(ARRAY).names
    if n_topics == N_IMUS:
        return [imu_topic(n) for n in names]
    return ["/bench/one_topic/data_raw" if n_topics == 1 else "/bench/array_samples"]


def _msg_type(n_topics: int):
    if n_topics == 0:  # one message per array sample: the 32 IMUs' 6 values, float64
        from std_msgs.msg import Float64MultiArray

        return Float64MultiArray
    from sensor_msgs.msg import Imu

    return Imu


def role_bare_sub(args) -> int:
    """Plain rclpy subscriber: deserializing callbacks (``--raw``: serialized) that count."""
    import rclpy
    from rclpy.executors import ExternalShutdownException
    from rclpy.experimental import EventsExecutor

    from imu_array_ros.nodes.runtime import qos

    topics = _topics(args.topics)
    msg_type = _msg_type(args.topics)
    rclpy.init()
    node = rclpy.create_node("bare_subscriber")
    counts = [0] * len(topics)
    total = [0]
    last = [None]
    q = qos(True, keep_all=True)  # the fusion node's input QoS with reliable:=true

    stamps_cb = [None, None]  # drain mode: wall time of the first and the last callback

    def make(k):
        def cb(msg):
            counts[k] += 1
            total[0] += 1
            last[0] = msg

        def cb_timed(msg):
            counts[k] += 1
            total[0] += 1
            stamps_cb[1] = time.time_ns()
            if stamps_cb[0] is None:
                stamps_cb[0] = stamps_cb[1]

        return cb_timed if args.hold_until else cb

    for k, topic in enumerate(topics):
        node.create_subscription(msg_type, topic, make(k), q, raw=args.raw)
    executor = EventsExecutor()
    executor.add_node(node)
    print("ready", flush=True)
    if args.hold_until:  # let the source fill the queues first (DDS receives in its own threads), then drain
        limit = time.monotonic() + args.timeout
        while not Path(args.hold_until).exists() and time.monotonic() < limit:
            time.sleep(0.05)
    t_first = t_last = None
    seen = 0
    end = time.monotonic() + args.timeout
    idle_ns = int(args.idle * 1e9) if args.idle else None
    try:
        while time.monotonic() < end and total[0] < args.count:
            executor.spin_once(timeout_sec=0.05)
            if total[0] != seen:
                seen = total[0]
                t_last = time.time_ns()
                if t_first is None:
                    t_first = t_last
            elif idle_ns and t_last is not None and time.time_ns() - t_last > idle_ns:
                break  # the source has stopped
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    if args.hold_until:
        t_first, t_last = stamps_cb
    stamp = None
    if last[0] is not None and not args.raw and hasattr(last[0], "header"):
        s = last[0].header.stamp
        stamp = s.sec * 1_000_000_000 + s.nanosec
    Path(args.out).write_text(json.dumps({"total": total[0], "per_topic": counts, "t_first_ns": t_first,
                                          "t_last_ns": t_last, "last_stamp_ns": stamp}))
    node.destroy_node()
    rclpy.try_shutdown()
    return 0


def role_pub(args) -> int:
    """Synthetic source: the Imu payloads of ``--bag`` (as the driver encodes them), encoded beforehand and
    published as fast as possible, reliable, keep last 1000 (``--keep-all``: keep all), on the 32 topics, all
    on one topic, or (``--topics 0``) one Float64MultiArray of the 32 IMUs' values per array sample (repeated
    up to ``--count`` messages); writes ``--out`` once every subscriber has acknowledged everything."""
    import numpy as np
    import rclpy
    from rclpy.duration import Duration
    from rclpy.experimental import EventsExecutor
    from rclpy.serialization import serialize_message

    from imu_array_ros.io.messages import raw_imu_payloads
    from imu_array_ros.io.rosbag.recording import read_imu_recording
    from imu_array_ros.model.description import load_description
    from imu_array_ros.nodes.runtime import qos

    desc = load_description(ARRAY)
    samples, _ = read_imu_recording(args.bag, desc)
    msg_type = _msg_type(args.topics)
    if args.topics == 0:
        values = np.concatenate([samples.accel, samples.gyro], axis=2).reshape(len(samples), -1)
        msgs = [(0, serialize_message(msg_type(data=row.tolist()))) for row in values]
        msgs = (msgs * (args.count // len(msgs) + 1))[:args.count] if args.count else msgs
    else:
        if args.count:
            samples = samples.select(slice(0, -(-args.count // N_IMUS)))
        per_imu = raw_imu_payloads(samples, desc)
        msgs = [(k, per_imu[k][1][i].tobytes()) for i in range(len(samples)) for k in range(len(per_imu))]
        msgs = msgs[:args.count or len(msgs)]
    topics = _topics(args.topics)
    rclpy.init()
    node = rclpy.create_node("bench_publisher")
    q = qos(True, keep_all=args.keep_all)  # keep last 1000 (the driver's reliable:=true) or keep all
    pubs = [node.create_publisher(msg_type, t, q) for t in topics]
    executor = EventsExecutor()
    executor.add_node(node)
    while any(p.get_subscription_count() < 1 for p in pubs):
        executor.spin_once(timeout_sec=0.01)
    time.sleep(0.5)  # let the reliable endpoints settle
    fns = [p.publish for p in pubs] if len(pubs) > 1 else [pubs[0].publish] * N_IMUS
    t0 = time.time_ns()
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
    from rclpy.executors import ExternalShutdownException
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
    except (KeyboardInterrupt, ExternalShutdownException):
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
    """Busy CPU of everything else (cores); /proc/stat and per-process ticks are counted apart, so the
    difference can come out slightly negative: clamped at 0."""
    ours = sum(cpu.used(n, t0, t1) for n in names)
    return max(0.0, (cpu.used("_machine", t0, t1) - ours) / max((t1 - t0) / 1e9, 1e-9))


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
        timeout = 120 if replay_rate == 0 else duration + 20
        s = run.start("bare", sys.executable, Path(__file__).resolve(), "--role", "bare-sub", "--out", out,
                      "--count", pt.expected, "--timeout", timeout)
        run.wait_line("bare", "ready")
        d = run.start("driver", *driver_cmd(bag, replay_rate))
        cpu = CpuSampler({"bare": s.pid, "driver": d.pid})
        run.wait("bare", timeout + 10, unless="driver")
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
        pt.note = "; ".join(([f"{pt.lost:,} messages lost"] if pt.lost else [])
                            + ([f"fell behind: last message {pt.lag_s:.2f} s after its stamp"] if not keeps_up else []))
        return pt
    finally:
        run.stop_all()


DRAIN_PER_TOPIC = 5000  # within Fast DDS's keep-all resource limits (20,000 on one topic made publish fail)


def measure_synthetic(work: Path, bag: Path, topics: int, raw: bool) -> Point:
    """Subscriber capacity by topic layout, without the driver and without the DDS receive path: a publisher
    of payloads encoded beforehand fills the subscriber's keep-all queues while it does not spin (DDS receives
    and acknowledges in its own threads), then the subscriber drains them as fast as it can.

    topics 32: 5,000 of the driver's Imu messages on each of the 32 topics; 1: 5,000 Imu messages on one
    topic; 0: 5,000 Float64MultiArray messages (the 32 IMUs' 6 values: one message per array sample)."""
    tag = f"drain_{topics}topics{'_raw' if raw else ''}"
    run = Procs(work, tag)
    n_msgs = DRAIN_PER_TOPIC * max(topics, 1)
    samples = n_msgs if topics == 0 else n_msgs // N_IMUS
    pt = Point("drain", 0, samples, expected=n_msgs)
    out, pub_out = run.dir / "bare.json", run.dir / "pub.json"
    me = Path(__file__).resolve()
    try:
        s = run.start("bare", sys.executable, me, "--role", "bare-sub", "--out", out, "--count", n_msgs,
                      "--timeout", 120, "--idle", 3, "--topics", topics, "--hold-until", pub_out,
                      *(["--raw"] if raw else []))
        run.wait_line("bare", "ready")
        cpu = CpuSampler({"bare": s.pid}, period=0.02)
        run.start("pub", sys.executable, me, "--role", "pub", "--out", pub_out, "--bag", bag, "--topics", topics,
                  "--count", n_msgs, "--keep-all")
        run.wait("bare", 130, unless="pub")
        run.stop("bare")
        run.wait("pub", 35)
        cpu.stop()
        if not out.exists() or not pub_out.exists():
            pt.note = f"drain failed: {run.text('bare')[-300:]} {run.text('pub')[-300:]}"
            return pt
        r, w = json.loads(out.read_text()), json.loads(pub_out.read_text())
        pt.received, pt.expected = r["total"], w["published"]
        if r["t_first_ns"] and r["t_last_ns"] and r["t_last_ns"] > r["t_first_ns"]:
            a, b = r["t_first_ns"], r["t_last_ns"]
            rate = (r["total"] - 1) / ((b - a) / 1e9)
            pt.msgs_per_s = rate * N_IMUS if topics == 0 else rate  # in Imu-message equivalents
            pt.counts["messages_per_s"] = rate
            pt.counts["drain_s"] = (b - a) / 1e9
            if b - a > 0.2e9:
                pt.cpu = {"bare": cpu.share("bare", a, b)}
                pt.others = window_others(cpu, ["bare"], a, b)
        pt.counts["acked"] = bool(w.get("acked"))
        pt.note = ("1 topic, one Float64MultiArray (32 x 6 values) per array sample, deserializing callbacks"
                   if topics == 0 else f"{topics} topic{'s' if topics > 1 else ''} of Imu, "
                   + ("raw (serialized) callbacks" if raw else "deserializing callbacks"))
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
                   period: float | None = None, warmup: float = 2.0) -> Point:
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
        notes = []
        if pt.lost:
            notes.append(f"{pt.lost} samples lost")
        if len(arrival) < 2:
            pt.note = "; ".join(notes + ["fewer than 2 fused samples"])
            return pt
        # steady state: from `warmup` s after the first sample on (the start is reported on its own)
        steady = stamps >= stamps[0] + int(warmup * 1e9)
        if steady.sum() < 2:
            steady[:] = True
        # samples fused with IMUs missing have a larger CRB than complete ones
        tr = np.nansum(np.diagonal(got["covariance"], axis1=1, axis2=2)[:, 6:9], axis=1)
        incomplete = ~np.isclose(tr, np.nanmin(tr), rtol=1e-6)
        pt.counts["incomplete_start"] = int(incomplete[~steady].sum())
        pt.counts["incomplete_steady"] = int(incomplete[steady].sum())
        inc = np.flatnonzero(incomplete)
        if len(inc):
            cut = np.flatnonzero(np.diff(inc) > 1)
            starts, ends = np.r_[inc[0], inc[cut + 1]], np.r_[inc[cut], inc[-1]]
            longest = int(np.argmax(ends - starts))
            pt.counts["incomplete_runs"] = len(starts)
            pt.counts["longest_run_samples"] = int(ends[longest] - starts[longest] + 1)
            pt.counts["longest_run_s"] = float((stamps[ends[longest]] - stamps[starts[longest]]) / 1e9)
            pt.counts["longest_run_from_s"] = float((stamps[starts[longest]] - stamps[0]) / 1e9)
        lat = (arrival - stamps) / 1e9
        ls = lat[steady]
        pt.lat_probe = (float(np.percentile(ls, 50)), float(np.percentile(ls, 99)), float(ls.max()))
        pt.counts["probe_p99_all"] = float(np.percentile(lat, 99))
        pt.counts["probe_max_all"] = float(lat.max())
        pt.lag_s = float(lat[-1])
        # the fusion node's once-a-second diagnostics: are the slow samples the ones published around them?
        diag_t = np.array([r["t_ns"] for r in fus], dtype=np.int64)
        if len(diag_t):
            arr = arrival[steady]
            pos = np.searchsorted(diag_t, arr)
            after = arr - diag_t[np.maximum(pos - 1, 0)]
            before = diag_t[np.minimum(pos, len(diag_t) - 1)] - arr
            near = ((pos > 0) & (after <= 0.1e9)) | ((pos < len(diag_t)) & (before <= 0.03e9))
            slow = ls > np.percentile(ls, 50) + 0.01
            pt.counts["slow"] = int(slow.sum())
            pt.counts["slow_at_diag"] = int((slow & near).sum())
            pt.counts["near_diag_share"] = float(near.mean())
            if (~near).sum() > 10:
                pt.counts["probe_p99_away_from_diag"] = float(np.percentile(ls[~near], 99))
        a, b = int(arrival[steady][0]), int(arrival[-1])
        pt.msgs_per_s = (steady.sum() - 1) * N_IMUS / max((b - a) / 1e9, 1e-9)
        pt.cpu = {n: cpu.share(n, a, b) for n in ("driver", "fusion", "probe")}
        pt.others = window_others(cpu, ["driver", "fusion", "probe"], a, b)
        pt.lat_diag = _diag_latency(records, a, b)
        keeps_up = pt.lag_s <= max_lag
        overflow = pt.counts.get("overflow_samples", 0)
        pt.sustained = bool(fus) and pt.lost == 0 and pt.counts["incomplete_steady"] == 0 and not overflow and keeps_up
        if not fus:
            notes.append("no fusion diagnostics recorded")
        if pt.counts["incomplete_steady"]:
            notes.append(f"{pt.counts['incomplete_steady']} samples fused incomplete after the first {warmup:g} s")
        if overflow:
            notes.append(f"{overflow} overflow samples")
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
    for rate in (200, 1000):  # the diagnostics, once a second, over a full 1 s window
        n = min(rate, len(samples))
        live = LiveFusion(desc)
        per_imu = raw_imu_payloads(samples.select(slice(0, n)), desc)
        every = max(1, rate // 200)  # 5 ms steps
        t0 = int(samples.stamps[0])
        for lo in range(0, n, every):
            hi = min(n, lo + every)
            payloads = [per_imu[k][1][i].tobytes() for i in range(lo, hi) for k in range(N_IMUS)]
            index = [k for _ in range(lo, hi) for k in range(N_IMUS)]
            now = t0 + int((hi - 1) * 1e9 / rate) + 1
            live.add(payloads, index, now)
            live.step(now)
        t = timed(lambda: live.summary(now), 5)
        out.append((f"fusion: `LiveFusion.summary` (the 1 s diagnostics) with a full window at {rate} Hz",
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
    return (f"{pt.kind} {'' if pt.kind == 'drain' else 'flat out' if pt.rate_hz == 0 else f'{pt.rate_hz:g} Hz'}"
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
                        f"- command: `{res['command']}`"
                        + (f"\n- report written again from that run's points.json (`--render`): {res['rendered']}"
                           if res.get("rendered") else ""))
    if res.get("date"):
        text = text.replace(text[text.index("- date:"):text.index("\n", text.index("- date:"))],
                            f"- date: {res['date']}")
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
        "more).\n\n"
        "The bare-subscriber ceiling is measured like the fusion pipeline: the driver replays at real time up a "
        "ladder of sample rates (then bisection), and a rate counts as sustained when every message arrived "
        f"and the last one within {a['max_lag']:g} s of its stamp (the subscriber kept up); for the fusion "
        "pipeline, in addition, no sample fused incomplete after the start-up and no overflow.\n\n")

    text += "## Bare subscriber, driver at real time (`rate:=1`): the ceiling\n\n"
    text += ("| sample rate (Hz) | messages published | received | lost | msgs/s | CPU driver | CPU bare sub | "
             "CPU/msg driver, bare (us) | others (cores) | last message lag (ms) | sustained |\n"
             "|---|---|---|---|---|---|---|---|---|---|---|\n")
    for p in sorted(bare, key=lambda p: p.rate_hz):
        text += (f"| {p.rate_hz:g} | {p.expected:,} | {p.received:,} | {p.lost:,} | {p.msgs_per_s:,.0f} | "
                 f"{_pct(p.cpu.get('driver', float('nan')))} | {_pct(p.cpu.get('bare', float('nan')))} | "
                 f"{_us_per_msg(p, 'driver')}, {_us_per_msg(p, 'bare')} | {p.others:.2f} | {1e3 * p.lag_s:.0f} | "
                 f"{'yes' if p.sustained else 'no'}{' (' + p.note + ')' if p.note else ''} |\n")

    text += ("\n## Flat out (`driver_node rate:=0`)\n\n"
             "`rate:=0` publishes reliable keep-all: nothing can be lost, `publish` blocks while the subscriber "
             "has not acknowledged.\n\n"
             "| source -> subscriber | messages/s | array samples/s | CPU (% of a core) | CPU per message (us) | "
             "others (cores) | lost |\n|---|---|---|---|---|---|---|\n")
    for name, p in (("driver alone, no subscriber: its publish ceiling", drv),
                    ("driver -> bare subscriber (32 topics of Imu, deserializing callbacks)", bare_flat)):
        text += (f"| {name} | {p.msgs_per_s:,.0f} | {p.msgs_per_s / N_IMUS:,.0f} | "
                 + ", ".join(f"{k} {_pct(v)}" for k, v in p.cpu.items()) + " | "
                 + ", ".join(f"{k} {_us_per_msg(p, k)}" for k in p.cpu)
                 + f" | {p.others:.2f} | {p.lost:,} |\n")
    text += ("\n## Subscriber capacity by topic layout (queues filled, then drained)\n\n"
             "A publisher of payloads encoded beforehand (no driver) fills the subscriber's keep-all queues "
             f"({DRAIN_PER_TOPIC:,} messages per topic, within Fast DDS's keep-all resource limits: 20,000 on one "
             "topic made `publish` fail) while the subscriber does not spin (DDS "
             "receives and acknowledges in its own threads); then the subscriber drains them, timed from its first "
             "to its last callback: the cost of taking, deserializing and dispatching a message in rclpy, without "
             "the DDS receive path.  The array-message layout is one `std_msgs/Float64MultiArray` with the 32 "
             "IMUs' 6 values per array sample.\n\n"
             f"Best of {a.get('drains', 1)} drains (all of them in the last column; they vary by up to several "
             "times between repeats, so read the orders of magnitude).\n\n"
             "| layout, callbacks | messages | messages/s | array samples/s | us per message | subscriber CPU | "
             "others (cores) | every drain (msgs/s) |\n|---|---|---|---|---|---|---|---|\n")
    for p in synth:
        m = p.counts.get("messages_per_s", float("nan"))
        tries = ", ".join(f"{t:,}" for t in p.counts.get("tries_msgs_per_s", []))
        text += (f"| {p.note} | {p.received:,} of {p.expected:,} | {m:,.0f} | {p.msgs_per_s / N_IMUS:,.0f} | "
                 f"{1e6 / m:.1f} | {_pct(p.cpu.get('bare', float('nan')))} | "
                 f"{'-' if p.others != p.others else f'{p.others:.2f}'} | {tries} |\n")

    w = a.get("warmup", 2.0)
    text += "\n## driver_node -> fusion_node -> probe, driver at real time (`rate:=1`)\n\n"
    text += (f"Steady state = from {w:g} s after the first sample on (CPU, rates, latencies and the sustained "
             f"verdict); the first {w:g} s are reported on their own (incomplete samples, probe p99 of the whole "
             "run).  Incomplete samples are counted from the probe's output (a sample fused with IMUs missing has "
             "a larger covariance); *late* is the fusion node's own count of messages dropped because their sample "
             "had gone without them (whole run).\n\n")
    text += ("| sample rate (Hz) | fusion period (s) | samples published | fused received | lost | incomplete: "
             f"first {w:g} s / after | late msgs | msgs/s in | CPU driver | CPU fusion | CPU probe | CPU/msg driver, "
             "fusion (us) | others (cores) | diag p50 / p99 / worst p99 (ms) | probe p50 / p99 / max (ms) | "
             "probe p99 whole run (ms) | sustained |\n"
             "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|\n")
    for p in sorted(fusion, key=lambda p: p.rate_hz) + extra:
        c = p.counts
        text += (f"| {p.rate_hz:g} | {p.period or 0.005:g} | {p.expected:,} | {p.received:,} | {p.lost:,} | "
                 f"{c.get('incomplete_start', '-')} / {c.get('incomplete_steady', '-')} | {c.get('late', '-')} | "
                 f"{p.msgs_per_s:,.0f} | "
                 f"{_pct(p.cpu.get('driver', float('nan')))} | {_pct(p.cpu.get('fusion', float('nan')))} | "
                 f"{_pct(p.cpu.get('probe', float('nan')))} | {_us_per_msg(p, 'driver')}, {_us_per_msg(p, 'fusion')} | "
                 f"{p.others:.2f} | {_ms(p.lat_diag, 0)} / {_ms(p.lat_diag, 1)} / {_ms(p.lat_diag, 2)} | "
                 f"{_ms(p.lat_probe, 0)} / {_ms(p.lat_probe, 1)} / {_ms(p.lat_probe, 2)} | "
                 + (f"{1e3 * c['probe_p99_all']:.1f} | " if "probe_p99_all" in c else "- | "))
        text += f"{'yes' if p.sustained else 'no'}{' (' + p.note + ')' if p.note else ''} |\n"

    tail = [p for p in sorted(fusion, key=lambda p: p.rate_hz) + extra if "slow" in p.counts]
    if tail:
        text += ("\nLatency tail against the fusion node's once-a-second /diagnostics (steady state): *slow* = "
                 "probe latency more than 10 ms over the median; *at diagnostics* = arrived within 100 ms after or "
                 "30 ms before a fusion /diagnostics message (those windows hold the share of all samples given).\n\n"
                 "| sample rate (Hz) | fusion period (s) | slow samples | of them at diagnostics | share of all samples "
                 "in those windows | probe p99 (ms) | probe p99 outside those windows (ms) |\n"
                 "|---|---|---|---|---|---|---|\n")
        for p in tail:
            c = p.counts
            away = c.get("probe_p99_away_from_diag")
            text += (f"| {p.rate_hz:g} | {p.period or 0.005:g} | {c['slow']:,} | {c['slow_at_diag']:,} | "
                     f"{100 * c['near_diag_share']:.0f} % | {_ms(p.lat_probe, 1)} | "
                     f"{'-' if away is None else f'{1e3 * away:.1f}'} |\n")

    text += ("\n## Per-call costs of the nodes' work (this process, no DDS; best of 3, CPU time)\n\n"
             "| what | us per call | us per Imu message |\n|---|---|---|\n")
    for what, per_call, per_msg in costs:
        text += f"| {what} | {per_call:,.0f} | {per_msg:.1f} |\n"

    fb, bb = best(fusion), best(bare)
    f_msgs = fb.rate_hz * N_IMUS if fb else 0.0
    ceiling = bb.rate_hz * N_IMUS if bb else 0.0
    ratio = f_msgs / ceiling if ceiling > 0 else float("nan")
    p200 = next((p for p in fusion if p.rate_hz == 200 and p.period is None), None)
    ffail, bfail = first_failed(fusion), first_failed(bare)
    text += "\n## Result against the targets\n\n"
    text += ("- highest rate driver -> fusion sustained: " + (f"**{fb.rate_hz:g} Hz x 32 IMUs = {f_msgs:,.0f} "
             f"Imu messages/s**" if fb else "**none of the rates tested**")
             + (f" (lowest rate not sustained: {ffail.rate_hz:g} Hz)" if ffail else " (no rate tested failed)")
             + "\n")
    text += ("- bare subscriber ceiling, same run, same driver: " + (f"**{bb.rate_hz:g} Hz x 32 = {ceiling:,.0f} "
             "messages/s**" if bb else "**none of the rates tested**")
             + (f" (lowest rate not sustained: {bfail.rate_hz:g} Hz)" if bfail else " (no rate tested failed)")
             + f"; flat out through the driver's flow control it received {bare_flat.msgs_per_s:,.0f} msgs/s\n")
    text += (f"- fusion / bare ceiling: **{100 * ratio:.0f} %** (target >= 80 %): "
             f"**{'met' if ratio >= 0.8 else 'NOT met'}**\n")
    text += (f"- at least 32 IMUs x 200 Hz without loss: **{'met' if fb and fb.rate_hz >= 200 else 'NOT met'}**\n")
    if p200:
        lat = p200.lat_diag[1] if p200.lat_diag else float("nan")
        worst = p200.lat_probe[1] if p200.lat_probe else float("nan")
        text += (f"- p99 latency < 5 ms at 200 Hz, default parameters: diag p99 {1e3 * lat:.1f} ms (worst window "
                 f"{_ms(p200.lat_diag, 2)} ms); probe (one hop more) p99 {1e3 * worst:.1f} ms: "
                 f"**{'met' if lat < 5e-3 else 'NOT met'}** (judged on the diag p99)\n")
    for p in extra:
        lat = p.lat_diag[1] if p.lat_diag else float("nan")
        worst = p.lat_probe[1] if p.lat_probe else float("nan")
        text += (f"- the same with the fusion node at `period:={p.period:g}`: diag p99 {1e3 * lat:.1f} ms, probe p99 "
                 f"{1e3 * worst:.1f} ms: **{'met' if lat < 5e-3 else 'NOT met'}**\n")
    text += "\n## What limits the rate\n\n" + analysis(res, fb, bb, ceiling) + "\n"
    path.write_text(text)


def analysis(res: dict, fb: Point | None, bb: Point | None, ceiling: float) -> str:
    """The paragraphs on what limits rate and latency, from this run's numbers."""
    drv, bare_flat, synth, costs = res["driver"], res["bare_flat"], res["synthetic"], res["costs"]
    ncores = os.cpu_count() or 1
    w = res["args"].get("warmup", 2.0)

    def cost(prefix: str, n: str, per_msg: bool = False) -> float:
        return next((m if per_msg else c) for what, c, m in costs if what.startswith(prefix) and f" of {n} " in what)

    enc1, enc100 = cost("driver", "1"), cost("driver", "100", True)
    deser = next(c for what, c, m in costs if "deserialize" in what)
    dec32 = cost("fusion: `decode", "32")
    step1, step100 = cost("fusion: `Live", "1"), cost("fusion: `Live", "100", True)
    summ = {int(what.split(" at ")[1].split(" ")[0]): c for what, c, m in costs if "summary" in what}
    s32 = next((p for p in synth if p.note.startswith("32 topics of Imu, deser")), None)
    s1 = next((p for p in synth if p.note.startswith("1 topic of Imu")), None)
    s0 = next((p for p in synth if "Float64MultiArray" in p.note), None)
    sraw = next((p for p in synth if "raw" in p.note), None)
    para = []

    def mps(p: Point) -> float:
        return p.counts.get("messages_per_s", float("nan"))

    out = ["**Subscriber side: the cost is per message.**  The bare subscriber kept up with the driver up to "
           + (f"{bb.rate_hz:g} Hz = {ceiling:,.0f} msgs/s, using {_pct(bb.cpu.get('bare', float('nan')))} of a "
              f"core there ({_us_per_msg(bb, 'bare')} us per message, DDS receive included; the driver "
              f"{_pct(bb.cpu.get('driver', float('nan')))})" if bb else "none of the rates tested")
           + f"; `deserialize_message(Imu)` alone costs {deser:.0f} us in process."]
    if s32 and sraw and mps(s32) > 0:
        out.append(f"Drained from full queues, rclpy delivers {mps(s32):,.0f} Imu messages/s deserialized and "
                   f"{mps(sraw):,.0f} serialized (`raw=True`, as the fusion node takes them): "
                   f"{1e6 / mps(s32):.0f} vs {1e6 / mps(sraw):.0f} us per message.")
    if s32 and s1 and mps(s32) > 0:
        r = mps(s1) / mps(s32)
        if r < 1.15:
            out.append(f"**The 32 separate topics do not cap the rate**: the same Imu messages on one topic are not "
                       f"taken faster ({mps(s1):,.0f} msgs/s vs {mps(s32):,.0f} on 32 topics, best drains).")
        else:
            out.append(f"The same Imu messages on one topic drain at {mps(s1):,.0f} msgs/s vs {mps(s32):,.0f} on 32 "
                       f"topics ({r:.2f}x): the 32 topics cost {100 * (1 - 1 / r):.0f} % of the rate.")
    if s32 and s0 and mps(s32) > 0:
        out.append(f"**The 32 messages per array sample do**: one `Float64MultiArray` per array sample drains at "
                   f"{mps(s0):,.0f} array samples/s against {mps(s32) / N_IMUS:,.0f} as 32 Imu messages "
                   f"({mps(s0) / (mps(s32) / N_IMUS):.0f}x): every per-message cost (take, deserialization, "
                   "executor dispatch, and over DDS the receive path) is paid 32 times per sample.")
    if bare_flat.msgs_per_s > 0 and bare_flat.cpu:
        out.append(f"Flat out (`rate:=0`, keep-all publishers that block until acknowledged) the bare subscriber "
                   f"received {bare_flat.msgs_per_s:,.0f} msgs/s with the driver at "
                   f"{_pct(bare_flat.cpu.get('driver', 0))} and the subscriber at "
                   f"{_pct(bare_flat.cpu.get('bare', 0))} of a core"
                   + (": the reliable protocol's acknowledgements, not CPU, set that pace." if
                      max(bare_flat.cpu.values()) < 0.8 else "."))
    para.append("  ".join(out))

    out = [f"**Driver: a fixed encode cost per tick.**  Flat out (`rate:=0`, batches of 200 samples) the driver "
           f"alone publishes {drv.msgs_per_s:,.0f} msgs/s ({_us_per_msg(drv, 'driver')} us of CPU per message; "
           f"encoding a 100-sample batch costs {enc100:.1f} us per message)"
           + (", more than any subscriber here takes." if drv.msgs_per_s > ceiling else ".")]
    out.append(f"At real time a tick holds one or a few samples, and `raw_imu_payloads` encodes them with 32 "
               f"per-IMU `encode_imu` calls: {enc1 / 1e3:.1f} ms per tick whatever it holds.  At 200 Hz that is "
               f"{0.2 * enc1 / 1e1:.0f} % of a core for encoding alone (the driver used "
               + ", ".join(f"{_pct(p.cpu.get('driver', float('nan')))} at {p.rate_hz:g} Hz"
                           for p in sorted(res["fusion"], key=lambda p: p.rate_hz)[:3] if p.period is None)
               + f" in the fusion runs), and {enc1 / 1e3:.1f} ms added to every sample's latency before its first "
               "message leaves.")
    para.append("  ".join(out))

    out = [f"**Fusion node: fixed costs per step and per second.**  One step (`LiveFusion.add` + `step`) of one "
           f"array sample costs {step1 / 1e3:.1f} ms ({dec32 / 1e3:.1f} ms of it in `decode_raw_imu`, whose "
           f"frame_id check loops over the 32 IMUs), against {step100:.1f} us per message in 100-sample batches; "
           f"with the default 5 ms period that is up to {step1 / 5e3 * 100:.0f} % of a core before the executor's "
           "per-message dispatch of the raw callbacks."]
    if summ:
        out.append("Once a second the diagnostics (`LiveFusion.summary`: NIS residuals of every sample of the last "
                   "second, recomputed) block the node's only thread for "
                   + " and ".join(f"{c / 1e3:.0f} ms at {r} Hz" for r, c in sorted(summ.items())) + ".")
    if fb and bb and fb.rate_hz > bb.rate_hz and s32 and sraw:
        out.append(f"The fusion pipeline sustains more than the bare subscriber ({fb.rate_hz:g} vs {bb.rate_hz:g} Hz) "
                   f"because the fusion node takes its messages serialized ({1e6 / mps(sraw):.0f} vs "
                   f"{1e6 / mps(s32):.0f} us per message drained) and decodes them column-wise in batches.")
    if fb:
        out.append(f"At {fb.rate_hz:g} Hz, the highest rate sustained, the driver used "
                   f"{_pct(fb.cpu.get('driver', float('nan')))}, the fusion node "
                   f"{_pct(fb.cpu.get('fusion', float('nan')))} and the probe {_pct(fb.cpu.get('probe', float('nan')))} "
                   f"of a core, other jobs {fb.others:.2f} of the {ncores} cores"
                   + (": the driver is the process at its limit." if fb.cpu.get("driver", 0) >= 0.95 else "."))
    ff = first_failed(res["fusion"])
    if ff:
        busy = sum(v for v in ff.cpu.values() if v == v) + (ff.others if ff.others == ff.others else 0)
        out.append(f"At {ff.rate_hz:g} Hz, the lowest rate not sustained ({ff.note or 'samples lost'}), the driver "
                   f"used {_pct(ff.cpu.get('driver', float('nan')))}, the fusion node "
                   f"{_pct(ff.cpu.get('fusion', float('nan')))}, the probe {_pct(ff.cpu.get('probe', float('nan')))} "
                   f"and other jobs {ff.others:.2f} cores: {busy:.2f} of {ncores} cores busy"
                   + (", the machine saturated." if busy > 0.9 * ncores else "."))
    para.append("  ".join(out))

    degraded = [p for p in res["fusion"] + res["extra"]
                if p.counts.get("incomplete_steady") or p.counts.get("incomplete_start")]
    if degraded:
        out = ["**Incomplete samples and late messages.**  Where the fusion node fell short it did not only fall "
               "behind: " + "; ".join(
                   f"at {p.rate_hz:g} Hz{f' (period {p.period:g})' if p.period else ''} "
                   f"{p.counts.get('incomplete_start', 0):,} samples in the first {w:g} s and "
                   f"{p.counts.get('incomplete_steady', 0):,} after were fused with IMUs missing and "
                   f"{p.counts.get('late', 0):,} messages dropped as late, in {p.counts.get('incomplete_runs', 0)} "
                   f"runs, the longest {p.counts.get('longest_run_samples', 0):,} consecutive samples from "
                   f"{p.counts.get('longest_run_from_s', 0):.2f} s"
                   for p in sorted(degraded, key=lambda p: (p.period or 0, p.rate_hz))) + ".",
               "Some IMUs' topics delivered nothing for more than `sync_timeout` (0.05 s) while the other IMUs' "
               "messages of the same samples had arrived, so those samples went without them and the stragglers, "
               "arriving later, were rejected as late."]
        busy_all = [(p, sum(v for v in p.cpu.values() if v == v) + p.others) for p in degraded]
        if busy_all and all(b > 0.9 * ncores for _, b in busy_all):
            out.append("Every such point ran with the machine saturated ("
                       + ", ".join(f"{b:.2f} of {ncores} cores busy at {p.rate_hz:g} Hz" for p, b in busy_all) + ").")
        para.append("  ".join(out))

    p200 = next((p for p in res["fusion"] if p.rate_hz == 200 and p.period is None), None)
    if p200 and p200.lat_diag:
        out = [f"**Latency.**  At 200 Hz the fusion node reports p50 {_ms(p200.lat_diag, 0)} ms and p99 "
               f"{_ms(p200.lat_diag, 1)} ms (median of its 1 s windows) from stamp to fused publish; the probe "
               f"saw p99 {_ms(p200.lat_probe, 1)} ms in steady state and "
               f"{1e3 * p200.counts.get('probe_p99_all', float('nan')):.0f} ms over the whole run including the "
               f"start.  It adds up from the driver's encode per tick ({enc1 / 1e3:.1f} ms) and poll (<= 0.5 ms), "
               f"DDS, the fusion node's timer (a sample waits up to one `period`, 5 ms by default, whose p99 alone "
               f"is ~5 ms), its step ({step1 / 1e3:.1f} ms for one sample) and, once a second, its diagnostics "
               + (f"({summ[200] / 1e3:.0f} ms at 200 Hz)" if 200 in summ else "")
               + f"; other jobs used {p200.others:.2f} cores meanwhile."]
        c = p200.counts
        if "slow_at_diag" in c:
            away = c.get("probe_p99_away_from_diag", float("nan"))
            out.append(f"{'Most of the' if c['slow_at_diag'] >= 0.5 * c['slow'] else 'Part of the'} tail is the "
                       f"diagnostics: of the {c['slow']} steady-state samples more than 10 ms over the median, "
                       f"{c['slow_at_diag']} arrived within 100 ms after (or 30 ms before) one of the fusion node's "
                       f"/diagnostics messages (windows holding {100 * c['near_diag_share']:.0f} % of all samples); "
                       f"away from those windows the probe's p99 is {1e3 * away:.1f} ms instead of "
                       f"{_ms(p200.lat_probe, 1)} ms"
                       + (", still above 5 ms: the timer wait, the fixed step and encode costs and the scheduling of "
                          f"three busy processes on {ncores} cores remain (not broken down further here)."
                          if away > 5e-3 else "."))
        for p in res["extra"]:
            if p.lat_diag:
                aw, aw0 = p.counts.get("probe_p99_away_from_diag"), c.get("probe_p99_away_from_diag")
                out.append(f"With `period:={p.period:g}` the same run gives p50 {_ms(p.lat_diag, 0)} ms and p99 "
                           f"{_ms(p.lat_diag, 1)} ms"
                           + (f" (probe p99 outside the diagnostics windows {1e3 * aw:.1f} ms vs {1e3 * aw0:.1f} ms)"
                              if aw and aw0 else "")
                           + f" at a fusion CPU of {_pct(p.cpu.get('fusion', float('nan')))} (vs "
                           f"{_pct(p200.cpu.get('fusion', float('nan')))}, one fixed step cost per period): a shorter "
                           "period trims the body of the distribution, not the once-a-second stall.")
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
    ap.add_argument("--idle", type=float, default=0.0, help=argparse.SUPPRESS)
    ap.add_argument("--hold-until", help=argparse.SUPPRESS)
    ap.add_argument("--keep-all", action="store_true", help=argparse.SUPPRESS)
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
        if not res.get("date"):  # runs before the date was saved: when points.json was written
            res["date"] = datetime.datetime.fromtimestamp(Path(args.render).stat().st_mtime, datetime.timezone.utc
                                                          ).strftime("%Y-%m-%d %H:%M UTC")
        res["rendered"] = datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%d %H:%M UTC")
        write_report(Path(args.out), res)
        print(f"wrote {args.out}")
        return

    command = " ".join(["python", os.path.relpath(__file__, Path.cwd())] + sys.argv[1:])
    t_start = time.perf_counter()
    date = datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%d %H:%M UTC")
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

        load_end = loadavg()
        print(f"load average at end: {load_end}", flush=True)
        res = {"args": vars(args), "command": command, "date": date, "load_start": load_start, "load_end": load_end,
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
