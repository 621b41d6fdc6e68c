"""Gyroscope biases as session states (imu_array_ros/calibration/bias_tracking.py): the batch estimator recovers a
known bias within its std, the live tracker finds the offline numbers, the fusion with tracking is back at its
Cramér-Rao covariance, and ``imu-array fuse --no-bias-tracking`` turns it off."""

from __future__ import annotations

import numpy as np
import pytest

from imu_array_ros.calibration.bias_tracking import BiasTracker, equivalent_sigma, track_biases
from imu_array_ros.io.rosbag.recording import read_fused_recording, write_imu_recording
from imu_array_ros.model.samples import ImuSamples
from imu_array_ros.model.sensor_model import SensorModel
from imu_array_ros.workflows import fuse, load_array
from imu_array_ros.workflows.live_session import BiasSessionTracker
from imu_array_ros.workflows.recordings import simulate

from conftest import REPO, cli

MIMU = REPO / "config" / "mimu4444bt_corners.yaml"


def biased(seed: int, *, still=3.0, twist=10.0, rate=62.5, scale=0.02):
    """An icosahedron session (20 rests, then twisting) of the MIMU-like array measured by gyroscopes with
    biases b_true ~ N(0, scale) per axis; the description says 0."""
    desc, _ = load_array(MIMU)
    b_true = np.random.default_rng(100 + seed).normal(0.0, scale, (len(desc.names), 3))
    true_desc = SensorModel.from_description(desc).with_terms(gyroscope_bias=b_true).to_description(
        desc, names=["gyroscope_bias"])
    sim = simulate(desc, motion="icosahedron", rate=rate, still_seconds=still, transition_seconds=2.0,
                   twist_seconds=twist, rms_rate=200.0, true_desc=true_desc, seed=seed)
    return desc, sim, b_true


@pytest.fixture(scope="module")
def session():
    return biased(1)


def nees_omega(fused, truth):
    idx = np.searchsorted(truth.stamps, fused.stamps)
    err = fused.omega - truth.omega[idx]
    return np.einsum("ni,nij,nj->n", err, np.linalg.inv(fused.covariance[:, :3, :3]), err)


def test_each_still_piece_measures_the_true_bias_within_its_std():
    z, final = [], []
    for seed in range(3):
        desc, sim, b_true = biased(seed)
        track = track_biases(sim.samples, SensorModel.from_description(desc))
        assert len(track.updates) == 20  # one piece per rest: 3 s rests keep ~2.5 s
        z += [(u.measured - b_true) / u.measured_std for u in track.updates]
        last = track.updates[-1]
        final.append((last.bias - b_true) / last.bias_std)
    z, final = np.array(z), np.array(final)
    assert np.isfinite(z).all()
    # white noise: the batch-means std is at least the white one, so E[z^2] is 1 or a little below
    assert 0.6 < np.mean(z ** 2) < 1.2, np.mean(z ** 2)
    assert np.abs(z).max() < 5.0
    assert 0.4 < np.mean(final ** 2) < 1.6, np.mean(final ** 2)  # the Kalman combination of the 20 rests


def test_without_a_rest_the_description_holds():
    desc, _ = load_array(MIMU)
    sim = simulate(desc, motion="twist", duration=4.0, rate=62.5, rms_rate=200.0, seed=2)
    track = track_biases(sim.samples, SensorModel.from_description(desc))
    assert not track.updates
    assert track.correct(sim.samples, SensorModel.from_description(desc)) is sim.samples
    assert "description's biases kept" in track.notes()[0]


def test_offline_biases_are_piecewise_and_the_first_reaches_back(session):
    desc, sim, _ = session
    model = SensorModel.from_description(desc)
    track = track_biases(sim.samples, model)
    table = track.biases_at(sim.samples.stamps)
    u = track.updates
    np.testing.assert_array_equal(table[0], u[0].bias)  # before the first rest: the first rest's estimate
    inside = np.searchsorted(sim.samples.stamps, u[3].piece.start_ns)
    np.testing.assert_array_equal(table[inside], u[3].bias)
    np.testing.assert_array_equal(table[inside - 1], u[2].bias)
    corrected = track.correct(sim.samples, model)
    np.testing.assert_allclose(sim.samples.gyro - corrected.gyro, table, atol=1e-15)


def test_the_live_tracker_finds_the_offline_numbers(session):
    desc, sim, _ = session
    model = SensorModel.from_description(desc)
    offline = track_biases(sim.samples, model)
    live = BiasSessionTracker(model, batch_s=0.3)
    s = sim.samples
    cuts = np.sort(np.random.default_rng(4).choice(np.arange(1, len(s.stamps)), 400, replace=False))
    for lo, hi in zip(np.concatenate([[0], cuts]), np.concatenate([cuts, [len(s.stamps)]])):
        live.add(ImuSamples(s.stamps[lo:hi], s.accel[lo:hi], s.gyro[lo:hi], s.names), None)
        live.poll(int(s.stamps[0]))
        live.wait()
    live.poll(int(s.stamps[0]))
    live.wait()
    live.poll(int(s.stamps[0]))
    assert live.error is None
    # the offline track ends the last rest at the end of the recording; live it is never over
    assert len(offline.updates) - 1 <= len(live.updates) <= len(offline.updates)
    assert len(live.updates) >= 19
    for a, b in zip(live.updates, offline.updates):
        assert (a.piece.start_ns, a.piece.stop_ns) == (b.piece.start_ns, b.piece.stop_ns)
        np.testing.assert_allclose(a.measured, b.measured, rtol=0, atol=1e-15)
        np.testing.assert_allclose(a.bias, b.bias, rtol=0, atol=1e-15)
    np.testing.assert_array_equal(live.apply(model).terms["gyroscope_bias"].values, live.updates[-1].bias)
    v = live.values()
    assert v["gyro_bias_updates"] == len(live.updates) and v["gyro_bias_source"] == "still intervals"
    assert v[f"gyro_bias_z_rad_s/{desc.names[2]}"] == float(live.updates[-1].bias[2, 2])
    assert v[f"gyro_bias_x_std_rad_s/{desc.names[0]}"] > 0


def test_long_rests_are_cut_into_pieces_live_and_offline():
    desc, sim, _ = biased(3, still=8.0, twist=2.0)
    model = SensorModel.from_description(desc)
    a = track_biases(sim.samples, model, max_piece_s=3.0)
    b = track_biases(sim.samples, model, max_piece_s=3.0, chunk=37)
    assert len(a.updates) == len(b.updates) > 20
    assert max(u.piece.seconds for u in a.updates) <= 3.0
    for x, y in zip(a.updates, b.updates):
        np.testing.assert_allclose(x.bias, y.bias, rtol=0, atol=1e-15)


def test_fused_omega_is_back_at_its_covariance_with_tracking(session):
    desc, sim, _ = session
    stale, _ = fuse(sim.samples, desc, bias_tracking=False)
    tracked, _ = fuse(sim.samples, desc)
    n_stale, n_tracked = nees_omega(stale, sim.truth).mean(), nees_omega(tracked, sim.truth).mean()
    se = np.sqrt(2 * 3 / len(tracked))  # NEES of 3 dof, independent samples
    assert n_stale > 20.0, n_stale
    assert abs(n_tracked / 3.0 - 1.0) < 5 * se + 0.05, n_tracked


def test_a_jump_is_judged_on_the_three_axes_together():
    np.testing.assert_allclose(equivalent_sigma(np.array([9.0]), np.array([1])), [3.0], rtol=1e-9)
    assert equivalent_sigma(np.array([9.0]), np.array([3]))[0] < 3.0  # 3 sigma on one of three axes is less
    assert equivalent_sigma(np.array([5.0]), np.array([0]))[0] == 0.0
    desc, sim, b_true = biased(2)
    model = SensorModel.from_description(desc)
    tracker = BiasTracker(model)
    tracker.add(sim.samples)
    first = tracker.updates[0]
    assert (first.jump_sigma > 10).all()  # 0.02 rad/s biases against a description of 0


def test_fuse_cli_tracks_by_default_and_the_flag_turns_it_off(session, tmp_path, capsys):
    desc, sim, _ = session
    rec = tmp_path / "rec.mcap"
    write_imu_recording(rec, sim.samples, desc)
    code, _, err = cli(capsys, "fuse", rec, "--array", MIMU, "--out", tmp_path / "on.mcap")
    assert code == 0, err
    pieces = len(track_biases(sim.samples, SensorModel.from_description(desc)).updates)
    assert f"gyroscope biases: {pieces} still pieces" in err, err
    code, _, err_off = cli(capsys, "fuse", rec, "--array", MIMU, "--out", tmp_path / "off.mcap", "--no-bias-tracking")
    assert code == 0, err_off
    assert "gyroscope biases" not in err_off
    on, off = read_fused_recording(tmp_path / "on.mcap"), read_fused_recording(tmp_path / "off.mcap")
    want_on, _ = fuse(sim.samples, desc)
    want_off, _ = fuse(sim.samples, desc, bias_tracking=False)
    np.testing.assert_allclose(on.omega, want_on.omega, rtol=0, atol=1e-12)
    np.testing.assert_allclose(off.omega, want_off.omega, rtol=0, atol=1e-12)
    assert np.abs(on.omega - off.omega).max() > 1e-3


def test_many_bias_jumps_share_one_console_line():
    """A real capture jumps dozens of times (helper-31's trial: ~20 lines per fuse): the first few are listed,
    the rest summed up in one line with their times."""
    from imu_array_ros.calibration.bias_tracking import (MAX_JUMP_LINES, BiasTrack, BiasUpdate, StillPiece)

    names, z = ("a", "b"), np.zeros((2, 3))

    def update(t_s, sigma):
        piece = StillPiece(int(t_s * 1e9), int((t_s + 1) * 1e9), int((t_s + 0.5) * 1e9), np.array([50, 50]), z, z,
                           z)
        return BiasUpdate(piece, z, z, z, z, z, np.array([sigma, 0.0]))

    jumps = 3 * MAX_JUMP_LINES
    track = BiasTrack(names, z, [update(0, 0)] + [update(10 * (i + 1), 5.0) for i in range(jumps)])
    notes = track.notes()
    listed = [n for n in notes if n.startswith("gyroscope biases: update")]
    assert len(listed) == MAX_JUMP_LINES and "a (5.0 sigma)" in listed[0], notes
    assert len(notes) == 1 + MAX_JUMP_LINES + 1 and f"{jumps - MAX_JUMP_LINES} more updates" in notes[-1], notes
    assert notes[-1].endswith(f"{10 * jumps} s"), notes[-1]


def test_session_notes_are_prefixed_once():
    """Each session state's note is one console line that says 'session states' once."""
    from types import SimpleNamespace

    from imu_array_ros.workflows.fusion import session_notes

    notes = session_notes(SimpleNamespace(notes=["session states estimated from 114 s of motion",
                                                 "imu_1 gyroscope clock phase 0.3 ms"]), None)
    assert notes == ["session states estimated from 114 s of motion",
                     "session states: imu_1 gyroscope clock phase 0.3 ms"]
