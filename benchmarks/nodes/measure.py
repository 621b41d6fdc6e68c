"""The measurements of the live-node benchmark: one :class:`Point` each, from processes of their own.

* :func:`measure_driver_alone`: the driver's publish ceiling (no subscriber, flat out);
* :func:`measure_bare`: driver -> bare subscriber (real time or flat out);
* :func:`measure_synthetic`: subscriber capacity by topic layout (queues filled, then drained);
* :func:`measure_fusion`: driver -> fusion_node -> probe at real time."""

from __future__ import annotations

import json
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

from benchmarks.nodes.cpu import CpuSampler, window_others
from benchmarks.nodes.procs import ARRAY, BIN, N_IMUS, Procs, driver_cmd, log_time, role_cmd



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
        s = run.start("bare", *role_cmd("bare-sub", "--out", out, "--count", pt.expected, "--timeout", timeout))
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
    try:
        s = run.start("bare", *role_cmd("bare-sub", "--out", out, "--count", n_msgs, "--timeout", 120, "--idle", 3,
                                        "--topics", topics, "--hold-until", pub_out, *(["--raw"] if raw else [])))
        run.wait_line("bare", "ready")
        cpu = CpuSampler({"bare": s.pid}, period=0.02)
        run.start("pub", *role_cmd("pub", "--out", pub_out, "--bag", bag, "--topics", topics, "--count", n_msgs,
                                   "--keep-all"))
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
        run.start("diag", *role_cmd("diag", "--out", diag_out))
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
