"""Simulated icosahedron calibration session (nilsson2014 Sec. III, Fig. 2).

The array sits inside a regular icosahedron that is set down on each of its 20
faces in turn: at rest on face i the outward normal n_i of that face (array
frame) points down, so the specific force is s = R_i^T [0, 0, g] = -g n_i (g
times the outward normal of the top face) up to a small unknown tilt (the print
is not perfect, the table not level: ``tilt_std`` about each horizontal axis,
seeded) and any yaw (a fixed one per face plus a random one).  Between faces the
hand carries the solid for ``transition_s``: a slerp
q(t) = q_i exp(tau(u) v_i) exp(b(u) c_i), u = (t - t_i) / T, with the
minimum-jerk profile tau = 10u^3 - 15u^4 + 6u^5, a wobble b(u) = A 64 (u(1-u))^3
(A ~ N(0, 5 deg)) about a random axis c_i, and a lift-and-carry translation of
the same bump shape (~5 cm).  omega and omega_dot are analytic (omega_dot is the
exact derivative of omega; both vanish at the ends of a transition) and the
attitude is exact.  Optionally ``twist_s`` seconds of hand twisting follow
(:class:`~imu_array_ros.simulation.motion.TwistTrajectory` from the last
attitude, faded in over 1 s so omega stays continuous), as in the real
MIMU4444BT captures.  The measurements come from
:func:`~imu_array_ros.simulation.simulator.simulate_measurements` (the one
forward model); a timed model (time offsets, sample clocks) reads the exact
motion at every reading's true sample time (``exact_timing``).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from scipy.spatial.transform import Rotation

from imu_array_ros.model.constants import STANDARD_GRAVITY
from imu_array_ros.model.description import ArrayDescription
from imu_array_ros.model.sensor_model import SensorModel
from imu_array_ros.model.samples import ImuSamples, MotionTruth
from imu_array_ros.simulation.motion import TwistTrajectory, quat_exp, quat_multiply, quat_to_matrix
from imu_array_ros.simulation.simulator import as_sensor_model, simulate_measurements

__all__ = ["IcosahedronInfo", "icosahedron_face_normals", "simulate_icosahedron", "FACES"]

FACES = 20
_GOLDEN_ANGLE = np.pi * (3.0 - np.sqrt(5.0))
#: 1-sigma of the wobble angle about a random axis during a transition, rad.
WOBBLE_STD = np.deg2rad(5.0)
#: Fade-in of the hand twisting after the last face, s.
TWIST_RAMP_S = 1.0


def icosahedron_face_normals() -> np.ndarray:
    """(20, 3) outward unit normals of a regular icosahedron with vertices at the cyclic
    permutations of (0, +-1, +-phi); ordered by descending z, then azimuth (deterministic)."""
    phi = (1.0 + np.sqrt(5.0)) / 2.0
    base = np.array([[0.0, s1, s2 * phi] for s1 in (-1, 1) for s2 in (-1, 1)])
    verts = np.vstack([np.roll(base, r, axis=1) for r in range(3)])  # (12, 3), edge length 2
    dist = np.linalg.norm(verts[:, None] - verts[None], axis=2)
    adj = np.isclose(dist, 2.0)
    faces = [(i, j, k) for i in range(12) for j in range(i + 1, 12) for k in range(j + 1, 12)
             if adj[i, j] and adj[j, k] and adj[i, k]]
    normals = np.array([verts[list(f)].sum(axis=0) for f in faces])
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    order = np.lexsort((np.round(np.arctan2(normals[:, 1], normals[:, 0]), 9), -np.round(normals[:, 2], 9)))
    return normals[order]


@dataclass
class IcosahedronInfo:
    """What the session simulator did (ground truth beside :class:`MotionTruth`).

    normals (20, 3) outward normal of the face the array rests on, array frame (the one
    pointing down); attitudes (20, 4) true resting attitude per face, [w, x, y, z] body ->
    world (yaw and tilt included); face (N,) face index of each sample, -1 while moving;
    intervals (20, 2) sample index [start, stop) of each rest; twist_start: first sample of
    the hand twisting (N when there is none).
    """

    normals: np.ndarray
    attitudes: np.ndarray
    face: np.ndarray
    intervals: np.ndarray
    twist_start: int

    @property
    def directions(self) -> np.ndarray:
        """(20, 3) true unit specific-force direction at rest, array frame: R_i^T e_z (= -normal without tilt)."""
        return quat_to_matrix(self.attitudes)[:, 2, :]


def _down_rotation(n: np.ndarray) -> Rotation:
    """The smallest rotation taking the unit vector ``n`` to [0, 0, -1]."""
    target = np.array([0.0, 0.0, -1.0])
    axis = np.cross(n, target)
    s, c = np.linalg.norm(axis), float(np.dot(n, target))
    if s < 1e-12:
        return Rotation.identity() if c > 0 else Rotation.from_rotvec([np.pi, 0.0, 0.0])
    return Rotation.from_rotvec(axis / s * np.arctan2(s, c))


def _wxyz(rot: Rotation) -> np.ndarray:
    q = rot.as_quat()  # [x, y, z, w]
    q = np.concatenate([q[..., 3:], q[..., :3]], axis=-1)
    return q * np.where(q[..., :1] < 0, -1.0, 1.0)


def _quat_log(q: np.ndarray) -> np.ndarray:
    """Rotation vector of unit quaternions (..., 4) [w, x, y, z], angle in [0, pi]."""
    q = q * np.where(q[..., :1] < 0, -1.0, 1.0)
    v = q[..., 1:]
    s = np.linalg.norm(v, axis=-1, keepdims=True)
    angle = 2.0 * np.arctan2(s, q[..., :1])
    return np.where(s > 1e-15, v * angle / np.where(s > 1e-15, s, 1.0), 2.0 * v)


@dataclass(frozen=True)
class _FadedTwist(TwistTrajectory):
    """Hand twisting whose omega and sway fade in over ``ramp_s`` (minimum-jerk envelope)."""

    ramp_s: float = TWIST_RAMP_S

    def _envelope(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        u = np.clip(np.asarray(t, dtype=float) / self.ramp_s, 0.0, 1.0)
        return (u**3 * (10 - 15 * u + 6 * u * u))[:, None], (30 * u**2 * (1 - u) ** 2 / self.ramp_s)[:, None]

    def omega(self, t: np.ndarray) -> np.ndarray:
        return self._envelope(t)[0] * super().omega(t)

    def omega_dot(self, t: np.ndarray) -> np.ndarray:
        e, de = self._envelope(t)
        return de * super().omega(t) + e * super().omega_dot(t)

    def acceleration_world(self, t: np.ndarray) -> np.ndarray:
        return self._envelope(t)[0] * super().acceleration_world(t)


@dataclass(frozen=True)
class _Handling:
    """The faces and the transitions between them as a function of time (s from the start; before 0 at rest on
    the first face, after the last transition on the last): (q (n, 4) [w, x, y, z] body -> world, omega,
    omega_dot (n, 3) body, acceleration (n, 3) world)."""

    q_face: np.ndarray
    v: np.ndarray
    wobble: np.ndarray
    axis: np.ndarray
    lift: np.ndarray
    still_s: float
    transition_s: float

    def phase(self, t: np.ndarray):
        """(face or transition index seg, s since its rest began, in a transition) at times t >= 0 (s)."""
        period = self.still_s + self.transition_s
        seg = np.minimum(np.floor(t / period).astype(np.int64), FACES - 1)
        local = t - seg * period
        return seg, local, (local >= self.still_s) & (seg < FACES - 1)

    def __call__(self, t: np.ndarray):
        t = np.maximum(np.asarray(t, dtype=float), 0.0)
        q_face, v, wobble, axis, lift, still_s = self.q_face, self.v, self.wobble, self.axis, self.lift, self.still_s
        seg, local, moving = self.phase(t)
        n = len(t)
        q = q_face[np.clip(seg, 0, FACES - 1)].copy()
        omega = np.zeros((n, 3))
        omega_dot = np.zeros((n, 3))
        acc_world = np.zeros((n, 3))
        if moving.any():
            j = seg[moving]
            T = self.transition_s
            u = (local[moving] - still_s) / T
            p = u * (1.0 - u)
            tau = u**3 * (10 - 15 * u + 6 * u * u)
            d_tau = 30.0 * p * p / T
            dd_tau = 60.0 * p * (1.0 - 2.0 * u) / T**2
            bump = 64.0 * p**3
            d_bump = 64.0 * 3.0 * p * p * (1.0 - 2.0 * u) / T
            dd_bump = 64.0 * (6.0 * p * (1.0 - 2.0 * u) ** 2 - 6.0 * p * p) / T**2
            b, db, ddb = (wobble[j] * x for x in (bump, d_bump, dd_bump))
            c, vj = axis[j], v[j]
            q_b = quat_exp(b[:, None] * c)
            q[moving] = quat_multiply(quat_multiply(q_face[j], quat_exp(tau[:, None] * vj)), q_b)
            rb_t = np.swapaxes(quat_to_matrix(q_b), 1, 2)  # R_B^T
            w_a = np.einsum("nij,nj->ni", rb_t, d_tau[:, None] * vj)  # path rate seen in the wobbled frame
            omega[moving] = w_a + db[:, None] * c
            omega_dot[moving] = (-np.cross(db[:, None] * c, w_a)
                                 + np.einsum("nij,nj->ni", rb_t, dd_tau[:, None] * vj) + ddb[:, None] * c)
            acc_world[moving] = dd_bump[:, None] * lift[j]
        return q, omega, omega_dot, acc_world


@dataclass(frozen=True)
class _SessionFunction:
    """The session's motion as a function of int64 ns time (any shape): (omega, omega_dot, specific_force), each
    shape + (3,), array frame -- the ``MotionContext.trajectory`` with which a timed model reads the motion at every
    reading's true sample time (as :func:`~imu_array_ros.simulation.simulator.simulate_trajectory` does), not
    through local cubics of the truth at the stamps (those smooth the 0.3 s transitions: at 62.5 Hz the fitted
    accelerometer delays came out ~300 us late and gyroscope offsets 1 % short with the true model)."""

    handling: _Handling
    start_ns: int
    twist: TwistTrajectory | None
    twist_ns: int

    def __call__(self, stamps_ns: np.ndarray):
        stamps = np.asarray(stamps_ns, dtype=np.int64)
        flat = stamps.reshape(-1)
        q, omega, omega_dot, acc_world = self.handling((flat - np.int64(self.start_ns)) * 1e-9)
        s = _specific_force(q, acc_world)
        if self.twist is not None:
            on = flat >= self.twist_ns
            if on.any():
                w, wd, sf, _ = self.twist.motion_at(flat[on], self.twist_ns)
                omega[on], omega_dot[on], s[on] = w, wd, sf
        shape = stamps.shape + (3,)
        return omega.reshape(shape), omega_dot.reshape(shape), s.reshape(shape)


def simulate_icosahedron(
    model: SensorModel | ArrayDescription,
    rng: np.random.Generator,
    *,
    rate_hz: float = 100.0,
    still_s: float = 3.0,
    transition_s: float = 2.0,
    tilt_std: float = float(np.deg2rad(1.0)),
    twist_s: float = 0.0,
    rms_rate: float = float(np.deg2rad(600.0)),
    start_ns: int = 0,
    exact_timing: bool = True,
) -> tuple[ImuSamples, MotionTruth, IcosahedronInfo]:
    """An icosahedron session: 20 rests of ``still_s`` joined by ``transition_s`` of handling,
    then ``twist_s`` of hand twisting at ``rms_rate`` rad/s RMS (see the module docstring).

    Stamps start at ``start_ns`` and are 1/rate_hz apart; duration
    20 still_s + 19 transition_s + twist_s.  ``tilt_std``: rad about each horizontal (world) axis.
    A timed model (time offsets, sample clocks) reads the motion at every reading's true sample time
    (``exact_timing``, as :func:`~imu_array_ros.simulation.simulator.simulate_twist`); ``exact_timing=False``: through
    local cubics of the truth at the stamps, as before 2026-11-28 (inexact on the 0.3 s transitions at 62.5 Hz).
    """
    if not (rate_hz > 0 and still_s > 0 and transition_s > 0 and tilt_std >= 0 and twist_s >= 0):
        raise ValueError("rate_hz, still_s and transition_s must be > 0, tilt_std and twist_s >= 0")
    model = as_sensor_model(model)
    normals = icosahedron_face_normals()

    # resting attitudes: tilt (world) * yaw (world z) * (face normal -> down)
    yaw = _GOLDEN_ANGLE * np.arange(FACES) + rng.uniform(0.0, 2.0 * np.pi, FACES)
    tilt = rng.normal(0.0, tilt_std, (FACES, 3)) * np.array([1.0, 1.0, 0.0])
    rests = [Rotation.from_rotvec(tilt[i]) * Rotation.from_rotvec([0.0, 0.0, yaw[i]]) * _down_rotation(normals[i])
             for i in range(FACES)]
    q_face = np.array([_wxyz(r) for r in rests])
    # transitions j -> j + 1: body-frame rotation vector, wobble, lift-and-carry
    rel = quat_multiply(q_face[:-1] * np.array([1.0, -1.0, -1.0, -1.0]), q_face[1:])  # q_j^-1 q_{j+1}
    v = _quat_log(rel)
    wobble = rng.normal(0.0, WOBBLE_STD, FACES - 1)
    axis = rng.normal(size=(FACES - 1, 3))
    axis /= np.linalg.norm(axis, axis=1, keepdims=True)
    lift = rng.normal(0.0, 0.02, (FACES - 1, 3)) + np.array([0.0, 0.0, 0.05])  # m: carried over, lifted ~5 cm
    handling = _Handling(q_face, v, wobble, axis, lift, still_s, transition_s)

    faces_end = FACES * still_s + (FACES - 1) * transition_s
    n = int(round((faces_end + twist_s) * rate_hz))
    stamps = int(start_ns) + np.round(np.arange(n) * (1e9 / rate_hz)).astype(np.int64)
    t = (stamps - int(start_ns)) * 1e-9

    seg, _, moving = handling.phase(t)
    twisting = t >= faces_end if twist_s > 0 else np.zeros(n, dtype=bool)
    face = np.where(moving | twisting, -1, seg)

    q, omega, omega_dot, acc_world = handling(t)
    twist_start, traj = n, None
    if twisting.any():
        twist_start = int(np.flatnonzero(twisting)[0])
        traj = replace(_FadedTwist(*_twist_fields(TwistTrajectory.random(rng, rms_rate=rms_rate))),
                       initial_attitude=q_face[-1])
        tt = t[twisting] - faces_end
        q[twisting] = traj.attitude(np.concatenate([[0.0], tt]))[1:]
        omega[twisting] = traj.omega(tt)
        omega_dot[twisting] = traj.omega_dot(tt)
        acc_world[twisting] = traj.acceleration_world(tt)

    s = _specific_force(q, acc_world)
    truth = MotionTruth(stamps=stamps, omega=omega, omega_dot=omega_dot, specific_force=s, attitude=q)
    counts = np.bincount(face[face >= 0], minlength=FACES)
    if counts.min() < 1:
        raise ValueError(f"still_s {still_s:g} s at {rate_hz:g} Hz leaves a face without samples")
    ids, first = np.unique(face, return_index=True)  # each face is one contiguous run
    first = first[ids >= 0]
    intervals = np.column_stack([first, first + counts]).astype(np.int64)
    info = IcosahedronInfo(normals=normals, attitudes=q_face, face=face, intervals=intervals, twist_start=twist_start)
    function = _SessionFunction(handling, int(start_ns), traj, int(start_ns) + int(round(faces_end * 1e9)))
    return simulate_measurements(model, truth, rng, trajectory=function if exact_timing else None), truth, info


def _specific_force(q: np.ndarray, acc_world: np.ndarray) -> np.ndarray:
    """(n, 3) body-frame specific force of attitudes q (n, 4) body -> world under world acceleration (n, 3)."""
    return np.einsum("nji,nj->ni", quat_to_matrix(q), acc_world + np.array([0.0, 0.0, STANDARD_GRAVITY]))


def _twist_fields(traj: TwistTrajectory) -> tuple:
    return (traj.amplitudes, traj.frequencies, traj.phases, traj.sway_amplitudes, traj.sway_frequencies,
            traj.sway_phases, traj.initial_attitude)
