"""The "every IMU its own value" scope on the 32-IMU grid, and the block-robust test it gets.

Before 261a61f the own scope was scored on arrays of at most 16 IMUs only, and its block-robust test was always
Hotelling's, which cannot even be formed with K x p dof above the number of time blocks (96 dof, ~40 blocks): a
scattered group of weak carriers on the grid had no pooled test at all.
"""

from __future__ import annotations

import numpy as np
import pytest

from imu_array_ros.discovery.discover import DiscoveryOptions, discover
from imu_array_ros.discovery.explain import block_tests
from imu_array_ros.discovery.scopes import OWN_MAX_IMUS, geometry_groups, scopes_for
from imu_array_ros.model.layouts import grid_array32
from imu_array_ros.model.sensor_model import SensorModel

from conftest import icosahedron_recording


def test_the_grid_has_an_own_scope():
    nominal = SensorModel.from_description(grid_array32())
    assert OWN_MAX_IMUS >= 32
    scopes, _ = scopes_for(32, geometry_groups(nominal.positions, nominal.rotations))
    assert [s.imus for s in scopes if s.kind == "own"] == [tuple(range(32))]


@pytest.mark.parametrize("blocks,dof,expect", [(40, 30, "dispersion"), (80, 30, "hotelling"), (59, 30, "dispersion")])
def test_the_own_scope_test_switches_to_the_dispersion_form_below_twice_its_dof(blocks, dof, expect):
    """dispersion=None: the quasi-likelihood form where B < 2q, else Hotelling's -- the same p as asking for it."""
    rng = np.random.default_rng(blocks)
    a = rng.normal(size=(blocks, dof, dof))
    sb = np.einsum("bij,bkj->bik", a, a) / dof + np.eye(dof)[None] * 0.1
    gb = np.einsum("bij,bj->bi", np.linalg.cholesky(sb), rng.normal(size=(blocks, dof)))
    folds = np.arange(blocks) % 5
    auto = block_tests(gb, sb, folds, np.unique(folds), dispersion=None)
    want = block_tests(gb, sb, folds, np.unique(folds), dispersion=expect == "dispersion")
    other = block_tests(gb, sb, folds, np.unique(folds), dispersion=expect != "dispersion")
    assert auto[4] == want[4] and auto[4] != other[4]


def test_a_null_grid_recording_scores_every_term_at_the_own_scope_and_finds_nothing():
    """A short 32-grid session with no effect: every candidate term has an 'all own' candidate (K x p dof, a finite
    dispersion-robust p: more dof than twice the blocks), none passes."""
    nominal = SensorModel.from_description(grid_array32())
    terms = ("accelerometer_gain", "gyroscope_bias", "position")
    s = icosahedron_recording(nominal, nominal, 17, twist_s=4.0, still_s=0.3, transition_s=0.3)
    d = discover(s, nominal, options=DiscoveryOptions(terms=terms, empirical=False, heldout=False, timing=False))
    assert d.findings == []
    own = {c.effect: c for c in d.candidates if c.scope == "all own"}
    assert set(own) == set(terms)
    for c in own.values():
        assert c.dof >= 90 and np.isfinite(c.robust_p) and c.robust_p > 1e-3, (c.effect, c.dof, c.robust_p)
