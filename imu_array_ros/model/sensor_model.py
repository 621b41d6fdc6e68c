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
                   acc_std=desc.noise_std("accelerometer"), gyro_std=desc.noise_std("gyroscope"), terms=terms,
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
        out = [t for t in self.terms.values() if sensor in t.sensors and (t.name in keep or not _is_identity(t))]
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

    def timing_delays(self, ctx: MotionContext) -> dict[str, np.ndarray]:
        """Sensor -> (N, K) s, the delays of the timing stage of that sensor's chain (sensors without one are
        left out); the delays common to both sensors (the clocks', the stamp delays) computed once.  As
        :meth:`sample_delays`, for :meth:`predict_nonlinear`."""
        return self._timing_delays(self._prepare(ctx), {s: self.chain(s, ctx=ctx) for s in SENSORS})

    def _timing_delays(self, ctx: MotionContext, chains: dict[str, list]) -> dict[str, np.ndarray]:
        stages = {s: next((t for t in chains[s] if isinstance(t, TimingStage)), None) for s in SENSORS}
        stages = {s: t for s, t in stages.items() if t is not None}
        if not stages:
            return {}
        # every stage's terms in the model's order, the order of each stage's sum (a term counts for the
        # sensors it acts on)
        members = {id(term) for t in stages.values() for term in t.terms}
        union = [term for term in self.terms.values() if id(term) in members]
        return TimingStage(union).delays(ctx, tuple(stages))

    def predict_nonlinear(self, ctx: MotionContext, *, delays: dict[str, np.ndarray] | None = None,
                          out: tuple[np.ndarray, np.ndarray] | None = None,
                          subtract_from: tuple[np.ndarray, np.ndarray] | None = None,
                          chunk: int = 4096) -> tuple[np.ndarray, np.ndarray]:
        """What the terms that are not linear add to the noise-free readings: :meth:`predict` minus the
        :meth:`linear_part`'s prediction of the same motion with every reading at its stamp (accelerometers,
        gyroscopes), each (N, K, 3); equal to that difference to rounding (without its cancellation).
        ``delays``: :meth:`timing_delays` of ``ctx`` when already known; ``out``: two (N, K, 3) arrays to write
        the result into; ``subtract_from``: readings (accelerometers, gyroscopes) to return minus the result
        instead (the readings compensated for those terms).

        Computed along each chain without evaluating it twice: the linear terms are affine in the signal, so
        the difference d between the two chains only passes through their linear maps (``d_input``, composed
        into one 3x3 map per IMU) and additive terms cancel; a term that is not linear adds ``apply(d) - d``
        when it is additive (no ``d_input``), else ``apply(x + d) - x`` with x the linear chain's signal; the
        timing stage adds its shift (:meth:`~imu_array_ros.model.terms.timing.TimingStage.shift`) mapped by
        the linear maps that follow it.  In ``chunk`` samples at a time (a trajectory that gives ``rows``, or
        none), so that no temporary grows with the batch."""
        ctx = self._prepare(ctx)
        n, k = ctx.n, self.n_imus
        chains = {s: self.chain(s, ctx=ctx) for s in SENSORS}
        plans = {s: self._difference_plan(chains[s], ctx, s) for s in SENSORS}
        if out is None:
            out = (np.empty((n, k, 3)), np.empty((n, k, 3)))
        traj = ctx.trajectory
        step = n if traj is not None and not hasattr(traj, "rows") else max(int(chunk), 1)
        for lo in range(0, n, step):
            sel = slice(lo, min(lo + step, n))
            sub = ctx if step >= n else _context_rows(ctx, sel)
            d_sub = self._timing_delays(sub, chains) if delays is None else \
                {s: d if step >= n else d[sel] for s, d in delays.items()}
            for s, sensor in enumerate(SENSORS):
                into = out[s] if step >= n else out[s][sel]
                d = self._difference(plans[sensor], sub, sensor, d_sub, into)
                if subtract_from is not None:
                    np.subtract(subtract_from[s][sel], d, out=into)
                elif d is not into:
                    into[...] = d
        return out[0], out[1]

    def _difference_plan(self, chain: list, ctx: MotionContext, sensor: str) -> tuple[bool, list]:
        """(reads_x, steps) of :meth:`predict_nonlinear` along one chain: whether the linear chain's signal is
        needed (a non-linear term reads its input), and the steps ("x", term): the linear chain's signal
        through a linear term; ("map", a): the difference through a linear map (K, 3, 3); ("stage", stage,
        maps, basis): plus a timing stage's shift mapped by the linear maps that follow it (composed, and
        their feature basis);
        ("add", term): plus an additive term; ("read", term): a term that reads its input."""
        k = self.n_imus
        reads_x = any(not _in_linear_part(t) and not _additive(t) for t in chain)
        steps, pending = [], None  # pending: [timing stage, the linear maps after it]

        def flush():
            steps.append(("stage", pending[0], pending[1], pending[0].shift_basis(ctx, sensor, pending[1])))

        for term in chain:
            if _in_linear_part(term):
                if reads_x:
                    steps.append(("x", term))
                if not _additive(term):  # a linear map: d_input is the same for every signal
                    a = np.array(np.asarray(term.d_input(np.zeros((1, k, 3)), ctx, sensor))[0])
                    steps.append(("map", a))
                    if pending is not None:
                        pending[1] = a if pending[1] is None else np.matmul(a, pending[1])
                continue
            if pending is not None:
                flush()
                pending = None
            if isinstance(term, TimingStage):
                pending = [term, None]
            else:
                steps.append(("add" if _additive(term) else "read", term))
        if pending is not None:
            flush()
        return reads_x, steps

    def _difference(self, plan, ctx: MotionContext, sensor: str, delays: dict, into: np.ndarray) -> np.ndarray:
        """The difference of one sensor's chains for the samples of ``ctx`` (see :meth:`_difference_plan`)."""
        reads_x, steps = plan
        x = self._base(ctx, sensor) if reads_x else None
        d = None
        for step in steps:
            kind, term = step[0], step[1]
            if kind == "x":
                x = term.apply(x, ctx, sensor)
            elif kind == "map":
                if d is not None:  # a_k d_nk, one product per IMU
                    d = np.matmul(d.transpose(1, 0, 2), term.transpose(0, 2, 1)).transpose(1, 0, 2)
            elif kind == "stage":
                shift = term.shift(ctx, sensor, maps=step[2], basis=step[3], delta=delays.get(sensor),
                                   out=into if d is None else None)
                d = shift if d is None else d + shift
            elif kind == "add":
                d = term.apply(np.zeros((ctx.n, ctx.k, 3)) if d is None else d, ctx, sensor)
            else:
                d = term.apply(x if d is None else x + d, ctx, sensor) - x
        return np.zeros((ctx.n, ctx.k, 3)) if d is None else d

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
            chain = [t.memoised() if isinstance(t, TimingStage) else t for t in self.chain(sensor, keep=free, ctx=ctx)]
            x = self._base(ctx, sensor)
            inputs = []
            for term in chain:
                inputs.append(x)
                x = term.apply(x, ctx, sensor)
            predicted[:, :, rows] = x
            # d y / d (signal after the current term); None: the identity (no product needed); (K, 3, 3) while it
            # is the same for every sample (the linear maps' d_input: broadcast), one map per IMU; else (n, K, 3, 3)
            d = None
            times = lambda a: a if d is None else np.matmul(d, a)  # noqa: E731
            # the terms' direct motion rows since d last changed, summed before their one product with it
            pending, owned = None, False
            for term, x_in in zip(reversed(chain), reversed(inputs)):
                if isinstance(term, TimingStage):
                    for member in term.terms:
                        if member.name in params:
                            params[member.name][:, :, rows] += times(term.d_params_of(member, x_in, ctx, sensor))
                elif term.name in params:
                    params[term.name][:, :, rows] += times(term.d_params(x_in, ctx, sensor))
                dm = term.d_motion(x_in, ctx, sensor) if with_motion else None
                if dm is not None:
                    pending, owned = (dm, False) if pending is None else (pending + dm, True)
                if "position" in params:
                    dp = term.d_positions(x_in, ctx, sensor)  # terms that read the positions
                    if dp is not None:
                        params["position"][:, :, rows] += times(dp)
                di = term.d_input(x_in, ctx, sensor)
                if di is not None:
                    if pending is not None:
                        motion[:, :, rows] += times(pending)
                        pending = None
                    di = di[0] if di.ndim == 4 and di.strides[0] == 0 else di  # one map per IMU
                    d = times(di)
            base = 6 if sensor == "accelerometer" else 0  # R^T s or R^T omega
            if with_motion:
                if pending is None:
                    motion[:, :, rows, base:base + 3] += times(ctx.rot_t[None])
                else:
                    pending = pending if owned else pending.copy()
                    pending[..., base:base + 3] += ctx.rot_t[None]
                    motion[:, :, rows] += times(pending)
        return ModelJacobians(predicted=predicted, motion=motion, params=params)



_DEFAULT_ROWS: dict[type, np.ndarray] = {}


def _is_identity(term) -> bool:
    """``term.is_identity`` without building the (K, P) identity values (the term class's default row, once)."""
    cls = type(term)
    if cls.is_identity is not Term.is_identity:
        return term.is_identity
    row = _DEFAULT_ROWS.get(cls)
    if row is None:
        row = _DEFAULT_ROWS[cls] = cls.default_values(1)[0]
    values = term.values
    return values.shape[1:] == row.shape and bool((values == row).all())


def _context_rows(ctx: MotionContext, sel: slice) -> MotionContext:
    """The context of the samples ``sel`` only (its drift reference, the first stamp of the whole, kept)."""
    cut = lambda a: None if a is None else a[sel]  # noqa: E731
    t0 = ctx.t0_ns if ctx.t0_ns is not None or not ctx.n else int(ctx.stamps[0])
    out = MotionContext(stamps=ctx.stamps[sel], omega=ctx.omega[sel], omega_dot=ctx.omega_dot[sel],
                        specific_force=ctx.specific_force[sel], rotations=ctx.rotations, t0_ns=t0,
                        omega_ddot=cut(ctx.omega_ddot), specific_force_dot=cut(ctx.specific_force_dot),
                        stamp_delays=cut(ctx.stamp_delays),
                        trajectory=None if ctx.trajectory is None else ctx.trajectory.rows(sel),
                        omega_rate=cut(ctx.omega_rate))
    out.positions = ctx.positions
    return out


def _in_linear_part(term) -> bool:
    """True for a term the :meth:`SensorModel.linear_part` keeps (linear, hence affine in the signal)."""
    return bool(getattr(term, "linear", False))


def _additive(term) -> bool:
    """True for a term that adds to the signal what does not depend on it (no ``d_input``: x + f(motion))."""
    return isinstance(term, TimingStage) or type(term).d_input is Term.d_input


def _split(term_class, values: np.ndarray) -> dict[str, np.ndarray]:
    """Field key -> (K, *shape) of a (K, P) array laid out as ``term_class``'s parameters (no validation:
    standard deviations are not term values)."""
    out, i = {}, 0
    for f in term_class.fields:
        out[f.key] = values[:, i:i + f.size].reshape((len(values),) + f.shape)
        i += f.size
    return out
