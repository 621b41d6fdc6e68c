"""Simulated time over real DDS: the replay driver publishes /clock, and a node run with use_sim_time
sees the recording's time while the replay runs, never behind the IMU messages it has received."""

from __future__ import annotations

import importlib.util
import struct
import time

import numpy as np

from conftest import REPO
from dds_harness import BIN
from imu_array_ros.nodes.frames import NO_TF_MESSAGE

ARRAY8 = REPO / "config" / "mimu4444bt_corners.yaml"


def test_use_sim_time_node_sees_the_recording_time(dds, tmp_path):
    import rclpy
    from rclpy.experimental import EventsExecutor
    from rclpy.parameter import Parameter
    from sensor_msgs.msg import Imu

    from imu_array_ros.io.rosbag.recording import imu_topic, write_imu_recording
    from imu_array_ros.model.description import load_description
    from imu_array_ros.nodes.runtime import qos
    from imu_array_ros.simulation.simulator import simulate_twist

    rng = np.random.default_rng(int(time.time()))
    desc = load_description(ARRAY8)
    start_ns = int(rng.integers(1_600_000_000, 2_000_000_000)) * 10**9 + int(rng.integers(0, 10**9))
    samples, _ = simulate_twist(desc, 1.0, 200.0, rng, start_ns=start_ns)
    bag = tmp_path / "rec.mcap"
    write_imu_recording(bag, samples, desc)
    first, last = int(samples.stamps[0]), int(samples.stamps[-1])

    # started first (it starts up while this process does); it waits for the subscriptions below
    # (wait_for_subscribers: 1 in replay), then plays 1 s of recording in 0.5 s
    driver = dds.start("driver", BIN / "driver_node", "--ros-args", "-p", f"array_config:={ARRAY8}", "-p",
                       "mode:=replay", "-p", f"bag:={bag}", "-p", "rate:=2.0", "-p", "use_sim_time:=true")
    rclpy.init()
    try:
        node = rclpy.create_node("sim_time_listener", parameter_overrides=[Parameter("use_sim_time", value=True)])
        arrivals = []  # (message stamp, node clock at arrival)

        def receive(payload: bytes) -> None:
            sec, nsec = struct.unpack_from("<iI", payload, 4)  # header.stamp after the CDR encapsulation header
            arrivals.append((sec * 10**9 + nsec, node.get_clock().now().nanoseconds))

        for name in desc.names:
            node.create_subscription(Imu, imu_topic(name), receive, qos(True, keep_all=True), raw=True)
        ex = EventsExecutor()
        ex.add_node(node)
        clock = []  # the node's clock, read while it spins
        want = len(samples) * len(desc.names)
        end = time.monotonic() + 20.0
        while time.monotonic() < end and driver.poll() is None and len(arrivals) < want:
            ex.spin_once(timeout_sec=0.005)
            clock.append(node.get_clock().now().nanoseconds)
        _, _, err = driver.stop()  # every message is in (or the time is up): no need to wait for the acks
        node.destroy_node()
    finally:
        rclpy.try_shutdown()
    assert driver.returncode == 0 and "Traceback" not in err and "200 samples (1600 messages) published" in err, err
    # the driver was given use_sim_time too: it runs on the system clock anyway, and says so
    assert "use_sim_time ignored" in err, err
    if importlib.util.find_spec("tf2_msgs") is None:  # a PyPI-only ROS: the driver says once that it has no TF
        assert err.count(NO_TF_MESSAGE) == 1, err
    got = np.array(arrivals, dtype=np.int64).reshape(-1, 2)
    assert len(got) == want, (len(got), err)
    ticking = np.array(clock, dtype=np.int64)
    ticking = ticking[ticking != 0]  # 0: no /clock received yet
    # the clock the node sees is the recording's: within its span, never going back, covering it
    assert len(ticking) and ticking.min() >= first and ticking.max() <= last, (ticking.min() - first,
                                                                               last - ticking.max())
    assert np.all(np.diff(ticking) >= 0)
    assert ticking.max() - ticking.min() >= 0.9 * (last - first), (ticking.max() - ticking.min(), last - first)
    # /clock goes out before the samples of its time: no message arrives ahead of the node's clock
    ahead = got[:, 0] - got[:, 1]
    assert ahead.max() <= 0, (f"{np.sum(ahead > 0)} of {len(ahead)} messages ahead of the clock, "
                              f"by up to {ahead.max()} ns")


def test_replay_clock_is_between_the_samples_handed_out_and_those_to_come(tmp_path):
    """Without DDS: at every step of a replay, the clock is not behind any sample handed out and not ahead
    of any sample still to come (random step lengths, rates, loop and restamp)."""
    from imu_array_ros.io.replay import Replay
    from imu_array_ros.io.rosbag.recording import write_imu_recording
    from imu_array_ros.model.description import load_description
    from imu_array_ros.nodes.driver_node import replay_clock_ns
    from imu_array_ros.simulation.simulator import simulate_twist

    seed = int(time.time())
    rng = np.random.default_rng(seed)
    desc = load_description(ARRAY8)
    start = int(rng.integers(1_600_000_000, 2_000_000_000)) * 10**9
    samples, _ = simulate_twist(desc, 0.3, float(rng.choice([62.5, 200.0, 500.0])), rng, start_ns=start)
    bag = tmp_path / "rec.mcap"
    write_imu_recording(bag, samples, desc)
    first, last = int(samples.stamps[0]), int(samples.stamps[-1])
    for rate in (0.5, 1.0, float(rng.uniform(1.5, 20.0))):
        for loop in (False, True):
            for restamp in (None, int(rng.integers(10**18, 2 * 10**18))):
                replay = Replay(bag, desc, rate=rate, loop=loop)
                elapsed, handed, clocks = 0, [], []
                span = (last - first) / rate * (2.5 if loop else 1.2)
                while True:  # the last step at or past the span
                    out = replay.due(elapsed, restamp)
                    clock = replay_clock_ns(first, last, elapsed, rate, loop=loop, restamp_ns=restamp)
                    handed.append(out.stamps)
                    clocks.append(clock)
                    if elapsed >= span:
                        break
                    elapsed += int(rng.exponential(6e6))
                clocks = np.array(clocks)
                assert np.all(np.diff(clocks) >= 0), (seed, rate, loop, restamp)
                for k, st in enumerate(handed):
                    if len(st):  # handed out at step k: at or before the clock of step k, after that of step k-1
                        assert st.max() <= clocks[k] and (k == 0 or st.min() >= clocks[k - 1]), (seed, rate, loop)
                if not loop:
                    end = last if restamp is None else restamp + int((last - first) / rate)
                    assert clocks.max() == end and sum(map(len, handed)) == len(samples), (seed, rate, restamp)
                else:
                    assert sum(map(len, handed)) > len(samples)
    assert replay_clock_ns(first, last, 10**9, 0.0) == -1  # rate 0: the stamps handed out are the clock
