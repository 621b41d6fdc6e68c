"""Optional dependencies: each belongs to an extra of the package, and a missing one is a one-line error.

The core needs numpy, scipy, pyyaml and the recording libraries only.  What
some commands need beyond that is an *extra* (``setup.py`` ``extras_require``):

* ``plots``: matplotlib (``--plot``, report figures);
* ``bayes``: arviz, h5netcdf and dask (``imu-array calibrate bayes``);
* ``noise``: allantools (``imu-array calibrate noise``).

:func:`require` imports such a module or raises
:class:`~imu_array_ros.errors.MissingDependencyError` naming the extra to install.
"""

from __future__ import annotations

import importlib
from types import ModuleType

from imu_array_ros.errors import MissingDependencyError

__all__ = ["require", "EXTRAS"]

#: extra -> the modules it provides (what ``pip install 'imu_array_ros[<extra>]'`` installs)
EXTRAS = {
    "plots": ("matplotlib",),
    "bayes": ("arviz", "h5netcdf", "dask", "distributed"),
    "noise": ("allantools",),
}


def require(module: str, extra: str, what: str, instead: str | None = None) -> ModuleType:
    """``import module``; MissingDependencyError "<module>, needed for ``what``, is not installed (pip install
    'imu_array_ros[<extra>]', or ``instead``)" when it is not installed (``what`` singular or plural alike:
    "--plot cal.png", "the report's plots"; ``instead``: what to do without it, e.g. "pass --no-plots")."""
    if extra not in EXTRAS:
        raise ValueError(f"unknown extra {extra!r} (known: {', '.join(EXTRAS)})")
    try:
        return importlib.import_module(module)
    except ImportError as err:
        top = module.split(".")[0]
        if getattr(err, "name", None) not in (None, module, top):
            raise  # the module is there but something it imports is broken: not a missing extra
        raise MissingDependencyError(f"{top}, needed for {what}, is not installed "
                                     f"(pip install 'imu_array_ros[{extra}]'{f', or {instead}' if instead else ''})"
                                     ) from None
