"""Which IMUs carry a pooled finding (:mod:`imu_array_ros.discovery.subset`): an effect on some IMUs of a scope
is reported on exactly those, an effect on every IMU stays on every IMU.

The carrier logic on hand-made joint fits (exact numbers, no engine), then short simulated sessions of the
4-IMU planar array and the 8-corner array (fixed seeds) through the whole discovery.
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from imu_array_ros.discovery.discover import DiscoveryOptions, discover
from imu_array_ros.discovery.scopes import geometry_groups
from imu_array_ros.discovery.subset import propose, restricted, scope_label, wald
from imu_array_ros.model.description import load_description
from imu_array_ros.model.layouts import planar_square4
from imu_array_ros.model.sensor_model import SensorModel

from conftest import icosahedron_recording, with_change

ROOT = Path(__file__).resolve().parents[1]
OPTIONS = dict(empirical=False, heldout=False, timing=False)
TERM = "gyroscope_bias"  # 3 parameters


def _fit(d, sd, gauge=None):
    """A joint fit of gyroscope_bias on 4 IMUs (values = changes d (4, 3), independent std sd (4,))."""
    d = np.asarray(d, dtype=float)
    var = np.repeat(np.asarray(sd, dtype=float) ** 2, 3)
    names = tuple(f"imu_{k}" for k in range(len(d)))
    return SimpleNamespace(free=(TERM,), imus=names, model=SimpleNamespace(names=names), theta=d.reshape(-1),
                           covariance=np.diag(var), gauge_directions=np.zeros((d.size, 0)) if gauge is None else gauge)


def test_wald_and_restriction_statistics():
    """Independent unit-variance values: the Wald statistic is their sum of squares; one shared value leaves
    the squares about their mean."""
    d, cov = np.array([1.0, 2.0, 3.0]), np.eye(3)
    stat, dof, _ = wald(d, cov)
    assert (stat, dof) == (pytest.approx(14.0), 3)
    stat, dof = restricted(d, cov, np.ones((3, 1)))
    assert (stat, dof) == (pytest.approx(2.0), 2)
    held = np.diag([1.0, 0.0, 1.0])  # a held parameter carries no information
    assert wald(d, held)[:2] == (pytest.approx(10.0), 2)


def test_carriers_of_an_effect_on_two_of_four():
    v = np.array([1.0, -0.6, 0.8]) * 10.0
    fit = _fit([0 * v, v, v, 0 * v], [1.0] * 4)
    prop = propose(fit, TERM, (0, 1, 2, 3), np.zeros((4, 3)), 0.01)
    assert prop.imus == (1, 2)
    assert set(prop.p) == {1, 2} and max(prop.p.values()) < 1e-10  # each needed given the other
    assert prop.zero_dof == 6 and prop.zero_stat == pytest.approx(0.0)
    assert prop.alternatives == []


def test_the_smallest_adequate_set_wins():
    """IMU 3 at 1.5 sigma: the set without it is accepted at alpha (nothing on IMUs 0 and 3: Wald 2.25 on 6
    dof), so it is left out; at 5 sigma (Wald 25, p 3e-4) it is needed."""
    v = np.array([1.0, -0.6, 0.8])
    u = v / np.linalg.norm(v)
    assert propose(_fit([0 * v, 10 * v, 10 * v, 1.5 * u], [1.0] * 4), TERM, range(4), np.zeros((4, 3)),
                   0.01).imus == (1, 2)
    assert propose(_fit([0 * v, 10 * v, 10 * v, 5.0 * u], [1.0] * 4), TERM, range(4), np.zeros((4, 3)),
                   0.01).imus == (1, 2, 3)


def test_no_subset_when_every_imu_or_none_carries_it():
    v = np.array([1.0, -0.6, 0.8]) * 10.0
    assert propose(_fit([v, v, v, v], [1.0] * 4), TERM, (0, 1, 2, 3), np.zeros((4, 3)), 0.01) is None
    # every IMU too uncertain alone: the pooled evidence is all there is
    assert propose(_fit([v, v, v, v], [20.0] * 4), TERM, (0, 1, 2, 3), np.zeros((4, 3)), 0.01) is None


def test_no_subset_when_the_rest_is_not_zero():
    """IMUs 1, 2 strong, IMU 3 below its own Bonferroni level but jointly not zero with IMU 0: no subset."""
    v = np.array([1.0, -0.6, 0.8])
    prop = propose(_fit([2.5 * v, 10 * v, 10 * v, 2.5 * v], [1.0] * 4), TERM, (0, 1, 2, 3), np.zeros((4, 3)),
                   0.01)
    assert prop is None


def test_gauge_the_sparsest_representation():
    """A common bias of every IMU is a gauge freedom (absorbed by the motion), the fit holds IMU 0's: an effect
    on IMU 0 alone shows as the opposite value on IMUs 1-3.  Re-expressed in the gauge that puts IMU 1 at zero,
    IMU 0 alone carries it: the sparsest explanation."""
    v = np.array([1.0, -0.6, 0.8]) * 10.0
    gauge = np.tile(np.eye(3), (4, 1)) / 2.0  # theta + gauge @ c: the same readings
    fit = _fit([0 * v, -v, -v, -v], [0.0, 1.0, 1.0, 1.0], gauge=gauge)
    prop = propose(fit, TERM, (0, 1, 2, 3), np.zeros((4, 3)), 0.01)
    assert prop.imus == (0,)
    assert prop.zero in (1, 2, 3)


def test_scope_labels_name_the_imus():
    names = [f"imu_{k}" for k in range(1, 9)]
    groups = [("top", (0, 2, 4, 6)), ("bottom", (1, 3, 5, 7))]
    assert scope_label((6, 2, 0, 4), names, groups, True) == "top shared"
    assert scope_label((1, 3, 5, 7), names, groups, False) == "bottom own"
    assert scope_label((0, 5), names, groups, True) == "imu_1,imu_6 shared"
    assert scope_label(range(8), names, groups, True) == "all shared"


# --------------------------------------------------------------------------------------------- end to end

def _recording(nominal, model, seed, twist_s=4.0):
    return icosahedron_recording(nominal, model, seed, twist_s=twist_s, still_s=0.3, transition_s=0.3)


def _found(d):
    return [(f.effect, f.imus) for f in d.findings]


@pytest.mark.parametrize("imus, scope", [((0, 2), "imu_00,imu_02 shared"), ((1, 2), "back shared")])
def test_effect_on_two_of_four_imus_is_reported_on_those_two(imus, scope):
    """A non-linearity on two IMUs of the planar 4 (evidence ~190).  On a diagonal pair, which no geometry
    group is, its pooled test passes at 'all own' and the finding is narrowed to the pair; on the back half
    the 'back shared' scope is tested directly.  Either way reported on exactly those IMUs, one shared value
    within 3 std of the truth."""
    nominal = SensorModel.from_description(planar_square4())
    value = np.array([1.0, -0.6, 0.8]) * 1.5e-4
    s = _recording(nominal, with_change(nominal, "accelerometer_nonlinearity", value, imus), 5)
    d = discover(s, nominal, options=DiscoveryOptions(terms=("accelerometer_nonlinearity", "accelerometer_bias",
                                                             "gyroscope_gain"), **OPTIONS))
    assert _found(d) == [("accelerometer_nonlinearity", imus)]
    f = d.findings[0]
    assert f.scope == scope and f.shared
    names = [nominal.names[k] for k in imus]
    if scope.startswith("imu_"):
        assert f"carried by {', '.join(names)} only" in f.candidate.note
    else:
        assert f.candidate.scope == scope and "carried by" not in f.candidate.note
    assert np.all(np.abs(f.values - value) < 3 * f.std)
    assert d.to_dict()["findings"][0]["sensors"] == names


@pytest.fixture(scope="module")
def corners():
    return SensorModel.from_description(load_description(str(ROOT / "config" / "mimu4444bt_corners.yaml")))


def test_effect_on_four_corners_is_reported_on_those_four(corners):
    """A non-linearity on corners 0, 1, 2, 5 (two top, two bottom: no geometry group; evidence ~740): its pooled
    test passes at 'all own'; reported on exactly those four, not on all eight."""
    value = np.array([1.0, -0.6, 0.8]) * 2e-4
    s = _recording(corners, with_change(corners, "accelerometer_nonlinearity", value, (0, 1, 2, 5)), 13)
    d = discover(s, corners, options=DiscoveryOptions(terms=("accelerometer_nonlinearity", "accelerometer_bias"),
                                                      **OPTIONS))
    assert _found(d) == [("accelerometer_nonlinearity", (0, 1, 2, 5))]
    assert d.findings[0].scope == "imu_1,imu_2,imu_3,imu_6 shared"


def test_effect_on_every_imu_stays_on_every_imu_with_one_noisy_imu(corners):
    """One value on all 8 corners (evidence ~1400), IMU 3's accelerometer 30x noisier: the 7 others explain the
    pooled fit without it, but one value shared by all 8 is as likely (the tie test accepts it), so the
    finding stays on all 8 ('all shared'), not narrowed to the 7."""
    noisy = corners.acc_std.copy()
    noisy[3] *= 30.0
    nominal = replace(corners, acc_std=noisy)
    value = np.array([1.0, -0.6, 0.8]) * 2.5e-4
    s = _recording(nominal, with_change(nominal, "accelerometer_nonlinearity", value, range(8)), 24)
    d = discover(s, nominal, options=DiscoveryOptions(terms=("accelerometer_nonlinearity", "accelerometer_bias"),
                                                      **OPTIONS))
    assert [(f.effect, f.scope) for f in d.findings] == [("accelerometer_nonlinearity", "all shared")]
    f = d.findings[0]
    assert f.imus == tuple(range(8)) and f.shared
    assert f.candidate.note.startswith("narrowing to imu_1, imu_2, imu_3, imu_5, imu_6, imu_7, imu_8")
    assert f.candidate.note.endswith("the scope stands")
    assert np.all(np.abs(f.values - value) < 3 * f.std)


def test_geometry_groups_are_named(corners):
    assert dict(geometry_groups(corners.positions, corners.rotations))["top"] == (0, 2, 4, 6)


def test_leaving_out_only_the_gauge_reference_is_no_narrowing():
    """Every IMU with its own value and the fit's gauge holding IMU 0's (as the per-axis accelerometer
    offsets of the real captures, where 'imu_2..imu_8' was reported for all 8): dropping just the IMU the
    gauge puts at zero says nothing about which IMUs carry the effect."""
    rng = np.random.default_rng(3)
    d = rng.normal(0.0, 10.0, (4, 3))
    d[0] = 0.0
    gauge = np.tile(np.eye(3), (4, 1)) / 2.0
    fit = _fit(d, [0.0, 1.0, 1.0, 1.0], gauge=gauge)
    assert propose(fit, TERM, (0, 1, 2, 3), np.zeros((4, 3)), 0.01) is None
