"""The calibration report of ``imu-array calibrate all --report DIR``: what was calibrated, how well, and how sure.

:func:`write_calibration_report` writes, for one or more
:class:`~imu_array_ros.calibration.result.Calibration` results (the first is the
one reported in full, e.g. the one installed; every further one is the same
calibration on another recording of the same array, for the repeatability
section):

* ``index.md``: values with their intervals (value ± written std per IMU and
  parameter, and the written std over the Cramér-Rao bound), the stages (what
  was fitted on which data, what was skipped and why), the normalised residual
  RMS per IMU and axis before (the starting description) and after (the
  calibration) on the calibration's own data (the still poses and the moving
  window), and, with several recordings, the spread of every field across them
  against the std they report;
* ``calibration.json``: the same numbers, machine-readable (SI units);
* the PNG plots of :data:`PLOTS` (:mod:`~imu_array_ros.calibration.report_plots`);
* ``manifest.json``: the files of the report, so that a later report may replace
  this one (:func:`check_report_dir`) and nothing else.

The report directory is written as a whole, atomically
(:func:`~imu_array_ros.util.files.atomic_path` with ``directory=True``): a reader
sees the previous report or the new one, never a mix.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Sequence

import numpy as np

from imu_array_ros.calibration.result import Calibration
from imu_array_ros.calibration.static import pose_samples
from imu_array_ros.fitting.engine import fit_motion
from imu_array_ros.fitting.motion_models import StaticMotion
from imu_array_ros.fusion.residuals import AXES
from imu_array_ros.model.constants import STANDARD_GRAVITY
from imu_array_ros.model.description import ArrayDescription
from imu_array_ros.model.sensor_model import SensorModel
from imu_array_ros.model.terms import REGISTRY
from imu_array_ros.io.outputs import MANIFEST, check_report_directory, write_report_manifest
from imu_array_ros.util.files import atomic_path, atomic_write_text
from imu_array_ros.util.jsontools import json_safe

__all__ = ["write_calibration_report", "check_report_dir", "report_data", "markdown", "residual_maps",
           "repeatability", "MANIFEST", "PLOTS", "DISPLAY_UNITS"]

_KIND = "imu_array_ros calibration report"
#: the plots written next to index.md (when there are data for them)
PLOTS = {"residual_map.png": "normalised residual RMS per IMU and axis, before (starting description) and after "
                             "(calibration), on the still poses and the moving window",
         "residual_time.png": "normalised residual RMS over the moving window, before and after",
         "residual_rate.png": "normalised residual RMS against the angular rate, before and after",
         "repeatability.png": "every field's deviation from the recordings' weighted mean, in units of its "
                              "reported std"}
#: fewer still poses than this get no residual map (each pose's direction is fitted: too few to judge)
MIN_POSES = 3
#: SI unit -> (unit shown in index.md, factor); calibration.json keeps SI
DISPLAY_UNITS = {"m": ("mm", 1e3), "rad": ("deg", 180 / np.pi), "rad/s": ("deg/s", 180 / np.pi), "s": ("ms", 1e3)}


# --------------------------------------------------------------------------- where the report may go


def check_report_dir(directory: str | os.PathLike, inputs: Sequence, force: bool, *, option: str = "--report",
                     other_outputs: Sequence[tuple[str, object]] = ()) -> Path:
    """Refuse a report directory that may not be written; return it as a Path
    (:func:`~imu_array_ros.io.outputs.check_report_directory`: new, empty, or with ``force`` holding nothing but
    a previous calibration report of ours)."""
    return check_report_directory(directory, inputs, force, kind=_KIND, option=option, other_outputs=other_outputs)


# --------------------------------------------------------------------------- the numbers


def _model(m) -> SensorModel:
    return SensorModel.from_description(m) if isinstance(m, ArrayDescription) else m


def _rms(r) -> np.ndarray:
    """(K, 6) RMS over the samples of (N, K, 6) normalised residuals, NaN where none are finite."""
    r = np.asarray(r, dtype=float)
    ok = np.isfinite(r)
    n = ok.sum(axis=0)
    s = np.where(ok, r, 0.0) ** 2
    return np.where(n > 0, np.sqrt(s.sum(axis=0) / np.maximum(n, 1)), np.nan)


def pose_residuals(poses, model: SensorModel, gravity: float) -> np.ndarray:
    """(P, K, 6) normalised residuals of the still-pose averages under ``model``, every pose's direction
    fitted (the static stage's problem; noise of an average: the description's / sqrt(samples averaged))."""
    c = np.asarray(poses.counts, dtype=float)
    sigma = model.std[None] / np.sqrt(np.where(c > 0, c, 1.0))[..., None]
    return fit_motion(pose_samples(poses.accel, poses.gyro, model), model, motion_model=StaticMotion(gravity),
                      sigma=sigma)[2]


def residual_maps(cal: Calibration, start) -> dict:
    """The residuals of a ``calibrate all`` / ``static`` result (``cal.details`` an ArrayCalibration) on its
    own data, under the starting model ``start`` and the calibrated one.

    Returns {"still": {"before", "after"}: (K, 6) RMS, "moving": {"before", "after"}: (K, 6) RMS,
    "series": {"t" (N,) s from the window's first sample, "rate" (N,) |omega| rad/s, "before", "after"
    (N, K, 6) normalised residuals}}; a part is absent when there are no such data."""
    d, start = cal.details, _model(start)
    out: dict = {}
    poses = getattr(d, "poses", None)
    if poses is not None and len(poses.accel) >= MIN_POSES:
        gravity = d.static.gravity if getattr(d, "static", None) is not None else STANDARD_GRAVITY
        out["still"] = {"before": _rms(pose_residuals(poses, start, gravity)),
                        "after": _rms(pose_residuals(poses, cal.model, gravity)),
                        "poses": int(len(poses.accel))}
    window, moving = getattr(d, "moving_window", None), getattr(d, "moving", None)
    if window is not None and moving is not None and len(window):
        motion, _, before = fit_motion(window, start)
        after = moving.residuals
        if after.shape != before.shape:
            motion, _, after = fit_motion(window, cal.model)
        else:
            motion = np.where(np.isfinite(moving.motion), moving.motion, motion)
        out["moving"] = {"before": _rms(before), "after": _rms(after), "samples": int(len(window))}
        out["series"] = {"t": (window.stamps - window.stamps[0]) * 1e-9,
                         "rate": np.linalg.norm(motion[:, :3], axis=1), "before": before, "after": after}
    return out


def _crb(cal: Calibration) -> dict[str, np.ndarray]:
    """term -> (K, P) Cramér-Rao bound of a ``calibrate all`` / ``static`` result's stages (without the
    variance factor or any robust correction); empty for other methods."""
    d, out = cal.details, {}
    static, moving = getattr(d, "static", None), getattr(d, "moving", None)
    if static is not None and isinstance(getattr(static, "std", None), dict):
        out.update(static.std)
    if moving is not None and isinstance(getattr(moving, "std", None), dict):
        out.update(moving.std)
    return {t: np.asarray(v, dtype=float) for t, v in out.items() if t in cal.std}


def _std_meaning(cal: Calibration) -> list[str]:
    """What the written std is, per stage, from the record (the text after ``_std =`` in each stage's method)."""
    lines = []
    for s in cal.record.get("stages", []):
        method = str(s.get("method", ""))
        if "_std =" in method:
            lines.append(f"{s.get('stage', '?')}: {method.split('_std =', 1)[1].strip()}")
    if not lines and "_std" in str(cal.record.get("method", "")):
        lines.append(str(cal.record["method"]))
    robust = getattr(getattr(cal.details, "moving", None), "std_robust", None)
    if robust and not any("sandwich" in line for line in lines):
        lines.append("moving: the engine also reports a misfit-robust (sandwich) std (std_robust in calibration.json)")
    return lines


def _terms(cal: Calibration) -> dict:
    """term -> {"parameters", "units", "value" (K, P), "std" (K, P), "crb" (K, P) or None}, SI."""
    crb = _crb(cal)
    robust = getattr(getattr(cal.details, "moving", None), "std_robust", None)
    out = {}
    for t, std in cal.std.items():
        cls = REGISTRY[t]
        units = [f.unit for f in cls.fields for _ in range(f.size)]
        entry = {"parameters": cls.parameter_names(), "units": units,
                 "value": np.asarray(cal.model.terms[t].values, dtype=float),
                 "std": np.asarray(std, dtype=float), "crb": crb.get(t)}
        if isinstance(robust, dict) and t in robust:
            entry["std_robust"] = np.asarray(robust[t], dtype=float)
        out[t] = entry
    return out


def repeatability(cals: Sequence[Calibration]) -> dict:
    """Per term fitted by every calibration in ``cals`` (R >= 2, same IMUs, e.g. one per recording): "value"
    (R, K, P), "std" (R, K, P), "spread" (K, P) sample std across the recordings, "mean_std" (K, P) RMS of
    the std they report, "z" (R, K, P) deviation from the inverse-variance weighted mean in units of each
    one's std, and "ratio": sqrt(chi^2 / dof) over the term's parameters (1: the std explain the spread; > 1:
    the fields vary more between recordings than their std say).  Parameters without a finite positive std in
    every recording (e.g. held for the gauge) are left out (NaN)."""
    if len(cals) < 2:
        return {}
    names = cals[0].names
    if any(c.names != names for c in cals):
        raise ValueError("repeatability needs calibrations of the same IMUs")
    common = [t for t in cals[0].std if all(t in c.std for c in cals[1:])]
    out = {}
    for t in common:
        v = np.stack([np.asarray(c.model.terms[t].values, dtype=float) for c in cals])
        s = np.stack([np.asarray(c.std[t], dtype=float) for c in cals])
        ok = (np.isfinite(s) & (s > 0) & np.isfinite(v)).all(axis=0)
        v, s = np.where(ok, v, np.nan), np.where(ok, s, np.nan)
        w = 1.0 / s ** 2
        mean = np.sum(w * v, axis=0) / np.sum(w, axis=0)
        z = (v - mean) / s
        dof = ok.sum() * (len(cals) - 1)
        ratio = float(np.sqrt(np.nansum(z ** 2) / dof)) if dof else float("nan")
        out[t] = {"value": v, "std": s, "spread": np.std(v, axis=0, ddof=1),
                  "mean_std": np.sqrt(np.mean(s ** 2, axis=0)),
                  "z": z, "ratio": ratio, "parameters": REGISTRY[t].parameter_names()}
    return out


def report_data(cals: Sequence[Calibration], start, sources: Sequence[str] = ()) -> dict:
    """Everything the report shows, as one dict (numpy arrays inside; :func:`json_safe` for JSON)."""
    if not cals:
        raise ValueError("a calibration report needs at least one calibration")
    cal = cals[0]
    sources = list(sources) + [""] * (len(cals) - len(sources))
    return {"kind": _KIND, "recordings": sources, "method": cal.method, "imus": list(cal.names),
            "converged": bool(cal.converged), "summary": cal.summary(), "record": cal.record,
            "std_meaning": _std_meaning(cal), "terms": _terms(cal),
            "residuals": residual_maps(cal, start), "repeatability": repeatability(cals)}


# --------------------------------------------------------------------------- index.md


def _unit(si: str) -> tuple[str, float]:
    return DISPLAY_UNITS.get(si, ("" if si == "1" else si, 1.0))


def _num(v: float, s: float | None = None) -> str:
    """``v`` to the last digit that its std ``s`` leaves meaningful (two significant digits of ``s``)."""
    if not np.isfinite(v):
        return "—"
    if s is None or not np.isfinite(s) or s <= 0:
        return f"{v:.6g}"
    digits = int(min(12, max(0, 1 - np.floor(np.log10(s)))))
    return f"{v:.{digits}f}"


def _short(name: str) -> str:
    """Column label of a parameter: ``accelerometer.gain[1]`` -> ``y``; ``axis_offsets[0,2]`` -> ``[0,2]``."""
    field, _, idx = name.partition("[")
    if not idx:
        return field.split(".")[-1]
    idx = idx.rstrip("]")
    return {"0": "x", "1": "y", "2": "z"}.get(idx, f"[{idx}]")


def _value_table(t: str, e: dict, names: Sequence[str]) -> list[str]:
    units = [_unit(u) for u in e["units"]]
    head = ["IMU"] + [f"{_short(p)} [{u}]" if u else _short(p) for p, (u, _) in zip(e["parameters"], units)]
    has_crb = e["crb"] is not None
    if has_crb:
        head.append("std / CRB")
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for k, name in enumerate(names):
        cells = []
        for j, (_, f) in enumerate(units):
            v, s = e["value"][k, j] * f, e["std"][k, j] * f
            cells.append(f"{_num(v, s)} ± {_num(s, s)}" if np.isfinite(s) else f"{_num(v)} (held)")
        if has_crb:
            with np.errstate(all="ignore"):
                q = e["std"][k] / e["crb"][k]
            q = q[np.isfinite(q)]
            cells.append(f"{np.median(q):.3g}" if q.size else "—")
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    return lines


def _stages(record: dict) -> list[str]:
    lines = ["| stage | what | data | result |", "|---|---|---|---|"]
    g = lambda x, fmt=".4g": "—" if x is None else format(x, fmt)  # noqa: E731
    for s in record.get("stages", []):
        st = s.get("stage", "?")
        if st == "still poses":
            sp = s.get("spread", {})
            what, data = "still intervals, averaged per IMU", f"{s.get('poses', 0)} poses"
            res = (f"directions: smallest eigenvalue {g(sp.get('min_eigenvalue'), '.3g')} (1/3 even), every "
                   f"direction within {g(sp.get('coverage_deg'), '.0f')}° of a pose; "
                   f"{len(s.get('rejected', []))} intervals rejected")
        elif st == "timing":
            what, data, res = "sample clocks, time offsets", "moving samples", "; ".join(s.get("notes", []))
        else:
            what = ", ".join(s.get("terms", [])) or "—"
            data = (f"{s['poses']} poses" if "poses" in s else
                    f"{s.get('samples_used', '?')} of {s.get('samples_total', '?')} samples")
            res = (f"NIS {g(s.get('nis_before'))} → {g(s.get('nis_after'))}, {s.get('iterations', '?')} iterations"
                   f"{'' if s.get('converged', True) else ' (**not converged**)'}")
            if s.get("consistency_improvement_db") is not None:
                res += f"; consistency {s['consistency_improvement_db']:+.1f} dB"
            if s.get("downweighted"):
                res += f"; {len(s['downweighted'])} pose readings down-weighted"
            held = s.get("held") or s.get("held_for_gauge") or []
            if held:
                more = " …" if len(held) > 3 else ""
                res += f"; held for the gauge: {len(held)} parameters ({', '.join(held[:3])}{more})"
        lines.append(f"| {st} | {what} | {data} | {res} |")
    for st, why in record.get("skipped", {}).items():
        lines.append(f"| {st} | **skipped** | — | {why} |")
    return lines


def _map_table(before: np.ndarray, after: np.ndarray, names: Sequence[str]) -> list[str]:
    f = lambda x: "—" if not np.isfinite(x) else f"{x:.3g}"  # noqa: E731
    lines = ["| IMU | " + " | ".join(AXES) + " |", "|---|" + "---|" * len(AXES)]
    lines += [f"| {n} | " + " | ".join(f"{f(b)} → {f(a)}" for b, a in zip(rb, ra)) + " |"
              for n, rb, ra in zip(names, before, after)]
    return lines


def _repeat_table(t: str, r: dict, names: Sequence[str], units: list[str]) -> list[str]:
    conv = [_unit(u) for u in units]
    head = ["IMU"] + [f"{_short(p)} [{u}]" if u else _short(p) for p, (u, _) in zip(r["parameters"], conv)]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for k, name in enumerate(names):
        cells = [f"{_num(r['spread'][k, j] * f, r['mean_std'][k, j] * f)} / "
                 f"{_num(r['mean_std'][k, j] * f, r['mean_std'][k, j] * f)}"
                 if np.isfinite(r["spread"][k, j]) else "—" for j, (_, f) in enumerate(conv)]
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    return lines


def markdown(data: dict, figures: Sequence[str] = ()) -> str:
    """index.md of :func:`report_data`'s ``data``; ``figures``: the PNG names written beside it."""
    rec, names = data["record"], data["imus"]
    src = data["recordings"][0] if data["recordings"] else ""
    lines = [f"# Calibration report{': ' + src if src else ''}", "",
             f"`calibrate {data['method']}` of {len(names)} IMUs{'' if data['converged'] else ' (**NOT converged**)'}"
             f"; {rec.get('software', '')}, {rec.get('time', '')}.", "", data["summary"], ""]
    lines += ["## Stages", "", rec.get("method", ""), ""] + _stages(rec) + [""]
    lines += ["## Values", "", "Value ± the standard deviation written to the description, per IMU; the "
              "digits shown stop where the std leaves them meaningless. SI units but for mm, deg, deg/s and ms. "
              "**std / CRB**: the written std over the Cramér-Rao bound of the fit (median over the IMU's "
              "parameters): above 1 when the fit is worse than the noise explains and the std was widened.", ""]
    lines += [f"- {m}" for m in data["std_meaning"]] + [""]
    for t, e in data["terms"].items():
        lines += [f"### {t}", ""] + _value_table(t, e, names) + [""]
    res = data["residuals"]
    if res.get("still") or res.get("moving"):
        lines += ["## Residuals before → after", "",
                  "RMS of the normalised residual (reading − prediction) / noise std per IMU and axis, under the "
                  "starting description (before) and the calibration (after), each sample's motion (each pose's "
                  "direction) fitted: 1 = explained down to the sensor noise. A pose average's noise is the "
                  "sample noise / √samples, so small biases and drifts show strongly at rest.", ""]
        for part, what in (("still", "still poses"), ("moving", "moving window")):
            if part in res:
                n = res[part].get("poses", res[part].get("samples"))
                lines += [f"### {what} ({n} {'poses' if part == 'still' else 'samples'})", ""]
                lines += _map_table(res[part]["before"], res[part]["after"], names) + [""]
    rep = data["repeatability"]
    if rep:
        lines += ["## Repeatability across recordings", "", "Recordings: " + ", ".join(
                  f"`{s}`" if s else f"#{i + 1}" for i, s in enumerate(data["recordings"])) + ".", "",
                  "Per term, the **ratio** √(χ²/dof) of the fields' deviations from their inverse-variance "
                  "weighted mean in units of the std each recording reports: about 1 when the reported std "
                  "explain the spread between recordings, above 1 when they are too small (or the sensors "
                  "changed between recordings: MEMS biases change at every power-up, so the biases' ratio "
                  "measures that turn-on repeatability rather than the calibration). With few recordings the "
                  "ratio is itself uncertain: its relative std is about 1/√(2 dof).", "",
                  "| term | parameters | ratio | largest \\|z\\| |", "|---|---|---|---|"]
        for t, r in rep.items():
            n = int(np.isfinite(r["spread"]).sum())
            zmax = np.nanmax(np.abs(r["z"])) if n else float("nan")
            lines.append(f"| {t} | {n} | {r['ratio']:.3g} | {zmax:.3g} |")
        lines += ["", "Per IMU and parameter: spread (sample std across the recordings) / RMS reported std.", ""]
        for t, r in rep.items():
            lines += [f"### {t}", ""] + _repeat_table(t, r, names, data["terms"][t]["units"]) + [""]
    if figures:
        lines += ["## Plots", ""] + [f"![{f}]({f})\n\n{PLOTS.get(f, '')}\n" for f in figures]
    lines += ["## Files", "", "`calibration.json`: every value, written std and Cramér-Rao bound (SI units), "
              "the residual maps and the stages' record. `manifest.json`: the files of this report.", ""]
    return "\n".join(lines)


# --------------------------------------------------------------------------- writing


def _json(data: dict) -> dict:
    res = {k: v for k, v in data["residuals"].items() if k != "series"}
    rep = {t: {k: v for k, v in r.items() if k in ("spread", "mean_std", "ratio", "value", "std", "parameters")}
           for t, r in data["repeatability"].items()}
    return json_safe({**{k: v for k, v in data.items() if k not in ("residuals", "repeatability")},
                      "residual_rms": {**res, "axes": list(AXES)}, "repeatability": rep})


def write_calibration_report(directory: str | os.PathLike, calibrations: Sequence[Calibration], *, start,
                             sources: Sequence[str] = (), plots: bool = True) -> list[Path]:
    """Write the report of ``calibrations`` (module docstring; the first in full, all of them for the
    repeatability section) into ``directory`` as a whole, atomically, replacing what is there.

    start: the starting description or model (the residuals' "before"); sources: the recordings' names.
    Whether ``directory`` may be written is :func:`check_report_dir`'s business: call it first, before any
    work.  Returns the paths written."""
    directory = Path(directory)
    data = report_data(calibrations, start, sources)
    names: list[str] = []
    with atomic_path(directory, directory=True) as tmp:
        atomic_write_text(tmp / "calibration.json", json.dumps(_json(data), indent=1, allow_nan=False) + "\n")
        names.append("calibration.json")
        figures = []
        if plots:
            from imu_array_ros.calibration.report_plots import draw_all

            figures = draw_all(data, tmp)
            names += figures
        atomic_write_text(tmp / "index.md", markdown(data, figures))
        names.append("index.md")
        write_report_manifest(tmp, _KIND, names)
    return [directory / n for n in names + [MANIFEST]]
