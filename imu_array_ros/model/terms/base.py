"""The term interface of the sensor model, its registry, and the motion context.

A *term* is one piece of sensor physics acting on one sensor type of every IMU
(accelerometer, gyroscope or both): a named, per-IMU parameter vector with units and
an identity default, stored in the description under the YAML fields it owns,
and its effect on the signal as it passes along that sensor's measurement
chain (:mod:`imu_array_ros.model.linear`)::

    x  <-  term.apply(x, ctx, sensor)   x: (N, K, 3) the signal at the term's stage

with three analytic derivatives, all batched over samples and IMUs:

* ``d_input``  (N, K, 3, 3): d apply / d x (None: identity, the term is additive);
* ``d_params`` (N, K, 3, P): d apply / d theta_k (theta_k: the term's P parameters of IMU k);
* ``d_motion`` (N, K, 3, 9): direct dependence on the motion m = [omega, omega_dot, s]
  (None: none);
* ``d_positions`` (N, K, 3, 3): direct dependence on the accelerometer positions, for
  terms that read them (None: none).

The model chains them (forward for the prediction, backward for Jacobians), so a
term never needs to know what comes before or after it.  Terms are ordered by
``order`` within their sensor's chain.  Adding a term = one module in this
package defining a subclass decorated with :func:`register`; it is found and
imported automatically (see ``terms/__init__.py``) and its YAML fields are
parsed, written and fitted with nothing else edited.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property
from typing import ClassVar

import numpy as np

from imu_array_ros.model.kinematics import skew

__all__ = ["Field", "Term", "MotionContext", "REGISTRY", "register", "SENSORS"]

SENSORS = ("accelerometer", "gyroscope")

#: registry name -> term class, filled by :func:`register` as the term modules are imported
REGISTRY: dict[str, type["Term"]] = {}


@dataclass(frozen=True)
class Field:
    """One YAML field a term owns, per IMU.

    path: keys below the IMU's mapping, e.g. ``("accelerometer", "gain")``;
    shape: per-IMU shape, () for a scalar; unit: SI unit text; default: the
    identity value of every element; positive: values must be > 0 (or 0 when
    ``default`` is 0); session: a *session state* (a value that changes at every
    power-up or recording, e.g. a clock phase), estimated from each recording and
    never written into a description as a device constant; fitted: the fitting
    engine estimates it (False: held, set by the user or by a dedicated estimator,
    e.g. a nominal clock period or a phase found by search); plausible: the largest
    |value - default| of an element a real sensor plausibly has, in ``unit`` (None: no bound),
    what :mod:`imu_array_ros.calibration.guards` refuses a calibration beyond; plausible_of_range:
    ``plausible`` is a fraction of the sensor's full-scale range instead (biases).
    """

    path: tuple[str, ...]
    shape: tuple[int, ...]
    unit: str
    default: float = 0.0
    positive: bool = False
    session: bool = False
    fitted: bool = True
    plausible: float | None = None
    plausible_of_range: bool = False

    @property
    def size(self) -> int:
        return int(np.prod(self.shape, dtype=int))

    @property
    def key(self) -> str:
        """Dotted YAML path, e.g. ``accelerometer.gain``."""
        return ".".join(self.path)

    def default_value(self) -> np.ndarray:
        return np.full(self.shape, float(self.default))


def register(cls: type["Term"]) -> type["Term"]:
    """Class decorator: add a term class to :data:`REGISTRY` under ``cls.name``."""
    if not cls.name or cls.name in REGISTRY:
        raise ValueError(f"term name {cls.name!r} is empty or registered twice")
    if not cls.sensors or not set(cls.sensors) <= set(SENSORS):
        raise ValueError(f"term {cls.name!r}: sensors must be a non-empty subset of {SENSORS}")
    REGISTRY[cls.name] = cls
    return cls


@dataclass
class MotionContext:
    """The motion the readings are predicted for, and what terms derive from it.

    stamps (N,) int64 ns; t (N,) s since ``t0_ns`` (the recording's first stamp,
    for drifts); omega (N, 3) rad/s, omega_dot (N, 3) rad/s^2, specific_force
    (N, 3) m/s^2 at the array origin, all in the array frame.  omega_ddot and
    specific_force_dot (N, 3): time derivatives, needed only by the timing terms
    (zeros when not given).  rotations (K, 3, 3): sensor -> array (nominal).
    positions (K, 3) m: accelerometer positions (the ``position`` term sets it).
    stamp_delays (N, K) s: for IMUs that stamp their own messages, each IMU's own
    stamp minus the array sample's stamp (None: every IMU carries the array's stamp).
    trajectory: the motion as a function of time (``trajectory(t_ns) -> (omega,
    omega_dot, specific_force)``, each (N, ..., 3), at int64 ns times (N, ...), row n
    near stamp n):
    when given, the timing terms evaluate every reading at its true sample time
    exactly (the simulator's dense truth, the fusion's interpolated estimate)
    instead of to first order.  omega_rate (N, 3): d omega / dt of the angular-rate
    estimates, the gyroscopes' rate of change for a first-order time shift (None: omega_dot).
    remainders: a dict the timing stage may keep its remainders in
    (:meth:`~imu_array_ros.model.terms.timing.TimingStage.remainder`), given by a caller whose contexts of these
    samples share one trajectory object for as long as the dict lives (the fitting engine's frozen trajectory);
    None: none kept.
    """

    stamps: np.ndarray
    omega: np.ndarray
    omega_dot: np.ndarray
    specific_force: np.ndarray
    rotations: np.ndarray
    t0_ns: int | None = None
    omega_ddot: np.ndarray | None = None
    specific_force_dot: np.ndarray | None = None
    positions: np.ndarray | None = field(default=None, repr=False)
    stamp_delays: np.ndarray | None = None
    trajectory: object | None = field(default=None, repr=False)
    omega_rate: np.ndarray | None = None
    remainders: dict | None = field(default=None, repr=False, compare=False)

    @property
    def n(self) -> int:
        return len(self.stamps)

    @property
    def k(self) -> int:
        return len(self.rotations)

    @cached_property
    def t(self) -> np.ndarray:
        t0 = int(self.stamps[0]) if self.t0_ns is None and len(self.stamps) else (self.t0_ns or 0)
        return (np.asarray(self.stamps, dtype=np.int64) - t0) * 1e-9

    @cached_property
    def rot_t(self) -> np.ndarray:
        """(K, 3, 3) array -> sensor."""
        return np.swapaxes(self.rotations, 1, 2)

    @cached_property
    def lever(self) -> np.ndarray:
        """(N, 3, 3) C with f(r) = s + C r: C = [omega]x^2 + [omega_dot]x (skog2016 eq. 1)."""
        w = skew(self.omega)
        return w @ w + skew(self.omega_dot)

    @cached_property
    def lever_dot(self) -> np.ndarray:
        """(N, 3, 3) dC/dt = [w_dot]x [w]x + [w]x [w_dot]x + [w_ddot]x."""
        w, wd = skew(self.omega), skew(self.omega_dot)
        wdd = skew(self.omega_ddot) if self.omega_ddot is not None else 0.0
        return wd @ w + w @ wd + wdd

    def force_at(self, r: np.ndarray) -> np.ndarray:
        """(N, K, 3) specific force in the array frame at positions r (K, 3)."""
        return self.specific_force[:, None, :] + np.einsum("nij,kj->nki", self.lever, r)

    def force_jacobian(self, r: np.ndarray) -> np.ndarray:
        """(N, K, 3, 9) d f(r) / d [omega, omega_dot, s] at positions r (K, 3), array frame.

        d/d omega of omega x (omega x r) is ``[omega]x^T [r]x + [r x omega]x``
        (skog2016 eq. 13's A(omega, r)); d/d omega_dot = -[r]x; d/d s = I.
        """
        su = skew(self.omega)[:, None]
        sr = skew(r)[None]
        a = np.swapaxes(su, -1, -2) @ sr + skew(np.cross(r[None], self.omega[:, None]))
        n, k = self.n, len(r)
        return np.concatenate([a, np.broadcast_to(-sr, (n, k, 3, 3)), np.broadcast_to(np.eye(3), (n, k, 3, 3))], axis=3)


class Term:
    """Base class of a sensor-model term (see module docstring).

    Class attributes: ``name`` (registry name), ``sensors`` (the chains it acts
    in: 'accelerometer', 'gyroscope' or both), ``order`` (position in a chain; lower first),
    ``fields`` (the YAML fields it owns, in parameter order), ``linear`` (True
    when the term keeps the reading linear in [q(omega), omega_dot, s], so the
    fusion can carry it exactly), ``hint`` (one short sentence: the motion that
    identifies the term's parameters, quoted when a fit cannot identify them),
    ``candidate`` (False for a term the engine cannot fit from its identity value alone:
    a sample clock needs its period and a phase search, a stamp clock needs messages
    with their own stamps; such terms are left out of the default candidate lists of
    discovery and of the simulated suites).
    Instances hold ``values`` (K, P).
    """

    name: ClassVar[str] = ""
    sensors: ClassVar[tuple[str, ...]] = ()
    order: ClassVar[int] = 0
    fields: ClassVar[tuple[Field, ...]] = ()
    linear: ClassVar[bool] = True
    candidate: ClassVar[bool] = True
    description: ClassVar[str] = ""
    hint: ClassVar[str] = ""

    def __init__(self, values: np.ndarray) -> None:
        values = np.asarray(values, dtype=float)
        if values.ndim != 2 or values.shape[1] != self.dim():
            raise ValueError(f"term {self.name!r}: values must be (K, {self.dim()}), got {values.shape}")
        self.values = values

    # ---- parameters
    @classmethod
    def dim(cls) -> int:
        """P, the number of parameters per IMU."""
        return sum(f.size for f in cls.fields)

    @classmethod
    def parameter_names(cls) -> list[str]:
        """Names of the P parameters, e.g. ``accelerometer.gain[0]``."""
        out = []
        for f in cls.fields:
            if f.shape == ():
                out.append(f.key)
            else:
                out += [f"{f.key}[{','.join(map(str, idx))}]" for idx in np.ndindex(*f.shape)]
        return out

    @classmethod
    def default_values(cls, k: int) -> np.ndarray:
        """(K, P) identity values."""
        row = np.concatenate([f.default_value().ravel() for f in cls.fields]) if cls.fields else np.zeros(0)
        return np.tile(row, (k, 1))

    @classmethod
    def identity(cls, k: int) -> "Term":
        return cls(cls.default_values(k))

    def split(self) -> dict[str, np.ndarray]:
        """Field key -> (K, *shape) values."""
        out, i = {}, 0
        for f in self.fields:
            out[f.key] = self.values[:, i:i + f.size].reshape((len(self.values),) + f.shape)
            i += f.size
        return out

    @property
    def is_identity(self) -> bool:
        return bool(np.array_equal(self.values, self.default_values(len(self.values))))

    def with_values(self, values: np.ndarray) -> "Term":
        return type(self)(values)

    # ---- physics (override)
    def apply(self, x: np.ndarray, ctx: MotionContext, sensor: str) -> np.ndarray:
        """The signal after this term, (N, K, 3)."""
        raise NotImplementedError

    def d_input(self, x: np.ndarray, ctx: MotionContext, sensor: str) -> np.ndarray | None:
        """(N, K, 3, 3) d apply / d x, or None for the identity."""
        return None

    def d_params(self, x: np.ndarray, ctx: MotionContext, sensor: str) -> np.ndarray:
        """(N, K, 3, P) d apply / d theta_k (zero columns for parameters of the other sensor)."""
        raise NotImplementedError

    def d_motion(self, x: np.ndarray, ctx: MotionContext, sensor: str) -> np.ndarray | None:
        """(N, K, 3, 9) direct d apply / d [omega, omega_dot, s], or None."""
        return None

    def d_positions(self, x: np.ndarray, ctx: MotionContext, sensor: str) -> np.ndarray | None:
        """(N, K, 3, 3) d apply / d p_k for a term that reads ``ctx.positions`` (the ``position``
        term's values), or None.  The model adds it to the position Jacobian."""
        return None

    def __repr__(self) -> str:
        return f"{type(self).__name__}(K={len(self.values)}, identity={self.is_identity})"
