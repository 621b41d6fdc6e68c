"""The calibration contract: what every calibration returns, and the one way it is installed.

Every calibration -- geometry (joint or BCD), static (ML or PCA), ``all``, ``fit``,
``bayes`` and ``discover --apply`` -- returns a :class:`Calibration`:

* ``model``: the calibrated :class:`~imu_array_ros.model.sensor_model.SensorModel` (every term);
* ``std``: the standard deviations written beside the fitted fields (``<field>_std``);
* ``record``: the ``calibration:`` block of the written file (method, provenance, statistics);
* ``scorer``: the log-likelihood of a model on the data this calibration used (a window of
  samples with the motion profiled out, or still-pose averages), so a calibration on file can be
  compared with the new one on the same data;
* ``details``: the method's own result (positions' history, the static stage's poses, the
  posterior, ...) for tables and plots.

It is applied to a description with :meth:`Calibration.apply` and written with
:meth:`Calibration.install`, the only install path:

* ``out`` absent: written atomically (:func:`~imu_array_ros.util.files.atomic_write_text`);
* ``out`` present and a description of the same IMUs: scored on the calibration's data; if
  it scores higher than the new calibration (by more than ``LOGLIK_TOLERANCE``; with the
  calibration's ``allowance`` added to the new score -- the Bayesian posterior mean is not the
  likelihood's maximum), nothing is written and :class:`~imu_array_ros.errors.CalibrationError`
  says so; otherwise its bytes are kept in ``<out>.bak`` and the new file replaces it (both atomic);
* ``out`` present but a description of other IMUs, or not a regular file: refused
  (:class:`~imu_array_ros.errors.OutputError`), nothing touched;
* ``out`` present but not a readable description: not a good calibration, so it is replaced,
  its bytes kept in ``<out>.bak``.

A failed calibration raises before it has a result, so it never touches ``out``.
"""

from __future__ import annotations

import datetime
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Protocol, Sequence

import numpy as np

from imu_array_ros.errors import CalibrationError, ConfigError, OutputError
from imu_array_ros.model.description import ArrayDescription, dump_description, load_description
from imu_array_ros.model.sensor_model import SensorModel
from imu_array_ros.util.files import atomic_write_bytes, atomic_write_text
from imu_array_ros.version import __version__

__all__ = ["Calibration", "Scorer", "SumScorer", "Installed", "install_description", "check_install_target",
           "backup_path", "provenance",
           "fit_statistics", "LOGLIK_TOLERANCE"]

#: a file on disk counts as better only when its log-likelihood is higher by more than this (a
#: likelihood ratio of 1.001: two converged solvers of the same problem differ by less)
LOGLIK_TOLERANCE = 1e-3


def provenance() -> dict:
    """The ``software`` and ``time`` (UTC, ISO 8601) entries of every ``calibration:`` record."""
    return {"software": f"imu_array_ros {__version__}",
            "time": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds")}


def fit_statistics(result) -> dict:
    """The iterations, convergence, log-likelihood and NIS before/after entries of a record, from a
    result with those attributes (the engine's FitResult, GeometryCalibration, StaticCalibration);
    non-finite -> None."""
    f = lambda x: float(x) if np.isfinite(x) else None  # noqa: E731
    return {"iterations": int(result.iterations), "converged": bool(result.converged),
            "log_likelihood_before": f(result.loglik_before), "log_likelihood_after": f(result.loglik_after),
            "nis_before": f(result.nis_before), "nis_after": f(result.nis_after)}


class Scorer(Protocol):
    """Log-likelihood of a sensor model on the data a calibration used (higher: fits better)."""

    def __call__(self, model: SensorModel) -> float: ...


@dataclass
class SumScorer:
    """The sum of several scorers (e.g. still poses and the moving window of ``calibrate all``)."""

    parts: Sequence[Scorer]

    def __call__(self, model: SensorModel) -> float:
        return float(sum(part(model) for part in self.parts))


@dataclass
class Installed:
    """What :meth:`Calibration.install` did: the file written, the backup (None: there was no previous
    file) and the previous file's score on the calibration's data (None: not scored)."""

    out: Path
    backup: Path | None
    previous_score: float | None


def backup_path(out: str | Path) -> Path:
    """``<out>.bak``: where the previous calibration is kept."""
    out = Path(out)
    return out.with_name(out.name + ".bak")


@dataclass
class Calibration:
    """What every calibration returns (module docstring).

    method: "geometry", "static", "all", "fit", "bayes" or "discover"; model: the calibrated model;
    std: term -> (K, P) standard deviations of the fitted fields (NaN: not written); record: the
    ``calibration:`` block; scorer: log-likelihood of a model on the calibration's data (None: not
    comparable, a file on disk is always replaced, kept as ``.bak``); score: the scorer's value for
    ``model`` (None: computed when needed); allowance: added to ``score`` before comparing with a
    file on disk; data: what the scorer scores on, for messages ("window", "poses", ...); converged: whether the method met its convergence test; summary_line: one line
    for a person; details: the method's own result.
    """

    method: str
    model: SensorModel
    std: dict[str, np.ndarray]
    record: dict
    scorer: Scorer | None = None
    score: float | None = None
    allowance: float = 0.0
    data: str = "window"
    converged: bool = True
    summary_line: str = ""
    details: Any = field(default=None, repr=False)

    @property
    def names(self) -> tuple[str, ...]:
        return self.model.names

    @property
    def terms(self) -> list[str]:
        """The terms written: the fitted ones (``std``) and every other term not at its identity value."""
        return list(self.std) + [n for n, t in self.model.terms.items() if n not in self.std and not t.is_identity]

    def summary(self) -> str:
        return self.summary_line

    def apply(self, desc: ArrayDescription) -> ArrayDescription:
        """``desc`` (same IMUs) with the calibrated values of :attr:`terms`, their ``_std`` and the record.
        When ``desc`` is itself calibrated, its record is kept in the new one as ``previous`` (one level:
        what the fields this calibration did not fit, and their ``_std``, come from)."""
        out = self.model.to_description(desc, names=self.terms, stds=self.std)
        record = dict(self.record)
        if desc.calibration:
            record["previous"] = {k: v for k, v in desc.calibration.items() if k != "previous"}
        return out.with_imus(out.imus, calibration=record)

    def score_of(self, model: SensorModel | ArrayDescription) -> float:
        """The scorer's log-likelihood of ``model`` (a description is turned into its model)."""
        if self.scorer is None:
            raise CalibrationError(f"{self.method}: this calibration has no data to score a model on")
        if isinstance(model, ArrayDescription):
            model = SensorModel.from_description(model)
        return float(self.scorer(model))

    def install(self, desc: ArrayDescription, out: str | Path) -> Installed:
        """Write :meth:`apply` of ``desc`` to ``out`` unless the file there fits better (module docstring)."""
        def new_score() -> float:  # only when a description on file is compared with it
            return (self.score_of(self.model) if self.score is None else self.score) + self.allowance

        return install_description(self.apply(desc), out, score=self.score_of if self.scorer else None,
                                   new_score=new_score if self.scorer else None, data=self.data)


def check_install_target(out: str | Path, names) -> ArrayDescription | None:
    """Refuse, before any work, what :func:`install_description` refuses whatever the result: ``out`` not a
    regular file, or a description of other IMUs than ``names``.  Returns the description on file (None: no
    file, or one that is no readable description -- not a good calibration, kept as the backup)."""
    out = Path(out)
    if out.is_symlink() or (out.exists() and not out.is_file()):
        raise OutputError(f"{out}: not a regular file; not replaced")
    if not out.exists():
        return None
    try:
        previous = load_description(out)
    except ConfigError:
        return None
    if tuple(previous.names) != tuple(names):
        raise OutputError(f"{out}: holds a description of other IMUs ({', '.join(previous.names[:4])}...); "
                          "not replaced")
    return previous


def install_description(new: ArrayDescription, out: str | Path, *, score=None,
                        new_score: float | Callable[[], float] | None = None, data: str = "window") -> Installed:
    """Write ``new`` to ``out`` unless the description already there scores higher than ``new_score``
    under ``score(description)`` (module docstring); ``new_score`` may be a function, called only when there is a
    description to compare with; ``data`` names what was scored, for the message."""
    out = Path(out)
    previous = check_install_target(out, new.names)
    previous_score = None
    if previous is not None and score is not None and new_score is not None:
        new_score = float(new_score() if callable(new_score) else new_score)
        previous_score = float(score(previous))
        if np.isfinite(previous_score) and previous_score > new_score + LOGLIK_TOLERANCE:
            raise CalibrationError(
                f"{out}: not replaced: the calibration on file fits this {data} better "
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
