"""The discovery report: ``report.json`` (the schema of the issue, plus detail), ``report.md`` and PNG plots.

:func:`write_report` writes a :class:`~imu_array_ros.discovery.discover.Discovery`
into a directory, every file atomically: a reader never sees half a report file.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from imu_array_ros.fusion.residuals import AXES
from imu_array_ros.util.files import atomic_write_text
from imu_array_ros.util.jsontools import json_safe
from imu_array_ros.model.terms import REGISTRY

__all__ = ["write_report", "markdown", "PLOTS", "MAX_MODE_PLOTS"]

#: a plot for each of the strongest modes, at most this many
MAX_MODE_PLOTS = 3

#: the plots written next to the report
PLOTS = {"residual_map.png": "normalised residual (observed / expected r^2) by IMU x axis, before and after",
         "spectra.png": "relative PSD of the residual of the cells in most excess, before and after",
         "evidence.png": "log-likelihood gain of every candidate that passed, accepted ones highlighted",
         "time.png": "residual ratio over time, before and after",
         "timing.png": "a sample clock found: one IMU's reading delay vs time with its sawtooth; its residual vs "
                       "angular acceleration without and with the clocks",
         **{f"mode_{i}.png": "a narrowband mode (outside the library): its shape across the array (IMU positions "
                             "coloured by signed amplitude, arrows its in-plane direction) and its line in the "
                             "spectrum" for i in range(1, MAX_MODE_PLOTS + 1)}}


def _g(x, fmt=".4g") -> str:
    return "—" if x is None or (isinstance(x, float) and not np.isfinite(x)) else format(x, fmt)


def write_report(d, directory: Path, *, plots: bool = True, source: str = "") -> list[Path]:
    """report.json, report.md and (``plots``) the PNGs of :data:`PLOTS` in ``directory``; the paths written."""
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    data = json_safe(d.to_dict())
    data["recording"] = source
    written = []
    path = directory / "report.json"
    atomic_write_text(path, json.dumps(data, indent=2, allow_nan=False) + "\n")
    written.append(path)
    figures = []
    if plots:
        figures = _plots(d, directory)
        written += figures
    path = directory / "report.md"
    atomic_write_text(path, markdown(d, source=source, figures=[p.name for p in figures]))
    written.append(path)
    return written


def _plots(d, directory: Path) -> list[Path]:
    from imu_array_ros.discovery import plots

    out = []
    lb, la = d.localization_before, d.localization_after
    path = directory / "residual_map.png"
    plots.plot_residual_maps(d.baseline.ratio("all"), d.after.ratio("all"), list(d.names), path,
                             title="observed / expected squared normalised residual (1 = noise)")
    out.append(path)
    if lb is not None and lb.freqs.size:
        path = directory / "spectra.png"
        after = la.psd if la is not None and la.psd.shape == lb.psd.shape else None
        plots.plot_spectra(lb.freqs, lb.psd, after, list(d.names), path)
        out.append(path)
    path = directory / "evidence.png"
    cands = [c.to_dict() for c in d.candidates if c.accepted or c.passes(d.level_per_step[min(c.step, len(d.level_per_step)) - 1])] \
        if d.level_per_step else []
    threshold = None
    if d.level_per_step:
        import scipy.stats
        threshold = 0.5 * float(scipy.stats.chi2.isf(d.level_per_step[0], 3))
    plots.plot_evidence(cands, path, threshold=threshold)
    out.append(path)
    if lb is not None and len(lb.windows):
        path = directory / "time.png"
        after = la.window_ratio if la is not None and len(la.window_ratio) == len(lb.window_ratio) else None
        plots.plot_time(lb.windows, lb.window_ratio, after, path, spans=lb.spans)
        out.append(path)
    search = _mode_search(d)
    if search is not None and search.positions is not None:
        for i, m in enumerate(search.modes[:MAX_MODE_PLOTS], start=1):
            path = directory / f"mode_{i}.png"
            plots.plot_mode(m.to_dict(d.names), list(d.names), search.positions, search.freqs, search.pooled,
                            search.pooled_threshold, path)
            out.append(path)
    timing = getattr(d, "timing", None)
    if timing is not None and timing.evidence:
        path = directory / "timing.png"
        plots.plot_timing(timing.evidence, path)
        out.append(path)
    return out


def _mode_search(d):
    """The mode search of the localisation the unexplained entries come from (after the findings, else before)."""
    loc = d.localization_after if d.localization_after is not None else d.localization_before
    return getattr(loc, "modes", None) if loc is not None else None


def _mode_lines(d) -> list[str]:
    """The report.md subsection on narrowband modes (:mod:`imu_array_ros.discovery.modes`)."""
    search = _mode_search(d)
    if search is None or not len(search.freqs):
        return []
    sm = search.summary()
    lines = ["", "### Narrowband modes (outside the library)", "",
             f"Searched {sm['bins_tested']} frequency bins of {_g(sm['resolution_hz'], '.3g')} Hz up to Nyquist in "
             f"every IMU x axis; false-alarm rate: {sm['false_alarm_rate']}.", ""]
    if not search.modes:
        lines.append("No narrowband mode.")
    for i, m in enumerate(search.modes, start=1):
        chans = ", ".join(f"{d.names[k]} {AXES[a]} {_g(float(m.amplitude[k, a]), '.2g')}σ"
                          f"∠{np.degrees(m.phase[k, a]):.0f}°" for k, a in m.channels[:8])
        more = f" (+{len(m.channels) - 8} more)" if len(m.channels) > 8 else ""
        sh, pr, em = m.shape, m.presence, m.model
        fits = ", ".join(f"{n} R² {v['r2']:.2f}" for n, v in sh.get("fits", {}).items())
        lines += [f"{i}. **{m.frequency_hz:.4g} Hz** (band {m.band_hz[0]:.4g}–{m.band_hz[1]:.4g} Hz, p = "
                  f"{m.p_value:.2g}, {m.test} test) on {len(m.imus)} IMU(s): {chans}{more} (in-band RMS in noise "
                  f"stds, phase relative to the strongest).",
                  f"   Shape ({sh.get('sensor', '')}, array frame): {sh.get('best') or '—'}"
                  + (f" [{fits}]" if fits else "") + ".",
                  f"   When: present in {pr.get('fraction_present', 0.0):.0%} of {pr.get('blocks', 0)} blocks of "
                  f"{pr.get('block_s', 0):g} s; regime {pr.get('regime', 'all')}.",
                  "   Empirical model: " + (f"{em['method']}: held-out sum of squared residuals of its channels × "
                                           f"{_g(em.get('ratio_after_before'), '.3g')}" if "ratio_after_before" in em
                                           else em.get("method", "not fitted")) + "."]
    if search.motion_lines:
        lines += ["", "Lines that follow the motion (a misfit for the library terms, not a mode): "
                      + ", ".join(f"{m.frequency_hz:.3g} Hz" for m in search.motion_lines) + "."]
    return lines


def _timing_lines(timing) -> list[str]:
    """The report.md section of the timing stage (:mod:`imu_array_ros.discovery.timing`)."""
    if timing is None:
        return []
    lines = ["", "## Timing (sample clocks, found by search)", ""]
    if timing.findings:
        lines += [f"- {f.text()}" for f in timing.findings]
        lines += ["", f"Log-likelihood at the ML motion with the clocks (rates held, phases estimated for this "
                      f"recording as session states): {_g(timing.loglik_before)} → {_g(timing.loglik_after)} "
                      f"(+{_g(timing.delta_loglik)})."]
    else:
        lines.append("No sample clock found." if timing.tested and not timing.dropped else
                     "No sample clock kept." if timing.tested else "Not tested.")
    if timing.dropped:
        lines += ["", "Found by the timing stage, then dropped: not found again given the library findings (a stand-in "
                      "for them; notes below):"] + [f"- {f.text()}" for f in timing.dropped]
    ctl = timing.to_dict()["false_finding_control"]
    null = ctl["measured_on_simulated_nulls"]
    lines += ["", f"False-finding control: {ctl['test']}; false-alarm rate per chip <= "
                  f"{ctl['false_alarm_rate_per_chip_bound']:.1g} (Rayleigh bound); on {null['chips']} simulated null "
                  f"chips the largest ratio was {_g(null['max_snr'], '.2g')}, {null['above_threshold']} reached it."]
    lines += [f"- {n}" for n in timing.notes]
    return lines


def _map_table(before: np.ndarray, after: np.ndarray, names) -> str:
    head = "| IMU | " + " | ".join(AXES) + " |\n|---|" + "---|" * len(AXES) + "\n"
    rows = "".join(f"| {n} | " + " | ".join(f"{_g(b, '.3g')} → {_g(a, '.3g')}" for b, a in zip(rb, ra)) + " |\n"
                   for n, rb, ra in zip(names, before, after))
    return head + rows


def markdown(d, *, source: str = "", figures=()) -> str:
    """The human-readable report."""
    data = d.to_dict()
    b, a = data["baseline"], data["after"]
    lines = [f"# Mismatch discovery{': ' + source if source else ''}", ""]
    s = d.settings
    lines += [f"{s['samples']} samples of {len(s['imus'])} IMUs; {len(s['terms'])} candidate terms per IMU; "
              f"time blocks of {s['block_s']} s dealt to {s['folds']} held-out folds. "
              f"False-finding rate: {s['false_finding_rate']}.", ""]
    lines += ["## Fit before and after", "",
              "| | log-likelihood | NIS still | NIS moving |", "|---|---|---|---|",
              f"| baseline (model as given) | {_g(b['loglik'], '.8g')} | {_g(b['nis_still'])} | {_g(b['nis_moving'])} |",
              f"| with the findings | {_g(a['loglik'], '.8g')} | {_g(a['nis_still'])} | {_g(a['nis_moving'])} |", ""]
    if d.heldout:
        h = d.heldout
        if "error" in h:
            lines += [f"Held-out check failed: {h['error']}", ""]
        else:
            lines += [f"Held-out blocks ({h['method']}): log-likelihood gain {_g(h['delta_loglik'])}, sum of "
                      f"squared normalised residuals × {_g(h['ratio_after_before'])}.", ""]
    if d.validation:
        lines += ["### Other recordings (`--validate`)", "", "| recording | Δ log-likelihood | NIS still | NIS moving |",
                  "|---|---|---|---|"]
        for v in d.validation:
            lines.append(f"| {v['recording']} | {_g(v['delta_loglik'])} | {_g(v['before']['nis_still'])} → "
                         f"{_g(v['after']['nis_still'])} | {_g(v['before']['nis_moving'])} → {_g(v['after']['nis_moving'])} |")
        lines.append("")
    lines += ["## Where the residual exceeds the noise", "", f"Source: {d.sim_source}.", ""]
    if data["localization"]:
        lines += ["| sensors (largest excess first) | axes | regime | band (Hz) | share of excess |", "|---|---|---|---|---|"]
        for e in data["localization"]:
            lines.append(f"| {', '.join(e['sensors'])} | {', '.join(e['axes'])} | {e['regime']} | "
                         f"{e['band_hz'][0]:.3g}–{e['band_hz'][1]:.3g} | {e['share_of_excess']:.1%} |")
    else:
        lines.append("Nothing: every IMU and axis is explained to the noise level.")
    lb = d.localization_before
    if lb is not None and lb.rigid is not None:
        lines += ["", f"Rigid-body test (accelerometer field not affine in position): ratio {_g(lb.rigid.ratio)} "
                      f"(1 = rigid), largest share on {d.names[int(np.nanargmax(lb.rigid.by_imu))]}."]
    if lb is not None and lb.spans:
        lines += ["", "Time spans in excess: " + ", ".join(f"{t0:.1f}–{t1:.1f} s" for t0, t1 in lb.spans[:12])
                  + (" ..." if len(lb.spans) > 12 else "")]
    lines += _timing_lines(getattr(d, "timing", None))
    lines += ["", "## Findings (terms of the sensor model)", ""]
    if d.findings:
        lines += ["| step | effect | sensor | parameters (± CRB std) | Δ log-lik | log p (LRT) | robust p | ΔBIC | held-out Δ log-lik |",
                  "|---|---|---|---|---|---|---|---|---|"]
        for f in d.findings:
            c = f.candidate
            units = {fl.key: fl.unit for fl in REGISTRY[f.effect].fields}
            pars = "; ".join(f"{n} = {v:.4g} ± {_g(sd, '.2g')} {units.get(n.split('[')[0], '')}"
                             for n, v, sd in zip(REGISTRY[f.effect].parameter_names(), f.values, f.std))
            lines.append(f"| {f.step} | {f.effect} | {f.sensor} | {pars} | {f.exact_delta_loglik:.4g} | "
                         f"{c.log_p:.4g} | {c.robust_p:.2g} | {c.delta_bic:.4g} | {c.heldout:.4g} |")
    else:
        lines.append("None: no term of the sensor model passes the corrected tests.")
    scoped = [f for f in d.findings if f.candidate.note and f.candidate.note.startswith(("tested at scope", "narrowing"))]
    if scoped:  # discovery/subset.py: which IMUs of a pooled scope carry the effect
        lines += ["", "### Which IMUs carry each pooled finding", ""]
        lines += [f"- {f.effect} on {f.sensor}: {f.candidate.note}" for f in scoped]
    if d.indistinguishable:
        lines += ["", "### Indistinguishable", ""]
        for e in d.indistinguishable:
            lines.append(f"- {' / '.join(e['effects'])} on {', '.join(e['sensors'])}: {e['reason']}")
    if d.rejected:
        lines += ["", "### Candidates the exact fit did not confirm", ""]
        lines += [f"- step {r['step']}: {r['effect']} on {', '.join(r['sensors'])}: {r['reason']}" for r in d.rejected]
    lines += ["", "## Unexplained (no term of the library)", ""]
    if d.unexplained:
        lines += ["| sensors | axes | regime | band (Hz) | share of residual excess | empirical model (held-out) |",
                  "|---|---|---|---|---|---|"]
        for u in d.unexplained:
            em = u["empirical_model"]
            feats = sorted({f for c in em["cells"] for f in c["features"]})
            what = (f"improves: +{em['heldout_delta_loglik']:.3g} log-lik, features {', '.join(feats[:6])}"
                    if em["improves_heldout"] else f"no motion feature predicts it (held-out {em['heldout_delta_loglik']:.3g})")
            lines.append(f"| {', '.join(u['sensors'])} | {', '.join(u['axes'])} | {u['regime']} | "
                         f"{u['band_hz'][0]:.3g}–{u['band_hz'][1]:.3g} | {u['share_of_residual']:.1%} | {what} |")
        lines += ["", "Empirical models are reported, never applied to the description."]
    else:
        lines.append("Nothing left above the noise.")
    lines += _mode_lines(d)
    if d.baseline.observed["all"].size:
        lines += ["", "## Residual map (observed / expected r², before → after)", "",
                  _map_table(d.baseline.ratio("all"), d.after.ratio("all"), d.names)]
    if figures:
        lines += ["## Plots", ""] + [f"![{f}]({f}) — {PLOTS.get(f, '')}" for f in figures] + [""]
    if d.notes:
        lines += ["## Notes", ""] + [f"- {n}" for n in d.notes] + [""]
    t = d.timings
    lines += ["Timings: " + ", ".join(f"{k} {v:.1f} s" for k, v in t.items()), ""]
    return "\n".join(lines)
