"""The live-node benchmark's results file: the setting, one table per measurement, the targets.

What limits the rate and the latency is the file's hand-written ``## Interpretation`` (kept by
:func:`benchmarks.harness.write_results`)."""

from __future__ import annotations

import os
from pathlib import Path

from benchmarks.harness import machine_header, write_results
from benchmarks.nodes.measure import DRAIN_PER_TOPIC, Point
from benchmarks.nodes.procs import N_IMUS


def _pct(x: float) -> str:
    return "-" if x != x else f"{100 * x:.0f} %"


def _ms(t, i: int) -> str:
    return f"{1e3 * t[i]:.1f}" if t else "-"


def _us_per_msg(p: Point, proc: str) -> str:
    c = p.cpu.get(proc, float("nan"))
    return "-" if c != c or not p.msgs_per_s > 0 else f"{1e6 * c / p.msgs_per_s:.0f}"


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
    facts = [f"load average (1, 5, 15 min) at start: {res['load_start']}; at end: {res['load_end']}; "
             f"whole run {res['minutes']:.1f} min",
             "rclpy (ROS 2 Jazzy, PyPI) with Fast DDS; every node its own process, localhost discovery, "
             "a DDS domain of its own for every measurement"]
    if res.get("rendered"):
        facts.append(f"report written again from that run's points.json (`--render`): {res['rendered']}")
    text = machine_header("Live nodes over DDS: driver_node -> fusion_node vs a bare rclpy subscriber, 32 IMUs",
                          date=res.get("date"), cmd=res["command"],
                          code=res.get("commit", "not recorded by that run"), extra=facts)
    text += (
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

    gaps = [p for p in sorted(fusion, key=lambda p: (p.period or 0, p.rate_hz)) + extra
            if p.counts.get("incomplete_runs")]
    if gaps:
        text += ("\nSamples fused with IMUs missing (whole run): runs of consecutive incomplete samples, the longest "
                 "one, and when it began (s after the first sample).\n\n"
                 "| sample rate (Hz) | fusion period (s) | incomplete: first {0:g} s / after | late msgs | runs | "
                 "longest run (samples) | longest run (s) | from (s) |\n|---|---|---|---|---|---|---|---|\n"
                 .format(w))
        for p in gaps:
            c = p.counts
            text += (f"| {p.rate_hz:g} | {p.period or 0.005:g} | {c.get('incomplete_start', 0):,} / "
                     f"{c.get('incomplete_steady', 0):,} | {c.get('late', '-')} | {c['incomplete_runs']} | "
                     f"{c['longest_run_samples']:,} | {c['longest_run_s']:.2f} | {c['longest_run_from_s']:.2f} |\n")

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
    write_results(path, text)
