"""driver_node replays a recording of IMUs with their own stamps over real DDS (own ROS_DOMAIN_ID,
localhost only): every message, each with its own recorded stamp and values, in stamp order per topic."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from imu_array_ros.io.messages import decode_raw_imu
from imu_array_ros.io.rosbag.mcap_writer import write_recording
from imu_array_ros.model.description import save_description
from imu_array_ros.model.layouts import planar_square4
from test_pairing import channels, own_clock_streams

BIN = Path(sys.executable).parent


@pytest.fixture
def ros_env(monkeypatch):
    domain = 100 + (os.getpid() * 11 + int(time.time() * 1000)) % 130
    env = dict(os.environ, ROS_DOMAIN_ID=str(domain), ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST",
               PYTHONUNBUFFERED="1")
    for key in ("ROS_DOMAIN_ID", "ROS_AUTOMATIC_DISCOVERY_RANGE"):
        monkeypatch.setenv(key, env[key])
    procs: list[subprocess.Popen] = []

    def start(*cmd):
        p = subprocess.Popen([str(c) for c in cmd], env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        procs.append(p)
        return p

    yield start
    for p in procs:
        if p.poll() is None:
            p.send_signal(signal.SIGINT)
            try:
                p.wait(10)
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait()


def test_replay_republishes_every_message_with_its_own_stamp(ros_env, tmp_path):
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
        driver = ros_env(BIN / "driver_node", "--ros-args", "-p", f"array_config:={tmp_path / 'array.yaml'}",
                         "-p", "mode:=replay", "-p", f"bag:={tmp_path / 'own.mcap'}", "-p", "rate:=0.0",
                         "-p", "wait_for_subscribers:=1", "-p", "exit_at_end:=true")
        end = time.monotonic() + 60
        while time.monotonic() < end and sum(map(len, got)) < total:
            ex.spin_once(timeout_sec=0.02)
        assert driver.wait(30) == 0, driver.stderr.read()
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
