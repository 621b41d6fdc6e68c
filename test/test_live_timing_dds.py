"""IMUs with their own stamps, live over real DDS (own ROS_DOMAIN_ID, localhost only): driver_node replays a
recording whose IMUs stamp their messages on their own clocks, fusion_node (``stamps:=own``) pairs them onto
the reference IMU's stamps, estimates the stamp clocks live and publishes on that grid; against
``imu-array fuse`` of the same recording."""

from __future__ import annotations

import re
import sys

import numpy as np
from conftest import REPO
from dds_harness import BIN
from imu_array_ros.io.pairing import ImuStream, pair_streams
from imu_array_ros.io.rosbag.recording import write_imu_recording
from imu_array_ros.model.description import load_description
from imu_array_ros.model.sensor_model import SensorModel
from imu_array_ros.simulation.clocks import simulate_own_clocks
from imu_array_ros.workflows.fusion import fuse_recording

CORNERS = REPO / "config" / "mimu4444bt_corners.yaml"
SECONDS, RATE = 8.0, 250.0


def test_own_stamp_replay_through_fusion_node_on_the_reference_grid(dds, tmp_path):
    desc = load_description(CORNERS)
    rng = np.random.default_rng(2024)
    streams = simulate_own_clocks(SensorModel.from_description(desc), rng, SECONDS, RATE,
                                  start_ns=1_790_000_000_000_000_000)
    samples, _ = pair_streams([ImuStream(s, a, g) for s, a, g in zip(streams.stamps, streams.accel, streams.gyro)],
                              desc.names)
    bag = tmp_path / "own.mcap"
    write_imu_recording(bag, samples, desc)  # every message with its own stamp
    want = fuse_recording(bag, desc)  # imu-array fuse: paired, stamp clocks from the whole recording
    assert want.session is not None and want.session.estimated
    n = len(want.fused)

    fusion = dds.start("fusion", BIN / "fusion_node", "--ros-args", "-p", f"array_config:={CORNERS}",
                       "-p", "reliable:=true", "-p", "stamps:=own", "-p", "sync_timeout:=0.3",
                       "-p", "session_window:=6.0", "-p", "session_interval:=2.0")
    probe = dds.start("probe", sys.executable, "-m", "imu_array_ros.nodes.probe", "--out", tmp_path / "got.npz",
                      "--count", n, "--timeout", 60, "--reliable")
    probe.wait_line("ready")
    driver = dds.start("driver", BIN / "driver_node", "--ros-args", "-p", f"array_config:={CORNERS}",
                       "-p", "mode:=replay", "-p", f"bag:={bag}", "-p", "rate:=1.0", "-p", "reliable:=true",
                       "-p", "wait_for_subscribers:=1", "-p", "exit_at_end:=true")
    code, _, err = probe.finish(90)
    assert code == 0, err
    code, _, err = driver.finish(30)
    assert code == 0, err
    code, _, err = fusion.stop()
    assert code == 0 and "Traceback" not in err and "[FATAL]" not in err, err
    got = np.load(tmp_path / "got.npz")

    # every sample on the reference IMU's grid, in order, none lost: the stamps offline fuse gives
    np.testing.assert_array_equal(got["stamps"], want.fused.stamps)
    assert "tracking session states (stamp clocks)" in err
    # the stamp clocks were estimated live; the samples fused after that agree with offline
    first = re.search(r"\[INFO\] \[(\d+\.\d+)\] \[imu_array_fusion\]: session states estimated", err)
    assert first, err
    after = got["arrival_ns"] > int(float(first.group(1)) * 1e9) + 200_000_000
    assert after.sum() > 0.15 * n, (after.sum(), n)
    x = np.concatenate([got["omega"], got["omega_dot"], got["specific_force"]], axis=1)[after]
    ref = want.fused
    y = np.concatenate([ref.omega, ref.omega_dot, ref.specific_force], axis=1)[after]
    sigma = np.sqrt(np.diagonal(ref.covariance, axis1=1, axis2=2))[after]
    z = (np.abs(x - y) / sigma).max(axis=1)  # the largest of the 9, per sample, in Cramér-Rao sigmas
    # the live estimate (a 6 s window) against the whole recording's, and the rate constant over a live batch
    # (test_live_timing.py): typically a few tenths of a sigma (measured: median 0.12-0.18, 95th percentile 0.32-0.45)
    assert np.median(z) < 0.4 and np.quantile(z, 0.95) < 1.0, (np.median(z), np.quantile(z, 0.95), z.max())
    # the covariance published is the time-aware CRB of the same model
    cov, cov_ref = got["covariance"][after][:, :3, :3], ref.covariance[after][:, :3, :3]
    np.testing.assert_allclose(cov, cov_ref, rtol=0.05, atol=1e-3 * float(np.abs(cov_ref).max()))
    print(f"{after.sum()} of {n} samples after the first estimate: |live - offline| / sigma median "
          f"{np.median(z):.3g}, 95th percentile {np.quantile(z, 0.95):.3g}, max {z.max():.3g}")


def test_unknown_reference_imu_is_one_line(dds):
    code, _, err = dds.start("fusion", BIN / "fusion_node", "--ros-args", "-p", f"array_config:={CORNERS}",
                             "-p", "stamps:=own", "-p", "reference_imu:=imu_99").finish(60)
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert code == 2 and len(lines) == 1, err
    assert lines[0].startswith("fusion_node: error: parameter 'reference_imu'") and "imu_99" in lines[0], err
