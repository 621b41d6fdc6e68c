"""THE forward model of the array: nominal geometry + noise + ordered terms.

Each sensor of IMU k is a chain that starts from the motion in the nominal
sensor frame and passes every term acting on that sensor, in ``order``::

    accelerometer:  x = R^T s  -> position -> axis_offsets -> timing -> misalignment
                      -> nonorthogonality -> nonlinearity -> gain -> bias -> bias_drift
    gyroscope:      x = R^T omega -> timing -> misalignment -> nonorthogonality
                      -> gain -> g_sensitivity -> bias -> bias_drift

where *timing* is one stage: the signal at the reading's true sample time, the
stamp plus the sum of the timing terms' delays (``time_offset``,
``sample_clock``, ``stamp_clock``; :mod:`~imu_array_ros.model.terms.timing`)

(with every term at its identity value this is skog2016 eq. 1-5; with the
nilsson2014 terms it is y = K L (I + [xi]x) R^T s(r) + b).  :meth:`SensorModel.predict`
is what the simulator measures with and what residuals compare against;
:meth:`SensorModel.jacobians` chains the terms' analytic derivatives backwards
into d y / d theta (per term, per IMU) and d y / d [omega, omega_dot, s] (per
sample) for the fitting engine and the discovery tool.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Iterable, Sequence

import numpy as np

from imu_array_ros.model.saturation import unsaturated
from imu_array_ros.model.terms import REGISTRY, SENSORS, MotionContext, Term, term_names
from imu_array_ros.model.terms.timing import TimingStage, TimingTerm

__all__ = ["SensorModel", "ModelJacobians", "motion_context", "motion_derivative"]


def motion_context(stamps, omega, omega_dot, specific_force, rotations, *, t0_ns=None, omega_ddot=None,
                   specific_force_dot=None, derivatives: bool = False, stamp_delays=None,
                   trajectory=None, omega_rate=None) -> MotionContext:
    """A :class:`MotionContext` from arrays (N, 3) in the array frame; rotations (K, 3, 3).

    ``derivatives``: fill omega_ddot and specific_force_dot (when not given) by
    differentiating omega_dot and specific_force over the stamps (second-order
    central differences, one-sided at the ends; :func:`numpy.gradient`).  This is
    how the fitting engine obtains the derivatives the timing terms' first-order
    shift needs.  stamp_delays (N, K) s, trajectory: see
    :class:`~imu_array_ros.model.terms.base.MotionContext`.
    """
    f = lambda a: None if a is None else np.asarray(a, dtype=float).reshape(-1, 3)  # noqa: E731
    if derivatives:
        omega_ddot = motion_derivative(stamps, omega_dot) if omega_ddot is None else omega_ddot
        specific_force_dot = motion_derivative(stamps, specific_force) if specific_force_dot is None else specific_force_dot
    return MotionContext(stamps=np.asarray(stamps, dtype=np.int64).reshape(-1), omega=f(omega), omega_dot=f(omega_dot),
                         specific_force=f(specific_force), rotations=np.asarray(rotations, dtype=float),
                         t0_ns=t0_ns, omega_ddot=f(omega_ddot), specific_force_dot=f(specific_force_dot),
                         stamp_delays=None if stamp_delays is None else np.asarray(stamp_delays, dtype=float),
                         trajectory=trajectory, omega_rate=f(omega_rate))


def motion_derivative(stamps, values) -> np.ndarray:
    """d values / dt (N, 3) over integer ns ``stamps`` (N,); zeros for fewer than two samples."""
    values = np.asarray(values, dtype=float).reshape(-1, 3)
    if len(values) < 2:
        return np.zeros_like(values)
    t = (np.asarray(stamps, dtype=np.int64) - int(stamps[0])) * 1e-9
    return np.gradient(values, t, axis=0)


@dataclass
class ModelJacobians:
    """Predictions and Jacobians of every reading, rows [acc x, y, z, gyro x, y, z] per IMU.

    predicted (N, K, 6); motion (N, K, 6, 9) d y / d [omega, omega_dot, s] (None when not asked for);
    params: term name -> (N, K, 6, P) d y / d theta_k (IMU k's P parameters).
    """

    predicted: np.ndarray
    motion: np.ndarray | None
    params: dict[str, np.ndarray] = field(default_factory=dict)


@dataclass(frozen=True)
class SensorModel:
    """Nominal geometry, noise and every registered term (at its identity value unless set).

    names (K,); rotations (K, 3, 3) nominal sensor -> array; acc_std, gyro_std
    (K, 3) white-noise standard deviations; terms: registry name -> :class:`Term`;
    acc_clip, gyro_clip: magnitude the raw readings clip at (inf: never);
    acc_clip_tolerance, gyro_clip_tolerance: a reading with |y| >= clip - tolerance
    is saturated (None: :func:`~imu_array_ros.model.saturation.clip_tolerance`; half an LSB when quantised).
    """

    names: tuple[str, ...]
    frame_id: str
    rotations: np.ndarray
    acc_std: np.ndarray
    gyro_std: np.ndarray
    terms: dict[str, Term]
    acc_clip: float = np.inf
    gyro_clip: float = np.inf
    acc_clip_tolerance: float | None = None
    gyro_clip_tolerance: float | None = None

    @property
    def n_imus(self) -> int:
        return len(self.names)

    @property
    def positions(self) -> np.ndarray:
        """(K, 3) accelerometer positions (the ``position`` term's values), m."""
        return self.terms["position"].values

    def acc_unsaturated(self, values: np.ndarray) -> np.ndarray:
        """Raw accelerometer readings (any shape) that are finite and not clipped."""
        return unsaturated(values, self.acc_clip, self.acc_clip_tolerance)

    def gyro_unsaturated(self, values: np.ndarray) -> np.ndarray:
        """Raw gyroscope readings (any shape) that are finite and not clipped."""
        return unsaturated(values, self.gyro_clip, self.gyro_clip_tolerance)

    def valid(self, accel: np.ndarray, gyro: np.ndarray) -> np.ndarray:
        """(N, K, 6) True for the axes that carry information (finite, not saturated),
        rows [acc x, y, z, gyro x, y, z] as in :class:`ModelJacobians`."""
        return np.concatenate([self.acc_unsaturated(accel), self.gyro_unsaturated(gyro)], axis=-1)

    @property
    def std(self) -> np.ndarray:
        """(K, 6) noise standard deviations, rows as in :meth:`valid`."""
        return np.concatenate([self.acc_std, self.gyro_std], axis=1)

    @classmethod
    def from_description(cls, desc) -> "SensorModel":
        """Every term's values from the description's fields (identity where absent)."""
        k = len(desc.imus)
        terms = {}
        for name in term_names():
            tc = REGISTRY[name]
            values = tc.default_values(k)
            for i, imu in enumerate(desc.imus):
                values[i] = np.concatenate([np.asarray(imu.value(f.key), dtype=float).ravel() for f in tc.fields])
            terms[name] = tc(values)
        half = lambda lsb: None if lsb is None else 0.5 * lsb  # noqa: E731
        return cls(names=desc.names, frame_id=desc.frame_id, rotations=desc.orientations,
                   acc_std=np.full((k, 3), desc.accelerometer_noise_std),
                   gyro_std=np.full((k, 3), desc.gyroscope_noise_std), terms=terms,
                   acc_clip=float(desc.accelerometer_clip or desc.accelerometer_range),
                   gyro_clip=float(desc.gyroscope_clip or desc.gyroscope_range),
                   acc_clip_tolerance=half(desc.accelerometer_lsb), gyro_clip_tolerance=half(desc.gyroscope_lsb))

    def to_description(self, desc, names: Iterable[str] | None = None, stds: dict[str, np.ndarray] | None = None):
        """``desc`` (an :class:`~imu_array_ros.model.description.ArrayDescription` of the same
        IMUs) with the values of the terms ``names`` (default: every term that is not at
        its identity value) written into its fields, and ``stds`` (term name -> (K, P)
        standard deviations; NaN entries are left out) written as ``<field>_std``."""
        if tuple(desc.names) != tuple(self.names):
            raise ValueError("the description's IMUs differ from the model's")
        names = [n for n in self.terms if not self.terms[n].is_identity] if names is None else list(names)
        stds = stds or {}
        session = {f.key: f.session for n in names for f in REGISTRY[n].fields}
        imus = []
        for i, imu in enumerate(desc.imus):
            values, sd = {}, {}
            for name in names:
                for key, v in self.terms[name].split().items():
                    if not session.get(key):  # a session state is never written as a device constant
                        values[key] = v[i]
                if name in stds:
                    for key, v in _split(type(self.terms[name]), np.asarray(stds[name])).items():
                        if np.all(np.isfinite(v[i])) and not session.get(key):
                            sd[key] = v[i]
            imus.append(imu.with_values(values, sd))
        return desc.with_imus(imus)

    def linear_part(self) -> "SensorModel":
        """A copy with every term that is not ``linear`` at its identity value."""
        return replace(self, terms={n: (t if t.linear else type(t).identity(self.n_imus)) for n, t in self.terms.items()})

    @property
    def nonlinear_terms(self) -> list[str]:
        """Names of the terms that are not linear and not at their identity value."""
        return [n for n, t in self.terms.items() if not t.linear and not t.is_identity]

    def with_terms(self, **values: np.ndarray) -> "SensorModel":
        """A copy with some terms' values (K, P) replaced."""
        terms = dict(self.terms)
        for name, v in values.items():
            terms[name] = terms[name].with_values(np.asarray(v, dtype=float).reshape(self.n_imus, -1))
        return replace(self, terms=terms)

    def chain(self, sensor: str, keep: Iterable[str] = (), ctx: MotionContext | None = None) -> list:
        """The terms acting on ``sensor`` in order; identity terms left out unless in ``keep``.  The timing
        terms come as one :class:`~imu_array_ros.model.terms.timing.TimingStage` (also when only ``ctx``
        has stamp delays)."""
        keep = set(keep)
        out = [t for t in self.terms.values() if sensor in t.sensors and (t.name in keep or not t.is_identity)]
        timing = [t for t in out if isinstance(t, TimingTerm)]
        if timing or (ctx is not None and ctx.stamp_delays is not None):
            out = [t for t in out if not isinstance(t, TimingTerm)] + [TimingStage(timing)]
        return sorted(out, key=lambda t: t.order)

    @property
    def timed(self) -> bool:
        """True when a timing term is away from its identity value (the readings are not all at their stamps)."""
        return any(isinstance(t, TimingTerm) and not t.is_identity for t in self.terms.values())

    def sample_delays(self, ctx: MotionContext) -> np.ndarray:
        """(N, K, 2) s: every reading's true sample time minus its stamp, [accelerometer, gyroscope]."""
        ctx = self._prepare(ctx)
        out = []
        for sensor in SENSORS:
            stage = [t for t in self.chain(sensor, ctx=ctx) if isinstance(t, TimingStage)]
            out.append(stage[0].delay(ctx, sensor) if stage else np.zeros((ctx.n, ctx.k)))
        return np.stack(out, axis=2)

    def _prepare(self, ctx: MotionContext) -> MotionContext:
        ctx.positions = self.terms["position"].values
        return ctx

    def _base(self, ctx: MotionContext, sensor: str) -> np.ndarray:
        v = ctx.specific_force if sensor == "accelerometer" else ctx.omega
        k = len(ctx.rotations)  # R_k^T v_n for all (n, k) as one matrix product: (N, 3) @ (3, 3K)
        return (v @ ctx.rotations.transpose(1, 0, 2).reshape(3, 3 * k)).reshape(len(v), k, 3)

    def predict(self, ctx: MotionContext) -> tuple[np.ndarray, np.ndarray]:
        """Noise-free readings (accelerometers, gyroscopes), each (N, K, 3), sensor frames, unclipped."""
        ctx = self._prepare(ctx)
        out = []
        for sensor in SENSORS:
            x = self._base(ctx, sensor)
            for term in self.chain(sensor, ctx=ctx):
                x = term.apply(x, ctx, sensor)
            out.append(x)
        return out[0], out[1]

    def jacobians(self, ctx: MotionContext, free: Sequence[str] = (), *, motion: bool = True) -> ModelJacobians:
        """Predictions and analytic Jacobians (motion, and the ``free`` terms' parameters);
        ``motion=False``: the parameters' only (``ModelJacobians.motion`` is None), e.g. for a
        parameter step with the motion held (the geometry calibration's block coordinate descent)."""
        with_motion = motion
        unknown = [n for n in free if n not in self.terms]
        if unknown:
            raise KeyError(f"unknown term {unknown[0]!r} (known: {', '.join(term_names())})")
        ctx = self._prepare(ctx)
        n, k = ctx.n, self.n_imus
        predicted = np.empty((n, k, 6))
        motion = np.zeros((n, k, 6, 9)) if with_motion else None
        params = {name: np.zeros((n, k, 6, self.terms[name].dim())) for name in free}
        for s, sensor in enumerate(SENSORS):
            rows = slice(3 * s, 3 * s + 3)
            chain = self.chain(sensor, keep=free, ctx=ctx)
            x = self._base(ctx, sensor)
            inputs = []
            for term in chain:
                inputs.append(x)
                x = term.apply(x, ctx, sensor)
            predicted[:, :, rows] = x
            d = None  # d y / d (signal after the current term); None: the identity (no product needed)
            times = lambda a: a if d is None else d @ a  # noqa: E731
            for term, x_in in zip(reversed(chain), reversed(inputs)):
                if isinstance(term, TimingStage):
                    for member in term.terms:
                        if member.name in params:
                            params[member.name][:, :, rows] += times(term.d_params_of(member, x_in, ctx, sensor))
                elif term.name in params:
                    params[term.name][:, :, rows] += times(term.d_params(x_in, ctx, sensor))
                dm = term.d_motion(x_in, ctx, sensor) if with_motion else None
                if dm is not None:
                    motion[:, :, rows] += times(dm)
                if "position" in params:
                    dp = term.d_positions(x_in, ctx, sensor)  # terms that read the positions
                    if dp is not None:
                        params["position"][:, :, rows] += times(dp)
                di = term.d_input(x_in, ctx, sensor)
                if di is not None:
                    d = times(di)
            base = 6 if sensor == "accelerometer" else 0  # R^T s or R^T omega
            if with_motion:
                motion[:, :, rows, base:base + 3] += times(ctx.rot_t[None])
        return ModelJacobians(predicted=predicted, motion=motion, params=params)



def _split(term_class, values: np.ndarray) -> dict[str, np.ndarray]:
    """Field key -> (K, *shape) of a (K, P) array laid out as ``term_class``'s parameters (no validation:
    standard deviations are not term values)."""
    out, i = {}, 0
    for f in term_class.fields:
        out[f.key] = values[:, i:i + f.size].reshape((len(values),) + f.shape)
        i += f.size
    return out
