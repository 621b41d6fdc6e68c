"""The command line with time-aware recordings: ``fuse`` and ``residuals`` of IMUs that stamp their own
messages (paired, session states estimated, every grid sample fused, the notes printed), and the
description's session states refused."""

from __future__ import annotations

import json

import numpy as np

from imu_array_ros.io.pairing import ImuStream, pair_streams
from imu_array_ros.io.rosbag.recording import read_fused_recording, write_imu_recording
from imu_array_ros.model.description import load_description
from imu_array_ros.model.sensor_model import SensorModel
from imu_array_ros.simulation.clocks import simulate_own_clocks

from conftest import REPO, assert_user_error, cli

CORNERS = REPO / "config" / "mimu4444bt_corners.yaml"


def test_fuse_and_residuals_of_own_stamps(tmp_path, capsys):
    desc = load_description(CORNERS)
    streams = simulate_own_clocks(SensorModel.from_description(desc), np.random.default_rng(4), 8.0, 200.0,
                                  start_ns=1_700_000_000 * 10**9)
    samples, _ = pair_streams([ImuStream(s, a, g) for s, a, g in zip(streams.stamps, streams.accel, streams.gyro)],
                              desc.names)
    rec = tmp_path / "own.mcap"
    write_imu_recording(rec, samples, desc)
    code, out, err = cli(capsys, "fuse", rec, "--array", CORNERS, "--out", tmp_path / "f.mcap")
    assert code == 0, err
    assert "paired" in err and "session states estimated from" in err and "states: session" not in err, err
    fused = read_fused_recording(tmp_path / "f.mcap")
    assert len(fused.stamps) == len(samples)  # no gaps on the reference's grid
    np.testing.assert_array_equal(fused.stamps, samples.stamps)
    code, out, err = cli(capsys, "residuals", rec, "--array", CORNERS, "--json", "-")
    assert code == 0, err
    result = json.loads(out)
    offsets = result["session_states"]["stamp_clock_offset_s"]
    assert set(offsets) == set(desc.names) and offsets[desc.names[0]] == 0.0
    assert result["recording"]["moving"]["ratio_all"] < 3.0, result["recording"]["moving"]


def test_a_description_holding_a_session_state_is_refused(tmp_path, capsys):
    text = CORNERS.read_text().replace("{name: imu_1, ", "{name: imu_1, stamp_clock: {offset: 0.001}, ", 1)
    bad = tmp_path / "bad.yaml"
    bad.write_text(text)
    assert "stamp_clock" in text
    assert_user_error(cli(capsys, "fuse", tmp_path / "missing.mcap", "--array", bad, "--out", tmp_path / "o.mcap"),
                      "stamp_clock.offset", "session state")
