"""Randomised recordings with concealed effects: the suite discovery is scored on but never tuned on.

:func:`draw_suite` draws scenarios from a seed (one independent stream per
(seed, class, index), so a scenario does not change when others are added):

* an **array**: 4 planar IMUs (:func:`~imu_array_ros.model.layouts.planar_square4`),
  the 8 corner IMUs of the MIMU4444BT (``config/mimu4444bt_corners.yaml``) or 32
  (:func:`~imu_array_ros.model.layouts.grid_array32`);
  -- or, with ``unseen=True``, an array none of them is (:data:`UNSEEN`: 5-16 IMUs at random 3D positions
  within 4 cm, each at a random orientation) at a rate none of them uses (:data:`UNSEEN_RATES`);
* a **rate** from :data:`RATES` (62.5-1000 Hz) and a **session**: 20 icosahedron
  rests then hand twisting, or hand twisting only; durations of a few tens of
  seconds, shortened (then lower rates only) so that samples x IMUs stays under
  :data:`READINGS_CAP`;
* an **effect class** (:data:`CLASSES`): ``single`` (one library term on one IMU),
  ``shared`` (one value on every IMU, as a chip family shares it), ``group`` (one
  value on a group of IMUs: a side, a half, the outer ring, or a random set),
  ``pair`` (two terms on two IMUs, a strong and a weak partner 3-10x apart in
  evidence), ``drift`` (a slow linear bias drift of one sensor, or a constant
  bias: which one it is), ``both`` (a constant bias and a slow drift of the same
  sensor of one IMU, each sized on its own: both must be named), ``vibration`` (outside the library: a narrowband board
  mode anywhere up to 0.4 x the sample rate whose amplitude grows with distance
  from the centre, a random mix of the quadratic mode shapes r^2, xy, x^2 - y^2,
  mostly out of plane) and ``null`` (nothing; shorter sessions).

Every effect is **sized by oracle evidence**: its target ``evidence`` is drawn
log-uniform in a range (just detectable to strong).  The oracle knows the
effect's shape and scope and refits its scale c along it (c = 1 the truth, every
other injected effect at its true value), the motion of every sample fitted by
the engine (:func:`~imu_array_ros.fitting.engine.fit_motion`) at each c: its
evidence is 2 max_c [log L(c) - log L(0)], what the effect adds after the motion
has absorbed what it can.  :func:`build` scales the effect so that this is the
target on the noise-free recording (the non-centrality of the oracle's test;
linear terms exactly, the others to within 35 %), then measures it on the noisy
recording: the *realised* evidence (target + a chi-square with 1 degree of
freedom, +- about 2 sqrt(target)), the figure power curves are binned by.  One
parameter for every class, so a value shared by 32 IMUs is not credited the
chi-square of 96 parameters.  For the vibration c scales the added signal.  A
drawn term the array cannot see (e.g. a bias common to identically oriented IMUs,
absorbed by the motion) needs more than :data:`MAX_FACTOR` x its test size; it
is redrawn from the class's terms (deterministically) and the replacement noted.

:func:`score` compares a discovery with the truth.  Library classes: *correct* when the
findings name exactly the injected terms, each on exactly its IMUs (one finding
per IMU or one finding at a group/shared scope: a finding covers the IMUs of its
``sensors``), and nothing else; each effect is also scored on its own
(``detected``: its term found on exactly its IMUs), the power curves of the
pairs use the weak partner.  Vibration: *located* (an unexplained entry whose
band holds the mode's frequency and whose IMUs include a largest-amplitude
one: symmetric shapes tie) and nothing forced (no finding at all); details in
:mod:`.suite_score`.  Null: correct without a finding.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from imu_array_ros.model.sensor_model import SensorModel
from imu_array_ros.model.terms import REGISTRY
from imu_array_ros.simulation.perturb import TERM_TEST_SIZES
from imu_array_ros.simulation.suite_score import score

__all__ = ["CLASSES", "ARRAYS", "RATES", "LIBRARY_TERMS", "SHARED_TERMS", "Effect", "Vibration", "SuiteScenario",
           "BuiltScenario", "draw_suite", "draw_scenario", "build", "score", "array_description", "imu_count",
           "UnsizableEffect", "UNSEEN", "UNSEEN_RATES"]

CLASSES = ("single", "shared", "group", "pair", "drift", "both", "vibration", "null")
#: each class's random stream id (a class added later gets a new id, so no earlier draw changes)
_STREAM = {"single": 0, "shared": 1, "group": 2, "pair": 3, "drift": 4, "vibration": 5, "null": 6, "both": 7}
ARRAYS = ("planar4", "corners8", "grid32")
IMUS = {"planar4": 4, "corners8": 8, "grid32": 32}
RATES = (62.5, 100.0, 200.0, 500.0, 1000.0)
#: the arrays of ``unseen`` draws: "random-<seed>" (:func:`array_description`), at these rates
UNSEEN = "random"
UNSEEN_RATES = (80.0, 125.0, 250.0, 400.0)
#: samples x IMUs of one recording at most (CPU): longer sessions are shortened, then lower rates drawn
READINGS_CAP = 120_000
#: the library terms drawn (the candidates of discovery when the suite was written; fixed, so the suite does
#: not change when a term becomes a candidate)
LIBRARY_TERMS = ("position", "axis_offsets", "time_offset", "accelerometer_misalignment",
                 "accelerometer_nonorthogonality", "accelerometer_nonlinearity", "accelerometer_gain",
                 "accelerometer_bias", "bias_drift", "gyroscope_misalignment", "gyroscope_nonorthogonality",
                 "gyroscope_gain", "gyroscope_g_sensitivity", "gyroscope_bias")
#: terms a chip family (or a group of IMUs) plausibly shares
SHARED_TERMS = ("accelerometer_nonlinearity", "gyroscope_g_sensitivity", "accelerometer_gain", "gyroscope_gain",
                "accelerometer_bias", "gyroscope_bias", "time_offset", "accelerometer_misalignment")
#: an effect needing more than this x its TERM_TEST_SIZES to reach its evidence is not visible: redrawn
MAX_FACTOR = 30.0
#: vibration amplitude (m/s^2 RMS at the largest-amplitude IMU) above which a mode shape is redrawn
MAX_VIBRATION = 5.0
CORNERS = Path(__file__).resolve().parents[2] / "config" / "mimu4444bt_corners.yaml"


class UnsizableEffect(ValueError):
    """No draw of the effect reaches its evidence on this recording."""


@dataclass
class Effect:
    """A library term with one value (direction (P,) x a scale found by :func:`build`) on the IMUs ``imus``;
    evidence: the target oracle evidence (2 delta log-likelihood)."""

    term: str
    imus: tuple[int, ...]
    direction: tuple[float, ...]
    evidence: float


@dataclass
class Vibration:
    """A narrowband mode: frequency_hz, bandwidth_hz (Lorentzian FWHM), direction (3,) array frame,
    shape (K,) signed relative amplitude per IMU (max |shape| = 1), evidence: target oracle evidence."""

    frequency_hz: float
    bandwidth_hz: float
    direction: tuple[float, ...]
    shape: tuple[float, ...]
    evidence: float


@dataclass
class SuiteScenario:
    """name; cls (one of CLASSES); array (one of ARRAYS); rate_hz; still_poses (20 icosahedron rests of still_s
    joined by transition_s, then twist_s of twisting; else twist_s of twisting only); effects; vibration;
    seed (of the recording's motion and noise); variant: class detail (drift: 'drift' or 'constant'; both: the
    sensor)."""

    name: str
    cls: str
    array: str
    rate_hz: float
    still_poses: bool
    still_s: float
    transition_s: float
    twist_s: float
    effects: list[Effect] = field(default_factory=list)
    vibration: Vibration | None = None
    seed: int = 0
    variant: str = ""

    @property
    def duration_s(self) -> float:
        return (20 * self.still_s + 19 * self.transition_s if self.still_poses else 0.0) + self.twist_s


# --------------------------------------------------------------------------------------------- drawing

def array_description(array: str):
    """The ArrayDescription of an ARRAYS key, or of "random-<seed>": 5-16 IMUs at random positions in a 4 cm
    cube, each at a random orientation (uniform on SO(3)), drawn from the seed."""
    from imu_array_ros.model.description import load_description
    from imu_array_ros.model.layouts import grid_array32, make_description, planar_square4

    if array.startswith(UNSEEN + "-") and array[len(UNSEEN) + 1:].isdigit():
        from scipy.spatial.transform import Rotation

        rng = np.random.default_rng([int(array[len(UNSEEN) + 1:]), 5])
        k = int(rng.integers(5, 17))
        return make_description(rng.uniform(-0.02, 0.02, (k, 3)), Rotation.random(k, random_state=rng).as_matrix())
    if array == "planar4":
        return planar_square4()
    if array == "grid32":
        return grid_array32()
    if array == "corners8":
        return load_description(CORNERS)
    raise ValueError(f"unknown array {array!r} (known: {', '.join(ARRAYS)})")


def _log_uniform(rng, lo: float, hi: float) -> float:
    return float(np.exp(rng.uniform(np.log(lo), np.log(hi))))


def imu_count(array: str) -> int:
    """The number of IMUs of an array key (:func:`array_description`)."""
    return IMUS[array] if array in IMUS else len(array_description(array).imus)


def _session(rng, cls: str, unseen: bool = False) -> dict:
    array = f"{UNSEEN}-{int(rng.integers(2**31))}" if unseen else str(rng.choice(ARRAYS))
    k = imu_count(array)
    still = bool(rng.random() < 0.5)
    short = cls == "null"
    if still:
        still_s, transition_s = rng.uniform(0.4, 1.0), rng.uniform(0.4, 0.8)
        twist = rng.uniform(5.0, 10.0) if short else rng.uniform(5.0, 20.0)
        fixed, least = 20 * still_s + 19 * transition_s, 5.0
    else:
        still_s = transition_s = 0.0
        twist = rng.uniform(8.0, 15.0) if short else rng.uniform(15.0, 40.0)
        fixed, least = 0.0, 8.0
    rates = [r for r in (UNSEEN_RATES if unseen else RATES) if (fixed + least) * r * k <= READINGS_CAP]
    rate = float(rng.choice(rates))
    twist = float(min(twist, READINGS_CAP / (rate * k) - fixed))
    return dict(array=array, rate_hz=rate, still_poses=still, still_s=float(still_s),
                transition_s=float(transition_s), twist_s=twist)


def _direction(rng, term: str, sensor: str | None = None) -> tuple[float, ...]:
    d = rng.normal(size=REGISTRY[term].dim()) * TERM_TEST_SIZES[term]
    if term == "bias_drift" and sensor is not None:  # one sensor's drift only
        d[3:] = 0.0 if sensor == "accelerometer" else d[3:]
        d[:3] = 0.0 if sensor == "gyroscope" else d[:3]
    return tuple(float(x) for x in d)


def _groups(positions: np.ndarray) -> list[tuple[int, ...]]:
    """Groups the geometry suggests: each side of the board (z), each half in x and in y, the outer ring."""
    out = []
    for axis in (2, 0, 1):
        c = positions[:, axis]
        if np.ptp(c) > 1e-9:
            out += [tuple(np.flatnonzero(c > c.mean()).tolist()), tuple(np.flatnonzero(c < c.mean()).tolist())]
    ax, ay = np.abs(positions[:, 0]), np.abs(positions[:, 1])
    ring = tuple(np.flatnonzero((ax > ax.max() - 1e-6) | (ay > ay.max() - 1e-6)).tolist())
    if 1 < len(ring) < len(positions):
        out.append(ring)
    return [g for g in dict.fromkeys(out) if 1 < len(g) < len(positions)]


def _mode_shape(rng, positions: np.ndarray) -> tuple[float, ...]:
    """Relative amplitude per IMU of a random mix of the quadratic plate-mode shapes (max |shape| = 1)."""
    p = positions - positions.mean(axis=0)
    x, y = p[:, 0], p[:, 1]
    basis = np.stack([x * x + y * y, x * y, x * x - y * y])
    shape = rng.normal(size=3) @ basis
    return tuple(float(v) for v in shape / np.abs(shape).max())


def draw_scenario(seed: int, cls: str, index: int, *, evidence=(10.0, 1000.0), unseen: bool = False) -> SuiteScenario:
    """Scenario ``index`` of class ``cls`` of the suite of ``seed``; evidence: (lo, hi) of the target oracle
    evidence (log-uniform; the pair's weak partner, its strong one 3-10x above); unseen: on a random array at a
    rate the suite's arrays are not drawn at (module docstring; its own streams)."""
    if cls not in CLASSES:
        raise ValueError(f"unknown class {cls!r} (known: {', '.join(CLASSES)})")
    rng = np.random.default_rng([int(seed), _STREAM[cls], int(index), 23] + ([int(unseen)] if unseen else []))
    s = _session(rng, cls, unseen)
    desc = array_description(s["array"])
    k, positions = len(desc.imus), desc.positions
    lo, hi = evidence
    e = _log_uniform(rng, lo, hi)
    effects, vib, variant = [], None, ""
    if cls == "single":
        term = str(rng.choice(LIBRARY_TERMS))
        effects = [Effect(term, (int(rng.integers(k)),), _direction(rng, term), e)]
    elif cls in ("shared", "group"):
        term = str(rng.choice(SHARED_TERMS))
        if cls == "shared":
            imus = tuple(range(k))
        else:
            groups = _groups(positions)
            if rng.random() < 0.5 and groups:
                imus = groups[int(rng.integers(len(groups)))]
            else:
                imus = tuple(sorted(rng.choice(k, size=int(rng.integers(2, max(3, k // 2 + 1))), replace=False)
                                    .tolist()))
        effects = [Effect(term, tuple(int(i) for i in imus), _direction(rng, term), e)]
    elif cls == "pair":
        a, b = rng.choice(LIBRARY_TERMS, size=2, replace=False)
        ka, kb = rng.choice(k, size=2, replace=False)
        strong = e * _log_uniform(rng, 3.0, 10.0)
        effects = [Effect(str(a), (int(ka),), _direction(rng, str(a)), strong),
                   Effect(str(b), (int(kb),), _direction(rng, str(b)), e)]
    elif cls == "drift":
        variant = "drift" if rng.random() < 0.5 else "constant"
        sensor = str(rng.choice(["accelerometer", "gyroscope"]))
        term = "bias_drift" if variant == "drift" else f"{sensor}_bias"
        effects = [Effect(term, (int(rng.integers(k)),), _direction(rng, term, sensor), e)]
    elif cls == "both":  # the drift at the drawn evidence, the constant bias at 1/3-3x it
        variant = sensor = str(rng.choice(["accelerometer", "gyroscope"]))
        imu = (int(rng.integers(k)),)
        effects = [Effect(f"{sensor}_bias", imu, _direction(rng, f"{sensor}_bias"), e * _log_uniform(rng, 1 / 3, 3)),
                   Effect("bias_drift", imu, _direction(rng, "bias_drift", sensor), e)]
    elif cls == "vibration":
        d = np.array([0.0, 0.0, 1.0]) + rng.normal(0.0, 0.3, 3)
        vib = Vibration(_log_uniform(rng, 3.0, 0.4 * s["rate_hz"]), float(rng.uniform(0.2, 2.0)),
                        tuple(float(v) for v in d / np.linalg.norm(d)), _mode_shape(rng, positions), e)
    what = (" + ".join(f"{x.term}@{','.join(str(i) for i in x.imus)}" for x in effects) if effects else
            f"vibration {vib.frequency_hz:.3g} Hz" if vib else "nothing")
    name = (f"{cls} {index}: {what} | {s['array']} {s['rate_hz']:g} Hz "
            f"{'rests+twist' if s['still_poses'] else 'twist'}")
    return SuiteScenario(name, cls, **s, effects=effects, vibration=vib, seed=int(rng.integers(2**31)),
                         variant=variant)


def draw_suite(seed: int, per_class: int, *, nulls: int = 50, classes=CLASSES[:-1],
               evidence=(10.0, 1000.0), unseen: bool = False) -> list[SuiteScenario]:
    """``per_class`` scenarios of every class in ``classes`` and ``nulls`` null recordings, drawn from ``seed``."""
    out = [draw_scenario(seed, c, i, evidence=evidence, unseen=unseen) for c in classes for i in range(per_class)]
    return out + [draw_scenario(seed, "null", i, evidence=evidence, unseen=unseen) for i in range(nulls)]


# --------------------------------------------------------------------------------------------- building

@dataclass
class BuiltScenario:
    """A built scenario: samples (noisy recording), nominal (the model it is analysed with), truth_model,
    effects (the effects as injected, replacements applied), values: effect index -> (P,) true value,
    oracle_target / oracle_noise_free / oracle: per effect (then the vibration) the target, the noise-free
    and the realised evidence; amplitude: the vibration's RMS (m/s^2) at its largest IMU; notes; added: (N, K, 6)
    the vibration's signal in the readings (None without one)."""

    scenario: SuiteScenario
    samples: object
    nominal: SensorModel
    truth_model: SensorModel
    effects: list[Effect]
    values: list[np.ndarray]
    oracle_target: list[float]
    oracle_noise_free: list[float]
    oracle: list[float]
    amplitude: float = 0.0
    notes: list[str] = field(default_factory=list)
    added: np.ndarray | None = None


def _motion(sc: SuiteScenario, nominal: SensorModel):
    from imu_array_ros.simulation.icosahedron import simulate_icosahedron
    from imu_array_ros.simulation.motion import TwistTrajectory

    rng = np.random.default_rng([sc.seed, 1])
    if sc.still_poses:
        return simulate_icosahedron(nominal, rng, rate_hz=sc.rate_hz, still_s=sc.still_s,
                                    transition_s=sc.transition_s, twist_s=sc.twist_s)[1]
    n = int(round(sc.twist_s * sc.rate_hz))
    stamps = np.round(np.arange(n) * (1e9 / sc.rate_hz)).astype(np.int64)
    return TwistTrajectory.random(rng).sample(stamps)


def _with(model: SensorModel, term: str, imus, value) -> SensorModel:
    v = model.terms[term].values.copy()
    v[list(imus)] = value
    return model.with_terms(**{term: v})


def _loglik(samples, model) -> float:
    from imu_array_ros.fitting.engine import fit_motion

    return fit_motion(samples, model)[1]


def _oracle_gain(ll) -> float:
    """2 max_c [ll(c) - ll(0)]: c the effect's scale along its true shape (1 = the truth); ll(c) the
    log-likelihood at the ML motion.  A parabola through c = 0, 1, 2, its top evaluated too."""
    l0, l1, l2 = ll(0.0), ll(1.0), ll(2.0)
    best = max(l1, l2)
    curv = l2 - 2.0 * l1 + l0
    if curv < 0:
        c = 0.5 * (l2 - 4.0 * l1 + 3.0 * l0) / curv  # argmax of the parabola l0 + b c + a c^2
        if 0.0 < c < 4.0 and abs(c - 1.0) > 0.02:
            best = max(best, ll(c))
    return float(2.0 * (best - l0))


def _size(effect: Effect, nominal: SensorModel, truth) -> tuple[np.ndarray, float]:
    """The value (P,) giving ``effect.evidence`` on the noise-free recording, and that evidence."""
    from imu_array_ros.simulation.simulator import simulate_measurements

    base = nominal.terms[effect.term].values[effect.imus[0]]
    direction = np.asarray(effect.direction)

    def evidence(scale):  # noise free: the true model fits exactly, 2 delta log L = what the motion cannot absorb
        true = _with(nominal, effect.term, effect.imus, base + scale * direction)
        clean = simulate_measurements(true, truth, None, noise=False)
        return 2.0 * (_loglik(clean, true) - _loglik(clean, nominal))
    scale, lam = 1.0, evidence(1.0)
    for _ in range(1 if REGISTRY[effect.term].linear else 3):
        if not (np.isfinite(lam) and lam > 0):
            break
        scale *= np.sqrt(effect.evidence / lam)
        if scale > MAX_FACTOR:
            break
        lam = evidence(scale)
    if not (np.isfinite(lam) and lam > 0) or scale > MAX_FACTOR or abs(np.log(lam / effect.evidence)) > 0.3:
        raise UnsizableEffect(f"{effect.term} on {effect.imus}: evidence {lam:.3g} at {scale:.3g} x its test size")
    return base + scale * direction, lam


def _vibration(samples, model: SensorModel, vib: Vibration, amplitude: float, seed: int):
    """samples with the mode added (one process x(t) for every IMU, amplitude x shape_k along +-direction)."""
    from imu_array_ros.simulation.effects import add_vibration

    out = samples
    for k, a in enumerate(vib.shape):
        if abs(a) > 0:
            out = add_vibration(out, model, sensors=[k], frequency_hz=vib.frequency_hz, amplitude=amplitude * abs(a),
                                direction=np.sign(a) * np.asarray(vib.direction), bandwidth_hz=vib.bandwidth_hz,
                                rng=np.random.default_rng([seed, 3]))
    return out


def _minus(samples, added: np.ndarray, c: float):
    """samples with c x ``added`` (N, K, 6) taken off (the oracle's explanation of the vibration at scale c)."""
    from imu_array_ros.model.samples import ImuSamples

    return ImuSamples(samples.stamps, samples.accel - c * added[..., :3], samples.gyro - c * added[..., 3:],
                      samples.names)


def _redraw(effect: Effect, rng) -> Effect:
    pool = [t for t in (SHARED_TERMS if len(effect.imus) > 1 else LIBRARY_TERMS) if t != effect.term]
    term = str(rng.choice(pool))
    return replace(effect, term=term, direction=_direction(rng, term))


def build(sc: SuiteScenario, *, attempts: int = 6) -> BuiltScenario:
    """Simulate the scenario: size every effect by its oracle evidence, record with noise, add the vibration,
    measure the realised oracle evidence."""
    from imu_array_ros.simulation.simulator import simulate_measurements

    nominal = SensorModel.from_description(array_description(sc.array))
    truth = _motion(sc, nominal)
    rng = np.random.default_rng([sc.seed, 2])
    effects, values, nf, notes = [], [], [], []
    for e in sc.effects:
        for _ in range(attempts):
            try:
                v, lam = _size(e, nominal, truth)
                break
            except UnsizableEffect as err:
                new = _redraw(e, rng)
                notes.append(f"{err}: redrawn as {new.term}")
                e = new
        else:
            raise UnsizableEffect(f"{sc.name}: no visible term after {attempts} draws")
        effects.append(e)
        values.append(v)
        nf.append(lam)
    true = nominal
    for e, v in zip(effects, values):
        true = _with(true, e.term, e.imus, v)
    samples = simulate_measurements(true, truth, np.random.default_rng([sc.seed, 4]))
    oracle = []
    for e, v in zip(effects, values):
        base = nominal.terms[e.term].values[e.imus[0]]
        oracle.append(_oracle_gain(lambda c: _loglik(samples, _with(true, e.term, e.imus, base + c * (v - base)))))
    targets = [e.evidence for e in effects]
    amplitude, added = 0.0, None
    if sc.vibration is not None:
        vib = sc.vibration
        clean = simulate_measurements(true, truth, None, noise=False)
        for _ in range(attempts):
            lam1 = 2.0 * (_loglik(clean, true) - _loglik(_vibration(clean, true, vib, 1.0, sc.seed), true))
            amplitude = float(np.sqrt(vib.evidence / lam1)) if lam1 > 0 else np.inf
            if amplitude <= MAX_VIBRATION:
                break
            new = replace(vib, shape=_mode_shape(rng, nominal.positions))
            notes.append(f"vibration shape {np.round(vib.shape, 2).tolist()} needs {amplitude:.3g} m/s^2: redrawn")
            vib = new
        else:
            raise UnsizableEffect(f"{sc.name}: no visible mode shape after {attempts} draws")
        sc = replace(sc, vibration=vib)
        noisy = _vibration(samples, nominal, vib, amplitude, sc.seed)
        added = np.concatenate([noisy.accel - samples.accel, noisy.gyro - samples.gyro], axis=2)
        nf.append(float(lam1 * amplitude ** 2))
        oracle.append(_oracle_gain(lambda c: _loglik(_minus(noisy, added, c), true)))
        targets.append(vib.evidence)
        samples = noisy
    return BuiltScenario(sc, samples, nominal, true, effects, values, targets, nf, oracle, amplitude, notes, added)
