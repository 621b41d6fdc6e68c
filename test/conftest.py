"""Shared fixtures: arrays and recordings built from fixed seeds."""

from __future__ import annotations

import functools
from pathlib import Path

import numpy as np
import pytest

from imu_array_ros.model.layouts import grid_array32, planar_square4, tetrahedron4

REPO = Path(__file__).resolve().parents[1]
ARRAY32 = REPO / "config" / "array32.yaml"
#: a fixed, realistic start time keeps simulated recordings reproducible
START = "2026-11-21T10:00:00Z"
SHARED_DATA = REPO.parent / "shared" / "data" / "openshoe_mimu4444bt"

#: skog2016 Sec. V-A noise figures: sigma_s = 0.01 m/s^2, sigma_w = 1 deg/s.
SKOG2016_NOISE = dict(accelerometer_noise_std=0.01, gyroscope_noise_std=float(np.deg2rad(1.0)))


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(20161)


@pytest.fixture
def array32():
    return grid_array32()


@pytest.fixture
def planar4():
    return planar_square4(**SKOG2016_NOISE)


@pytest.fixture
def tetra4():
    return tetrahedron4(**SKOG2016_NOISE)


# --------------------------------------------------------------------------- the command line, in-process


def cli(capsys, *args):
    """Run ``imu-array ARGS`` in-process; (exit status, stdout, stderr)."""
    from imu_array_ros.cli import main

    capsys.readouterr()
    code = main([str(a) for a in args])
    out, err = capsys.readouterr()
    return code, out, err


def assert_user_error(result, *fragments):
    """Exit status 2, nothing on stdout, exactly one line ``imu-array: error: ...`` on stderr
    holding every fragment, no traceback; returns that line."""
    code, out, err = result
    assert code == 2, (code, err)
    assert "Traceback" not in err and out == "", (out, err)
    lines = err.splitlines()
    assert len(lines) == 1 and lines[0].startswith("imu-array: error: "), err
    for frag in fragments:
        assert frag in lines[0], (frag, lines[0])
    return lines[0]


# --------------------------------------------------------------------------- true arrays


def perturbed(desc, rng, scales=None):
    """``desc`` with seeded errors in its terms (``perturb``; default sizes), as a description."""
    from imu_array_ros.model.sensor_model import SensorModel
    from imu_array_ros.simulation.perturb import DEFAULT_ERROR_SCALES, perturb

    scales = DEFAULT_ERROR_SCALES if scales is None else scales
    model = perturb(SensorModel.from_description(desc), rng, scales)
    return model.to_description(desc, names=[n for n, s in scales.items() if s])


def with_change(model, term: str, value, imus):
    """``model`` with ``value`` added to ``term``'s values on the IMUs ``imus`` (an injected effect)."""
    v = model.terms[term].values.copy()
    v[list(imus)] += value
    return model.with_terms(**{term: v})


def icosahedron_recording(nominal, model, seed: int, *, twist_s: float, still_s: float = 0.5,
                          transition_s: float = 0.5):
    """Readings of ``model`` along a short icosahedron session drawn for ``nominal`` from ``seed`` (rests and
    transitions of ``still_s`` / ``transition_s`` s, then ``twist_s`` s of twisting; 100 Hz); the noise from
    ``seed + 1``."""
    from imu_array_ros.simulation.icosahedron import simulate_icosahedron
    from imu_array_ros.simulation.simulator import simulate_measurements

    _, truth, _ = simulate_icosahedron(nominal, np.random.default_rng(seed), rate_hz=100.0, still_s=still_s,
                                       transition_s=transition_s, twist_s=twist_s)
    return simulate_measurements(model, truth, np.random.default_rng(seed + 1))


def gyro_chip_clocks(k: int, rng) -> np.ndarray:
    """(k, 3) MIMU-like gyroscope chip clocks drawn from ``rng``: period 1 ms, rate +-3000 ppm, random phase."""
    clock = np.column_stack([np.full(k, 1e-3), rng.uniform(-3000, 3000, k), np.zeros(k)])
    clock[:, 2] = rng.uniform(0, 1, k) * clock[:, 0] / (1 + clock[:, 1] * 1e-6)
    return clock


def clocked_twist_case(seed: int, stamps):
    """(clocked model, samples, ML motion with reading rates): sample clocks on the 8 corner IMUs
    (``mimu_like_clocks``, accelerometer lag 0.8 ms, gyroscope 2.9 ms), hand-like twisting plus motion faster than
    the reads follow, read at ``stamps`` (ns), all drawn from ``seed``."""
    from imu_array_ros.fitting.engine import fit_motion
    from imu_array_ros.fitting.reading_rates import reading_rates
    from imu_array_ros.model.description import load_description
    from imu_array_ros.model.sensor_model import SensorModel
    from imu_array_ros.simulation.clocks import mimu_like_clocks
    from imu_array_ros.simulation.motion import TwistTrajectory
    from imu_array_ros.simulation.simulator import simulate_trajectory

    root = Path(__file__).resolve().parents[1]
    corners = SensorModel.from_description(load_description(root / "config/mimu4444bt_corners.yaml"))
    rng = np.random.default_rng(seed)
    clocked = mimu_like_clocks(corners, rng, acc_lag=0.8e-3, gyro_lag=2.9e-3)
    a = np.array([[8.0, 1.4], [6.0, 1.2], [7.0, 1.3]])
    f = np.array([[1.1, 34.0], [1.7, 38.0], [0.9, 41.0]])
    sa = np.array([[2.0, 8.0], [2.0, 7.0], [2.0, 9.0]])
    sf = np.array([[0.7, 36.0], [1.2, 43.0], [0.5, 39.0]])
    twist = TwistTrajectory(a, f, rng.uniform(0, 2 * np.pi, (3, 2)), sa, sf, rng.uniform(0, 2 * np.pi, (3, 2)),
                            np.array([1.0, 0.0, 0.0, 0.0]))
    samples = simulate_trajectory(clocked, twist, stamps, rng)[0]
    with reading_rates():
        motion = fit_motion(samples, clocked)[0]
    return clocked, samples, motion


# --------------------------------------------------------------------------- node processes over real DDS


@pytest.fixture
def dds(monkeypatch, tmp_path):
    """:class:`dds_harness.DdsProcesses`: a DDS domain of this test's own (also for rclpy in the test
    process), processes with their output in files, stopped and their shared-memory files removed at the end."""
    from dds_harness import DdsProcesses

    procs = DdsProcesses(tmp_path / "procs")
    for key in ("ROS_DOMAIN_ID", "ROS_AUTOMATIC_DISCOVERY_RANGE"):
        monkeypatch.setenv(key, procs.env[key])
    try:
        yield procs
    finally:
        procs.close()


# --------------------------------------------------------------------------- parallel runs (pytest-xdist)

#: what marks a test module as talking ROS (rclpy in the test process, or node processes over DDS); a module
#: with a test using the ``dds`` fixture, directly or through another fixture, is known by the fixture closures
_ROS_WORDS = ("rclpy", "dds_env", "pick_domain", "DdsProcesses")


@functools.cache
def _talks_ros(path: Path) -> bool:
    text = path.read_text(encoding="utf-8")
    return any(w in text for w in _ROS_WORDS)


def pytest_configure(config):
    """In an xdist worker, one BLAS thread (for its child processes too): the workers already fill the cores,
    and OpenBLAS threads waiting on each other's cores cost more than they give on small products."""
    import os

    if os.environ.get("PYTEST_XDIST_WORKER"):
        from dds_harness import ONE_THREAD
        from threadpoolctl import threadpool_limits

        os.environ.update(ONE_THREAD)

        config._imu_array_blas = threadpool_limits(limits=1, user_api="blas")  # held for the session


def pytest_collection_modifyitems(config, items):
    """Under ``-n N --dist loadgroup`` every test of a module that talks ROS runs in one worker, one after
    another: the DDS tests keep the machine's other cores to their node processes' rhythm and never share a
    domain (and their module's real-time tests, e.g. the fake device's clock, keep a quiet core too), while the
    numerical tests spread over the other workers."""
    dds_modules = {Path(str(item.fspath)) for item in items if "dds" in getattr(item, "fixturenames", ())}
    for item in items:
        path = Path(str(item.fspath))
        if path in dds_modules or _talks_ros(path):
            item.add_marker(pytest.mark.xdist_group("ros"))
