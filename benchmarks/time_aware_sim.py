"""Time-aware arrays on simulated data (issue 21, the simulated targets): every reading at its true sample time.

Three measurements, every recording drawn from seeds of this run only (``--seed``; nothing here was tuned on
them), every reading sampled from the exact motion at its true sample time (not the first-order expansion the
model uses):

1. **MIMU-like array** (``config/mimu4444bt_corners.yaml``, 8 corner IMUs, 62.5 Hz;
   :func:`~imu_array_ros.simulation.clocks.mimu_like_clocks`: chip clocks of 1 ms at +-3000 ppm, random phases,
   accelerometers 1.6 ms behind their gyroscopes).  Per pair of recordings of the same chips:
   a *calibration recording* (20 icosahedron poses, then hand twisting; see :class:`DenseMotion`) and a
   *fused recording* (hand twisting, :func:`~imu_array_ros.simulation.simulator.simulate_trajectory`) with new
   phases (:func:`~imu_array_ros.simulation.clocks.new_session`).  The fused recording's angular-velocity RMS
   error is divided by that of the same motion and noise sampled synchronously (the same array without timing
   terms): (a) time-unaware fusion with the nominal description; (b) ``calibrate all`` without timing, then
   fusion; (c) ``calibrate all`` with timing (``clock_period`` 1 ms), its description written and read back
   (session states dropped), then :func:`imu_array_ros.workflows.fuse` (which estimates the session phases);
   and, to locate a failure, (b') and (c') = (b) and (c) with the truth's gyroscope gains and misalignments,
   (c'') = (c) moved along its gauge freedoms to the reference IMU's nominal values (:func:`in_gauge`), (d) the
   true device constants with the session estimated by ``fuse`` and (e) the true device constants and true
   session states; each also *aligned* (after the one time shift of the truth that fits best: a delay common
   to every sensor is not observable).  Target: (c) <= 1.5.
2. **Monte Carlo** of the time-aware fusion with the true description and true session states (new chips,
   phases, motion and noise every run): RMSE / sqrt(mean CRB) per fused component (the CRB: the covariance the
   fusion publishes) and the NEES; the same for the synchronous array beside it.  Target 1.0-1.2.
3. **Independent stamps** (:func:`~imu_array_ros.simulation.clocks.simulate_own_clocks`: 8 IMUs at 200 Hz on
   own clocks, +-200 ppm, offsets up to +-2 ms, 50 us jitter), paired with
   :func:`~imu_array_ros.io.pairing.pair_streams` and fused by :func:`imu_array_ros.workflows.fuse`: omega RMS
   error vs a synchronous oracle (every IMU sampled at the reference's true sample times), the grid samples
   fused (no gaps), and the estimated stamp-clock offsets and skews vs the truth.  Target <= 1.5.

Runs the jobs in a pool of ``--workers`` processes, one BLAS thread each.  Writes
benchmarks/results/time_aware_sim.md, .json and .png (``--render``: only re-write the .md/.png from the .json).

    python -m benchmarks.time_aware_sim [--pairs 5] [--mc-runs 20] [--own-runs 5] [--workers 2] [--seed 21021]
"""

from __future__ import annotations

from benchmarks.harness import REPO, RESULTS, load_average, machine_header, say, single_threaded_blas, write_results

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

TITLE = "Time-aware arrays on simulated data (issue 21)"
CORNERS = REPO / "config" / "mimu4444bt_corners.yaml"
OUT = RESULTS / "time_aware_sim"
RATE_HZ = 62.5
START_NS = 10**9
DENSE_HZ = 1000.0  # the calibration recording's motion is simulated at this rate and interpolated (DenseMotion)


# --------------------------------------------------------------------------------------------- helpers

def rng_of(seed: int, part: int, run: int, use: int) -> np.random.Generator:
    """One independent stream per (run seed, part of the benchmark, run, use)."""
    return np.random.default_rng([int(seed), part, run, use])


def nominal_model():
    from imu_array_ros.model.description import load_description
    from imu_array_ros.model.sensor_model import SensorModel

    desc = load_description(CORNERS)
    return desc, SensorModel.from_description(desc)


def rms_omega(fused, truth) -> float:
    """RMS over samples and axes of the fused angular velocity minus the truth at the fused stamps."""
    idx = np.searchsorted(truth.stamps, fused.stamps)
    if not np.array_equal(truth.stamps[idx], fused.stamps):
        raise RuntimeError("fused stamps not in the truth")
    return float(np.sqrt(np.mean((fused.omega - truth.omega[idx]) ** 2)))


def common_delay(fused, twist, origin_ns: int, iterations: int = 4) -> tuple[float, float]:
    """(delta s, RMS error after it): the one time shift of the truth, omega(t + delta), that fits the fused
    angular velocity best (least squares, Gauss-Newton on the analytic omega of the twist).  A delay common to
    every sensor is not observable from inertial data: it is what the description's gauge puts at the stamp."""
    t = (fused.stamps - origin_ns) * 1e-9
    delta = 0.0
    for _ in range(iterations):
        r = fused.omega - twist.omega(t + delta)
        j = twist.omega_dot(t + delta)
        delta += float(np.sum(j * r) / np.sum(j * j))
    return delta, float(np.sqrt(np.mean((fused.omega - twist.omega(t + delta)) ** 2)))


class DenseMotion:
    """The motion of a calibration recording as a function of int64 ns time (``MotionContext.trajectory``):
    :func:`~imu_array_ros.simulation.icosahedron.simulate_icosahedron`'s exact motion (20 rests, minimum-jerk
    transitions, faded-in hand twisting) on a 1 kHz grid, between the grid points omega by cubic Hermite
    interpolation through omega and omega_dot, omega_dot and the specific force by cubic splines (errors
    measured against a 2 kHz simulation: :func:`interpolation_check`).  Every reading is then the motion at its
    true sample time, as ``simulate_trajectory`` gives for pure twisting."""

    def __init__(self, dense) -> None:
        from scipy.interpolate import CubicHermiteSpline, CubicSpline

        t = (dense.stamps - dense.stamps[0]) * 1e-9
        self.origin = int(dense.stamps[0])
        self.omega = CubicHermiteSpline(t, dense.omega, dense.omega_dot, axis=0)
        self.omega_dot = CubicSpline(t, dense.omega_dot, axis=0)
        self.specific_force = CubicSpline(t, dense.specific_force, axis=0)

    def __call__(self, stamps_ns):
        t = (np.asarray(stamps_ns, dtype=np.int64) - self.origin) * 1e-9
        return self.omega(t), self.omega_dot(t), self.specific_force(t)


def dense_icosahedron(seed: int, run: int, still_s: float, transition_s: float, twist_s: float, rate_hz: float):
    from imu_array_ros.simulation.icosahedron import simulate_icosahedron

    _, nominal = nominal_model()
    _, dense, info = simulate_icosahedron(nominal, rng_of(seed, 1, run, 1), rate_hz=rate_hz, still_s=still_s,
                                          transition_s=transition_s, twist_s=twist_s, start_ns=START_NS)
    return dense, info


def calibration_recording(session, seed: int, run: int, still_s: float, transition_s: float, twist_s: float):
    """Still poses then twisting measured by ``session`` at 62.5 Hz, each reading at its true sample time."""
    from imu_array_ros.model.samples import MotionTruth
    from imu_array_ros.simulation.simulator import simulate_measurements

    dense, info = dense_icosahedron(seed, run, still_s, transition_s, twist_s, DENSE_HZ)
    step = int(round(DENSE_HZ / RATE_HZ))  # 16: the 62.5 Hz stamps are every 16th 1 kHz stamp
    idx = np.arange(0, len(dense.stamps), step)
    truth = MotionTruth(dense.stamps[idx], dense.omega[idx], dense.omega_dot[idx], dense.specific_force[idx],
                        dense.attitude[idx])
    samples = simulate_measurements(session, truth, rng_of(seed, 1, run, 2), trajectory=DenseMotion(dense))
    twist_start = int(np.searchsorted(truth.stamps, dense.stamps[min(info.twist_start, len(dense.stamps) - 1)]))
    return samples, truth, twist_start


def interpolation_check(seed: int, still_s: float, transition_s: float, twist_s: float) -> dict:
    """Largest error of :class:`DenseMotion` (1 kHz grid) at the midpoints, against the same motion simulated
    at 2 kHz (the twist's attitude integrated on the finer grid: an upper bound of the interpolation error)."""
    coarse, _ = dense_icosahedron(seed, 0, still_s, transition_s, twist_s, DENSE_HZ)
    fine, _ = dense_icosahedron(seed, 0, still_s, transition_s, twist_s, 2 * DENSE_HZ)
    mid = fine.stamps[1::2][:len(coarse.stamps) - 1]
    w, wd, s = DenseMotion(coarse)(mid)
    k = slice(1, None, 2)
    return {"omega_rad_s": float(np.max(np.abs(w - fine.omega[k][:len(mid)]))),
            "omega_dot_rad_s2": float(np.max(np.abs(wd - fine.omega_dot[k][:len(mid)]))),
            "specific_force_m_s2": float(np.max(np.abs(s - fine.specific_force[k][:len(mid)])))}


def reading_delays_of(model, stamps, t0_ns: int) -> np.ndarray:
    """(N, K, 2) s: every reading's true sample time minus its stamp under ``model`` [accelerometer, gyroscope]
    (whatever timing terms it has: the model's own sum of them)."""
    from imu_array_ros.model.sensor_model import motion_context

    z = np.zeros((len(stamps), 3))
    return model.sample_delays(motion_context(np.asarray(stamps, dtype=np.int64), z, z, z, model.rotations,
                                              t0_ns=t0_ns))


def delay_errors(model, true_session, stamps, t0_ns: int) -> dict:
    """Reading delays of ``model`` vs ``true_session`` over ``stamps``, us: the gyroscopes' error relative to
    the other IMUs (per sample, the mean over IMUs removed: what the data identify), RMS; the common part of
    the gyroscopes' error (the gauge), mean and RMS; the accelerometers' error relative to their own
    gyroscopes', mean and RMS.  A sawtooth whose wrap comes a read early or late is off by a whole period
    (T = 1 ms) at that read: each sensor's error is taken as its median over the recording plus the
    deviations from it wrapped to +-T/2."""
    d = reading_delays_of(model, stamps, t0_ns) - reading_delays_of(true_session, stamps, t0_ns)
    period = 1e-3
    m = np.median(d, axis=0, keepdims=True)
    d = m + np.mod(d - m + period / 2, period) - period / 2
    g = d[..., 1]
    common = g.mean(axis=1)
    lag = d[..., 0] - d[..., 1]
    return {"relative_rms_us": float(np.sqrt(np.mean((g - common[:, None]) ** 2)) * 1e6),
            "common_mean_us": float(common.mean() * 1e6), "common_rms_us": float(np.sqrt(np.mean(common ** 2)) * 1e6),
            "acc_vs_gyro_mean_us": float(lag.mean() * 1e6),
            "acc_vs_gyro_rms_us": float(np.sqrt(np.mean(lag ** 2)) * 1e6)}


def clock_terms(model) -> dict[str, np.ndarray]:
    """Name -> (K, P) values of every sample-clock term of ``model`` with a clock on some IMU."""
    return {n: t.values for n, t in model.terms.items() if n.endswith("sample_clock") and np.any(t.values[:, 0] > 0)}


# --------------------------------------------------------------------------------------------- part 1

def in_gauge(model, nominal, ref: int = 0):
    """``model`` moved along the gauge freedoms of the moving and timing stages to the gauge the engine means to
    hold (the reference IMU's position, x gyroscope gain and accelerometer time offset at their nominal
    values): gains / (1 + e) and positions / (1 + e)^2 (e: the reference's x gain - 1; the fused omega and
    the lever arms read the same), positions translated, every time offset shifted by one constant.  Each
    move leaves the readings of a synchronous array unchanged; a diagnostic of what holding them gives."""
    g = model.terms["gyroscope_gain"].values
    e = g[ref, 0] / nominal.terms["gyroscope_gain"].values[ref, 0] - 1.0
    pos = model.positions / (1.0 + e) ** 2
    pos = pos - (pos[ref] - nominal.positions[ref])
    off = model.terms["time_offset"].values
    off = off - (off[ref, 0] - nominal.terms["time_offset"].values[ref, 0])
    return model.with_terms(gyroscope_gain=g / (1.0 + e), position=pos, time_offset=off)


def session_summary(samples, array, true_session, stamps) -> dict:
    """The session states ``fuse`` finds for ``samples`` under ``array`` (the same call), and the error of
    the reading delays they give (:func:`delay_errors`); without sample clocks in ``array`` nothing is
    estimated and the delays are the description's."""
    from imu_array_ros.workflows.fusion import session_fusion

    fusion, states = session_fusion(samples, array)
    return {"common_rate_ppm": None if states is None else states.common_rate_ppm,
            "estimated": None if states is None else bool(states.estimated),
            "notes": [] if states is None else list(states.notes),
            **delay_errors(fusion.model, true_session, stamps, START_NS)}


def pair_job(args: dict) -> dict:
    """One pair of recordings of one set of chips: calibrate on the first, fuse the second (module docstring)."""
    from imu_array_ros.fusion.model_fusion import ModelFusion
    from imu_array_ros.model.sensor_model import SensorModel
    from imu_array_ros.simulation.clocks import mimu_like_clocks, new_session
    from imu_array_ros.simulation.motion import TwistTrajectory
    from imu_array_ros.simulation.simulator import simulate_trajectory
    from imu_array_ros.workflows.calibrations import calibrate
    from imu_array_ros.workflows.fusion import fuse

    seed, run = args["seed"], args["run"]
    t_start = time.perf_counter()
    desc, nominal = nominal_model()
    device = mimu_like_clocks(nominal, rng_of(seed, 1, run, 0))  # device constants + the phases of session 1
    cal, _, twist_start = calibration_recording(device, seed, run, args["still_s"], args["transition_s"],
                                                args["cal_twist_s"])
    session = new_session(device, rng_of(seed, 1, run, 3))  # the same chips powered up again
    twist = TwistTrajectory.random(rng_of(seed, 1, run, 4))
    stamps = START_NS + np.round(np.arange(int(round(args["fuse_s"] * RATE_HZ))) * (1e9 / RATE_HZ)).astype(np.int64)
    timed, truth = simulate_trajectory(session, twist, stamps, rng_of(seed, 1, run, 5))
    sync, sync_truth = simulate_trajectory(nominal, twist, stamps, rng_of(seed, 1, run, 5))  # same noise draws
    out: dict = {"run": run, "cal_samples": len(cal), "cal_twist_start": twist_start,
                 "fused_samples": len(timed), "rates_ppm": device.terms["sample_clock"].values[:, 1].tolist()}

    fused_sync = fuse(sync, desc)[0]
    e_sync = rms_omega(fused_sync, sync_truth)
    rows = {"sync": (fused_sync, e_sync)}

    def score(label, fused):
        e = rms_omega(fused, truth)
        delta, e_aligned = common_delay(fused, twist, START_NS)
        rows[label] = (fused, e)
        out[label] = {"rms": e, "ratio": e / e_sync, "common_delay_us": delta * 1e6,
                      "ratio_aligned": e_aligned / e_sync, "fused": len(fused)}

    out["sync"] = {"rms": e_sync, "ratio": 1.0, "fused": len(fused_sync)}
    score("a", fuse(timed, desc)[0])

    true_rates = device.terms["sample_clock"].values[:, 1]
    cal_stamps = cal.stamps[twist_start:]  # the delays compared over the calibration's twisting

    def calibration_summary(c, seconds):
        m = SensorModel.from_description(c.apply(desc))  # written and read back: session states dropped
        details = c.details
        mov = details.moving
        clocks = clock_terms(m)
        rate_err = [v[v[:, 0] > 0, 1] - true_rates[v[:, 0] > 0] for v in clocks.values()]
        rate_err = np.concatenate(rate_err) if rate_err else np.zeros(0)
        delays = reading_delays_of(m, cal_stamps, int(cal.stamps[0])).mean(axis=0)  # (K, 2) mean delays
        gain_err = m.terms["gyroscope_gain"].values - 1.0
        std = {} if mov is None else mov.std
        gain_std = np.asarray(std["gyroscope_gain"]) if "gyroscope_gain" in std else None
        return m, {"seconds": seconds, "summary": details.summary(), "skipped": dict(details.skipped),
                   "terms": [] if mov is None else list(mov.free),
                   "nis_after": None if mov is None else float(mov.nis_after),
                   "converged": None if mov is None else bool(mov.converged),
                   "iterations": None if mov is None else int(mov.iterations),
                   "position_err_rms_mm": float(np.sqrt(np.mean((m.positions - nominal.positions) ** 2)) * 1e3),
                   "position_err_max_mm": float(np.max(np.abs(m.positions - nominal.positions)) * 1e3),
                   "gyro_gain_err_rms": float(np.sqrt(np.mean(gain_err ** 2))),
                   "gyro_gain_err_max": float(np.max(np.abs(gain_err))),
                   # the gains' error common to all IMUs, per array axis: mean over IMUs of (R G R^T)_jj - 1
                   "gyro_gain_err_common_array_axes": np.einsum("kji,ki->kj", m.rotations ** 2,
                                                                gain_err).mean(axis=0).tolist(),
                   "gyro_gain_std_max": None if gain_std is None else float(np.nanmax(gain_std)),
                   "gyro_misalignment_err_max": float(np.max(np.abs(m.terms["gyroscope_misalignment"].values))),
                   "clock_terms": {n: int(np.sum(v[:, 0] > 0)) for n, v in clocks.items()},
                   "clocks_found": int(sum(np.sum(v[:, 0] > 0) for v in clocks.values())),
                   "rate_err_ppm": rate_err.tolist() if len(rate_err) else None,
                   "acc_minus_gyro_delay_us": ((delays[:, 0] - delays[:, 1]) * 1e6).tolist(),
                   "position_std_mm": (None if "position" not in std
                                       else float(np.sqrt(np.nanmean(np.asarray(std["position"]) ** 2)) * 1e3))}

    t0 = time.perf_counter()
    cal_b = calibrate("all", cal, desc, timing=False)
    model_b, out["calibration_b"] = calibration_summary(cal_b, time.perf_counter() - t0)
    score("b", fuse(timed, cal_b.apply(desc))[0])

    t0 = time.perf_counter()
    cal_c = calibrate("all", cal, desc, timing=True, clock_period=1e-3)
    model_c, out["calibration_c"] = calibration_summary(cal_c, time.perf_counter() - t0)
    desc_c = cal_c.apply(desc)
    t0 = time.perf_counter()
    score("c", fuse(timed, desc_c)[0])
    out["c"]["fuse_seconds"] = time.perf_counter() - t0
    out["c"]["session"] = session_summary(timed, desc_c, session, stamps)

    # (c'): the same, with the gyroscopes' gains and misalignments of the truth (1, 0): what the rest costs
    model_c1 = model_c.with_terms(gyroscope_gain=np.ones_like(model_c.terms["gyroscope_gain"].values),
                                  gyroscope_misalignment=np.zeros_like(model_c.terms["gyroscope_misalignment"].values))
    score("c1", fuse(timed, model_c1)[0])
    score("b1", fuse(timed, model_b.with_terms(
        gyroscope_gain=np.ones_like(model_b.terms["gyroscope_gain"].values),
        gyroscope_misalignment=np.zeros_like(model_b.terms["gyroscope_misalignment"].values)))[0])
    score("c2", fuse(timed, in_gauge(model_c, nominal))[0])
    score("d", fuse(timed, device)[0])  # the true device constants, the session estimated by fuse
    out["d"]["session"] = session_summary(timed, device, session, stamps)
    score("e", ModelFusion(session, t0_ns=START_NS).fuse(timed)[0])  # true device constants and session
    out["seconds"] = time.perf_counter() - t_start
    say(f"pair {run}: ratio (a) {out['a']['ratio']:.2f}, (b) {out['b']['ratio']:.2f}, (c) {out['c']['ratio']:.2f}, "
        f"(c') {out['c1']['ratio']:.2f}, (c'') {out['c2']['ratio']:.2f}, "
        f"(d) {out['d']['ratio']:.2f}, (e) {out['e']['ratio']:.2f}; "
        f"calibrate all {out['calibration_c']['seconds']:.0f} s"
        f" (timing) / {out['calibration_b']['seconds']:.0f} s; pair {out['seconds']:.0f} s")
    return out


# --------------------------------------------------------------------------------------------- part 2

QUANTITIES = ("omega", "omega_dot", "specific_force")
COMPONENTS = [f"{q}_{a}" for q in QUANTITIES for a in "xyz"]


def mc_job(args: dict) -> dict:
    """Monte Carlo runs of the fusion with the true description and session states (and of the synchronous
    array): per run new chips, phases, motion and noise.  Returns the errors, the published covariances'
    diagonals, the CRB at the true motion and the NEES of every fused sample."""
    from imu_array_ros.fusion.crb import fisher_information
    from imu_array_ros.fusion.model_fusion import ModelFusion
    from imu_array_ros.simulation.clocks import mimu_like_clocks
    from imu_array_ros.simulation.motion import TwistTrajectory
    from imu_array_ros.simulation.simulator import simulate_trajectory

    seed = args["seed"]
    _, nominal = nominal_model()
    stamps = START_NS + np.round(np.arange(int(round(args["seconds"] * RATE_HZ))) * (1e9 / RATE_HZ)).astype(np.int64)
    out = {k: {"err": [], "var": [], "crb_true": [], "nees": [], "dropped": 0} for k in ("timed", "sync")}
    for run in args["runs"]:
        session = mimu_like_clocks(nominal, rng_of(seed, 2, run, 0))
        twist = TwistTrajectory.random(rng_of(seed, 2, run, 1))
        for kind, model in (("timed", session), ("sync", nominal)):
            samples, truth = simulate_trajectory(model, twist, stamps, rng_of(seed, 2, run, 2))
            fusion = ModelFusion(model, t0_ns=START_NS)
            fused, stats = fusion.fuse(samples)
            idx = np.searchsorted(truth.stamps, fused.stamps)
            x = np.concatenate([fused.omega, fused.omega_dot, fused.specific_force], axis=1)
            x_true = np.concatenate([truth.omega, truth.omega_dot, truth.specific_force], axis=1)[idx]
            e = x - x_true
            cov = fused.covariance
            valid = samples.select(idx).valid(model)
            info = fisher_information(truth.omega[idx], fusion.linear, valid[..., :3], valid[..., 3:])
            o = out[kind]
            o["err"].append(e)
            o["var"].append(np.diagonal(cov, axis1=1, axis2=2))
            o["crb_true"].append(np.diagonal(np.linalg.inv(info), axis1=1, axis2=2))
            o["nees"].append(np.einsum("ni,ni->n", e, np.linalg.solve(cov, e[..., None])[..., 0]))
            o["dropped"] += len(samples) - len(fused)
    return {k: {"err": np.concatenate(v["err"]), "var": np.concatenate(v["var"]),
                "crb_true": np.concatenate(v["crb_true"]), "nees": np.concatenate(v["nees"]),
                "dropped": v["dropped"]} for k, v in out.items()}


def mc_summary(parts: list[dict], runs: int, seconds: float) -> dict:
    res: dict = {"runs": runs, "seconds_per_run": seconds}
    for kind in ("timed", "sync"):
        err = np.concatenate([p[kind]["err"] for p in parts])
        var = np.concatenate([p[kind]["var"] for p in parts])
        crb_true = np.concatenate([p[kind]["crb_true"] for p in parts])
        nees = np.concatenate([p[kind]["nees"] for p in parts])
        rmse = np.sqrt(np.mean(err ** 2, axis=0))
        comp = {c: {"rmse": float(rmse[i]), "sqrt_crb": float(np.sqrt(var[:, i].mean())),
                    "ratio": float(rmse[i] / np.sqrt(var[:, i].mean())),
                    "ratio_crb_at_truth": float(rmse[i] / np.sqrt(crb_true[:, i].mean())),
                    "rms_z": float(np.sqrt(np.mean(err[:, i] ** 2 / var[:, i])))} for i, c in enumerate(COMPONENTS)}
        quant = {}
        for qi, q in enumerate(QUANTITIES):
            s = slice(3 * qi, 3 * qi + 3)
            quant[q] = {"ratio": float(np.sqrt(np.mean(err[:, s] ** 2) / var[:, s].mean())),
                        "ratio_crb_at_truth": float(np.sqrt(np.mean(err[:, s] ** 2) / crb_true[:, s].mean()))}
        # NEES of 9 dof per sample; its mean / 9 ~ 1, with a 95 % band from the chi-square of all samples
        n = len(nees)
        res[kind] = {"samples": int(n), "dropped": int(sum(p[kind]["dropped"] for p in parts)), "components": comp,
                     "quantities": quant, "nees_per_dof": float(nees.mean() / 9.0),
                     "nees_median_per_dof": float(np.median(nees) / 9.0),
                     "nees_share_above_chi2_99": float(np.mean(nees > 21.666))}  # chi2(9) 99 % point
    return res


# --------------------------------------------------------------------------------------------- part 3

#: samples at either end of a fused own-stamp recording left out of the "interior" figure
EDGE = 5

def own_job(args: dict) -> dict:
    """IMUs with their own clocks and stamps, paired and fused (module docstring)."""
    from imu_array_ros.io.pairing import ImuStream, pair_streams
    from imu_array_ros.model.samples import ImuSamples
    from imu_array_ros.simulation.clocks import simulate_own_clocks
    from imu_array_ros.simulation.simulator import simulate_trajectory
    from imu_array_ros.timing import estimate_session
    from imu_array_ros.workflows.fusion import fuse

    seed, run = args["seed"], args["run"]
    t_start = time.perf_counter()
    desc, nominal = nominal_model()
    streams = simulate_own_clocks(nominal, rng_of(seed, 3, run, 0), args["seconds"], args["rate_hz"],
                                  start_ns=START_NS)
    samples, pstats = pair_streams([ImuStream(s, a, g) for s, a, g in zip(streams.stamps, streams.accel,
                                                                          streams.gyro)], nominal.names)
    t0 = time.perf_counter()
    fused, fstats = fuse(samples, desc)
    fuse_seconds = time.perf_counter() - t0
    ref_traj = streams.reference_trajectory()
    omega_true = ref_traj(fused.stamps[:, None])[0][:, 0]
    e = float(np.sqrt(np.mean((fused.omega - omega_true) ** 2)))
    # the same on the reference IMU's own stamps only (no grid sample added before or after it), and on those
    # more than EDGE samples from either end (the timing compensation's local cubics are one-sided there)
    on_ref = np.isin(fused.stamps, streams.stamps[0])
    interior = on_ref & (np.arange(len(fused)) >= EDGE) & (np.arange(len(fused)) < len(fused) - EDGE)
    e_ref = float(np.sqrt(np.mean((fused.omega[on_ref] - omega_true[on_ref]) ** 2)))
    e_interior = float(np.sqrt(np.mean((fused.omega[interior] - omega_true[interior]) ** 2)))
    worst = np.argsort(np.linalg.norm(fused.omega - omega_true, axis=1))[-3:][::-1]
    oracle, oracle_truth = simulate_trajectory(nominal, streams.truth.trajectory, streams.sample_times[0],
                                               rng_of(seed, 3, run, 1))
    e_oracle = rms_omega(fuse(oracle, desc)[0], oracle_truth)
    unaware = ImuSamples(samples.stamps, samples.accel, samples.gyro, samples.names)  # own stamps dropped
    fu = fuse(unaware, desc)[0]
    e_unaware = float(np.sqrt(np.mean((fu.omega - ref_traj(fu.stamps[:, None])[0][:, 0]) ** 2)))
    states = estimate_session(samples, nominal)
    true = streams.stamp_clock_values(int(samples.stamps[0]))
    others = np.arange(1, nominal.n_imus)
    d_off = (states.stamp_offset - true[:, 0])[others]
    d_skew = (states.stamp_skew - true[:, 1])[others]
    ref = streams.stamps[0]
    steps = np.diff(fused.stamps)
    period_ns = 1e9 / args["rate_hz"]
    out = {"run": run, "rms": e, "rms_oracle": e_oracle, "ratio": e / e_oracle, "ratio_unaware": e_unaware / e_oracle,
           "ratio_reference_stamps": e_ref / e_oracle, "ratio_interior": e_interior / e_oracle,
           "worst_samples": [{"index": int(i), "of": len(fused), "error_rad_s": float(np.linalg.norm(
               fused.omega[i] - omega_true[i])), "on_reference_stamp": bool(on_ref[i]),
               "imus_present": int(samples.present[np.searchsorted(samples.stamps, fused.stamps[i])].sum())}
               for i in worst],
           "reference_messages": int(len(ref)), "grid": int(pstats.grid), "grid_filled": int(pstats.grid_filled),
           "fused": int(fstats.fused), "samples": int(fstats.samples),
           "reference_stamps_fused": int(np.isin(ref, fused.stamps).sum()),
           "reference_stamps_not_fused": np.flatnonzero(~np.isin(ref, fused.stamps))[:10].tolist(),
           "fusion_stats": {k: int(v) for k, v in vars(fstats).items() if isinstance(v, (int, np.integer))},
           "largest_step_periods": float(steps.max() / period_ns) if len(steps) else None,
           "missing_slots": int(pstats.missing.sum()), "unused_messages": int(pstats.unused.sum()),
           "true_offset_ms": (true[:, 0] * 1e3).tolist(), "est_offset_ms": (states.stamp_offset * 1e3).tolist(),
           "offset_std_us": (states.stamp_offset_std * 1e6).tolist(),
           "offset_err_us_rms": float(np.sqrt(np.mean(d_off ** 2)) * 1e6),
           "offset_err_us_max": float(np.max(np.abs(d_off)) * 1e6),
           "offset_z_rms": float(np.sqrt(np.mean((d_off / states.stamp_offset_std[others]) ** 2))),
           "skew_err_ppm_rms": float(np.sqrt(np.mean(d_skew ** 2))),
           "skew_err_ppm_max": float(np.max(np.abs(d_skew))),
           "true_skew_ppm": true[:, 1].tolist(), "est_skew_ppm": np.asarray(states.stamp_skew).tolist(),
           "fuse_seconds": fuse_seconds, "seconds": time.perf_counter() - t_start}
    say(f"own clocks {run}: ratio {out['ratio']:.2f} (unaware {out['ratio_unaware']:.1f}), fused {out['fused']} of "
        f"{out['grid']} grid samples ({out['reference_messages']} reference messages), offsets "
        f"{out['offset_err_us_rms']:.1f}"
        f" us RMS")
    return out


# --------------------------------------------------------------------------------------------- the run

def library_state() -> str:
    """sha1 (12 digits) of ``git diff HEAD -- imu_array_ros`` and of the untracked files there: which uncommitted
    state of the package a run used (the tree is shared with other work in progress)."""
    import hashlib
    import subprocess

    try:
        diff = subprocess.run(["git", "diff", "HEAD", "--", "imu_array_ros"], cwd=REPO, capture_output=True,
                              timeout=30, check=True).stdout
        untracked = subprocess.run(["git", "ls-files", "--others", "--exclude-standard", "--", "imu_array_ros"],
                                   cwd=REPO, capture_output=True, text=True, timeout=30, check=True).stdout.split()
    except (OSError, subprocess.SubprocessError):
        return "unknown"
    if not diff and not untracked:
        return "clean (no uncommitted changes in imu_array_ros/)"
    h = hashlib.sha1(diff)
    for name in sorted(untracked):
        h.update(name.encode() + b"\0" + (REPO / name).read_bytes())
    files = len({line[6:] for line in diff.decode(errors="replace").splitlines() if line.startswith("+++ b/")})
    return f"{h.hexdigest()[:12]} ({files} modified and {len(untracked)} untracked files in imu_array_ros/)"


def import_package() -> None:
    """Import every module of the package now, before the pool's processes are forked from this one: every
    job then runs the code as it was when the run started, also where the package imports lazily."""
    import importlib
    import pkgutil

    import imu_array_ros

    for mod in pkgutil.walk_packages(imu_array_ros.__path__, "imu_array_ros."):
        if mod.name.startswith("imu_array_ros.nodes"):
            continue  # ROS 2 nodes: not used here
        try:
            importlib.import_module(mod.name)
        except Exception:  # noqa: BLE001 -- an optional extra missing: not used here either
            pass

def run_job(job: tuple[str, dict]):
    kind, args = job
    t0 = time.perf_counter()
    fn = {"pair": pair_job, "mc": mc_job, "own": own_job}[kind]
    return kind, fn(args), time.perf_counter() - t0


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--pairs", type=int, default=5, help="pairs of MIMU-like recordings (part 1)")
    ap.add_argument("--still-s", type=float, default=3.0, help="seconds at rest on each of the 20 poses")
    ap.add_argument("--transition-s", type=float, default=1.5, help="seconds between two poses")
    ap.add_argument("--cal-twist-s", type=float, default=30.0, help="seconds of twisting after the poses")
    ap.add_argument("--fuse-s", type=float, default=30.0, help="seconds of twisting of the fused recording")
    ap.add_argument("--mc-runs", type=int, default=20)
    ap.add_argument("--mc-seconds", type=float, default=10.0)
    ap.add_argument("--own-runs", type=int, default=5)
    ap.add_argument("--own-seconds", type=float, default=20.0)
    ap.add_argument("--own-rate", type=float, default=200.0)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--seed", type=int, default=21021)
    ap.add_argument("--out", type=Path, default=OUT)
    ap.add_argument("--render", action="store_true", help="only re-write the .md and .png from the saved .json")
    args = ap.parse_args(argv)
    if args.render:
        render(json.loads(args.out.with_suffix(".json").read_text()), args.out)
        return 0
    import_package()
    header = machine_header(TITLE, extra=[f"package state: {library_state()}",
                                          f"workers: {args.workers} processes (forked after the package was "
                                          f"imported), 1 BLAS thread each "
                                          f"(OMP_NUM_THREADS={os.environ.get('OMP_NUM_THREADS')})",
                                          f"seed: {args.seed}", f"load average at the start: {load_average()}"])
    settings = {k: v for k, v in vars(args).items() if k not in ("out", "render")}
    t_start = time.perf_counter()
    common = dict(seed=args.seed)
    jobs = [("pair", dict(common, run=i, still_s=args.still_s, transition_s=args.transition_s,
                          cal_twist_s=args.cal_twist_s, fuse_s=args.fuse_s)) for i in range(args.pairs)]
    chunks = [list(range(args.mc_runs))[i::4] for i in range(4)]
    jobs += [("mc", dict(common, runs=c, seconds=args.mc_seconds)) for c in chunks if c]
    jobs += [("own", dict(common, run=i, seconds=args.own_seconds, rate_hz=args.own_rate))
             for i in range(args.own_runs)]
    pairs, mc_parts, own, cpu = [], [], [], {"pair": 0.0, "mc": 0.0, "own": 0.0}
    with ProcessPoolExecutor(max_workers=args.workers, mp_context=multiprocessing.get_context("fork")) as pool:
        for kind, result, seconds in pool.map(run_job, jobs):
            cpu[kind] += seconds
            {"pair": pairs, "mc": mc_parts, "own": own}[kind].append(result)
    say("interpolation check ...")
    interp = interpolation_check(args.seed, args.still_s, args.transition_s, args.cal_twist_s)
    res = {"header": header, "settings": settings, "pairs": pairs,
           "mc": mc_summary(mc_parts, args.mc_runs, args.mc_seconds), "own": own, "interpolation": interp,
           "job_seconds": cpu, "total_wall_seconds": time.perf_counter() - t_start, "load_average_end": load_average()}
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.with_suffix(".json").write_text(json.dumps(res, indent=1) + "\n")
    render(res, args.out)
    return 0


# --------------------------------------------------------------------------------------------- the report

KEYS = ("a", "b", "b1", "c", "c1", "c2", "d", "e")
LABELS = {"a": "(a) time-unaware, nominal description", "b": "(b) `calibrate all` without timing",
          "b1": "(b') = (b) with the true gyroscope gains and misalignments",
          "c": "(c) `calibrate all` with timing, then `fuse`",
          "c1": "(c') = (c) with the true gyroscope gains and misalignments",
          "c2": "(c'') = (c) moved along its gauge freedoms to the reference IMU's nominal position, x gyroscope "
                "gain and accelerometer delay",
          "d": "(d) true device constants, session estimated by `fuse`",
          "e": "(e) true device constants and session states"}


def _f(x, fmt="{:.3g}"):
    if isinstance(x, dict):  # per sensor
        return ", ".join(f"{k}: {_f(v, fmt)}" for k, v in x.items()) or "—"
    return "—" if x is None or (isinstance(x, float) and not np.isfinite(x)) else fmt.format(x)


def join(values, fmt: str = "{:.2f}") -> str:
    return ", ".join(fmt.format(v) for v in values)


def markdown(res: dict) -> str:
    s, pairs, mc, own = res["settings"], res["pairs"], res["mc"], res["own"]
    med = lambda key, field="ratio": float(np.median([p[key][field] for p in pairs]))  # noqa: E731
    text = res["header"]
    text += (f"Total wall time {res['total_wall_seconds']:.0f} s on {s['workers']} worker processes (job seconds: "
             + ", ".join(f"{k} {v:.0f}" for k, v in res["job_seconds"].items())
             + f"; load average at the end {res.get('load_average_end', 'unknown')}).\n\n")
    text += "| target | measured | |\n|---|---|---|\n"
    text += (f"| MIMU-like, (c) time-aware calibrate + fuse, omega RMS / synchronous <= 1.5 | median "
             f"**{med('c'):.2f}** (pairs: {join(p['c']['ratio'] for p in pairs)}) | "
             f"{'met' if med('c') <= 1.5 else 'NOT met'} |\n")
    q = mc["timed"]["quantities"]
    se = 1.0 / np.sqrt(2.0 * mc["timed"]["samples"])  # relative standard error of an RMS over N samples
    inside = all(1.0 - 2 * se <= v["ratio"] <= 1.2 for v in q.values())
    text += ("| Monte Carlo RMSE / sqrt(CRB) within 1.0-1.2 (1.0 less 2 standard errors of the Monte Carlo, "
             f"{2 * se:.3f}) | " + ", ".join(f"{k} {v['ratio']:.3f}" for k, v in q.items())
             + f"; NEES/dof {mc['timed']['nees_per_dof']:.3f} | {'met' if inside else 'NOT met'} |\n")
    own_med = float(np.median([o['ratio'] for o in own]))
    gaps = all(o["reference_stamps_fused"] == o["reference_messages"] and o["largest_step_periods"] < 1.5
               for o in own)
    text += (f"| independent stamps, omega RMS / synchronous oracle <= 1.5, no gaps | median **{own_med:.2f}** "
             f"(runs: {join(o['ratio'] for o in own)}); every reference stamp fused, no step over 1.5 periods: "
             f"{gaps} | "
             f"{'met' if own_med <= 1.5 and gaps else 'NOT met'} |\n\n")

    # part 1
    text += "## 1. MIMU-like array: calibrate on one recording, fuse another\n\n"
    ip = res["interpolation"]
    cal_s = 20 * s["still_s"] + 19 * s["transition_s"] + s["cal_twist_s"]
    text += (f"`config/mimu4444bt_corners.yaml` (8 IMUs), 62.5 Hz, `mimu_like_clocks` (1 ms chip clocks, rates "
             "uniform in +-3000 ppm, accelerometers 1.6 ms behind; no other sensor error: the nominal description "
             f"is the truth apart from timing).  Calibration recording: 20 icosahedron poses of {s['still_s']:g} s, "
             f"{s['transition_s']:g} s transitions, then {s['cal_twist_s']:g} s of hand twisting (600 deg/s RMS) = "
             f"{cal_s:g} s; every reading the motion at its true sample time (`simulate_icosahedron`'s motion on a "
             f"1 kHz grid, interpolated: largest error at the midpoints against a 2 kHz simulation "
             f"{ip['omega_rad_s']:.1e} rad/s, {ip['omega_dot_rad_s2']:.1e} rad/s^2, "
             f"{ip['specific_force_m_s2']:.1e} m/s^2, against noise of 3.9e-3 rad/s and 4.5e-2 m/s^2).  Fused "
             f"recording: {s['fuse_s']:g} s of new hand twisting (`simulate_trajectory`, exact), the same chips "
             "with new phases (`new_session`; the chips' rates unchanged).  Synchronous: the same motion and noise "
             "draws measured by the nominal array (no timing terms).  Seeds of this run only.\n\n")
    text += ("Ratio = fused angular-velocity RMS error / the synchronous array's (both against the truth at the "
             "stamps).  *aligned*: the same after the one time shift of the truth that fits best (a delay "
             "common to every sensor is not observable; this is how far off the estimate's instant is, shown "
             "in the last table).\n\n")
    text += "| | " + " | ".join(f"pair {p['run']}" for p in pairs) + " | median |\n"
    text += "|---|" + "---|" * (len(pairs) + 1) + "\n"
    text += ("| synchronous omega RMS (rad/s) | " + " | ".join(f"{p['sync']['rms']:.2e}" for p in pairs)
             + f" | {float(np.median([p['sync']['rms'] for p in pairs])):.2e} |\n")
    for key in KEYS:
        text += (f"| {LABELS[key]} | " + " | ".join(f"{p[key]['ratio']:.2f}" for p in pairs)
                 + f" | **{med(key):.2f}** |\n")
    for key in KEYS:
        text += (f"| {key}, aligned | " + " | ".join(f"{p[key]['ratio_aligned']:.2f}" for p in pairs)
                 + f" | {med(key, 'ratio_aligned'):.2f} |\n")
    text += ("\nThe calibrations (truth: positions and gyroscope gains and misalignments nominal, rates as drawn, "
             "accelerometers' delay minus gyroscopes' -1600 us on every IMU).  Gyroscope gain error common to all "
             "IMUs per array axis: mean over the IMUs of the array-frame scale error (the reference IMU's gain "
             "holds the x axis: the gauge of the common scale with the positions); std: the largest CRB the "
             "fit reports for a gain:\n\n")
    text += ("| pair | calibration | seconds | NIS after (converged, iterations) | clocks found | rate error RMS "
             "(max) ppm | acc - gyro delay, mean (range) us | position error RMS (max) mm | position std mm | gyro "
             "gain error RMS (max) | common gain error x, y, z | gain std max | misalignment max rad | "
             "skipped |\n|---|---|---|---|---|---|---|---|---|---|---|---|---|---|\n")
    for p in pairs:
        for key in ("b", "c"):
            c = p[f"calibration_{key}"]
            rate = np.asarray(c["rate_err_ppm"]) if c["rate_err_ppm"] else None
            lag = np.asarray(c["acc_minus_gyro_delay_us"])
            text += (f"| {p['run']} | {key} | {c['seconds']:.0f} | {_f(c['nis_after'], '{:.3f}')} "
                     f"({c['converged']}, {c['iterations']}) | {c['clocks_found']} | "
                     + (f"{np.sqrt(np.mean(rate ** 2)):.2f} ({np.max(np.abs(rate)):.1f})"
                        if rate is not None else "—")
                     + f" | {lag.mean():.0f} ({lag.min():.0f} to {lag.max():.0f}) | "
                     f"{c['position_err_rms_mm']:.2f} ({c['position_err_max_mm']:.2f}) | "
                     f"{_f(c['position_std_mm'], '{:.2f}')} | {c['gyro_gain_err_rms']:.1e} "
                     f"({c['gyro_gain_err_max']:.1e}) | "
                     + ", ".join(f"{v:+.1e}" for v in c["gyro_gain_err_common_array_axes"])
                     + f" | {_f(c['gyro_gain_std_max'], '{:.1e}')} | {c['gyro_misalignment_err_max']:.1e} | "
                     + ("; ".join(f"{k}: {v}" for k, v in c["skipped"].items()) or "—") + " |\n")
    text += ("\nThe session states the fusion found for the fused recording (gyroscope reading delays of the "
             "model vs the truth over the recording: the error relative to the other IMUs, which the data "
             "identify, and the common part, which the description's gauge fixes), and the common delay of the "
             "fused estimate (best shift of the truth, us; positive: the estimate is of a later instant):\n\n"
             "| pair | (c) common rate ppm | (c) relative delay error RMS us | (c) common delay error mean (RMS) us "
             "| (c) acc - gyro delay error mean (RMS) us | (c) estimate's delay us | (d) common rate ppm | "
             "(d) relative us | (d) common mean (RMS) us | (d) estimate's delay us | (e) estimate's delay us | "
             "(a) estimate's delay us |\n|---|---|---|---|---|---|---|---|---|---|---|---|\n")
    for p in pairs:
        c, d = p["c"]["session"], p["d"]["session"]
        text += (f"| {p['run']} | {_f(c['common_rate_ppm'], '{:.2f}')} | {c['relative_rms_us']:.1f} | "
                 f"{c['common_mean_us']:.0f} ({c['common_rms_us']:.0f}) | {c['acc_vs_gyro_mean_us']:.0f} "
                 f"({c['acc_vs_gyro_rms_us']:.0f}) | {p['c']['common_delay_us']:.0f} | "
                 f"{_f(d['common_rate_ppm'], '{:.2f}')} | {d['relative_rms_us']:.1f} | {d['common_mean_us']:.0f} "
                 f"({d['common_rms_us']:.0f}) | {p['d']['common_delay_us']:.0f} | {p['e']['common_delay_us']:.0f} | "
                 f"{p['a']['common_delay_us']:.0f} |\n")
    text += ("\nTime per pair: " + ", ".join(f"{p['seconds']:.0f} s" for p in pairs)
             + f"; `calibrate all` with timing {join((p['calibration_c']['seconds'] for p in pairs), '{:.0f}')} s, "
             f"without {join((p['calibration_b']['seconds'] for p in pairs), '{:.0f}')} s; `fuse` of the "
             f"{s['fuse_s']:g} s recording with session estimation "
             f"{join((p['c']['fuse_seconds'] for p in pairs), '{:.1f}')} s.\n\n")

    # part 2
    text += "## 2. Monte Carlo: time-aware fusion against its Cramér-Rao bound\n\n"
    t, sy = mc["timed"], mc["sync"]
    text += (f"{mc['runs']} runs of {mc['seconds_per_run']:g} s at 62.5 Hz ({t['samples']} fused samples, "
             f"{t['dropped']} not fused), each with new chips (`mimu_like_clocks`), phases, hand twisting and noise; "
             "fused with the true device constants and true session states (`ModelFusion` of the simulated "
             "model, no estimation).  RMSE / sqrt(CRB): the RMS error over all samples divided by the square root "
             "of the mean published variance (the fusion's covariance, the CRB at the estimate); in brackets "
             "the same against the CRB at the true motion.  rms z: RMS of error / published std per sample.  "
             "Beside it the synchronous array (no timing terms) on the same motions and noise draws.\n\n")
    text += ("| component | RMSE | sqrt(mean CRB) | RMSE / sqrt(CRB) (at truth) | rms z | synchronous: RMSE / "
             "sqrt(CRB) |\n|---|---|---|---|---|---|\n")
    for c in COMPONENTS:
        a, b = t["components"][c], sy["components"][c]
        text += (f"| {c} | {a['rmse']:.3e} | {a['sqrt_crb']:.3e} | **{a['ratio']:.3f}** "
                 f"({a['ratio_crb_at_truth']:.3f}) | "
                 f"{a['rms_z']:.3f} | {b['ratio']:.3f} |\n")
    for qn in QUANTITIES:
        a, b = t["quantities"][qn], sy["quantities"][qn]
        text += (f"| **{qn}** (3 axes) | | | **{a['ratio']:.3f}** ({a['ratio_crb_at_truth']:.3f}) | | "
                 f"{b['ratio']:.3f} |\n")
    text += (f"\nNEES (9 dof per sample, the published covariance), mean / 9: **{t['nees_per_dof']:.3f}** (median / 9 "
             f"{t['nees_median_per_dof']:.3f}; share above the chi-square 99 % point "
             f"{t['nees_share_above_chi2_99']:.3%},"
             f" 1 % expected); synchronous {sy['nees_per_dof']:.3f} ({sy['nees_share_above_chi2_99']:.3%}).\n\n")

    # part 3
    text += "## 3. Independent stamps: own clocks, paired onto the reference's stamps\n\n"
    text += (f"`simulate_own_clocks`: 8 IMUs (the same array), {s['own_seconds']:g} s at {s['own_rate']:g} Hz each on "
             "its own clock (rates +-200 ppm, offsets +-2 ms, 50 us stamping jitter, the reference IMU too), hand "
             "twisting; `pair_streams` onto the reference IMU's stamps, `workflows.fuse` (stamp clocks estimated "
             "from the samples).  Oracle: every IMU sampled at the reference's true sample times, same motion, "
             "fused with the nominal description.  Unaware: the paired samples with their own stamps dropped.  "
             "Offsets and skews relative to the reference (7 IMUs per run), as `estimate_session` gives them.\n\n")
    text += ("| run | omega RMS / oracle | on the reference's stamps | interior | unaware / oracle | reference "
             "messages | grid samples (filled) | fused | "
             "reference stamps fused | largest step (periods) | missing slots | unused messages | offset error RMS "
             "(max) us | offset z RMS | skew error RMS (max) ppm | fuse s |\n"
             "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|\n")
    for o in own:
        text += (f"| {o['run']} | **{o['ratio']:.2f}** | {_f(o.get('ratio_reference_stamps'), '{:.2f}')} | "
                 f"{_f(o.get('ratio_interior'), '{:.2f}')} | {o['ratio_unaware']:.1f} | {o['reference_messages']} | "
                 f"{o['grid']} ({o['grid_filled']}) | {o['fused']} | {o['reference_stamps_fused']} | "
                 f"{_f(o['largest_step_periods'], '{:.2f}')} | {o['missing_slots']} | {o['unused_messages']} | "
                 f"{o['offset_err_us_rms']:.1f} ({o['offset_err_us_max']:.1f}) | {o['offset_z_rms']:.2f} | "
                 f"{o['skew_err_ppm_rms']:.2f} ({o['skew_err_ppm_max']:.2f}) | {o['fuse_seconds']:.1f} |\n")

    def med_of(key):
        return _f(float(np.median([o[key] for o in own])) if all(key in o for o in own) else None, "{:.2f}")

    text += (f"| median | **{own_med:.2f}** | {med_of('ratio_reference_stamps')} | {med_of('ratio_interior')} | "
             f"{float(np.median([o['ratio_unaware'] for o in own])):.1f} | | | | | | | | "
             f"{float(np.median([o['offset_err_us_rms'] for o in own])):.1f} | | "
             f"{float(np.median([o['skew_err_ppm_rms'] for o in own])):.2f} | |\n\n")
    text += (f"*on the reference's stamps*: the fused samples at the reference IMU's own stamps only (the grid "
             f"is extended past the reference's first and last stamp where other IMUs deliver); *interior*: those "
             f"more than {EDGE} samples from either end.  The largest errors (rad/s; sample index, IMUs present): "
             + "; ".join(f"run {o['run']}: " + ", ".join(
                 f"{w['error_rad_s']:.3g} (#{w['index']} of {w['of']}, {w['imus_present']} IMUs"
                 f"{'' if w['on_reference_stamp'] else ', not a reference stamp'})" for w in o["worst_samples"])
                 for o in own if "worst_samples" in o) + ".\n\n")
    gaps_at = [o for o in own if o.get("reference_stamps_not_fused")]
    if gaps_at:
        text += ("Reference stamps not fused: " + "; ".join(
            f"run {o['run']}: sample(s) {', '.join(map(str, o['reference_stamps_not_fused']))} of "
            f"{o['reference_messages']} (fusion counts: " + ", ".join(
                f"{k.replace('_', ' ')} {v}" for k, v in o.get("fusion_stats", {}).items() if v) + ")"
            for o in gaps_at) + ".\n\n")
    o = own[0]
    text += (f"Run {o['run']} in detail (ms; offset = the `stamp_clock` offset at the first grid stamp):\n\n"
             "| IMU | true offset | estimated | std us | true skew ppm | estimated |\n|---|---|---|---|---|---|\n")
    for k in range(len(o["true_offset_ms"])):
        text += (f"| {k} | {o['true_offset_ms'][k]:.4f} | {o['est_offset_ms'][k]:.4f} | "
                 f"{_f(o['offset_std_us'][k] if np.isfinite(o['offset_std_us'][k]) else None, '{:.1f}')} | "
                 f"{o['true_skew_ppm'][k]:.1f} | {o['est_skew_ppm'][k]:.1f} |\n")
    text += "\n![ratios, Monte Carlo, stamp clocks](time_aware_sim.png)\n"
    return text


def plot(res: dict, path: Path) -> None:
    from imu_array_ros.util.plotting import pyplot, save_png

    plt = pyplot(path)
    fig, ax = plt.subplots(1, 3, figsize=(15, 5.6))
    pairs = res["pairs"]
    width = 0.1
    for j, key in enumerate(KEYS):
        ax[0].bar(np.arange(len(pairs)) + (j - 3.5) * width, [p[key]["ratio"] for p in pairs], width,
                  label=LABELS[key].split(",")[0].split(" = ")[0] if key in ("b1", "c1", "c2", "d", "e")
                  else LABELS[key])
    ax[0].axhline(1.5, color="k", ls="--", lw=1, label="target 1.5")
    ax[0].set_yscale("log")
    ax[0].set_xticks(range(len(pairs)), [f"pair {p['run']}" for p in pairs])
    ax[0].set_ylabel("omega RMS / synchronous")
    ax[0].set_title("1. MIMU-like array")
    ax[0].legend(fontsize=6, loc="upper center", bbox_to_anchor=(0.5, -0.1), ncol=2)
    mc = res["mc"]
    x = np.arange(len(COMPONENTS))
    ax[1].bar(x - 0.2, [mc["timed"]["components"][c]["ratio"] for c in COMPONENTS], 0.4, label="time-aware")
    ax[1].bar(x + 0.2, [mc["sync"]["components"][c]["ratio"] for c in COMPONENTS], 0.4, label="synchronous")
    ax[1].axhspan(1.0, 1.2, color="g", alpha=0.15, label="target")
    ax[1].set_xticks(x, [c.replace("specific_force", "s").replace("omega_dot", "wdot").replace("omega", "w")
                         for c in COMPONENTS], rotation=45, fontsize=7)
    ax[1].set_ylim(0.8, 1.3)
    ax[1].set_ylabel("RMSE / sqrt(mean CRB)")
    ax[1].set_title(f"2. Monte Carlo ({mc['timed']['samples']} samples)")
    ax[1].legend(fontsize=7)
    for o in res["own"]:
        t, e = np.asarray(o["true_offset_ms"][1:]), np.asarray(o["est_offset_ms"][1:])
        ax[2].plot(t, (e - t) * 1e3, "o", ms=4, label=f"run {o['run']}")
    ax[2].axhline(0, color="k", lw=0.5)
    ax[2].set_xlabel("true stamp-clock offset (ms)")
    ax[2].set_ylabel("estimated - true (us)")
    ax[2].set_title("3. own stamps: offsets")
    ax[2].legend(fontsize=7)
    fig.tight_layout()
    save_png(fig, path)


def render(res: dict, out: Path) -> None:
    """The markdown and the PNG of a result (also from a saved .json: ``--render``)."""
    png = out.with_suffix(".png")
    plot(res, png)
    write_results(out.with_suffix(".md"), markdown(res))
    print(f"wrote {out.with_suffix('.md')}, .json, {png.name}; total {res['total_wall_seconds']:.0f} s")


if __name__ == "__main__":
    sys.exit(main())
