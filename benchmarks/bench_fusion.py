"""Array samples fused per second (32-IMU array), batch vs one sample at a time, IMU dropouts, and memory.

Targets: >= 400,000 array samples/s in batch on one core without dropouts
(issue 2, raised by issue 6); with 2 % random IMU dropouts (each IMU missing
in 2 % of the samples, ~1,000 distinct patterns of valid axes per 20,000
samples) at most 1.5x the time of the same samples without dropouts (issue 6
§5); memory linear in the number of samples.  Runs single-threaded BLAS
(OMP/OPENBLAS threads = 1) so the figures are per core; pin it to one core
with ``taskset -c 0``.  Every figure is the best of ``--repeat`` runs, and every
ratio compares two figures of the same run.  Writes benchmarks/results/fusion.md.

    taskset -c 0 python -m benchmarks.bench_fusion [--samples 200000] [--dropout-samples 20000] [--repeat 7]
                                                   [--reference 5d79859]

``--reference REV`` also times the fusion module of git revision REV (read with
``git show``, with the ``estimation/`` modules it imports at that revision; its
saturation rule shimmed in if the module predates the clip levels) on the same
samples in the same run.
"""

from __future__ import annotations

from benchmarks.harness import REPO, RESULTS, best_of, cpu_affinity, machine_header, single_threaded_blas, write_results

single_threaded_blas()

import argparse  # noqa: E402
import re  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import types  # noqa: E402
import tracemalloc  # noqa: E402

import numpy as np  # noqa: E402

from imu_array_ros.fusion.ml_fusion import MLFusion  # noqa: E402
from imu_array_ros.fusion.tensor_method import tensor_method  # noqa: E402
from imu_array_ros.model.layouts import grid_array32  # noqa: E402
from imu_array_ros.model.linear import LinearArrayModel  # noqa: E402
from imu_array_ros.model.samples import ImuSamples  # noqa: E402
from imu_array_ros.simulation.simulator import simulate_random, simulate_twist  # noqa: E402

DROPOUT_RATE = 0.02


def estimation_module_at(rev: str, name: str) -> types.ModuleType:
    """``imu_array_ros/estimation/<name>.py`` at git revision ``rev`` (read with ``git show``), as a module in memory.

    The ``imu_array_ros.estimation`` modules it imports (the fusion is split over several modules after
    c3a7fd0) are taken from ``rev`` too, each loaded once; everything else from this tree (the linear model
    from its present module, ``model/linear.py``; it was ``model/sensor_model.py`` before issue 20).
    """
    module_name = f"{name}_{re.sub(r'[^0-9A-Za-z_]', '_', rev)}"  # importable by that name
    if module_name in sys.modules:
        return sys.modules[module_name]
    src = subprocess.run(["git", "show", f"{rev}:imu_array_ros/estimation/{name}.py"], cwd=REPO, check=True,
                         capture_output=True, text=True).stdout
    old_import = "from imu_array_ros.model.sensor_model import SATURATION_MARGIN, LinearArrayModel, unsaturated"
    if old_import in src:  # before the clip levels: that version's own rule, |y| >= 0.998 * range
        src = src.replace(old_import, "from imu_array_ros.model.linear import LinearArrayModel\n"
                          "SATURATION_MARGIN = 0.998\n"
                          "def unsaturated(values, limit, margin):\n"
                          "    return np.abs(values) < margin * limit\n")
    src = re.sub(r"^(\s*)from imu_array_ros\.model\.sensor_model import", r"\1from imu_array_ros.model.linear import",
                 src, flags=re.M)
    pattern = r"^(\s*)from imu_array_ros\.estimation\.(\w+) import"
    for dep in sorted(set(m.group(2) for m in re.finditer(pattern, src, flags=re.M))):
        loaded = estimation_module_at(rev, dep)
        src = re.sub(rf"^(\s*)from imu_array_ros\.estimation\.{dep} import", rf"\1from {loaded.__name__} import",
                     src, flags=re.M)
    module = types.ModuleType(module_name)
    sys.modules[module.__name__] = module  # dataclasses look their module up; later imports find it here
    exec(compile(src, f"{rev}:{name}.py", "exec"), module.__dict__)
    return module


def reference_fusion(rev: str):
    """``MLFusion`` of ``imu_array_ros/estimation/ml_fusion.py`` at git revision ``rev`` (:func:`estimation_module_at`)."""
    return estimation_module_at(rev, "ml_fusion").MLFusion


def with_dropouts(s: ImuSamples, rate: float, rng: np.random.Generator) -> tuple[ImuSamples, np.ndarray]:
    """A copy of ``s`` with each IMU missing (accelerometer and gyroscope NaN) in a ``rate`` share of samples."""
    drop = rng.random(s.accel.shape[:2]) < rate
    accel, gyro = s.accel.copy(), s.gyro.copy()
    accel[drop] = np.nan
    gyro[drop] = np.nan
    return ImuSamples(s.stamps, accel, gyro, s.names), drop


def peak_memory(fusion: MLFusion, s: ImuSamples, k: int) -> int:
    tracemalloc.start()
    fusion.fuse(s.select(slice(0, k)))
    _, peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    return peak


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--samples", type=int, default=200_000)
    ap.add_argument("--dropout-samples", type=int, default=20_000)
    ap.add_argument("--repeat", type=int, default=7)
    ap.add_argument("--reference", help="git revision whose fusion module is timed as well")
    ap.add_argument("--out", default=str(RESULTS / "fusion.md"))
    args = ap.parse_args()
    rng = np.random.default_rng(7)
    desc = grid_array32()
    model = LinearArrayModel.from_description(desc)
    fusion = MLFusion(model)
    ref = reference_fusion(args.reference)(model) if args.reference else None
    n, r = args.samples, args.repeat

    # ---------------------------------------------------------------- throughput, tensor method as baseline
    cases = {
        "twisting, 600 deg/s RMS (no saturation)": simulate_twist(desc, n / 1000.0, 1000.0, rng)[0],
        "random, |w| = 1000 deg/s": simulate_random(desc, n, np.deg2rad(1000), np.deg2rad(2000), rng)[0],
        "random, |w| = 3000 deg/s (most gyros saturated)": simulate_random(desc, n, np.deg2rad(3000), np.deg2rad(2000), rng)[0],
    }
    rows = []
    for label, s in cases.items():
        fusion.fuse(s.select(slice(0, 100)))  # warm the geometry cache
        t_batch = best_of(lambda: fusion.fuse(s), r)
        t_tensor = best_of(lambda: tensor_method(s, model), r)  # same-run baseline: closed-form least squares
        m = 2000
        t_one = best_of(lambda: [fusion.fuse(s.select(slice(i, i + 1))) for i in range(m)], 1)
        t_ref = np.nan
        if ref is not None:
            ref.fuse(s.stamps[:100], s.accel[:100], s.gyro[:100])
            t_ref = best_of(lambda: ref.fuse(s.stamps, s.accel, s.gyro), r)
        rows.append((label, n / t_batch, n / t_tensor, t_batch / t_tensor, m / t_one, n / t_ref, t_batch / t_ref))
        print(f"{label}: batch {n / t_batch:,.0f} samples/s (tensor method {n / t_tensor:,.0f}/s, ML/tensor time "
              f"{t_batch / t_tensor:.2f}), one-at-a-time {m / t_one:,.0f} samples/s"
              + (f"; {args.reference}: {n / t_ref:,.0f}/s, time ratio {t_batch / t_ref:.2f}" if ref else ""), flush=True)

    # ---------------------------------------------------------------- IMU dropouts: same samples with and without
    twist = cases["twisting, 600 deg/s RMS (no saturation)"]
    drop_rows = []
    for nd in sorted({args.dropout_samples, n}):
        base = ImuSamples(twist.stamps[:nd], twist.accel[:nd], twist.gyro[:nd], twist.names)
        holes, drop = with_dropouts(base, DROPOUT_RATE, rng)
        fused, stats = fusion.fuse(holes)  # also builds the dropout table
        assert stats.fused == nd
        t_full, t_drop, t_ref = [], [], [np.nan]
        for _ in range(max(r, 15) if nd <= 50_000 else r):  # interleaved, so both see the same machine state
            t_full.append(best_of(lambda: fusion.fuse(base), 1))
            t_drop.append(best_of(lambda: fusion.fuse(holes), 1))
        if ref is not None and nd == args.dropout_samples:
            ref.fuse(holes.stamps, holes.accel, holes.gyro)  # warm its per-pattern cache, as above
            t_ref = [best_of(lambda: ref.fuse(holes.stamps, holes.accel, holes.gyro), 1) for _ in range(r)]
        tf, td, tr = min(t_full), min(t_drop), min(t_ref)
        share = float(np.mean(drop.any(axis=1)))
        drop_rows.append((nd, stats.patterns, share, nd / tf, nd / td, td / tf, nd / tr))
        print(f"N={nd}, {100 * DROPOUT_RATE:.0f} % IMU dropouts ({stats.patterns} patterns, {100 * share:.0f} % of samples "
              f"incomplete): {nd / td:,.0f} samples/s vs {nd / tf:,.0f} without, time ratio {td / tf:.2f}"
              + (f"; {args.reference}: {nd / tr:,.0f}/s" if np.isfinite(tr) else ""), flush=True)

    # ---------------------------------------------------------------- memory
    mem_rows = []
    holes_n, _ = with_dropouts(twist, DROPOUT_RATE, rng)
    for k in (n // 4, n // 2, n):
        p_full, p_drop = peak_memory(fusion, twist, k), peak_memory(fusion, holes_n, k)
        mem_rows.append((k, p_full, p_drop))
        print(f"N={k}: peak {p_full / 1e6:.1f} MB ({p_full / k:.0f} B/sample), with dropouts {p_drop / 1e6:.1f} MB "
              f"({p_drop / k:.0f} B/sample)", flush=True)

    text = machine_header("Fusion throughput, 32-IMU array")
    cpus = cpu_affinity()
    text += (f"Single core: BLAS threads = 1, CPU affinity {cpus} (`taskset -c 0`); best of {r} runs; one-at-a-time = "
             "2,000 calls of `MLFusion.fuse` with one sample.\n\n")
    text += ("Same-run baseline: the tensor method (skog2016 appendix, one closed-form least-squares solve per "
             "batch) on the same samples; the ratio is the machine-independent figure.\n\n")
    if ref is not None:
        text += (f"`{args.reference}`: `MLFusion` of `imu_array_ros/estimation/ml_fusion.py` at git revision "
                 f"{args.reference} (read with `git show`), timed on the same samples in the same run; before the "
                 "clip levels it is given its own saturation rule (|y| >= 0.998 range).\n\n")
    text += ("| case | ML batch (array samples/s) | tensor method (samples/s) | ML time / tensor time "
             "| ML, one sample per call (samples/s) |" + (f" {args.reference} (samples/s) | time / {args.reference} time |"
                                                          if ref else "") + "\n|---|---|---|---|---|" + ("---|---|" if ref else "") + "\n")
    text += "".join(f"| {a} | {b:,.0f} | {c:,.0f} | {d:.2f} | {e:,.0f} |" + (f" {f:,.0f} | {g:.2f} |" if ref else "") + "\n"
                    for a, b, c, d, e, f, g in rows)
    text += "\nTarget: >= 400,000 array samples/s in batch without dropouts.\n\n"
    text += (f"IMU dropouts: the twisting samples with each IMU missing (accelerometer and gyroscope NaN) in "
             f"{100 * DROPOUT_RATE:.0f} % of the samples, timed interleaved with the same samples complete (best of "
             f"{max(r, 15)} each up to 50,000 samples, else of {r}).\n\n")
    text += ("| N | distinct patterns | incomplete samples | without dropouts (samples/s) | with dropouts (samples/s) "
             "| time ratio |" + (f" {args.reference}, with dropouts (samples/s) |" if ref else "")
             + "\n|---|---|---|---|---|---|" + ("---|" if ref else "") + "\n")
    text += "".join(f"| {a} | {b} | {100 * c:.0f} % | {d:,.0f} | {e:,.0f} | {f:.2f} |"
                    + ((f" {g:,.0f} |" if np.isfinite(g) else " - |") if ref else "") + "\n"
                    for a, b, c, d, e, f, g in drop_rows)
    text += "\nTarget: time ratio <= 1.5.\n\n"
    text += "Peak memory allocated by one `fuse` call (tracemalloc; the (N, 32, 3) inputs are not counted):\n\n"
    text += ("| N | peak MB | bytes per sample | with dropouts: peak MB | bytes per sample |\n"
             "|---|---|---|---|---|\n")
    text += "".join(f"| {k} | {p / 1e6:.1f} | {p / k:.0f} | {q / 1e6:.1f} | {q / k:.0f} |\n" for k, p, q in mem_rows)
    (k0, p0, q0), (k1, p1, q1) = mem_rows[0], mem_rows[-1]
    text += (f"\nFrom N = {k0} to {k1} the peak grows by {(p1 - p0) / (k1 - k0):.0f} bytes per added sample without "
             f"dropouts and by {(q1 - q0) / (k1 - k0):.0f} with them (the solver works in chunks of samples: a fixed "
             "part comes on top).\n")
    print(f"wrote {write_results(args.out, text)}")


if __name__ == "__main__":
    main()
