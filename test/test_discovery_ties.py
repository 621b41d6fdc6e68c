"""Candidates whose scores tie: discovery confirms each exactly and keeps the largest exact gain."""

from __future__ import annotations

import numpy as np

from imu_array_ros.discovery.confirm import TIE_MAX, settle_ties, tied
from imu_array_ros.discovery.explain import BIC_GAP, Candidate


def _cand(effect, sensor, dof, bic, k=0):
    return Candidate(effect=effect, k=k, sensor=sensor, statistic=-bic, dof=dof, lrt_p=1e-9, robust_p=1e-9,
                     delta_loglik=-bic / 2, delta_bic=bic, heldout=1.0, theta=np.zeros(dof))


def test_only_same_dof_within_the_gap_are_tied():
    c = _cand("axis_offsets", "top", 9, -2.76e6)
    near = _cand("axis_offsets", "bottom", 9, -2.76e6 + 0.4 * BIC_GAP)
    other_dof = _cand("accelerometer_gain", "all", 3, -2.76e6 + 0.1)
    far = _cand("axis_offsets", "imu_8", 9, -2.76e6 + 2 * BIC_GAP)
    earlier = _cand("axis_offsets", "imu_1", 9, -2.76e6 - 1.0)  # ranked before c: tested already, not tied
    passing = [earlier, c, near, other_dof, far]
    assert tied(c, passing) == [near]
    many = [c] + [_cand("axis_offsets", f"imu_{i}", 9, -2.76e6 + 0.01 * i) for i in range(6)]
    assert len(tied(c, many)) == TIE_MAX - 1


def test_the_larger_exact_gain_wins_and_the_note_says_so():
    c = _cand("axis_offsets", "top", 9, -2.76e6)
    near = _cand("axis_offsets", "bottom", 9, -2.76e6 + 1.0)
    refused = _cand("axis_offsets", "outer", 9, -2.76e6 + 2.0)
    gains = {"bottom": ("fit-bottom", 1.457e6), "outer": "not confirmed by the exact fit: ..."}
    tried, notes, rejected, said = [], [], [], []

    def confirm_one(o):
        tried.append(o.sensor)
        return gains[o.sensor]

    best, result = settle_ties(c, ("fit-top", 1.429e6), [c, near, refused], confirm_one, 2, said.append, notes,
                               rejected)
    assert tried == ["bottom", "outer"] and best is near and result == ("fit-bottom", 1.457e6)
    assert len(notes) == 1 and "kept axis_offsets on bottom" in notes[0] and "+1.429e+06" in notes[0]
    assert [r["scope"] for r in rejected] == ["imu"] and refused.note.startswith("not confirmed")
    # the first one kept when it gains more; no tie, no note, no extra exact fit
    best, _ = settle_ties(c, ("fit-top", 2e6), [c, near], confirm_one, 2, said.append, notes := [], [])
    assert best is c and "kept axis_offsets on top" in notes[0]
    tried.clear()
    best, _ = settle_ties(c, ("fit-top", 2e6), [c], confirm_one, 2, said.append, notes := [], [])
    assert best is c and not notes and not tried


def test_gains_within_ln_one_over_alpha_are_reported_indistinguishable():
    """A tie whose exact gains differ by less than ln(1/alpha) is not settled by the larger one alone: both are
    named indistinguishable (complementary scopes of one term: what the data fix is the difference); a gap of
    ln(1/alpha) or more is settled silently."""
    left = _cand("gyroscope_bias", "left shared (imu_00, imu_01)", 3, -440.0)
    left.imus = (0, 1)
    right = _cand("gyroscope_bias", "right shared (imu_02, imu_03)", 3, -439.0)
    right.imus = (2, 3)
    for gap, alike in ((0.5, True), (np.log(100.0) + 1e-6, False)):
        left.note = right.note = ""
        indist, notes = [], []
        best, result = settle_ties(left, ("fit-left", 223.9), [left, right], lambda o: ("fit-right", 223.9 + gap),
                                   1, lambda text: None, notes, [], alpha=0.01, indist=indist, n_imus=4)
        assert best is right and result[0] == "fit-right"
        assert bool(indist) == alike and ("indistinguishable from" in right.note) == alike
        if alike:
            (e,) = indist
            assert e["sensors"] == [right.sensor, left.sensor] and abs(e["delta_loglik_gap"] - gap) < 1e-9
            assert "complements" in e["reason"] and "left shared" in right.note
    # not complements (overlapping scopes): indistinguishable, without the common-value reason
    top = _cand("gyroscope_bias", "imu_00,imu_02 shared", 3, -439.5)
    top.imus = (0, 2)
    indist = []
    settle_ties(left, ("fit-left", 223.9), [left, top], lambda o: ("fit-top", 224.0), 1, lambda text: None, [], [],
                alpha=0.01, indist=indist, n_imus=4)
    assert len(indist) == 1 and "complements" not in indist[0]["reason"]


def test_shared_scopes_are_ranked_by_the_gain_of_the_shared_value():
    """Two complementary shared scopes (grid32's top and bottom halves, one value each): each is confirmed by a
    refit with every IMU's own value, whose gain holds the per-IMU values' noise (~45 dof of it).  The tie is
    settled by the gain of the shared value (exact_gain: the per-IMU gain less half the tie statistic), not the
    per-IMU fit's: here 66.31 against 66.24 -- indistinguishable -- although the per-IMU fits gained 81.5 and
    89.7 (the discovery_generalisation_283334 group 8 miss, reported on the wrong half with no note)."""
    top = _cand("accelerometer_misalignment", "top shared", 3, -93.9)
    top.imus = tuple(range(16))
    bottom = _cand("accelerometer_misalignment", "bottom shared", 3, -93.8)
    bottom.imus = tuple(range(16, 32))
    top.exact_gain, bottom.exact_gain = 66.31, 66.24
    indist, notes = [], []
    best, result = settle_ties(top, ("fit-top", 81.49), [top, bottom], lambda o: ("fit-bottom", 89.67), 1,
                               lambda text: None, notes, [], alpha=0.01, indist=indist, n_imus=32)
    assert best is top and result == ("fit-top", 81.49)
    (e,) = indist
    assert e["alternatives"][1]["effect"] == "accelerometer_misalignment" and "complements" in e["reason"]
    assert abs(e["delta_loglik_gap"] - 0.07) < 1e-9


def test_the_complement_is_tied_whatever_its_bic():
    """The same term at the complementary scope differs from the finding only by a value common to every IMU
    (nearly absorbed by the motion): it is confirmed exactly too, however far its first-order BIC."""
    c = _cand("gyroscope_bias", "left shared", 3, -440.0)
    c.imus = (0, 1)
    comp = _cand("gyroscope_bias", "right shared", 3, -440.0 + 5 * BIC_GAP)
    comp.imus = (2, 3)
    other = _cand("gyroscope_bias", "imu_00,imu_02 shared", 3, -440.0 + 5 * BIC_GAP)
    other.imus = (0, 2)
    assert tied(c, [c, comp, other], 4) == [comp]
    assert tied(c, [c, comp, other]) == []


def test_a_narrowed_findings_equivalent_sets_are_reported_with_alternatives():
    """A narrowed finding's sets that fit as well (Candidate.equivalents) become "indistinguishable" entries
    whose alternatives the suite's scorer reads (the kept one first)."""
    c = _cand("accelerometer_bias", "imu_01,imu_03 shared (imu_01, imu_03)", 3, -380.0)
    c.imus, c.sensors = (1, 3), ("imu_01", "imu_03")
    c.equivalents = [{"sensors": ["imu_00,imu_02 shared (imu_00, imu_02)"], "names": ["imu_00", "imu_02"],
                      "reason": "gauge: a common accelerometer_bias is absorbed by the fused motion"}]
    indist = []
    settle_ties(c, ("fit", 190.0), [c], lambda o: None, 1, lambda text: None, [], [], alpha=0.01, indist=indist,
                n_imus=4)
    (e,) = indist
    assert e["sensors"] == [c.sensor, "imu_00,imu_02 shared (imu_00, imu_02)"]
    assert e["alternatives"] == [{"effect": "accelerometer_bias", "sensors": ["imu_01", "imu_03"]},
                                 {"effect": "accelerometer_bias", "sensors": ["imu_00", "imu_02"]}]
