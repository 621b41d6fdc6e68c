"""Discovery's speed against the calibration's on the same real capture, same run (issue 23 item 7: a
10-minute 8-IMU capture discovered within 4x the time of ``imu-array calibrate all`` on it).

For each code tree given (``--tree DIR``, default this repository; e.g. an older checkout made with
``git worktree add``), in one run, as the user runs them (the CLI, a fresh process each, under
``/usr/bin/time -v``, niced):

1. ``imu-array import-openshoe`` of the capture (once, with this repository's code);
2. ``imu-array calibrate all`` of the capture from config/mimu4444bt_corners.yaml;
3. ``imu-array discover --calibration <that calibration> --apply`` of the capture (plots included).

The table gives wall time, peak resident memory (max RSS) and the ratio discover / calibrate all, and the
findings discover reported (to compare the trees' results).  Results are appended to
benchmarks/results/discovery_speed.json (one entry per tree and run) and the markdown rebuilt from it.

``--clocks`` (with ``--window``): the description discover starts from carries the sample clocks the timing
stage finds on the *whole* capture (their phases re-estimated on the window, as ``discover`` does for a
description with clocks), so a window exercises the clocked model's refits (the timing stage finds no clock on a window of exp_3
alone: 60+180, 300+180 and 0+300 s gave largest sawtooths 4.2-5.6x their median, 8x needed; the whole
capture 38-46x on every gyroscope).  ``--rates`` (with ``--window``): discover runs in the reading rates' scope,
as ``imu-array discover`` does (its timing stage then tests each sample's reading rates; without it, as before,
it does not); a window longer than the whole capture is the whole capture.

    python -m benchmarks.bench_discovery_speed [--capture exp_2] [--tree DIR --label NAME ...]
        [--window START DURATION --max-findings N [--clocks] [--rates]]
"""

from __future__ import annotations

import argparse
import json
import os
import re
import subprocess
import sys
import tempfile
from pathlib import Path

from benchmarks.harness import DATA, REPO, RESULTS, load_average, machine_header, say, write_results

OUT = RESULTS / "discovery_speed.md"
JSON = RESULTS / "discovery_speed.json"
CHUNK_JSON = RESULTS / "discovery_speed_chunk.json"
ARRAY = REPO / "config" / "mimu4444bt_corners.yaml"
CLI = "import sys; from imu_array_ros.cli import main; sys.exit(main())"


def _run(tree: Path, args: list[str], log: Path) -> dict:
    """Wall seconds and max RSS (MB) of ``imu-array args`` run with ``tree``'s package, niced."""
    env = dict(os.environ, PYTHONPATH=str(tree))
    cmd = ["/usr/bin/time", "-v", "nice", sys.executable, "-c", CLI, *args]
    with open(log, "w") as fh:
        proc = subprocess.run(cmd, env=env, stdout=fh, stderr=subprocess.STDOUT, cwd=tree)
    text = log.read_text()
    if proc.returncode != 0:
        raise SystemExit(f"{' '.join(args[:2])} failed (exit {proc.returncode}), see {log}")
    wall = re.search(r"Elapsed \(wall clock\) time \(h:mm:ss or m:ss\): (\S+)", text).group(1)
    parts = [float(x) for x in wall.split(":")]
    seconds = sum(v * 60 ** i for i, v in enumerate(reversed(parts)))
    rss = int(re.search(r"Maximum resident set size \(kbytes\): (\d+)", text).group(1)) / 1024
    user = float(re.search(r"User time \(seconds\): (\S+)", text).group(1))
    return {"wall_s": seconds, "max_rss_mb": rss, "user_s": user}


def _findings(report: Path) -> list[str]:
    data = json.loads((report / "report.json").read_text())
    return [f"{f['effect']}@{f['scope']}:{','.join(f['sensors'])}" for f in data["findings"]]


def measure(tree: Path, label: str, capture: Path, work: Path) -> dict:
    cal = work / f"{label}_cal.yaml"
    say(f"[{label}] calibrate all")
    c = _run(tree, ["calibrate", "all", str(capture), "--array", str(ARRAY), "--out", str(cal), "-q"],
             work / f"{label}_calibrate.log")
    say(f"[{label}] calibrate all: {c['wall_s']:.1f} s; discover")
    report = work / f"{label}_report"
    d = _run(tree, ["discover", str(capture), "--array", str(ARRAY), "--calibration", str(cal),
                    "--report", str(report), "--apply", str(work / f"{label}_found.yaml")],
             work / f"{label}_discover.log")
    say(f"[{label}] discover: {d['wall_s']:.1f} s")
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=tree, capture_output=True,
                            text=True).stdout.strip()
    dirty = subprocess.run(["git", "status", "--porcelain", "--", "imu_array_ros"], cwd=tree,
                           capture_output=True, text=True).stdout.strip()
    return {"label": label, "commit": commit + (" + uncommitted" if dirty else ""), "capture": capture.stem,
            "calibrate": c, "discover": d, "ratio": d["wall_s"] / c["wall_s"], "findings": _findings(report),
            "load_average": load_average()}


CHUNK = """
import json, resource, sys, time
from pathlib import Path
from imu_array_ros import workflows
from imu_array_ros.discovery.discover import DiscoveryOptions, discover
from imu_array_ros.workflows.arrays import as_model
capture, cal, start, dur, n = sys.argv[1], sys.argv[2], float(sys.argv[3]), float(sys.argv[4]), int(sys.argv[5])
desc, _ = workflows.load_array(Path(sys.argv[6]), Path(cal))
whole = workflows.read_imu_recording(Path(capture), desc)[0]
samples = whole.window(start, dur)
model = as_model(desc)
if sys.argv[7] == "clocks":  # the whole capture's sample clocks (not timed)
    from imu_array_ros.discovery.timing import timing_stage
    model = timing_stage(whole, model).model
from contextlib import nullcontext
from imu_array_ros.fitting.reading_rates import rates_scope
t0, c0 = time.perf_counter(), time.process_time()
with rates_scope() if sys.argv[8] == "rates" else nullcontext():  # the reading rates' decision, as the CLI's
    d = discover(samples, model, options=DiscoveryOptions(max_findings=n),
                 progress=lambda text: print(f"{time.perf_counter() - t0:8.1f} s {text}", file=sys.stderr, flush=True))
print(json.dumps({"wall_s": time.perf_counter() - t0, "cpu_s": time.process_time() - c0, "samples": len(samples),
                  "timings": d.timings,
                  "max_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
                  "findings": [f"{f.effect}@{f.scope}:{','.join(f.candidate.sensors)}" for f in d.findings],
                  "values": {f"{f.effect}@{f.scope}": [[float(v) for v in f.values], [float(v) for v in f.std]]
                             for f in d.findings},
                  "exact_delta_loglik": [float(f.exact_delta_loglik) for f in d.findings]}))
"""


def measure_chunk(tree: Path, label: str, capture: Path, cal: Path, window, max_findings: int,
                  clocks: bool = False, log: Path | None = None, rates: bool = False) -> dict:
    """discover (Python API, defaults but max_findings) on a window of the capture, from ``cal`` (``clocks``: with
    the whole capture's sample clocks; ``rates``: in the reading rates' scope, as ``imu-array discover`` runs it);
    its progress lines (seconds since its start) into ``log``."""
    env = dict(os.environ, PYTHONPATH=str(tree))
    load_before = load_average()
    say(f"[{label}] discover on {window[1]:g} s from {window[0]:g} s, at most {max_findings} findings"
        + (", the whole capture's sample clocks" if clocks else ""))
    out = subprocess.run(["nice", sys.executable, "-c", CHUNK, str(capture), str(cal), str(window[0]), str(window[1]),
                          str(max_findings), str(ARRAY), "clocks" if clocks else "-", "rates" if rates else "-"],
                         env=env, capture_output=True,
                         text=True, cwd=tree)
    if log is not None:
        log.write_text(out.stderr)
    if out.returncode != 0:
        raise SystemExit(f"chunk discover failed: {out.stderr[-2000:]}")
    r = json.loads(out.stdout.strip().splitlines()[-1])
    say(f"[{label}] {r['wall_s']:.1f} s, {r['cpu_s']:.1f} CPU s")
    return {"label": label, "capture": capture.stem, "window_s": list(window), "max_findings": max_findings,
            "clocks": clocks, "rates": rates, **r, "load_before": load_before, "load_average": load_average()}


def _cpu(r: dict) -> str:
    """CPU seconds of a window run (not recorded before 2026-11-29 14:45 UTC)."""
    return f"{r['cpu_s']:.1f} s" if "cpu_s" in r else "—"


def _table(entries: list[dict]) -> str:
    text = ("| tree (commit) | capture | load avg | calibrate all | discover | ratio | max RSS calibrate / "
            "discover | findings |\n|---|---|---|---|---|---|---|---|\n")
    for e in entries:
        c, d = e["calibrate"], e["discover"]
        text += (f"| {e['label']} ({e['commit']}) | {e['capture']} | {e['load_average']} | {c['wall_s']:.1f} s "
                 f"| {d['wall_s']:.1f} s | {e['ratio']:.2f} | {c['max_rss_mb']:.0f} / {d['max_rss_mb']:.0f} MB "
                 f"| {'; '.join(e['findings']) or '—'} |\n")
    return text


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--capture", default="exp_2", help="capture of ../shared/data/openshoe_mimu4444bt")
    ap.add_argument("--tree", action="append", default=[], help="code tree (default this repository)")
    ap.add_argument("--label", action="append", default=[], help="label of each --tree")
    ap.add_argument("--window", nargs=2, type=float, metavar=("START", "DURATION"),
                    help="instead: discover alone (Python API) on this window (s) of the capture, from a calibrate "
                         "all of the whole capture, every tree in turn (speed and findings compared)")
    ap.add_argument("--max-findings", type=int, default=8, help="with --window (default 8)")
    ap.add_argument("--clocks", action="store_true", help="with --window: start from the whole capture's sample "
                                                         "clocks (module docstring)")
    ap.add_argument("--rates", action="store_true", help="with --window: discover in the reading rates' scope, as "
                                                        "imu-array discover runs it (its timing stage decides them)")
    args = ap.parse_args()
    trees = [Path(t).resolve() for t in args.tree] or [REPO]
    labels = args.label or [("current" if t == REPO else t.name) for t in trees]
    if len(labels) != len(trees):
        raise SystemExit("give one --label per --tree")
    work = Path(tempfile.mkdtemp(prefix="bench_discovery_speed_"))
    capture = work / f"{args.capture}.mcap"
    subprocess.run([sys.executable, "-c", CLI, "import-openshoe", str(DATA / f"{args.capture}.bin"), "--array",
                    str(ARRAY), "--out", str(capture)], check=True, cwd=REPO, env=dict(os.environ,
                                                                                       PYTHONPATH=str(REPO)))
    if args.window:
        cal = work / "cal.yaml"
        c = _run(REPO, ["calibrate", "all", str(capture), "--array", str(ARRAY), "--out", str(cal), "-q"],
                 work / "calibrate.log")
        say(f"calibrate all (this repository's code, whole capture): {c['wall_s']:.1f} s, {c['user_s']:.1f} user s")
        runs = [dict(measure_chunk(t, lab, capture, cal, args.window, args.max_findings, args.clocks,
                                   work / f"{lab.replace(' ', '_').replace('/', '_')}_progress.log", args.rates),
                     calibrate=c) for t, lab in zip(trees, labels)]
        say(f"progress logs in {work}")
        text = "| tree | capture | window (s) | max findings | samples | discover | CPU | max RSS | findings | load avg |\n"
        text += "|---|---|---|---|---|---|---|---|---|---|\n" + "".join(
            f"| {r['label']} | {r['capture']}{' (clocks)' if r['clocks'] else ''}"
            f"{' (rates)' if r.get('rates') else ''} | {r['window_s'][0]:g}+{r['window_s'][1]:g} | "
            f"{r['max_findings']} | "
            f"{r['samples']} | "
            f"{r['wall_s']:.1f} s | {_cpu(r)} | {r['max_rss_mb']:.0f} MB | {'; '.join(r['findings']) or '—'} | "
            f"{r['load_average']} |\n" for r in runs)
        CHUNK_JSON.write_text(json.dumps((json.loads(CHUNK_JSON.read_text()) if CHUNK_JSON.exists() else []) + runs,
                                         indent=1) + "\n")
        _write_md()
        print(text)
        return 0
    runs = [measure(t, lab, capture, work) for t, lab in zip(trees, labels)]
    entries = json.loads(JSON.read_text()) if JSON.exists() else []
    JSON.write_text(json.dumps(entries + runs, indent=1) + "\n")
    _write_md()
    print(_table(runs))
    return 0


def _write_md() -> None:
    """The results file from every run saved in the two JSON files."""
    text = machine_header("Discovery speed against calibrate all, same capture, same run")
    text += __doc__.split("\n\n", 1)[1].rsplit("\n\n", 1)[0] + "\n\n"
    entries = json.loads(JSON.read_text()) if JSON.exists() else []
    text += "## Whole capture (target: ratio <= 4)\n\n" + (_table(entries) if entries else "(no complete run)\n")
    chunks = json.loads(CHUNK_JSON.read_text()) if CHUNK_JSON.exists() else []
    if chunks:
        text += ("\n## A window of the capture (`--window`), discover alone, trees in turn\n\n"
                 "| tree | capture | window (s) | max findings | samples | discover | CPU | max RSS | findings | load avg |\n"
                 "|---|---|---|---|---|---|---|---|---|---|\n" + "".join(
                     f"| {r['label']} | {r.get('capture', '?')}{' (clocks)' if r.get('clocks') else ''}"
                     f"{' (rates)' if r.get('rates') else ''} | "
                     f"{r['window_s'][0]:g}+{r['window_s'][1]:g} | "
                     f"{r['max_findings']} | "
                     f"{r['samples']} | {r['wall_s']:.1f} s | {_cpu(r)} | {r['max_rss_mb']:.0f} MB | "
                     f"{'; '.join(r['findings']) or '—'} | {r['load_average']} |\n" for r in chunks))
    write_results(OUT, text)


if __name__ == "__main__":
    sys.exit(main())
