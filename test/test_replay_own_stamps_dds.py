"""driver_node replays a recording of IMUs with their own stamps over real DDS (own ROS_DOMAIN_ID,
localhost only): every message, each with its own recorded stamp and values, in stamp order per topic."""

from __future__ import annotations

import time

import numpy as np

from imu_array_ros.io.messages import decode_raw_imu
from imu_array_ros.io.rosbag.mcap_writer import write_recording
from imu_array_ros.model.description import save_description
from imu_array_ros.model.layouts import planar_square4
from dds_harness import BIN, COME_UP_S
from test_pairing import channels, own_clock_streams



def test_replay_republishes_every_message_with_its_own_stamp(dds, tmp_path):
    import rclpy
    from rclpy.experimental import EventsExecutor
    from sensor_msgs.msg import Imu

    from imu_array_ros.io.rosbag.recording import imu_topic
    from imu_array_ros.nodes.runtime import qos

    desc = planar_square4()
    save_description(desc, tmp_path / "array.yaml")
    streams, _ = own_clock_streams(seed=22, k=4, seconds=2.0)  # 27 messages the pairing leaves unused
    write_recording(tmp_path / "own.mcap", channels(streams, desc))
    total = sum(len(s.stamps) for s in streams)
    rclpy.init()
    try:
        node = rclpy.create_node("own_stamp_listener")
        got: list[list[bytes]] = [[] for _ in desc.names]
        for k, name in enumerate(desc.names):
            node.create_subscription(Imu, imu_topic(name), got[k].append, qos(True, True), raw=True)
        ex = EventsExecutor()
        ex.add_node(node)
        driver = dds.start("driver", BIN / "driver_node", "--ros-args",
                           "-p", f"array_config:={tmp_path / 'array.yaml'}", "-p", "mode:=replay",
                           "-p", f"bag:={tmp_path / 'own.mcap'}", "-p", "rate:=0.0",
                           "-p", "wait_for_subscribers:=1", "-p", "exit_at_end:=true")
        end = time.monotonic() + COME_UP_S
        while time.monotonic() < end and sum(map(len, got)) < total and driver.poll() is None:
            ex.spin_once(timeout_sec=0.02)
        end = time.monotonic() + 5  # what is still on its way when the driver has ended
        while time.monotonic() < end and sum(map(len, got)) < total:
            ex.spin_once(timeout_sec=0.02)
        code, _, err = driver.finish(30)
        assert code == 0, err
        node.destroy_node()
    finally:
        rclpy.try_shutdown()
    assert [len(g) for g in got] == [len(s.stamps) for s in streams]
    for k, (name, s) in enumerate(zip(desc.names, streams)):
        dec = decode_raw_imu(got[k], np.zeros(len(got[k]), np.int64), [name])
        assert dec.usable.all()
        np.testing.assert_array_equal(dec.stamps, s.stamps)  # its own stamps, in order
        np.testing.assert_array_equal(dec.gyro, s.gyro)
        np.testing.assert_array_equal(dec.accel, s.accel)
