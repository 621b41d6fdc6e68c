"""calibration_node's /calibrate_geometry over real DDS vs the same calibration in-process, same run.

A 32-IMU twist (config/array32.yaml, every IMU moved by ~0.5 mm per axis, seeded;
``imu-array simulate --true-array``) of ``--duration`` s at ``--rate`` Hz is
replayed in a loop by ``driver_node`` (real time, reliable) into
``calibration_node`` (``window_samples`` = the recording's sample count: the
whole recording, rotated); once the window is full the benchmark calls the
service ``--repeat`` times from its own rclpy client (``output_file`` removed
before each call, so every call calibrates from the nominal positions and
writes), timing call -> response.  Baseline, in this process, alternating with
the calls (so under the same background: the driver streaming, the node
buffering): what the node runs, :func:`imu_array_ros.workflows.calibrate`
(``"geometry"``) and the result's ``install``, on the recording's samples with
the node's defaults.

Also measured: the node's own calibration time (its log line ``calibration
done in X s``), a second call made while the first runs (refused: its round
trip), and the rate at which the window kept receiving array samples while a
calibration ran (the node's /diagnostics ``samples_received_while_calibrating``
/ ``calibrating_for_s``).

    python -m benchmarks.bench_calibration_service [--duration 10] [--rate 200] [--repeat 5]
                                                   [--out benchmarks/results/calibration_service.md]
"""

from __future__ import annotations

import argparse
import os
import re
import shutil
import signal
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from benchmarks.harness import REPO, RESULTS, load_average, machine_header, write_results
from benchmarks.nodes.cpu import machine_cpu, proc_cpu_s

ARRAY = REPO / "config" / "array32.yaml"
BIN = Path(sys.executable).parent
DONE = re.compile(r"calibration done in ([0-9.]+) s")


def true_array(work: Path) -> Path:
    from imu_array_ros.model.description import load_description, save_description

    desc = load_description(ARRAY)
    rng = np.random.default_rng(5)
    true = desc.with_imus([imu.__class__(**{**imu.__dict__, "position": imu.position + rng.normal(0, 5e-4, 3)})
                           for imu in desc.imus])
    save_description(true, work / "true.yaml")
    return work / "true.yaml"


class Others:
    """CPU the rest of the machine used (cores) while something ran: busy CPU of the machine less
    that of this benchmark's own processes (/proc)."""

    def __init__(self, pids) -> None:
        self.pids = pids

    def __enter__(self):
        self._t, self._m, self._own = time.perf_counter(), machine_cpu()[0], self._own_cpu()
        return self

    def _own_cpu(self) -> float:
        return sum(c for c in (proc_cpu_s(pid) for pid in self.pids) if c is not None)

    def __exit__(self, *exc) -> None:
        wall = time.perf_counter() - self._t
        self.cores = ((machine_cpu()[0] - self._m) - (self._own_cpu() - self._own)) / max(wall, 1e-9)


def baseline(desc, samples, out: Path) -> tuple[float, str]:
    """The node's calibration called directly: seconds, summary."""
    from imu_array_ros.workflows import calibrate

    out.unlink(missing_ok=True)
    t0 = time.perf_counter()
    cal = calibrate("geometry", samples, desc)
    cal.install(desc, out)
    return time.perf_counter() - t0, cal.summary()


class Client:
    """The benchmark's rclpy node: the service client and the calibration node's diagnostics."""

    def __init__(self) -> None:
        import rclpy
        from diagnostic_msgs.msg import DiagnosticArray
        from rclpy.experimental import EventsExecutor
        from std_srvs.srv import Trigger

        rclpy.init()
        self.node = rclpy.create_node("bench_calibration_client")
        self.client = self.node.create_client(Trigger, "/calibrate_geometry")
        self.request = Trigger.Request
        self.diags: list[dict] = []
        self.node.create_subscription(DiagnosticArray, "/diagnostics", self._on_diag, 50)
        self.executor = EventsExecutor()
        self.executor.add_node(self.node)

    def _on_diag(self, msg) -> None:
        for s in msg.status:
            if s.name.startswith("imu_array_calibration"):
                self.diags.append({kv.key: kv.value for kv in s.values})

    def spin_until(self, cond, timeout: float) -> bool:
        end = time.monotonic() + timeout
        while time.monotonic() < end and not cond():
            self.executor.spin_once(timeout_sec=0.002)
        return cond()

    def close(self) -> None:
        import rclpy

        self.node.destroy_node()
        rclpy.try_shutdown()


def run(args, work: Path) -> dict:
    true = true_array(work)
    bag = work / "twist"
    subprocess.run([BIN / "imu-array", "simulate", "--array", ARRAY, "--true-array", true, "--out", bag,
                    "--duration", str(args.duration), "--rate", str(args.rate), "--rms-rate", "900", "--seed", "1",
                    "--start-time", "0", "-q"], check=True)
    n = int(round(args.duration * args.rate))
    from imu_array_ros.io.rosbag.recording import read_imu_recording
    from imu_array_ros.model.description import load_description

    desc = load_description(ARRAY)
    samples, _ = read_imu_recording(bag, desc)

    domain = 30 + (os.getpid() * 7) % 70  # the DDS tests use 100..229
    env = dict(os.environ, ROS_DOMAIN_ID=str(domain), ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST",
               PYTHONUNBUFFERED="1")
    os.environ.update(ROS_DOMAIN_ID=env["ROS_DOMAIN_ID"], ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST")
    out = work / "calibrated.yaml"
    procs = []

    def start(name, *cmd):
        log = open(work / f"{name}.log", "w")
        p = subprocess.Popen([str(c) for c in cmd], env=env, stdout=log, stderr=subprocess.STDOUT,
                             stdin=subprocess.DEVNULL)
        log.close()
        procs.append(p)
        return p

    res = {"n": n, "domain": domain}
    base, base_summary, others_base, others_call = [], "", [], []
    client = None
    try:
        start("calibration", BIN / "calibration_node", "--ros-args", "-p", f"array_config:={ARRAY}",
              "-p", f"output_file:={out}", "-p", f"window_samples:={n}", "-p", "reliable:=true")
        start("driver", BIN / "driver_node", "--ros-args", "-p", f"array_config:={ARRAY}", "-p", "mode:=replay",
              "-p", f"bag:={bag}", "-p", "loop:=true", "-p", "reliable:=true", "-p", "wait_for_subscribers:=1")
        client = Client()
        t_fill = time.monotonic()
        if not client.spin_until(lambda: client.client.service_is_ready() and client.diags
                                 and float(client.diags[-1]["window_fill"]) >= 1.0, args.duration + 60):
            raise RuntimeError(f"the window never filled: {client.diags[-1:]}")
        print(f"window full after {time.monotonic() - t_fill:.1f} s", flush=True)
        trips, messages, refused = [], [], None
        pids = [os.getpid()] + [p.pid for p in procs]
        for i in range(args.repeat):
            with Others(pids) as o:
                seconds, base_summary = baseline(desc, samples, work / "inprocess.yaml")
            base.append(seconds)
            others_base.append(o.cores)
            print(f"  in-process {i + 1}: {seconds:.2f} s", flush=True)
            client.spin_until(lambda: False, 0.5)  # take the diagnostics that came meanwhile
            for f in (out, out.with_name(out.name + ".bak")):
                f.unlink(missing_ok=True)
            o = Others(pids).__enter__()
            t0 = time.perf_counter()
            fut = client.client.call_async(client.request())
            if i == 0:  # a second call while the first runs
                client.spin_until(lambda: False, 0.2)
                t1 = time.perf_counter()
                fut2 = client.client.call_async(client.request())
                client.spin_until(fut2.done, 30)
                refused = (time.perf_counter() - t1, fut2.result().success, fut2.result().message)
            if not client.spin_until(fut.done, 300):
                raise RuntimeError("no response within 300 s")
            trips.append(time.perf_counter() - t0)
            o.__exit__()
            others_call.append(o.cores)
            r = fut.result()
            messages.append(r.message)
            print(f"  call {i + 1}: {trips[-1]:.2f} s, success {r.success}: {r.message[:100]}...", flush=True)
            if not r.success:
                raise RuntimeError(r.message)
            client.spin_until(lambda: False, 1.0)  # one more diagnostics round between calls
        time.sleep(0.5)
        log = (work / "calibration.log").read_text()
        res.update(trips=trips, messages=messages, refused=refused, base=base, base_summary=base_summary,
                   others_base=others_base, others_call=others_call,
                   node_s=[float(m) for m in DONE.findall(log)],
                   rates=[int(d["samples_received_while_calibrating"]) / float(d["calibrating_for_s"])
                          for d in client.diags if d["busy"] == "True" and float(d["calibrating_for_s"]) > 0.5])
    finally:
        if client is not None:
            client.close()
        for p in procs:
            if p.poll() is None:
                p.send_signal(signal.SIGINT)
        for p in procs:
            try:
                p.wait(15)
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait()
    return res


def stats(values) -> str:
    return f"{statistics.median(values):.2f} / {max(values):.2f}"


def report(args, res: dict, load: tuple[str, str]) -> str:
    trips, base, node_s = res["trips"], res["base"], res["node_s"]
    ratio = statistics.median(trips) / statistics.median(base)
    refused_s, refused_ok, refused_msg = res["refused"]
    rates = res["rates"]
    target = 3.0
    verdict = lambda t: "met" if t < target else "NOT met"  # noqa: E731
    return (
        machine_header(f"calibration_node: /calibrate_geometry round trip, {args.duration:g} s at {args.rate:g} Hz, "
                       "32 IMUs")
        + f"- load average (1, 5, 15 min) at start: {load[0]}; at end: {load[1]}\n"
        + "- rclpy (ROS 2 Jazzy, PyPI) with Fast DDS; every node its own process, localhost discovery, "
          f"DDS domain {res['domain']}\n\n"
        + f"Recording: `imu-array simulate --array config/array32.yaml --true-array TRUE --duration {args.duration:g} "
          f"--rate {args.rate:g} --rms-rate 900 --seed 1 --start-time 0`, TRUE = array32 with every IMU moved by "
          "N(0, 0.5 mm) per axis (seed 5).  `driver_node mode:=replay loop:=true reliable:=true` streams it at real "
          f"time the whole run; `calibration_node window_samples:={res['n']} reliable:=true` (other parameters "
          "default: method joint, min_excitation 1.0); the benchmark's own rclpy client calls "
          "`/calibrate_geometry` once the window is full, with `output_file` removed before every call (so each "
          "calibrates from the nominal positions and writes the file).\n\n"
          "Baseline, same run: `calibrate('geometry', ...)` then `.install` (what the node runs) on the "
          f"recording's {res['n']} samples with the same defaults (the node's window holds the same samples, "
          "rotated by the loop), called in the benchmark's process alternately with the service calls, so under "
          "the same background (the driver streaming, the node buffering).\n\n"
          "| | runs | median / max (s) |\n|---|---|---|\n"
          f"| service round trip (call -> response) | {len(trips)} | **{stats(trips)}** |\n"
          f"| calibration inside the node (its log) | {len(node_s)} | {stats(node_s) if node_s else '-'} |\n"
          f"| the same calibration in-process (baseline) | {len(base)} | {stats(base)} |\n\n"
          f"- round trip / in-process (medians): **{ratio:.2f}**\n"
          f"- target round trip < {target:g} s: median {statistics.median(trips):.2f} s **"
          f"{verdict(statistics.median(trips))}**, worst {max(trips):.2f} s **{verdict(max(trips))}**\n"
          f"- other jobs on the machine meanwhile (cores of 2; median / max): during the calls "
          f"{statistics.median(res['others_call']):.2f} / {max(res['others_call']):.2f}, during the in-process "
          f"runs {statistics.median(res['others_base']):.2f} / {max(res['others_base']):.2f}\n"
          f"- round trip - calibration inside the node (medians): "
          f"{statistics.median(trips) - statistics.median(node_s) if node_s else float('nan'):.3f} s "
          "(window snapshot, DDS request and response)\n"
          f"- a second call 0.2 s into the first: answered in {refused_s * 1e3:.1f} ms, success {refused_ok}: "
          f"\"{refused_msg}\"\n"
          f"- buffering while calibrating: the window received {min(rates) if rates else float('nan'):.0f}"
          f"-{max(rates) if rates else float('nan'):.0f} array samples/s during the calibrations (the stream: "
          f"{args.rate:g}/s; from the node's 1 Hz /diagnostics, {len(rates)} readings)\n\n"
          f"The first call's response:\n\n> {res['messages'][0]}\n\n"
          f"In-process summary (the last):\n\n> {res['base_summary']}\n\n"
          "Every run, in order (s; other jobs' cores in brackets): round trip "
        + ", ".join(f"{t:.2f} ({c:.2f})" for t, c in zip(trips, res["others_call"]))
        + "; in the node " + ", ".join(f"{t:.2f}" for t in node_s)
        + "; in-process " + ", ".join(f"{t:.2f} ({c:.2f})" for t, c in zip(base, res["others_base"])) + "\n\n"
          "Both compete with the driver (real-time replay of 32 topics) for the 2 cores; the node's calibration "
          "also with its own buffering (same process, other thread).\n"
    )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--duration", type=float, default=10.0, help="seconds of window / recording (default 10)")
    ap.add_argument("--rate", type=float, default=200.0, help="array sample rate, Hz (default 200)")
    ap.add_argument("--repeat", type=int, default=5, help="service calls and in-process runs (default 5)")
    ap.add_argument("--workdir", help="keep the recording and the node logs here (default: a temp dir, removed)")
    ap.add_argument("--out", default=str(RESULTS / "calibration_service.md"))
    args = ap.parse_args()
    load_start = load_average()
    work = Path(args.workdir or tempfile.mkdtemp(prefix="imu_bench_calsrv_"))
    work.mkdir(parents=True, exist_ok=True)
    try:
        res = run(args, work)
    finally:
        if not args.workdir:
            shutil.rmtree(work, ignore_errors=True)
    text = report(args, res, (load_start, load_average()))
    write_results(args.out, text)
    print(text)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
