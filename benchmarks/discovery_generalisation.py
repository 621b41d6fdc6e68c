"""Discovery on a randomised suite it was never tuned on (issue 23, item 6): power curves and false findings.

Generator: :func:`imu_array_ros.simulation.suites.draw_suite` from ``--seed`` (a fresh seed nobody tuned on):
per class ``--per-class`` scenarios, random array (4 planar, 8 corner, 32), rate (62.5-1000 Hz), session
(icosahedron rests + twisting, or twisting only; tens of seconds), placement and scope; effect classes single,
shared (every IMU one value), group, pair (strong + weak partner), drift (slow drift or constant bias),
both (a constant bias and a drift of the same sensor of one IMU: the harder one's evidence bins it),
vibration (out-of-library board mode growing with distance from the centre), and ``--nulls`` null recordings.
``--unseen``: every scenario on an array and at a rate the suite never draws (5-16 IMUs at random 3D positions
and orientations, 80-400 Hz): what a suite made elsewhere may use.
Every effect is sized by oracle evidence (2 delta log-likelihood of the true effect's refit along its true
shape after motion absorption; target log-uniform in ``--evidence``) and binned by its realised evidence on the
noisy recording (a pair: its weak partner's; both: the smaller).  Every recording is analysed with the nominal model by
:func:`imu_array_ros.discovery.discover.discover` with its defaults except the held-out refit of the findings
(``heldout=False``, a report figure that does not change the findings).

Scored (:func:`imu_array_ros.simulation.suites.score`): correct = exactly the injected terms, each on exactly
its IMUs (per-IMU findings or one finding at the shared/group scope), nothing else; vibration: located (an
unexplained entry holding its frequency and a largest-amplitude IMU, several when the shape ties) and no finding
at all; null: no finding.  In every class a sample clock the discovery keeps is a false finding (the recordings have
exact stamps; counted since c945c07, before which the scorer ignored the timing stage).
Detection probability per class and evidence bin with Clopper-Pearson 95 % intervals.

Runs in a pool of ``--workers`` processes, one BLAS thread each.  Writes
benchmarks/results/discovery_generalisation.md, .json and .png (``--render``: only re-write .md/.png from the
.json).  ``--quick``: 1 scenario per class and 3 nulls, written to /tmp (a smoke run).

    python -m benchmarks.discovery_generalisation [--seed S] [--per-class 10] [--nulls 50] [--workers 2] [--quick]
        [--classes group shared single]
"""

from __future__ import annotations

from benchmarks.harness import RESULTS, load_average, machine_header, say, single_threaded_blas, write_results

single_threaded_blas()

import argparse  # noqa: E402
import json  # noqa: E402
import multiprocessing  # noqa: E402
import os  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from concurrent.futures import ProcessPoolExecutor  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

TITLE = "Discovery on a randomised suite it was never tuned on (issue 23, item 6)"
OUT = RESULTS / "discovery_generalisation"
#: the committed run's seed: drawn at random (secrets.randbelow(10**6)) when the benchmark was written,
#: before any discovery code was scored on it
SEED = 621165
BINS = (0.0, 10.0, 30.0, 100.0, 300.0, 1000.0, np.inf)
LIBRARY = ("single", "shared", "group", "pair", "drift", "both")


def run_job(job: tuple[int, str, int, tuple[float, float], bool]) -> dict:
    from imu_array_ros.discovery.discover import DiscoveryOptions, discover
    from imu_array_ros.simulation.suites import build, draw_scenario, score

    seed, cls, index, evidence, unseen = job
    t0 = time.perf_counter()
    sc = draw_scenario(seed, cls, index, evidence=evidence, unseen=unseen)
    try:
        built = build(sc)
    except ValueError as err:  # UnsizableEffect: reported, not scored
        return {"scenario": sc.name, "class": cls, "error": str(err), "seconds": time.perf_counter() - t0}
    t1 = time.perf_counter()
    try:
        d = discover(built.samples, built.nominal, options=DiscoveryOptions(heldout=False))
    except Exception as err:  # noqa: BLE001 -- a crash of discovery is a result too (scored wrong)
        say(f"discover failed on {sc.name}: {type(err).__name__}: {err}")
        return {"scenario": sc.name, "class": cls, "error": f"discover failed: {type(err).__name__}: {err}",
                "seconds": time.perf_counter() - t0}
    r = score(built, d)
    r.update(index=index, build_seconds=t1 - t0, discover_seconds=time.perf_counter() - t1,
             seconds=time.perf_counter() - t0, samples=int(len(built.samples.stamps)))
    say(f"{r['seconds']:6.1f} s  {'ok ' if r['correct'] else 'BAD'}  {sc.name}  evidence "
        f"{', '.join(f'{e:.0f}' for e in r['evidence']) or '—'}  found {r['found']}")
    return r


def clopper_pearson(k: int, n: int, level: float = 0.95) -> tuple[float, float]:
    """Exact binomial interval of k successes in n trials."""
    import scipy.stats

    if n == 0:
        return float("nan"), float("nan")
    a = 1.0 - level
    lo = 0.0 if k == 0 else float(scipy.stats.beta.ppf(a / 2, k, n - k + 1))
    hi = 1.0 if k == n else float(scipy.stats.beta.ppf(1 - a / 2, k + 1, n - k))
    return lo, hi


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seed", type=int, default=SEED)
    ap.add_argument("--per-class", type=int, default=10, help="scenarios per effect class")
    ap.add_argument("--nulls", type=int, default=50)
    ap.add_argument("--evidence", type=float, nargs=2, default=(10.0, 1000.0), metavar=("LO", "HI"),
                    help="range of the target oracle evidence (log-uniform)")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--classes", nargs="+", default=None, metavar="CLASS",
                    help="effect classes to draw (default every class but null; the nulls: --nulls)")
    ap.add_argument("--unseen", action="store_true",
                    help="arrays and rates the suite never draws: 5-16 IMUs at random 3D positions and orientations, "
                         "80-400 Hz (simulation.suites.UNSEEN_RATES)")
    ap.add_argument("--quick", action="store_true", help="1 per class, 3 nulls, written to /tmp")
    ap.add_argument("--out", type=Path, default=OUT)
    ap.add_argument("--render", action="store_true", help="only re-write the .md and .png from the saved .json")
    ap.add_argument("--baseline", type=Path, default=None, metavar="JSON",
                    help="a run of the same suite (same seed and settings) by other code: the .md compares the two")
    args = ap.parse_args(argv)
    if args.render:
        render(json.loads(args.out.with_suffix(".json").read_text()), args.out, _baseline(args.baseline))
        return 0
    if args.quick:
        args.per_class, args.nulls = 1, 3
        if args.out == OUT:
            args.out = Path("/tmp") / "discovery_generalisation_quick"
    from benchmarks.time_aware_sim import import_package, library_state
    from imu_array_ros.simulation.suites import CLASSES

    classes = tuple(CLASSES[:-1]) if args.classes is None else tuple(dict.fromkeys(args.classes))
    unknown = [c for c in classes if c not in CLASSES[:-1]]
    if unknown:
        print(f"discovery_generalisation: unknown class {unknown[0]!r} (known: {', '.join(CLASSES[:-1])}; "
              f"the nulls: --nulls)", file=sys.stderr)
        return 2
    args.classes = list(classes)
    import_package()
    header = machine_header(TITLE, extra=[
        f"package state: {library_state()}",
        f"workers: {args.workers} processes (forked after the package was imported), 1 BLAS thread each "
        f"(OMP_NUM_THREADS={os.environ.get('OMP_NUM_THREADS')})",
        f"seed: {args.seed} (drawn at random for this benchmark; no discovery code was tuned on it)",
        f"load average at the start: {load_average()}"])
    ev = tuple(args.evidence)
    # index-major, the nulls spread through: a run stopped early (--render) still covers every class evenly
    jobs = [(args.seed, c, i, ev, args.unseen) for i in range(args.per_class) for c in classes]
    step = max(1, len(jobs) // max(args.nulls, 1))
    for i in range(args.nulls):
        jobs.insert(min(len(jobs), (i + 1) * (step + 1) - 1), (args.seed, "null", i, ev, args.unseen))
    settings = {k: (list(v) if isinstance(v, tuple) else v) for k, v in vars(args).items()
                if k not in ("out", "render", "baseline")}
    args.out.parent.mkdir(parents=True, exist_ok=True)
    t0, rows = time.perf_counter(), []
    with ProcessPoolExecutor(max_workers=args.workers, mp_context=multiprocessing.get_context("fork")) as pool:
        for r in pool.map(run_job, jobs):
            rows.append(r)
            res = {"header": header, "settings": settings, "rows": rows, "jobs_total": len(jobs),
                   "total_wall_seconds": time.perf_counter() - t0, "load_average_end": load_average()}
            _save(res, args.out)  # after every job: a run cut short keeps what it measured
    render(res, args.out, _baseline(args.baseline))
    say(f"wrote {args.out.with_suffix('.md')}")
    return 0


def _save(res: dict, out: Path) -> None:
    from imu_array_ros.util.files import atomic_write_text

    atomic_write_text(out.with_suffix(".json"), json.dumps(res, indent=1, default=_jsonable) + "\n")


def _jsonable(x):
    if isinstance(x, (np.floating, np.integer, np.bool_)):
        return x.item()
    raise TypeError(type(x).__name__)


# --------------------------------------------------------------------------------------------- the report

def _rate(rows, key="correct") -> str:
    n, k = len(rows), sum(bool(r[key]) for r in rows)
    if not n:
        return "—"
    lo, hi = clopper_pearson(k, n)
    return f"{k}/{n} ({100 * k / n:.0f} %, 95 % CI {100 * lo:.0f}-{100 * hi:.0f} %)"


def _named(rows) -> str:
    """How many of ``rows`` were wrong with the truth among the alternatives discovery named indistinguishable."""
    return str(sum(bool(r.get("named_alternative")) for r in rows)) if rows else "—"


def _bin_label(i: int) -> str:
    lo, hi = BINS[i], BINS[i + 1]
    return f">= {lo:g}" if not np.isfinite(hi) else f"{lo:g}-{hi:g}"


def _baseline(path: Path | None) -> dict | None:
    if path is None:
        return None
    try:
        return json.loads(Path(path).read_text())
    except (OSError, ValueError) as err:
        raise SystemExit(f"discovery_generalisation: --baseline {path}: {err}") from None


def _comparison(res: dict, base: dict) -> str:
    """Per class, the correct rate of this run against the baseline run of the same scenarios."""
    def key(r):
        return r["scenario"]
    rows = {key(r): r for r in res["rows"] if "error" not in r}
    brows = {key(r): r for r in base["rows"] if "error" not in r}
    both = sorted(set(rows) & set(brows), key=lambda k: list(rows).index(k))
    bs = base["settings"]
    def fact(name):
        line = [x for x in base["header"].splitlines() if x.startswith(f"- {name}: ")]
        return line[0].split(": ", 1)[1] if line else "?"
    text = (f"## Against the baseline\n\nBaseline: {fact('command')} at {fact('commit')}, package state "
            f"{fact('package state')}, seed {bs.get('seed')}; {len(both)} scenarios scored in both runs.\n\n")
    if bs.get("seed") != res["settings"].get("seed"):
        text += "**The baseline ran another seed: the rates do not compare scenario by scenario.**\n\n"
    text += ("| class | baseline correct | correct | ratio | baseline at >= 100 | at >= 100 | ratio | wrong, truth "
             "named indistinguishable: baseline / this run |\n|---|---|---|---|---|---|---|---|\n")
    from imu_array_ros.simulation.suites import CLASSES

    def rate(rs):
        k = sum(bool(r["correct"]) for r in rs)
        return k, len(rs)

    def ratio(a, b):
        return f"{(a[0] / a[1]) / (b[0] / b[1]):.2f}" if a[1] and b[1] and b[0] else "—"
    for c in CLASSES:
        sel = [k for k in both if rows[k]["class"] == c]
        if not sel:
            continue
        strong = [k for k in sel if c != "null" and (rows[k]["power_evidence"] or 0) >= 100]
        b, a = rate([brows[k] for k in sel]), rate([rows[k] for k in sel])
        bs_, as_ = rate([brows[k] for k in strong]), rate([rows[k] for k in strong])
        text += (f"| {c} | {b[0]}/{b[1]} | {a[0]}/{a[1]} | {ratio(a, b)} | "
                 + (f"{bs_[0]}/{bs_[1]} | {as_[0]}/{as_[1]} | {ratio(as_, bs_)} |" if strong else "— | — | — |")
                 + f" {_named([brows[k] for k in sel])} / {_named([rows[k] for k in sel])} |\n")
    changed = [k for k in both if bool(rows[k]["correct"]) != bool(brows[k]["correct"])
               or rows[k]["found"] != brows[k]["found"]
               or bool(rows[k].get("named_alternative")) != bool(brows[k].get("named_alternative"))]

    def verdict(r):
        return "correct" if r["correct"] else ("wrong, truth named indistinguishable" if r.get("named_alternative")
                                               else "wrong")
    if changed:
        text += "\nScenarios whose findings changed (baseline → this run):\n\n"
        for k in changed:
            text += (f"- {k.replace('|', '/')}: {', '.join(brows[k]['found']) or '—'} "
                     f"({verdict(brows[k])}) → {', '.join(rows[k]['found']) or '—'} ({verdict(rows[k])})\n")
    return text + "\n"


def render(res: dict, out: Path, base: dict | None = None) -> None:
    rows = [r for r in res["rows"] if "error" not in r]
    errors = [r for r in res["rows"] if "error" in r]
    s = res["settings"]
    text = res["header"]
    text += __doc__.split("\n\n", 1)[1].rsplit("\n\n", 2)[0] + "\n\n"
    done, total = len(res["rows"]), res.get("jobs_total", len(res["rows"]))
    text += (f"Total wall time {res['total_wall_seconds']:.0f} s on {s['workers']} workers "
             f"({sum(r['seconds'] for r in res['rows']):.0f} s of jobs; load average at the end "
             f"{res.get('load_average_end', 'unknown')}); {s['per_class']} scenarios per class, {s['nulls']} nulls, "
             f"target evidence {s['evidence'][0]:g}-{s['evidence'][1]:g}."
             + (f" **The run was stopped after {done} of its {total} jobs** (jobs run class by class, index by "
                f"index, the nulls between them, so every class is covered alike)." if done < total else "")
             + "\n\n")
    from imu_array_ros.simulation.suites import CLASSES

    classes = [c for c in CLASSES if any(r["class"] == c for r in rows)]
    text += ("## Summary\n\n| class | correct, all | correct at realised evidence >= 100 | wrong, truth named "
             "indistinguishable (all / >= 100; not counted correct) | target |\n|---|---|---|---|---|\n")
    for c in classes:
        rc = [r for r in rows if r["class"] == c]
        strong = [r for r in rc if r["power_evidence"] is not None and r["power_evidence"] >= 100]
        target = "0 false findings" if c == "null" else ">= 95 % at >= 100"
        text += (f"| {c} | {_rate(rc)} | {_rate(strong) if c != 'null' else '—'} | "
                 f"{_named(rc)} / {_named(strong)} | {target} |\n")
    lib = [r for r in rows if r["class"] in LIBRARY and r["power_evidence"] >= 100]
    text += (f"| all library classes | {_rate([r for r in rows if r['class'] in LIBRARY])} | {_rate(lib)} | "
             f"{_named([r for r in rows if r['class'] in LIBRARY])} / {_named(lib)} | |\n")
    nulls = [r for r in rows if r["class"] == "null"]
    if nulls:
        k = sum(bool(r["found"]) for r in nulls)
        lo, hi = clopper_pearson(k, len(nulls))
        text += (f"\nNull recordings with a false finding: **{k}/{len(nulls)}** (95 % CI {100 * lo:.0f}-"
                 f"{100 * hi:.0f} %); with an unexplained entry: {sum(r['unexplained_entries'] > 0 for r in nulls)}"
                 f"/{len(nulls)}.\n")
    pairs = [r for r in rows if r["class"] == "pair"]
    if pairs:
        text += (f"Pairs: strong partner found on its IMU {sum(r['detected'][0] for r in pairs)}/{len(pairs)}, "
                 f"weak partner {sum(r['detected'][1] for r in pairs)}/{len(pairs)}.\n")
    named = [r for r in rows if r.get("named_alternative")]
    text += (f"Wrong answers whose finding discovery itself named indistinguishable from the truth (an "
             f"'indistinguishable' entry whose alternative, taken instead of the finding, is exactly the truth: a tie "
             f"of exact gains within ln(1/alpha), or a narrowed scope's set that fits as well up to the gauge; a "
             f"report of 'this or that' has not found which, so these are counted wrong above): {len(named)}"
             + (f" ({', '.join(r['scenario'].split(':')[0] for r in named)})" if named else "") + ".\n")
    z = [v for r in rows for v in r["max_abs_z"].values() if v is not None]
    if z:
        text += f"Magnitudes of findings on injected (term, IMU): {sum(v <= 3 for v in z)}/{len(z)} within 3 sigma.\n"
    if errors:
        text += (f"Not scored (no visible draw, or discovery raised): {len(errors)}: "
                 + "; ".join(f"{r['scenario']} ({r['error']})" for r in errors) + "\n")
    if base is not None:
        text += "\n" + _comparison(res, base)
    text += "\n## Power curves (correct vs realised oracle evidence)\n\n![power](" + out.with_suffix(".png").name + ")\n\n"
    text += "| class | " + " | ".join(_bin_label(i) for i in range(len(BINS) - 1)) + " |\n"
    text += "|---" * len(BINS) + "|\n"
    for c in classes:
        if c == "null":
            continue
        rc = [r for r in rows if r["class"] == c]
        cells = []
        for i in range(len(BINS) - 1):
            b = [r for r in rc if BINS[i] <= r["power_evidence"] < BINS[i + 1]]
            cells.append(f"{sum(r['correct'] for r in b)}/{len(b)}" if b else "—")
        text += f"| {c} | " + " | ".join(cells) + " |\n"
    text += "\n## Every recording\n\n| scenario | evidence (target / realised) | found | correct | s |\n|---|---|---|---|---|\n"
    for r in rows:
        ev = "; ".join(f"{t:.0f} / {e:.0f}" for t, e in zip(r["evidence_target"], r["evidence"])) or "—"
        found = ", ".join(r["found"]) or "—"
        if r["class"] == "vibration":
            found += "; unexplained: " + ("; ".join(
                f"{', '.join(u['sensors'][:3])}{' ...' if len(u['sensors']) > 3 else ''} {'/'.join(u['axes'])} "
                f"{u['band_hz'][0]:.3g}-{u['band_hz'][1]:.3g} Hz" for u in r["unexplained"]) or "none")
        name = r["scenario"].replace("|", "\\|")
        verdict = "yes" if r["correct"] else ("**no** (truth named indistinguishable)" if r.get("named_alternative")
                                              else "**no**")
        text += (f"| {name} | {ev} | {found} | {verdict} | "
                 f"{r['seconds']:.0f} |\n")
    write_results(out.with_suffix(".md"), text)
    _plot(rows, classes, out.with_suffix(".png"))


def _plot(rows, classes, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from imu_array_ros.util.files import atomic_write_bytes

    fig, ax = plt.subplots(figsize=(8, 5))
    centres = np.sqrt(np.array([3.0, *BINS[1:-1]]) * np.array([*BINS[1:-1], 3000.0]))
    lib = [c for c in classes if c != "null"]
    for j, c in enumerate(lib):
        rc = [r for r in rows if r["class"] == c]
        xs, ps, lo, hi = [], [], [], []
        for i in range(len(BINS) - 1):
            b = [r for r in rc if BINS[i] <= r["power_evidence"] < BINS[i + 1]]
            if not b:
                continue
            k = sum(r["correct"] for r in b)
            a, z = clopper_pearson(k, len(b))
            xs.append(centres[i] * 1.06 ** (j - len(lib) / 2))
            ps.append(k / len(b))
            lo.append(k / len(b) - a)
            hi.append(z - k / len(b))
        ax.errorbar(xs, ps, yerr=[lo, hi], marker="o", capsize=3, label=c)
    ax.set_xscale("log")
    ax.set_xlabel("realised oracle evidence, 2 delta log-likelihood (bins: " +
                  ", ".join(_bin_label(i) for i in range(len(BINS) - 1)) + ")")
    ax.set_ylabel("P(correct)")
    ax.set_ylim(-0.05, 1.05)
    ax.axvline(100.0, color="grey", lw=0.8, ls="--")
    ax.axhline(0.95, color="grey", lw=0.8, ls=":")
    ax.legend(loc="lower right", fontsize=8)
    ax.set_title("discovery: correct vs oracle evidence (95 % Clopper-Pearson)")
    fig.tight_layout()
    import io

    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=110)
    plt.close(fig)
    atomic_write_bytes(path, buf.getvalue())


if __name__ == "__main__":
    sys.exit(main())
