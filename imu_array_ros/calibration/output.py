"""Writing a calibration: atomically, with a backup, and never over a better one.

:func:`install_calibration` is what the calibration node and ``imu-array
calibrate geometry`` call to put a calibrated description at ``out``:

* ``out`` absent: written atomically (:func:`~imu_array_ros.io.outputs.atomic_write_text`);
* ``out`` present and a description of the same IMUs: scored on the same
  window as the new calibration (``score``, e.g. the window's log-likelihood
  with the motion fitted); if it scores higher, nothing is written and
  :class:`~imu_array_ros.errors.CalibrationError` says so (higher by more
  than ``LOGLIK_TOLERANCE``: equal within rounding is not better); otherwise its bytes
  are copied to ``<out>.bak`` and the new file replaces it (both atomic);
* ``out`` present but a description of other IMUs, or not a regular file:
  refused (:class:`~imu_array_ros.errors.OutputError`), nothing touched;
* ``out`` present but not a readable description (half-written by another
  program, hand-edited into an error): not a good calibration, so it is
  replaced, its bytes kept in ``<out>.bak``.

A failed calibration never reaches this function, so it never touches ``out``.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np

from imu_array_ros.errors import CalibrationError, ConfigError, OutputError
from imu_array_ros.util.files import atomic_write_bytes, atomic_write_text
from imu_array_ros.model.description import ArrayDescription, dump_description, load_description

__all__ = ["Installed", "install_calibration", "backup_path", "geometry_description", "positions_description", "provenance", "fit_statistics",
           "LOGLIK_TOLERANCE"]

#: a file on disk counts as better only when its log-likelihood is higher by more than this (a
#: likelihood ratio of 1.001: two converged solvers of the same problem differ by less)
LOGLIK_TOLERANCE = 1e-3


def provenance() -> dict:
    """The ``software`` and ``time`` (UTC, ISO 8601) entries of every ``calibration:`` record."""
    import datetime

    from imu_array_ros.version import __version__

    return {"software": f"imu_array_ros {__version__}",
            "time": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds")}


def fit_statistics(result) -> dict:
    """The iterations, convergence, log-likelihood and NIS before/after entries of a fit's record (any result
    with those attributes: the engine's, the geometry's, the static calibration's); non-finite -> None."""
    f = lambda x: float(x) if np.isfinite(x) else None  # noqa: E731
    return {"iterations": int(result.iterations), "converged": bool(result.converged),
            "log_likelihood_before": f(result.loglik_before), "log_likelihood_after": f(result.loglik_after),
            "nis_before": f(result.nis_before), "nis_after": f(result.nis_after)}


@dataclass
class Installed:
    """What :func:`install_calibration` did: the file written, the backup (None: there was no
    previous file) and the previous file's score on the window (None: not scored)."""

    out: Path
    backup: Path | None
    previous_score: float | None


def backup_path(out: str | Path) -> Path:
    """``<out>.bak``: where the previous calibration is kept."""
    out = Path(out)
    return out.with_name(out.name + ".bak")


def positions_description(desc: ArrayDescription, model, position_std: np.ndarray, record: dict) -> ArrayDescription:
    """``desc`` with the positions of ``model``, their ``position_std`` (K, 3), every other term of ``model``
    not at its identity, and the ``calibration:`` ``record``."""
    names = ["position"] + [n for n, t in model.terms.items() if n != "position" and not t.is_identity]
    out = model.to_description(desc, names=names, stds={"position": position_std})
    return out.with_imus(out.imus, calibration=record)


def geometry_description(desc: ArrayDescription, result) -> ArrayDescription:
    """``desc`` with the calibrated positions of a :class:`~imu_array_ros.calibration.geometry.GeometryCalibration`,
    their ``position_std`` and its ``calibration:`` block (the other calibrated fields as in ``result.model``)."""
    return positions_description(desc, result.model, result.position_std, result.record())


def install_calibration(new: ArrayDescription, out: str | Path, *,
                        score: Callable[[ArrayDescription], float] | None = None,
                        new_score: float | None = None) -> Installed:
    """Write ``new`` to ``out`` unless the description already there scores higher (module docstring)."""
    out = Path(out)
    if out.is_symlink() or (out.exists() and not out.is_file()):
        raise OutputError(f"{out}: not a regular file; not replaced")
    previous_score = None
    if out.exists():
        try:
            previous = load_description(out)
        except ConfigError:
            previous = None  # unreadable: not a good calibration; kept as the backup
        if previous is not None:
            if tuple(previous.names) != tuple(new.names):
                raise OutputError(f"{out}: holds a description of other IMUs ({', '.join(previous.names[:4])}...); "
                                  "not replaced")
            if score is not None and new_score is not None:
                previous_score = float(score(previous))
                if np.isfinite(previous_score) and previous_score > new_score + LOGLIK_TOLERANCE:
                    raise CalibrationError(
                        f"{out}: not replaced: the calibration on file fits this window better "
                        f"(log-likelihood {previous_score:.10g} > {new_score:.10g} of the new one)")
    backup = None
    try:
        if out.exists():
            backup = backup_path(out)
            if backup.is_symlink() or (backup.exists() and not backup.is_file()):
                raise OutputError(f"{backup}: not a regular file; cannot keep the previous calibration there")
            atomic_write_bytes(backup, out.read_bytes())
        atomic_write_text(out, dump_description(new))
    except OSError as err:
        raise OutputError(f"{out}: cannot write: {err.strerror or err}") from None
    return Installed(out, backup, previous_score)
