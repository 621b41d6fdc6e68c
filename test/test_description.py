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
from imu_array_ros.model.sensor_model import apply_terms, random_error_terms

from conftest import REPO


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
    desc = apply_terms(array32, random_error_terms(32, rng))
    desc = desc.with_imus(
        [imu.__class__(**{**imu.__dict__, "position_std": np.full(3, 1e-5)}) for imu in desc.imus],
        calibration={"method": "test", "residual_rms": 0.1},
    )
    path = tmp_path / "cal.yaml"
    save_description(desc, path)
    back = load_description(path)
    assert back.calibration == {"method": "test", "residual_rms": 0.1}
    for a, b in zip(desc.imus, back.imus):
        for field in ("gain", "nonorthogonality", "misalignment", "bias"):
            np.testing.assert_array_equal(getattr(a.accelerometer, field), getattr(b.accelerometer, field))
        np.testing.assert_array_equal(a.gyroscope.bias, b.gyroscope.bias)
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
    import imu_array_ros.io.atomic as atomic

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
