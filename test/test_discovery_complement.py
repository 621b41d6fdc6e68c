"""A finding's value on some IMUs against the opposite value on the others (discovery/complement.py): named
indistinguishable when the fit's gauge (a common shift of every sensor's time offset) makes them the same readings,
not otherwise (a change across the gauge; a term no gauge moves; a finding on one IMU)."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from imu_array_ros.discovery import complement
from imu_array_ros.model.description import load_description
from imu_array_ros.model.sensor_model import SensorModel

STD = 5e-6  # s, each free offset's CRB std


@pytest.fixture(scope="module")
def corners():
    return SensorModel.from_description(load_description("config/mimu4444bt_corners.yaml"))


def _fit(model, change, gauge=True, seed=0):
    """time_offset free on all 8 IMUs (16 parameters, IMU-major): ``change`` (8, 2) plus a common shift and CRB
    noise, imu_1's accelerometer offset held (the gauge's reference)."""
    rng = np.random.default_rng(seed)
    d = np.asarray(change, dtype=float).reshape(-1) + rng.normal(size=16) * STD
    d += (-d[0]) if gauge else 0.0  # the fit's gauge: the held offset at its starting value
    cov = np.eye(16) * STD ** 2
    if gauge:
        cov[0, 0] = 0.0
    theta = model.terms["time_offset"].values.reshape(-1) + d
    return SimpleNamespace(free=("time_offset",), imus=tuple(model.names), theta=theta, covariance=cov,
                           model=model.with_terms(time_offset=theta.reshape(8, 2)),
                           gauge_directions=np.full((16, 1), 0.25) if gauge else np.zeros((16, 0)))


def _finding(imus, scope="imu_00,imu_01,imu_02 shared", shared=True):
    return SimpleNamespace(effect="time_offset", imus=tuple(imus), scope=scope, shared=shared, sensor=scope, step=1)


def _ties(monkeypatch, model, fit, finding):
    monkeypatch.setattr(complement, "refit", lambda *a, **k: fit)
    out = []
    n = complement.complement_ties(None, model, model, [finding], None, 0.01, out)
    assert n == len(out)
    return out


def test_an_offset_on_three_imus_is_the_opposite_offset_on_the_other_five(monkeypatch, corners):
    change = np.zeros((8, 2))
    change[:3] = 300e-6  # accelerometer and gyroscope alike: along the common shift
    out = _ties(monkeypatch, corners, _fit(corners, change), _finding((0, 1, 2)))
    assert len(out) == 1
    alts = out[0]["alternatives"]
    assert alts[0]["sensors"] == [corners.names[k] for k in (0, 1, 2)]
    assert alts[1]["sensors"] == [corners.names[k] for k in range(3, 8)]
    assert "does not tell" in out[0]["reason"]


def test_a_lag_across_the_gauge_has_no_complement(monkeypatch, corners):
    change = np.zeros((8, 2))
    change[:3] = (300e-6, -300e-6)  # accelerometer against gyroscope: no common shift makes it the others'
    assert _ties(monkeypatch, corners, _fit(corners, change), _finding((0, 1, 2))) == []


def test_no_gauge_no_complement_and_single_imus_are_left(monkeypatch, corners):
    change = np.zeros((8, 2))
    change[:3] = 300e-6
    assert _ties(monkeypatch, corners, _fit(corners, change, gauge=False), _finding((0, 1, 2))) == []
    assert _ties(monkeypatch, corners, _fit(corners, change), _finding((0,), scope="imu")) == []
    assert _ties(monkeypatch, corners, _fit(corners, change), _finding((0, 1, 2), shared=False)) == []


def test_a_complement_already_named_is_not_named_twice(monkeypatch, corners):
    change = np.zeros((8, 2))
    change[:3] = 300e-6
    named = {"alternatives": [{"effect": "time_offset", "sensors": [corners.names[k] for k in (0, 1, 2)]},
                              {"effect": "time_offset", "sensors": [corners.names[k] for k in range(3, 8)]}]}
    monkeypatch.setattr(complement, "refit", lambda *a, **k: _fit(corners, change))
    out = [named]
    assert complement.complement_ties(None, corners, corners, [_finding((0, 1, 2))], None, 0.01, out) == 0
    assert out == [named]


def test_the_refit_starts_from_the_current_model_with_the_term_reset(monkeypatch, corners):
    """What the search kept beside the findings (the timing stage's clocks; here a changed gyroscope bias) stays
    in the refit's model; the finding's term starts from the input model's values on every IMU."""
    change = np.zeros((8, 2))
    change[:3] = 300e-6
    kept = corners.terms["gyroscope_bias"].values + 0.01
    current = corners.with_terms(gyroscope_bias=kept, time_offset=corners.terms["time_offset"].values + change)
    seen = []
    monkeypatch.setattr(complement, "refit", lambda samples, model, pairs, motion: seen.append(model) or
                        _fit(corners, change))
    complement.complement_ties(None, corners, current, [_finding((0, 1, 2))], None, 0.01, [])
    (model,) = seen
    assert np.array_equal(model.terms["gyroscope_bias"].values, kept)
    assert np.array_equal(model.terms["time_offset"].values, corners.terms["time_offset"].values)
