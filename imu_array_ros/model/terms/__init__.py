"""The sensor model's terms: one module per term, found and registered automatically.

``REGISTRY`` maps registry names (``position``, ``accelerometer_gain``, ...) to term
classes.  To add a term, add one module here defining a :class:`Term` subclass
decorated with :func:`register` (see :mod:`.base`); nothing else is edited.
"""

import importlib
import pkgutil

from imu_array_ros.model.terms.base import REGISTRY, SENSORS, Field, MotionContext, Term, register

__all__ = ["REGISTRY", "SENSORS", "Field", "MotionContext", "Term", "register", "term_names", "candidate_names"]

for _info in pkgutil.iter_modules(__path__):
    importlib.import_module(f"{__name__}.{_info.name}")


def term_names() -> list[str]:
    """Registry names in chain order (accelerometer chain first, then gyroscope-only terms)."""
    return sorted(REGISTRY, key=lambda n: (REGISTRY[n].sensors[0] != "accelerometer", REGISTRY[n].order, n))


def candidate_names() -> list[str]:
    """:func:`term_names` of the terms that are candidates by default (``Term.candidate``)."""
    return [n for n in term_names() if REGISTRY[n].candidate]
