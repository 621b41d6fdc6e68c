"""Recordings with concealed effects: the proving ground of mismatch discovery.

Each :class:`Scenario` is a simulated session (an icosahedron of still poses,
then hand twisting; :func:`~imu_array_ros.simulation.icosahedron.simulate_icosahedron`)
of a nominal array whose *true* sensors differ from the nominal model by
injected effects, analysed with the nominal model:

* a library term on one IMU (``effects=[(term, imu)]``), sized so that its
  RMS over the recording on the most affected axis is ``size`` x that axis'
  noise std (0.3 by default): no single sample reveals it, only a fit over the
  whole recording can;
* confounded pairs (e.g. a time offset on one IMU and a position error on
  another) injected together;
* effects outside the library (:mod:`~imu_array_ros.simulation.effects`: a
  narrowband board vibration on the outer IMUs, an IMU whose noise is not
  white), which discovery must locate and report as unexplained;
* null recordings with nothing injected.

:func:`score` compares a :class:`~imu_array_ros.discovery.discover.Discovery`
with the truth: right terms on the right IMUs and nothing else, magnitudes in
standard deviations of the CRB, and for out-of-library effects whether they
were located among the unexplained residual without a term finding on them.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from imu_array_ros.model.sensor_model import SensorModel, motion_context
from imu_array_ros.model.terms import REGISTRY
from imu_array_ros.simulation.icosahedron import simulate_icosahedron
from imu_array_ros.simulation.perturb import TERM_TEST_SIZES
from imu_array_ros.simulation.simulator import simulate_measurements

__all__ = ["Scenario", "build", "score", "standard_suite", "CONFOUNDED_PAIRS"]

#: pairs the issue names as confounded, injected together on different IMUs
CONFOUNDED_PAIRS = (("time_offset", "position"), ("accelerometer_gain", "accelerometer_nonlinearity"),
                    ("gyroscope_g_sensitivity", "gyroscope_bias"), ("axis_offsets", "position"))


@dataclass
class Scenario:
    """name; array: description path; effects: [(term, imu index)]; outside: [(kind, kwargs)] out-of-library
    effects (kind 'vibration' or 'colored_noise'); seed; size: RMS of each injected effect on its most affected
    axis in noise stds; rate_hz, still_s, transition_s, twist_s: the session (20 rests)."""

    name: str
    array: str
    effects: list = field(default_factory=list)
    outside: list = field(default_factory=list)
    seed: int = 0
    size: float = 0.3
    rate_hz: float = 100.0
    still_s: float = 0.5
    transition_s: float = 0.5
    twist_s: float = 20.0

    @property
    def kind(self) -> str:
        if self.outside:
            return "outside_library"
        if not self.effects:
            return "null"
        return "single" if len(self.effects) == 1 else "confounded_pair"


@dataclass
class Built:
    """A built scenario: the recording, the nominal model it is analysed with, the true model, and the
    injected values per (term, k): (P,) true parameter values."""

    scenario: Scenario
    samples: object
    nominal: SensorModel
    truth_model: SensorModel
    injected: dict
    outside_sensors: list


def _effect_rms(model: SensorModel, term: str, k: int, values: np.ndarray, truth) -> float:
    """Largest RMS over the recording, in noise stds, of the change ``values`` makes on IMU k's axes."""
    ctx = motion_context(truth.stamps, truth.omega, truth.omega_dot, truth.specific_force, model.rotations,
                         derivatives=True)
    a0, g0 = model.predict(ctx)
    v = model.terms[term].values.copy()
    v[k] = values
    a1, g1 = model.with_terms(**{term: v}).predict(ctx)
    d = np.concatenate([a1 - a0, g1 - g0], axis=2)[:, k] / model.std[k]
    return float(np.sqrt(np.mean(d ** 2, axis=0)).max())


def build(sc: Scenario) -> Built:
    """Simulate the scenario: inject its effects at their size into the nominal model, record, add the
    out-of-library effects."""
    from imu_array_ros.model.description import load_description
    from imu_array_ros.simulation import effects as fx

    nominal = SensorModel.from_description(load_description(sc.array))
    rng = np.random.default_rng(sc.seed)
    # the motion first (noise-free), to size the effects on it
    _, truth, _ = simulate_icosahedron(nominal, np.random.default_rng(sc.seed + 10_000), rate_hz=sc.rate_hz,
                                       still_s=sc.still_s, transition_s=sc.transition_s, twist_s=sc.twist_s)
    true_model, injected = nominal, {}
    for term, k in sc.effects:
        cls = REGISTRY[term]
        direction = rng.normal(size=cls.dim()) * TERM_TEST_SIZES[term]
        base = true_model.terms[term].values[k]
        unit = _effect_rms(true_model, term, k, base + direction, truth)
        values = base + direction * (sc.size / unit)
        for _ in range(3):  # non-linear terms: rescale to the size
            got = _effect_rms(true_model, term, k, values, truth)
            values = base + (values - base) * (sc.size / got)
        v = true_model.terms[term].values.copy()
        v[k] = values
        true_model = true_model.with_terms(**{term: v})
        injected[(term, k)] = values.copy()
    samples = simulate_measurements(true_model, truth, np.random.default_rng(sc.seed + 20_000))
    outside_sensors = []
    for kind, kwargs in sc.outside:
        if kind == "vibration":
            samples = fx.add_vibration(samples, true_model, rng=rng, **kwargs)
            outside_sensors += [true_model.names[s] if isinstance(s, int) else s for s in kwargs["sensors"]]
        elif kind == "colored_noise":
            samples = fx.add_colored_noise(samples, true_model, rng=rng, **kwargs)
            s = kwargs["sensor"]
            outside_sensors.append(true_model.names[s] if isinstance(s, int) else s)
        else:
            raise ValueError(f"unknown out-of-library effect {kind!r}")
    return Built(sc, samples, nominal, true_model, injected, outside_sensors)


def _covered(f) -> tuple:
    """The IMU indexes a finding (discover.Finding) claims its effect on: every IMU of a pooled scope."""
    return tuple(getattr(f, "imus", ()) or (f.k,))


def score(built: Built, d) -> dict:
    """How discovery ``d`` did on ``built``: correct (exactly the injected (term, IMU) pairs found, nothing
    else), false findings (findings not injected), magnitudes (max |estimate - truth| / std per finding),
    and for out-of-library effects: located (their IMUs among the unexplained entries) and not forced into a
    term (no finding on them).

    A finding at a pooled scope (several IMUs) is matched by its whole IMU set: it is right only when the
    effect was injected on every one of its IMUs (a scope wider than the truth is a false finding on the IMUs
    it adds; one narrower leaves the others missed); its per-IMU values are compared with each IMU's truth."""
    sc = built.scenario
    names = built.nominal.names
    truth = set(built.injected)
    found = {}  # (term, k) -> (values, std) of that IMU
    false = []
    for f in d.findings:
        imus = _covered(f)
        wrong = [k for k in imus if (f.effect, k) not in truth]
        if wrong:
            false.append(f"{f.effect}@{f.sensor}" if len(imus) == 1 else
                         f"{f.effect}@{f.scope} ({', '.join(names[k] for k in imus)})")
        for i, k in enumerate(imus):
            if len(imus) == 1 or getattr(f, "imu_values", None) is None:
                found[(f.effect, k)] = (f.values, f.std)
            else:
                found[(f.effect, k)] = (f.imu_values[i], f.imu_std[i])
    z = {}
    for key in truth & set(found):
        values, std = found[key]
        with np.errstate(invalid="ignore", divide="ignore"):
            zz = np.abs(np.asarray(values) - built.injected[key]) / np.asarray(std)
        z[f"{key[0]}@{names[key[1]]}"] = float(np.nanmax(zz)) if np.isfinite(zz).any() else None
    false = sorted(false)
    out = {"scenario": sc.name, "kind": sc.kind, "array": sc.array, "injected":
           [f"{t}@{built.nominal.names[k]}" for (t, k) in sorted(truth)],
           "found": [f"{t}@{built.nominal.names[k]}" for (t, k) in sorted(found)],
           "correct": not false and set(found) == truth,
           "missed": sorted(f"{t}@{built.nominal.names[k]}" for (t, k) in truth - set(found)),
           "false_findings": false, "max_abs_z": z,
           "within_3sigma": all(v is not None and v <= 3.0 for v in z.values()) if z else None,
           "indistinguishable": [e["effects"] for e in d.indistinguishable],
           "unexplained_entries": len(d.unexplained)}
    if sc.outside:
        n, hit = len(built.outside_sensors), set(built.outside_sensors)
        freqs = [kw["frequency_hz"] for kind, kw in sc.outside if kind == "vibration"]

        def covers(e):  # the entry holds the affected IMUs (and, for a vibration, its frequency)
            return hit <= set(e["sensors"]) and all(e["band_hz"][0] <= f <= e["band_hz"][1] for f in freqs)
        forced = {names[k] for f in d.findings for k in _covered(f)} & hit
        out["outside_sensors"] = built.outside_sensors
        out["located"] = any(covers(e) for e in d.unexplained)
        # the affected IMUs carry most of the entry's excess (not always possible: a vibration at one corner of
        # a four-corner layout leaves the same residual at every corner once the rigid motion absorbs its
        # affine part)
        out["led_by_affected"] = any(covers(e) and set(e["sensors"][:n]) == hit for e in d.unexplained)
        out["unexplained"] = [{"sensors": e["sensors"], "axes": e["axes"], "band_hz": e["band_hz"],
                               "improves_heldout": e["empirical_model"]["improves_heldout"]} for e in d.unexplained]
        out["forced_into_term"] = sorted(forced)
        out["correct"] = out["located"] and not forced and not found
    return out


def _outer(path: str) -> list[int]:
    """Indexes of the IMUs on the outer ring of a planar grid layout (largest |x| or |y|)."""
    from imu_array_ros.model.description import load_description

    p = load_description(path).positions
    ax, ay = np.abs(p[:, 0]), np.abs(p[:, 1])
    return [int(i) for i in np.flatnonzero((ax > ax.max() - 1e-6) | (ay > ay.max() - 1e-6))]


def standard_suite(*, arrays=("config/mimu4444bt_corners.yaml", "config/array32.yaml"), nulls: int = 20,
                   seed: int = 1) -> list[Scenario]:
    """The committed suite: every registered term on one IMU of the 8-IMU array; the confounded pairs on
    different IMUs; two out-of-library effects; ``nulls`` null recordings; and on the 32-IMU array a subset
    of single terms and nulls."""
    from imu_array_ros.model.terms import candidate_names

    corners, big = arrays
    out, s = [], seed
    for i, term in enumerate(candidate_names()):
        out.append(Scenario(f"{term}@imu_{i % 8 + 1}", corners, [(term, i % 8)], seed=s))
        s += 1
    for i, (a, b) in enumerate(CONFOUNDED_PAIRS):
        ka, kb = (2 * i) % 8, (2 * i + 5) % 8
        out.append(Scenario(f"{a}@imu_{ka + 1}+{b}@imu_{kb + 1}", corners, [(a, ka), (b, kb)], seed=s))
        s += 1
    out.append(Scenario("vibration 38 Hz @imu_1,imu_2", corners,
                        outside=[("vibration", {"sensors": [0, 1], "frequency_hz": 38.0, "amplitude": 0.045})],
                        seed=s))
    out.append(Scenario("vibration 45 Hz @outer ring (32 IMUs)", big,
                        outside=[("vibration", {"sensors": _outer(big), "frequency_hz": 45.0, "amplitude": 0.04})],
                        seed=s + 100))
    out.append(Scenario("coloured noise @imu_6 acc", corners,
                        outside=[("colored_noise", {"sensor": 5, "correlation_time_s": 0.05, "std_ratio": 1.0})],
                        seed=s + 1))
    s += 2
    for i in range(nulls):
        out.append(Scenario(f"null {i + 1}", corners, seed=s))
        s += 1
    big_terms = ("position", "time_offset", "accelerometer_bias", "gyroscope_gain", "accelerometer_misalignment")
    for i, term in enumerate(big_terms):
        k = (7 * i + 3) % 32
        out.append(Scenario(f"{term}@imu_{k:02d} (32 IMUs)", big, [(term, k)], seed=s))
        s += 1
    for i in range(3):
        out.append(Scenario(f"null {i + 1} (32 IMUs)", big, seed=s))
        s += 1
    return out
