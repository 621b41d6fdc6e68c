"""Does the narrowband line test (``spectra.line_bins``) hold its family-wise level on white residuals?

Each recording: K IMUs (4, 8 or 32, equally likely) x 6 channels of n samples (log-uniform 400-12,000), white
Gaussian noise, optionally (every second recording) made a least-squares residual of 12 smooth regressors per
channel (a cubic and 4 low sinusoids: a fit's leverage, floor (n - 12) / n as ``excess`` reports it).  Relative
PSDs by ``spectra.imu_spectra``, floor as above, then ``line_bins`` (Bonferroni over every bin of every cell at
``LINE_ALPHA`` = 0.01): a recording with any bin flagged is a false line.  Baseline in the same run, on the same
spectra: the limit used before, Welch's equivalent degrees of freedom (chi^2_nu / nu, nu = 2 L / 1.056).

    python -m benchmarks.line_test_null [--seed S] [--recordings 1500]
"""

from __future__ import annotations

from benchmarks.harness import RESULTS, machine_header, say, single_threaded_blas, write_results

single_threaded_blas()

import argparse  # noqa: E402
import json  # noqa: E402
import time  # noqa: E402

import numpy as np  # noqa: E402
from scipy import stats  # noqa: E402

TITLE = "The narrowband line test on white residuals: family-wise false-line rate, saddlepoint vs Welch-dof limit"
OUT = RESULTS / "line_test_null"
#: drawn for this benchmark (not in any benchmarks/results file when it was written)
SEED = 846213


def _residual(rng, n: int, k: int, fit: bool) -> tuple[np.ndarray, float]:
    r = rng.normal(size=(n, k, 6))
    if not fit:
        return r, 1.0
    t = np.linspace(-1.0, 1.0, n)
    x = np.column_stack([t ** j for j in range(4)] + [f(np.pi * m * t) for m in (1, 2) for f in (np.sin, np.cos)]
                        + [np.sin(3 * np.pi * t), np.cos(3 * np.pi * t), np.sin(4 * np.pi * t), np.cos(4 * np.pi * t)])
    q, _ = np.linalg.qr(x)
    flat = r.reshape(n, -1)
    flat -= q @ (q.T @ flat)
    return flat.reshape(n, k, 6), (n - x.shape[1]) / n


def run(seed: int, recordings: int) -> dict:
    from imu_array_ros.discovery.spectra import LINE_ALPHA, imu_spectra, line_bins, welch_dof, welch_segments

    rng = np.random.default_rng(seed)
    rows = []
    t0 = time.time()
    for i in range(recordings):
        k = int(rng.choice([4, 8, 32]))
        n = int(np.exp(rng.uniform(np.log(400), np.log(12000))))
        fit = bool(i % 2)
        r, fl = _residual(rng, n, k, fit)
        _, psd = imu_spectra(r, np.ones(r.shape, dtype=bool), 100.0)
        floor = np.full((k, 6), fl)
        new = bool(line_bins(psd, floor, n).any())
        seg = welch_segments(n)
        nu = welch_dof(seg)
        inner = psd[..., 1:-1]
        old = bool((inner / fl > stats.chi2.isf(LINE_ALPHA / (k * 6 * inner.shape[-1]), nu) / nu).any())
        rows.append({"k": k, "n": n, "segments": seg, "fit": fit, "new": new, "old": old})
        if (i + 1) % 250 == 0:
            say(f"{i + 1}/{recordings} recordings, {time.time() - t0:.0f} s")
    return {"seed": seed, "recordings": recordings, "alpha": LINE_ALPHA, "rows": rows}


def _cp(x: int, n: int) -> str:
    from benchmarks.discovery_generalisation import clopper_pearson

    lo, hi = clopper_pearson(x, n)
    return f"{100 * x / n:.2f} % ({100 * lo:.2f}-{100 * hi:.2f})"


def render(res: dict) -> str:
    rows = res["rows"]
    lines = [f"Seed {res['seed']}, {res['recordings']} recordings, family-wise level {res['alpha']}: fraction of "
             "recordings with any bin flagged (Clopper-Pearson 95 %).", "",
             "| recordings | n | saddlepoint (now) | Welch dof (before) |", "|---|---|---|---|"]
    groups = [("all", lambda r: True), ("white", lambda r: not r["fit"]), ("fit residual", lambda r: r["fit"]),
              ("<= 5 segments", lambda r: r["segments"] <= 5), ("6-20 segments", lambda r: 6 <= r["segments"] <= 20),
              ("> 20 segments", lambda r: r["segments"] > 20)]
    for g in ("4", "8", "32"):
        groups.append((f"{g} IMUs", lambda r, g=g: r["k"] == int(g)))
    for name, sel in groups:
        s = [r for r in rows if sel(r)]
        if s:
            lines.append(f"| {name} | {len(s)} | {_cp(sum(r['new'] for r in s), len(s))} | "
                         f"{_cp(sum(r['old'] for r in s), len(s))} |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seed", type=int, default=SEED)
    ap.add_argument("--recordings", type=int, default=1500)
    a = ap.parse_args(argv)
    res = run(a.seed, a.recordings)
    from imu_array_ros.util.files import atomic_write_text

    atomic_write_text(OUT.with_suffix(".json"), json.dumps(res))
    write_results(OUT.with_suffix(".md"), machine_header(TITLE) + render(res))
    say(render(res))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
