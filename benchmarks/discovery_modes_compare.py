"""A/B of two runs of :mod:`benchmarks.discovery_modes` on the same seed (a baseline tree and a changed one): the
nulls with a mode, the whole-pipeline nulls, the modes detected by oracle evidence, each side by side with the
ratio changed / baseline, and every recording whose answer differs.

    python -m benchmarks.discovery_modes_compare BASE.json NEW.json --md OUT.md [--base-label b4592a6]
        [--new-label 15b05eb] [--commands "..."]

An "## Interpretation" section is left for a hand-written one (kept when the file is rewritten).
"""

from __future__ import annotations

import argparse
import json

import numpy as np

from benchmarks.discovery_modes import EDGES, count_ci, pipeline_verdict

#: the whole-pipeline answers counted per tree (:func:`benchmarks.discovery_modes.pipeline_verdict`)
VERDICTS = (("false_clock", "a false sample clock kept in the final model"), ("false_mode", "a false mode reported"),
            ("wrong_finding", "a wrong library finding (not the missing term on its IMU alone)"),
            ("found", "the missing term found on its IMU alone"), ("correct", "correct (that finding only)"))


def _clocks(rows) -> str:
    return "n/a" if rows is None else (", ".join(f"{c[1]} {c[0]} {c[2]:+.0f} ppm" for c in rows) or "none")


def _ratio(a: int, b: int) -> str:
    return f"{b / a:.2f}" if a else ("—" if not b else "∞")


def _load(summary: dict) -> str:
    return " ".join(f"{x:.2f}" for x in summary.get("load_average", []))


def compare(base: dict, new: dict, labels: tuple[str, str]) -> str:
    lb, ln = labels
    text = (f"## Nulls (any mode reported = a false finding)\n\n| kind | recordings | with a mode, {lb} | with a mode, "
            f"{ln} | ratio | motion lines set aside, {lb} | {ln} |\n|---|---|---|---|---|---|---|\n")
    kinds = sorted({r["kind"].split(" ")[0] for r in base["nulls"]})
    for kd in kinds + ["all"]:
        rb = [r for r in base["nulls"] if kd == "all" or r["kind"].startswith(kd)]
        rn = [r for r in new["nulls"] if kd == "all" or r["kind"].startswith(kd)]
        nb, nn = sum(bool(r["modes"]) for r in rb), sum(bool(r["modes"]) for r in rn)
        text += (f"| {kd} | {len(rb)} | {count_ci(nb, len(rb))} | {count_ci(nn, len(rn))} | {_ratio(nb, nn)} | "
                 f"{sum(r['motion_lines'] for r in rb)} | {sum(r['motion_lines'] for r in rn)} |\n")
    diff = [(a, b) for a, b in zip(base["nulls"], new["nulls"]) if a["modes"] != b["modes"]]
    text += "\nNulls whose reported modes differ: " + ("none" if not diff else "") + "\n\n"
    for a, b in diff:
        text += (f"- {a['seed']} {a['kind']} ({a['array']}, {a['rate_hz']:g} Hz): {lb} "
                 + (", ".join(f"{m[0]:g} Hz (p {m[1]:.2g}, {m[2]})" for m in a["modes"]) or "none") + f"; {ln} "
                 + (", ".join(f"{m[0]:g} Hz (p {m[1]:.2g}, {m[2]})" for m in b["modes"]) or "none") + "\n")
    pb, pn = base.get("pipeline") or [], new.get("pipeline") or []
    if pb or pn:
        text += (f"\n## Whole pipeline (`discover`) on library nulls\n\n| recordings | with a mode after the findings, {lb} "
                 f"| {ln} | with a mode in the localisation before the search, {lb} | {ln} | with a finding, {lb} | "
                 f"{ln} |\n|---|---|---|---|---|---|---|\n| {len(pb)} | "
                 + " | ".join(count_ci(sum(bool(r[key]) for r in rows), len(rows)) for key in ("modes_after", "modes_before",
                                                                                        "findings") for rows in (pb, pn))
                 + " |\n\n")
        vb, vn = [pipeline_verdict(r) for r in pb], [pipeline_verdict(r) for r in pn]
        if any(v["correct"] is not None for v in vb + vn):
            text += f"| recordings with | {lb} | {ln} |\n|---|---|---|\n"
            for key, name in VERDICTS:
                text += f"| {name} | " + " | ".join(
                    "n/a" if any(v[key] is None for v in vs) else count_ci(sum(v[key] for v in vs), len(vs))
                    for vs in (vb, vn)) + " |\n"
            text += "\n"
        for a, b in zip(pb, pn):
            text += (f"- {a['seed']} {a['kind']} ({a['array']}, {a['rate_hz']:g} Hz, {a['samples']} samples): findings "
                     + (", ".join(f"{e} on {s}" for e, s in a["findings"]) or "none")
                     + ("" if a["findings"] == b["findings"] else " (" + ln + ": "
                        + (", ".join(f"{e} on {s}" for e, s in b["findings"]) or "none") + ")")
                     + f"; modes before {len(a['modes_before'])} / {len(b['modes_before'])}, after "
                     f"{len(a['modes_after'])} / {len(b['modes_after'])} ({lb} / {ln})"
                     + ("" if "missing_imu" not in a else f"; missing on {a['missing_imu']}; sample clocks kept "
                        f"{_clocks(a.get('clocks'))} / {_clocks(b.get('clocks'))}, dropped given the findings "
                        f"{_clocks(a.get('clocks_dropped'))} / {_clocks(b.get('clocks_dropped'))}") + "\n")
    mb, mn = base["modes"], new["modes"]
    if mb:
        text += (f"\n## Mode scenarios: detected (located in band with the strongest IMU)\n\n| evidence | scenarios | "
                 f"{lb} | {ln} | ratio |\n|---|---|---|---|---|\n")
        ev = np.array([r["evidence"] for r in mb])
        for lo, hi in list(zip(EDGES[:-1], EDGES[1:])) + [(0, np.inf)]:
            sel = [i for i, e in enumerate(ev) if lo <= e < hi]
            db, dn = sum(mb[i]["detected"] for i in sel), sum(mn[i]["detected"] for i in sel)
            text += (f"| {'all' if (lo, hi) == (0, np.inf) else f'{lo:g}–{hi:g}'} | {len(sel)} | {count_ci(db, len(sel))} | "
                     f"{count_ci(dn, len(sel))} | {_ratio(db, dn)} |\n")
        text += (f"\nThe injected mode in the motion lines (set aside as following the motion): {lb} "
                 f"{sum(r['in_motion_lines'] for r in mb)}, {ln} {sum(r['in_motion_lines'] for r in mn)}; modes reported "
                 f"away from the injected frequency: {lb} {sum(r['other_modes'] for r in mb)}, {ln} "
                 f"{sum(r['other_modes'] for r in mn)}.\n\nMode scenarios whose answer differs: ")
        diff = [(a, b) for a, b in zip(mb, mn) if (a["detected"], a["in_motion_lines"], a["other_modes"])
                != (b["detected"], b["in_motion_lines"], b["other_modes"])]
        text += ("none" if not diff else "") + "\n\n"
        for a, b in diff:
            text += (f"- {a['seed']} ({a['array']}, {a['rate_hz']:g} Hz, {a['frequency_hz']:.3g} Hz, "
                     f"{a['bandwidth_hz']:.2g} Hz wide, evidence {a['evidence']:.0f}): detected {a['detected']} / "
                     f"{b['detected']}, in motion lines {a['in_motion_lines']} / {b['in_motion_lines']}, other modes "
                     f"{a['other_modes']} / {b['other_modes']} ({lb} / {ln})\n")
    return text


def main() -> None:
    from benchmarks.harness import load_average, machine_header, write_results

    ap = argparse.ArgumentParser()
    ap.add_argument("base")
    ap.add_argument("new")
    ap.add_argument("--md", required=True)
    ap.add_argument("--base-label", default="baseline")
    ap.add_argument("--new-label", default="changed")
    ap.add_argument("--commands", default="", help="the two runs' commands, for the header")
    ap.add_argument("--title", default="Narrowband-mode search: A/B on the same recordings")
    a = ap.parse_args()
    with open(a.base) as fh:
        base = json.load(fh)
    with open(a.new) as fh:
        new = json.load(fh)
    sb, sn = base["summary"], new["summary"]
    extra = [f"runs: {a.commands}" if a.commands else "runs: (not given)",
             f"baseline: {a.base_label} ({a.base}; {sb['seconds']:.0f} s, load {_load(sb)})",
             f"changed: {a.new_label} ({a.new}; {sn['seconds']:.0f} s, load {_load(sn)})",
             f"load average at comparison: {load_average()}", f"detector alpha (family-wise per recording): {sb['alpha']}"]
    write_results(a.md, machine_header(a.title, extra=extra) + compare(base, new, (a.base_label, a.new_label)))


if __name__ == "__main__":
    main()
