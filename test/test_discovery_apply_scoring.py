"""``discover --apply``: the findings' calibration scores the whole recording once per model, on one BLAS thread.

Each score is a motion fit of the whole recording (helper-65's profile of whole exp_3: the --apply check took 167 of
519 s with three such fits on the default BLAS threads).  The new model is scored once and the install reuses that
score; the start model once for the fits-better check."""

from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace

import pytest

import imu_array_ros.calibration.scoring as scoring
from imu_array_ros.discovery.apply import findings_calibration
from imu_array_ros.discovery.threads import limiter_available
from imu_array_ros.model.description import load_description
from imu_array_ros.model.sensor_model import SensorModel

CORNERS = Path(__file__).resolve().parents[1] / "config" / "mimu4444bt_corners.yaml"


def test_the_new_model_is_scored_once_and_on_one_blas_thread(monkeypatch, tmp_path):
    desc = load_description(CORNERS)
    start = SensorModel.from_description(desc)
    found = SensorModel.from_description(desc)
    calls = []

    def counting(samples, model):
        threads = None
        if limiter_available():
            from threadpoolctl import threadpool_info

            threads = {i["num_threads"] for i in threadpool_info() if i["user_api"] == "blas"}
        calls.append((model is found, threads))
        return 10.0 if model is found else 5.0

    monkeypatch.setattr(scoring, "window_loglik", counting)
    d = SimpleNamespace(findings=[], model=found, baseline=SimpleNamespace(loglik=5.0),
                        after=SimpleNamespace(loglik=10.0))
    cal = findings_calibration(d, samples=None, start=start)
    cal.install(desc, tmp_path / "out.yaml")
    assert sorted(c[0] for c in calls) == [False, True]  # start once, the new model once
    assert cal.score == pytest.approx(10.0)
    if limiter_available():
        assert all(c[1] == {1} for c in calls), calls
    assert (tmp_path / "out.yaml").exists()


def test_a_worse_fit_is_still_refused(monkeypatch):
    from imu_array_ros.errors import CalibrationError

    desc = load_description(CORNERS)
    start, found = SensorModel.from_description(desc), SensorModel.from_description(desc)
    monkeypatch.setattr(scoring, "window_loglik", lambda samples, model: 1.0 if model is found else 2.0)
    d = SimpleNamespace(findings=[], model=found, baseline=SimpleNamespace(loglik=2.0),
                        after=SimpleNamespace(loglik=1.0))
    with pytest.raises(CalibrationError, match="worse"):
        findings_calibration(d, samples=None, start=start)
