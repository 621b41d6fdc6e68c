"""Discovery never reports a finding whose exact fit is physically implausible (the calibrations' bound,
:func:`imu_array_ros.calibration.guards.implausible`): it is set aside with the reason, and ``--apply`` is not
left to refuse a report that already told the user the implausible values."""

from __future__ import annotations

from pathlib import Path

from imu_array_ros.calibration.guards import implausible
from imu_array_ros.discovery.discover import DiscoveryOptions, discover
from imu_array_ros.model.description import load_description
from imu_array_ros.model.sensor_model import SensorModel

from conftest import icosahedron_recording, with_change

ROOT = Path(__file__).resolve().parents[1]
CORNERS = str(ROOT / "config" / "mimu4444bt_corners.yaml")
OPTIONS = dict(empirical=False, heldout=False, timing=False)


def _gain(nominal, change):  # every IMU's gyroscope gains
    return with_change(nominal, "gyroscope_gain", change, range(nominal.n_imus))


def test_implausible_names_the_worst_value():
    nominal = SensorModel.from_description(load_description(CORNERS))
    assert implausible(_gain(nominal, 0.05), nominal) is None
    why = implausible(_gain(nominal, 0.3), nominal)
    assert "gyroscope.gain" in why and "more than 0.2 from 1" in why


def _moved(nominal, k, dx):
    return with_change(nominal, "position", [dx, 0.0, 0.0], [k])


def test_an_implausible_fit_is_set_aside_not_found():
    """imu_3's accelerometer 8 mm from where the description puts it (beyond the calibrations' 5 mm bound: a
    chip does not move on its board): the data want it, discovery must not report it as a finding; the
    rejected entry says why, and the search stops there.  (Plausible position errors are found: the suites.)"""
    nominal = SensorModel.from_description(load_description(CORNERS))
    opts = DiscoveryOptions(terms=("position",), **OPTIONS)
    d = discover(icosahedron_recording(nominal, _moved(nominal, 2, 8e-3), 5, twist_s=3.0), nominal, options=opts)
    assert not d.findings, [(f.effect, f.sensor) for f in d.findings]
    assert any("implausible" in r["reason"] and r["effect"] == "position" for r in d.rejected), d.rejected
    # and no plausible term is then made to stand in for it (other IMUs' positions did, before the stop)
    assert any("stopped" in n and "position on imu_3" in n for n in d.notes), d.notes
