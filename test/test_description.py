"""The array description contract: strict parsing, round trips, atomic writes."""

from __future__ import annotations

import numpy as np
import pytest
import yaml

from imu_array_ros.model.layouts import ROT_180_ABOUT_Y_EQ_X
from imu_array_ros.model.identifiability import check_identifiable
from imu_array_ros.model.description import (
    description_to_dict,
    load_description,
    save_description,
)
from imu_array_ros.errors import ConfigError, IdentifiabilityError

from conftest import REPO, perturbed


def test_shipped_array32_matches_the_papers():
    desc = load_description(REPO / "config" / "array32.yaml")
    assert len(desc.imus) == 32
    pos = desc.positions
    np.testing.assert_allclose(sorted(set(np.round(pos[:, 0], 6))), np.array([-9.45, -3.15, 3.15, 9.45]) * 1e-3)
    assert np.allclose(pos[:16, 2], 0.001) and np.allclose(pos[16:, 2], -0.001)  # underside 2 mm lower
    np.testing.assert_allclose(desc.orientations[16:], np.broadcast_to(ROT_180_ABOUT_Y_EQ_X, (16, 3, 3)))
    # 180 deg about y = x keeps the axis [1, 1, 0] and flips z
    np.testing.assert_allclose(ROT_180_ABOUT_Y_EQ_X @ [1, 1, 0], [1, 1, 0])
    np.testing.assert_allclose(ROT_180_ABOUT_Y_EQ_X @ [0, 0, 1], [0, 0, -1])


@pytest.mark.parametrize("name", ["array32.yaml", "planar4.yaml"])
def test_shipped_descriptions_load_and_are_identifiable(name):
    desc = load_description(REPO / "config" / name)
    check_identifiable(desc.positions, len(desc.imus))


def test_round_trip_with_calibration_fields(tmp_path, array32, rng):
    desc = perturbed(array32, rng)
    desc = desc.with_imus(
        [imu.with_values(stds={"position": np.full(3, 1e-5)}) for imu in desc.imus],
        calibration={"method": "test", "residual_rms": 0.1},
    )
    path = tmp_path / "cal.yaml"
    save_description(desc, path)
    back = load_description(path)
    assert back.calibration == {"method": "test", "residual_rms": 0.1}
    for a, b in zip(desc.imus, back.imus):
        for field in ("gain", "nonorthogonality", "misalignment", "bias"):
            np.testing.assert_array_equal(a.value(f"accelerometer.{field}"), b.value(f"accelerometer.{field}"))
        np.testing.assert_array_equal(a.value("gyroscope.bias"), b.value("gyroscope.bias"))
        assert set(a.values) == set(b.values) and a.values  # the perturbed fields, and only those
        np.testing.assert_array_equal(a.position, b.position)
        np.testing.assert_array_equal(a.position_std, b.position_std)


def _write(tmp_path, data) -> str:
    p = tmp_path / "a.yaml"
    p.write_text(yaml.safe_dump(data) if not isinstance(data, str) else data)
    return p


def _base(array32):
    return description_to_dict(array32)


@pytest.mark.parametrize(
    "mutate, message",
    [
        (lambda d: d["imu_array"].update(colour="red"), "unknown key 'colour'"),
        (lambda d: d["imu_array"]["imus"][3].update(posiiton=[0, 0, 0]), "unknown key 'posiiton'"),
        (lambda d: d["imu_array"]["imus"][3]["accelerometer"].update(scale=[1, 1, 1]), "unknown key 'scale'"),
        (lambda d: d["imu_array"].pop("gyroscope_noise_std"), "missing key 'gyroscope_noise_std'"),
        (lambda d: d["imu_array"]["imus"][2].update(position=[0, 0]), "imu 'imu_02'.position"),
        (lambda d: d["imu_array"]["imus"][2].update(orientation=[1, 0, 0, 0, 1, 0, 0, 0, 2]), "proper rotation"),
        (lambda d: d["imu_array"]["imus"][2].update(name="imu_01"), "duplicate IMU name"),
        (lambda d: d["imu_array"].update(accelerometer_noise_std=-1), "must be > 0"),
        (lambda d: d["imu_array"].update(gyroscope_range=".nan"), "expected a number"),
        (lambda d: d["imu_array"]["imus"][3]["accelerometer"].update(gain=[1, 0, 1]), "must be > 0"),
    ],
)
def test_bad_descriptions_give_one_line_errors(tmp_path, array32, mutate, message):
    data = _base(array32)
    data["imu_array"]["imus"][3]["accelerometer"] = {"bias": [0.1, 0, 0]}
    mutate(data)
    path = _write(tmp_path, data)
    with pytest.raises(ConfigError) as err:
        load_description(path)
    text = str(err.value)
    assert message in text and str(path) in text and "\n" not in text


def test_malformed_and_missing_files(tmp_path):
    with pytest.raises(ConfigError, match="not found"):
        load_description(tmp_path / "nope.yaml")
    with pytest.raises(ConfigError, match=r"line \d+: malformed YAML"):
        load_description(_write(tmp_path, "imu_array:\n  frame_id: [unclosed\n"))
    with pytest.raises(ConfigError, match="expected a mapping"):
        load_description(_write(tmp_path, "- just a list\n"))


def test_save_is_atomic_and_keeps_previous_on_failure(tmp_path, array32, monkeypatch):
    path = tmp_path / "good.yaml"
    save_description(array32, path)
    before = path.read_bytes()
    import imu_array_ros.util.files as atomic

    def boom(*a, **k):
        raise OSError("disk full")

    monkeypatch.setattr(atomic.os, "replace", boom)
    with pytest.raises(OSError):
        save_description(array32.with_imus(array32.imus[:5]), path)
    assert path.read_bytes() == before
    assert [p.name for p in tmp_path.iterdir()] == ["good.yaml"]  # no temp file left behind


def test_identifiability_conditions():
    check_identifiable([[0, 0, 0], [0.01, 0, 0], [0, 0.01, 0]], 1)
    with pytest.raises(IdentifiabilityError, match="no gyroscope"):
        check_identifiable([[0, 0, 0], [0.01, 0, 0], [0, 0.01, 0]], 0)
    with pytest.raises(IdentifiabilityError, match="at least 3"):
        check_identifiable([[0, 0, 0], [0.01, 0, 0]], 2)
    with pytest.raises(IdentifiabilityError, match="collinear"):
        check_identifiable([[0, 0, 0], [0.01, 0.01, 0], [0.02, 0.02, 0]], 3)


# --------------------------------------------------------------------------- the registry-driven schema

from hypothesis import HealthCheck, given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402

from imu_array_ros.model.description import description_from_dict, dump_description, term_fields  # noqa: E402
from imu_array_ros.model.sensor_model import SensorModel  # noqa: E402
from imu_array_ros.model.terms import REGISTRY, candidate_names  # noqa: E402

_FINITE = st.floats(-1e3, 1e3, allow_nan=False, allow_infinity=False)
_POSITIVE = st.floats(1e-3, 1e3, allow_nan=False, allow_infinity=False)
_STD = st.floats(0.0, 1e3, allow_nan=False, allow_infinity=False)


def _field_strategy(f, numbers):
    if f.shape == ():
        return numbers
    leaf = st.lists(numbers, min_size=f.shape[-1], max_size=f.shape[-1])
    return leaf if len(f.shape) == 1 else st.lists(leaf, min_size=f.shape[0], max_size=f.shape[0])


@st.composite
def _imu_dicts(draw, i):
    d = {"name": f"imu_{i}", "position": draw(_field_strategy(term_fields()["position"], _FINITE)),
         "orientation": [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]}
    for key, f in term_fields().items():
        if f.session:
            continue  # refused in a description (test_session_states_are_refused)
        section = d if len(f.path) == 1 else d.setdefault(f.path[0], {})
        if key != "position" and draw(st.booleans()):
            section[f.path[-1]] = draw(_field_strategy(f, _POSITIVE if f.positive else _FINITE))
        if draw(st.booleans()):
            section[f.path[-1] + "_std"] = draw(_field_strategy(f, _STD))
    return {k: v for k, v in d.items() if v != {}}


@st.composite
def _description_dicts(draw):
    n = draw(st.integers(1, 3))
    return {"imu_array": {"frame_id": "array", "accelerometer_noise_std": 0.05, "gyroscope_noise_std": 0.01,
                          "gyroscope_range": 35.0, "accelerometer_range": 160.0,
                          "imus": [draw(_imu_dicts(i)) for i in range(n)]}}


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(_description_dicts())
def test_every_term_field_and_its_std_round_trips(data):
    """save(load(x)) == x for every registered term's fields and their _std, in any combination."""
    desc = description_from_dict(data)
    assert description_to_dict(desc) == data
    back = description_from_dict(yaml.safe_load(dump_description(desc)))
    assert description_to_dict(back) == data


def test_session_states_are_refused(tmp_path, array32):
    """A session state (a clock phase) is not a device constant: a description holding one is refused by
    name, and a model holding one writes every field but it."""
    data = description_to_dict(array32)
    data["imu_array"]["imus"][2]["sample_clock"] = {"period": 1e-3, "phase": 2e-4}
    with pytest.raises(ConfigError, match=r"sample_clock.phase.*session state"):
        description_from_dict(data, "x.yaml")
    model = SensorModel.from_description(array32)
    clock = np.tile([1e-3, 250.0, 3e-4], (32, 1))
    desc = model.with_terms(sample_clock=clock).to_description(array32, stds={"sample_clock": np.full((32, 3), 1.0)})
    assert desc.imus[2].value("sample_clock.rate") == 250.0 and desc.imus[2].value("sample_clock.phase") == 0.0
    text = dump_description(desc)
    assert "phase" not in text and "rate: 250.0" in text and "rate_std: 1.0" in text


def test_schema_is_the_registry():
    """Every registered term's fields are keys (gyroscope.nonorthogonality included); nothing else is."""
    keys = {f.key for cls in REGISTRY.values() for f in cls.fields}
    assert set(term_fields()) == keys
    assert {"gyroscope.nonorthogonality", "accelerometer.axis_offsets", "accelerometer.quadratic",
            "gyroscope.g_sensitivity", "accelerometer.time_offset", "gyroscope.time_offset",
            "accelerometer.bias_drift", "gyroscope.bias_drift"} <= keys


def test_foundation_files_load_unchanged(tmp_path):
    """A file in the foundation's schema (nilsson2014 triads, position_std) gives the same model values."""
    text = """imu_array:
  frame_id: array
  accelerometer_noise_std: 0.05
  gyroscope_noise_std: 0.01
  gyroscope_range: 34.9
  accelerometer_range: 156.9
  imus:
  - name: a
    position: [0.01, 0.02, 0.0]
    position_std: [1.0e-05, 2.0e-05, 3.0e-05]
    orientation: [1, 0, 0, 0, 1, 0, 0, 0, 1]
    accelerometer: {gain: [1.01, 0.99, 1.0], nonorthogonality: [0.001, 0.0, -0.002], misalignment: [0.0, 0.01, 0.0],
                    bias: [0.1, -0.1, 0.2]}
    gyroscope: {gain: [1.0, 1.02, 1.0], misalignment: [0.003, 0.0, 0.0], bias: [0.01, 0.0, -0.01]}
calibration: {method: geometry}
"""
    path = tmp_path / "old.yaml"
    path.write_text(text)
    desc = load_description(path)
    model = SensorModel.from_description(desc)
    np.testing.assert_array_equal(model.terms["accelerometer_gain"].values, [[1.01, 0.99, 1.0]])
    np.testing.assert_array_equal(model.terms["accelerometer_nonorthogonality"].values, [[0.001, 0.0, -0.002]])
    np.testing.assert_array_equal(model.terms["gyroscope_misalignment"].values, [[0.003, 0.0, 0.0]])
    np.testing.assert_array_equal(model.terms["gyroscope_bias"].values, [[0.01, 0.0, -0.01]])
    np.testing.assert_array_equal(model.terms["gyroscope_nonorthogonality"].values, [[0.0, 0.0, 0.0]])
    np.testing.assert_array_equal(desc.imus[0].position_std, [1e-5, 2e-5, 3e-5])
    assert description_to_dict(load_description(REPO / "config" / "array32.yaml")) == yaml.safe_load(
        (REPO / "config" / "array32.yaml").read_text())
    assert description_to_dict(desc) == yaml.safe_load(text)  # nothing dropped, nothing added


def test_saving_keeps_gyroscope_nonorthogonality_and_new_terms(tmp_path, array32, rng):
    """The foundation's writer dropped gyroscope.nonorthogonality; every term now survives a save."""
    model = SensorModel.from_description(array32)
    values = {name: REGISTRY[name].default_values(32) + rng.normal(0, 1e-3, (32, REGISTRY[name].dim()))
              for name in candidate_names()}
    model = model.with_terms(**values)
    stds = {name: np.full((32, REGISTRY[name].dim()), 1e-4) for name in ("position", "gyroscope_g_sensitivity")}
    path = tmp_path / "cal.yaml"
    save_description(model.to_description(array32, stds=stds), path)
    back = load_description(path)
    for name, term in SensorModel.from_description(back).terms.items():
        np.testing.assert_array_equal(term.values, values[name] if name in values else term.default_values(32),
                                      err_msg=name)
    np.testing.assert_array_equal(back.imus[5].stds["gyroscope.g_sensitivity"], np.full((3, 3), 1e-4))
    assert "g_sensitivity_std:" in path.read_text() and "nonorthogonality:" in path.read_text()


@pytest.mark.parametrize("mutate, message", [
    (lambda imu: imu["gyroscope"].update(g_sensitivity=[[0, 0], [0, 0], [0, 0]]), "gyroscope.g_sensitivity"),
    (lambda imu: imu["gyroscope"].update(gain_std=[0.1, -0.1, 0.1]), "must be >= 0"),
    (lambda imu: imu["accelerometer"].update(time_offset="soon"), "accelerometer.time_offset"),
    (lambda imu: imu.update(position_std=[1, 2]), "position_std"),
])
def test_bad_term_fields_are_one_line_errors(tmp_path, array32, mutate, message):
    data = _base(array32)
    imu = data["imu_array"]["imus"][0]
    imu["accelerometer"], imu["gyroscope"] = {}, {}
    mutate(imu)
    path = _write(tmp_path, data)
    with pytest.raises(ConfigError) as err:
        load_description(path)
    assert message in str(err.value) and "\n" not in str(err.value)


def test_yaml_12_numbers_are_numbers(tmp_path):
    """PyYAML (YAML 1.1) reads 1e-3 and -0.00945e3 as strings; a description must read them as numbers."""
    from imu_array_ros.util.files import parse_yaml

    doc = parse_yaml("a: 1e-3\nb: -0.00945e3\nc: 5E2\nd: .5e1\ne: 12\nf: 1.5\ng: e3\nh: 1e\ni: '1e-3'\nj: .inf\n")
    assert doc == {"a": 1e-3, "b": -9.45, "c": 500.0, "d": 5.0, "e": 12, "f": 1.5, "g": "e3", "h": "1e",
                   "i": "1e-3", "j": float("inf")}
    assert isinstance(doc["e"], int)
    text = (REPO / "config" / "mimu4444bt_corners.yaml").read_text()
    path = tmp_path / "mm.yaml"
    path.write_text(text.replace("accelerometer_noise_std: 0.045", "accelerometer_noise_std: 45e-3", 1))
    assert "45e-3" in path.read_text()
    assert load_description(path).accelerometer_noise_std == pytest.approx(0.045)
