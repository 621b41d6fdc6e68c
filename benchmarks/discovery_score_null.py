"""Is discovery's step-1 candidate test calibrated under the null?  Every candidate's score-test and block-robust
p-value on null recordings (the nominal model is the truth).

Recordings: :func:`imu_array_ros.simulation.suites.draw_scenario` (``seed``, "null", i) built by
:func:`~imu_array_ros.simulation.suites.build`, exactly the generalisation suite's nulls (random array planar4 /
corners8 / grid32, rate, session).  Each is run through :func:`imu_array_ros.discovery.discover.discover` itself
(default options, as the suite runs it but for ``heldout=False``, which acts after the search) up to the search:
its motion fit, short-recording blocks, timing stage (sample clocks) and search setup are discover's own.  Its
``ladder_search`` is replaced for the run by :func:`_step1`, which scores step 1 as
:func:`~imu_array_ros.discovery.search.greedy_search` does (``rescore`` on the first rung, then
``evaluate_candidates``, ``evaluate_scopes`` and ``extension_candidates`` with nothing found or excluded yet) and
stops discover there; its localisation (``locate.localize``, a report figure the search does not read) is
skipped.  The tests are the
package's (``explain.block_tests``), not re-implemented.

Reported: the fraction of p-values below 0.1, 0.01, 1e-3, 1e-4 (score test and robust test), overall, per term,
per array and per scope kind, with Clopper-Pearson 95 % intervals (the candidates of one recording are
correlated: the intervals are too narrow for the pooled fractions); per recording, min p x m (m candidates), whose
fraction below alpha is step 1's false-finding rate of each test alone, and the rate at which any candidate passes
discover's step-1 rule (both tests below alpha / m and a positive held-out gain) at alpha = 0.01 and 0.05; a QQ
plot of -log10 p against uniform.

    python -m benchmarks.discovery_score_null [--seed S] [--recordings 80] [--minutes 50] [--render]
"""

from __future__ import annotations

from benchmarks.harness import RESULTS, load_average, machine_header, say, single_threaded_blas, write_results

single_threaded_blas()

import argparse  # noqa: E402
import json  # noqa: E402
import time  # noqa: E402
from contextlib import contextmanager  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

TITLE = "Discovery's step-1 candidate tests under the null: are the score and block-robust p-values uniform?"
OUT = RESULTS / "discovery_score_null"
#: drawn for this benchmark (not in any benchmarks/results file when it was written)
SEED = 530871
LEVELS = (0.1, 0.01, 1e-3, 1e-4)
#: candidates kept in the .json: a p-value below this in either test (LEVELS[0]: every level's count stays exact)
TAIL = 0.1
ALPHAS = (0.01, 0.05)


class _Captured(Exception):
    """Raised by :func:`_step1` to stop discover once step 1 is scored."""

    def __init__(self, candidates, data, rungs, timing_kept):
        super().__init__("step 1 scored")
        self.candidates, self.data, self.rungs, self.timing_kept = candidates, data, rungs, timing_kept


def _step1(ladder, state, space, say_):
    """discover's search replaced: step 1's candidates on the first rung, as greedy_search builds them."""
    from imu_array_ros.discovery.explain import evaluate_candidates, evaluate_scopes
    from imu_array_ros.discovery.extend import extension_candidates
    from imu_array_ros.discovery.search import rescore

    data = ladder[0]
    sb = rescore(data, state, space)
    names = space.model.names
    cands = evaluate_candidates(sb, names, data.fold_of_block, terms=space.terms, exclude=set(), step=1)
    cands += evaluate_scopes(sb, names, data.fold_of_block, space.scopes, terms=space.terms, exclude=set(), step=1)
    cands += extension_candidates(sb, names, data.fold_of_block, state.accepted, state.current, space.model,
                                  space.groups, exclude=set(), step=1)
    raise _Captured(cands, data, len(ladder), state.current is not space.model)


@contextmanager
def _patched():
    import imu_array_ros.discovery.discover as d
    import imu_array_ros.discovery.locate as loc

    saved = d.ladder_search, loc.localize
    d.ladder_search, loc.localize = _step1, (lambda *a, **k: None)  # discover imports localize when it calls it
    try:
        yield d
    finally:
        d.ladder_search, loc.localize = saved


def run_recording(seed: int, index: int) -> dict:
    from imu_array_ros.simulation.suites import build, draw_scenario

    t0 = time.perf_counter()
    sc = draw_scenario(seed, "null", index)
    built = build(sc)
    with _patched() as d:
        try:
            d.discover(built.samples, built.nominal, options=d.DiscoveryOptions(heldout=False))
            raise RuntimeError("discover did not reach step 1")
        except _Captured as cap:
            got = cap
    cands = got.candidates
    row = {"index": index, "name": sc.name, "array": sc.array, "rate_hz": sc.rate_hz, "still_poses": sc.still_poses,
           "duration_s": sc.duration_s, "samples": int(len(built.samples.stamps)), "m": len(cands),
           "share": got.data.share, "rungs": got.rungs, "timing_kept_clock": bool(got.timing_kept),
           "seconds": time.perf_counter() - t0,
           "candidates": {"term": [c.effect for c in cands], "scope": [c.scope for c in cands],
                          "imus": [len(c.imus) for c in cands], "dof": [int(c.dof) for c in cands],
                          "log_lrt_p": [float(c.log_p) for c in cands],
                          "robust_p": [float(c.robust_p) if np.isfinite(c.robust_p) else None for c in cands],
                          "heldout": [float(c.heldout) for c in cands]}}
    return compact(row)


def compact(row: dict) -> dict:
    """``row`` with its minima over every candidate, its candidate counts (term, scope kind, dof) -> [n, n with a
    robust p-value], and only the candidates with a p-value below TAIL in either test (the fractions and the QQ
    plot's tail need no more; the whole list of a grid32 recording is ~0.2 MB), to 5 significant digits."""
    c = row["candidates"]
    lrt = np.exp(np.asarray(c["log_lrt_p"], dtype=float))
    rob = np.asarray([np.nan if p is None else p for p in c["robust_p"]], dtype=float)
    rule = np.where(np.asarray(c["heldout"]) > 0, np.fmax(lrt, np.nan_to_num(rob, nan=1.0)), 1.0)
    i = int(np.argmin(rule))
    totals = {}
    for t, sc, q, r in zip(c["term"], c["scope"], c["dof"], rob):
        n = totals.setdefault(f"{t}|{'imu' if sc == 'imu' else 'pooled'}|{q}", [0, 0])
        n[0] += 1
        n[1] += int(np.isfinite(r))
    keep = np.flatnonzero((lrt < TAIL) | (np.nan_to_num(rob, nan=1.0) < TAIL))
    out = {k: v for k, v in row.items() if k != "candidates"}
    out.update({"min_lrt_p": float(lrt.min()), "min_robust_p": float(np.nanmin(rob)), "min_rule_p": float(rule[i]),
                "rule_best": f"{c['term'][i]} @ {c['scope'][i]} ({c['imus'][i]} IMUs, {c['dof'][i]} dof)",
                "totals": totals,
                "candidates": {k: [_short(v[j]) for j in keep] for k, v in c.items()
                               if k in ("term", "scope", "dof", "log_lrt_p", "robust_p")}})
    return out


# ------------------------------------------------------------------------------------------------ analysis

def clopper_pearson(k: int, n: int, level: float = 0.95) -> tuple[float, float]:
    from benchmarks.discovery_generalisation import clopper_pearson as exact

    return exact(k, n, level)


def _short(x):
    """A float to 5 significant digits (the .json's size; the levels compared with are decades apart)."""
    return float(f"{x:.5g}") if isinstance(x, float) else x


GROUPS = (("by_term", "term"), ("by_array", "array"), ("by_session", "session"), ("by_scope", "scope"),
          ("by_dof", "dof"))


def _table(rows) -> dict:
    """Flat arrays of the kept candidates (a p-value below TAIL) of every recording."""
    cols = {k: [] for k in ("term", "scope", "array", "session", "dof", "lrt_p", "robust_p")}
    for r in rows:
        c = r["candidates"]
        n = len(c["term"])
        cols["term"] += c["term"]
        cols["scope"] += ["imu" if s == "imu" else "pooled" for s in c["scope"]]
        cols["array"] += [r["array"]] * n
        cols["session"] += [_session(r)] * n
        cols["dof"] += c["dof"]
        cols["lrt_p"] += list(np.exp(c["log_lrt_p"]))
        cols["robust_p"] += [np.nan if p is None else p for p in c["robust_p"]]
    return {k: np.asarray(v) for k, v in cols.items()}


def _session(r: dict) -> str:
    return "rests+twist" if r["still_poses"] else "twist"


def _counts(rows) -> list[dict]:
    """Every recording's candidate counts: [{term, scope, dof, array, session, lrt_p: n, robust_p: n}]."""
    out = []
    for r in rows:
        for key, (n, n_rob) in r["totals"].items():
            t, sc, q = key.split("|")
            out.append({"term": t, "scope": sc, "dof": int(q), "array": r["array"], "session": _session(r),
                        "lrt_p": n, "robust_p": n_rob})
    return out


def _fractions(p: np.ndarray, n: int) -> list[dict]:
    """Fractions of n p-values below each level, from those below TAIL (p)."""
    p = p[np.isfinite(p)]
    out = []
    for lv in LEVELS:
        k = int((p < lv).sum())
        lo, hi = clopper_pearson(k, n)
        out.append({"level": lv, "k": k, "n": int(n), "fraction": k / n if n else float("nan"),
                    "ci": [lo, hi], "ratio": (k / n) / lv if n else float("nan")})
    return out


def summarise(rows) -> dict:
    t, counts = _table(rows), _counts(rows)
    out = {"overall": {}, **{key: {} for key, _ in GROUPS}}
    for test in ("lrt_p", "robust_p"):
        out["overall"][test] = _fractions(t[test], sum(c[test] for c in counts))
        for key, col in GROUPS:
            for v in sorted({c[col] for c in counts}):
                n = sum(c[test] for c in counts if c[col] == v)
                out[key].setdefault(str(v), {})[test] = _fractions(t[test][t[col] == v], n)
    per = [{"index": r["index"], "array": r["array"], "m": r["m"], "share": r["share"], "session": _session(r),
            "min_lrt_p_m": r["min_lrt_p"] * r["m"] / r["share"],
            "min_robust_p_m": r["min_robust_p"] * r["m"] / r["share"],
            "min_pass_p_m": r["min_rule_p"] * r["m"] / r["share"], "best": r["rule_best"]} for r in rows]
    groups = {"all": per, **{s: [x for x in per if x["session"] == s] for s in ("rests+twist", "twist")},
              **{a: [x for x in per if x["array"] == a] for a in ("planar4", "corners8", "grid32")}}
    rec = {}
    for name, key in (("score test alone", "min_lrt_p_m"), ("robust test alone", "min_robust_p_m"),
                      ("step-1 rule (both tests + held-out gain > 0)", "min_pass_p_m")):
        for g, sub in groups.items():
            rec.setdefault(name, {})[g] = {str(a): {"k": sum(x[key] < a for x in sub), "n": len(sub),
                                                    "ci": clopper_pearson(sum(x[key] < a for x in sub), len(sub))}
                                           for a in ALPHAS}
    out["per_recording"], out["recording_rates"] = per, rec
    return out


# ------------------------------------------------------------------------------------------------ report

def _cell(f: dict) -> str:
    return f"{f['k']}/{f['n']} = {f['fraction']:.3g} [{f['ci'][0]:.3g}, {f['ci'][1]:.3g}]"


def _rows_md(groups: dict, test: str) -> list[str]:
    lines = ["| group | " + " | ".join(f"p < {lv:g}" for lv in LEVELS) + " | ratio at 1e-3 |",
             "|---|" + "---|" * (len(LEVELS) + 1)]
    for name, g in groups.items():
        fr = g[test]
        lines.append(f"| {name} | " + " | ".join(_cell(f) for f in fr) + f" | {fr[2]['ratio']:.2f} |")
    return lines


def render(res: dict, out: Path) -> None:
    rows = res["rows"] = [r if "totals" in r else compact(r) for r in res["rows"]]  # a .json of every candidate
    s = summarise(rows)
    res["summary"] = {k: v for k, v in s.items() if k != "per_recording"}
    arrays = {a: sum(r["array"] == a for r in rows) for a in ("planar4", "corners8", "grid32")}
    lines = [res["header"].rstrip(), "",
             f"{len(rows)} null recordings of seed {res['settings']['seed']} "
             f"({', '.join(f'{a}: {n}' for a, n in arrays.items())}), "
             f"{sum(r['m'] for r in rows)} candidates; wall {res['total_wall_seconds']:.0f} s; "
             f"load average at the end {res['load_average_end']}; sample clocks kept by the timing stage on "
             f"{sum(r['timing_kept_clock'] for r in rows)} recordings; searched on a subsample first on "
             f"{sum(r['rungs'] > 1 for r in rows)}.", "",
             "## Per recording: step 1's false-finding rate", "",
             "min p x m over the recording's m candidates (divided by the rung's alpha share when searched on a "
             "subsample) below alpha: a false finding at step 1 by that test (Bonferroni).  Clopper-Pearson 95 %.", "",
             "| test | " + " | ".join(f"alpha = {a:g}" for a in ALPHAS) + " |", "|---|" + "---|" * len(ALPHAS)]
    for name, by in s["recording_rates"].items():
        for g, r in by.items():
            lines.append(f"| {name}, {g} | " + " | ".join(
                f"{r[str(a)]['k']}/{r[str(a)]['n']} [{r[str(a)]['ci'][0]:.3g}, {r[str(a)]['ci'][1]:.3g}]"
                for a in ALPHAS) + " |")
    worst = sorted(s["per_recording"], key=lambda x: x["min_pass_p_m"])[:8]
    lines += ["", "Smallest step-1 rule figures (min over candidates passing the held-out check of max(p_score, "
              "p_robust) x m):", "", "| recording | array | m | min p_score x m | min p_robust x m | rule x m | "
              "best |", "|---|---|---|---|---|---|---|"]
    lines += [f"| {w['index']} | {w['array']} | {w['m']} | {w['min_lrt_p_m']:.3g} | {w['min_robust_p_m']:.3g} | "
              f"{w['min_pass_p_m']:.3g} | {w['best']} |" for w in worst]
    for test, label in (("lrt_p", "score test (chi-square)"), ("robust_p", "block-robust test (Hotelling F)")):
        lines += ["", f"## Candidates: {label}", "",
                  "Fraction of p-values below each level, k/n = fraction [95 % CI]; *ratio* = fraction / level "
                  "(1 when calibrated).  Candidates of one recording are correlated: the intervals are too narrow.", ""]
        lines += _rows_md({"all": s["overall"]}, test)
        for key in ("by_array", "by_session", "by_scope", "by_dof", "by_term"):
            lines += ["", f"{key.replace('_', ' ')}:", ""] + _rows_md(s[key], test)
    lines += ["", "![QQ](discovery_score_null.png)", ""]
    write_results(out.with_suffix(".md"), "\n".join(lines) + "\n")
    _save(res, out)
    _plot(rows, out.with_suffix(".png"))


def _plot(rows, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    t = _table(rows)
    fig, axes = plt.subplots(1, 3, figsize=(16, 5))
    panels = ((axes[0], "lrt_p", "score test", "array", ("planar4", "corners8", "grid32")),
              (axes[1], "robust_p", "block-robust test", "array", ("planar4", "corners8", "grid32")),
              (axes[2], "robust_p", "block-robust test", "session", ("rests+twist", "twist")))
    counts = _counts(rows)
    for ax, test, label, col, values in panels:
        for v, colour in zip(values + (None,), ("C0", "C1", "C2")[:len(values)] + ("k",)):
            p = t[test] if v is None else t[test][t[col] == v]
            p = np.sort(p[np.isfinite(p) & (p < TAIL)])  # the smallest of n: the upper tail of the plot
            n = sum(c[test] for c in counts if v is None or c[col] == v)
            if not len(p):
                continue
            u = np.arange(1, len(p) + 1) / (n + 1)
            ax.plot(-np.log10(u), -np.log10(np.clip(p, 1e-300, None)), ".", ms=2 if v else 3, color=colour,
                    label=f"{v or 'all'} ({n})")
        hi = -np.log10(1.0 / (sum(c[test] for c in counts) + 1))
        ax.plot([0, hi], [0, hi], "r--", lw=1, label="uniform")
        ax.set_xlabel("-log10 expected p (uniform)")
        ax.set_ylabel("-log10 observed p")
        ax.set_title(f"{label} by {col}: {len(rows)} null recordings", fontsize=10)
        ax.legend(fontsize=8)
    fig.tight_layout()
    tmp = path.with_name(path.stem + ".tmp.png")
    fig.savefig(tmp, dpi=110)
    plt.close(fig)
    tmp.replace(path)


def _save(res: dict, out: Path) -> None:
    from imu_array_ros.util.files import atomic_write_text

    atomic_write_text(out.with_suffix(".json"), json.dumps(res, separators=(",", ":"), default=float) + "\n")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seed", type=int, default=SEED)
    ap.add_argument("--recordings", type=int, default=80, help="null recordings 0 .. N-1 at most")
    ap.add_argument("--minutes", type=float, default=50.0, help="no new recording is started after this")
    ap.add_argument("--out", type=Path, default=OUT)
    ap.add_argument("--render", action="store_true", help="only re-write the .md and .png from the saved .json")
    args = ap.parse_args(argv)
    if args.render:
        render(json.loads(args.out.with_suffix(".json").read_text()), args.out)
        return 0
    from benchmarks.time_aware_sim import library_state

    header = machine_header(TITLE, extra=[
        f"package state: {library_state()}", "one process, 1 BLAS thread",
        f"seed: {args.seed} (fresh: in no benchmarks/results file when this ran)",
        f"load average at the start: {load_average()}"])
    settings = {"seed": args.seed, "recordings": args.recordings, "minutes": args.minutes}
    args.out.parent.mkdir(parents=True, exist_ok=True)
    t0, rows, res = time.perf_counter(), [], None
    for i in range(args.recordings):
        if time.perf_counter() - t0 > 60.0 * args.minutes:
            say(f"time budget spent after {len(rows)} recordings")
            break
        r = run_recording(args.seed, i)
        rows.append(r)
        say(f"{i}: {r['name']}: m {r['m']}, min p_score x m {r['min_lrt_p'] * r['m']:.3g}, "
            f"{r['seconds']:.0f} s")
        res = {"header": header, "settings": settings, "rows": rows, "total_wall_seconds": time.perf_counter() - t0,
               "load_average_end": load_average()}
        _save(res, args.out)  # after every recording: a run cut short keeps what it measured
    if res is not None:
        render(res, args.out)
        say(f"wrote {args.out.with_suffix('.md')}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
