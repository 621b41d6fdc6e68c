"""Issue 24 item 2, "nodes that speak": the console lines of the nodes, their content and their rate limits.

Fast: the fusion node's NIS line through its logging function; the driver node in this process (no process
start) against a fake device on a pseudo-terminal for the port missing, lost, back, and a device restart, its
console captured from file descriptor 2 (rcutils writes there) with the log stamps of the lines; the raw
subscriptions' best-effort switch and the incompatible-QoS line with a publisher in this process.
"""

from __future__ import annotations

import os
import re
import time
from types import SimpleNamespace

import numpy as np
import pytest

from conftest import REPO

CORNERS = REPO / "config" / "mimu4444bt_corners.yaml"
#: issue 24's target: a missing or lost port named on the console within this many seconds
PORT_LINE_S = 2.0
LINE = re.compile(r"^\[(DEBUG|INFO|WARN|ERROR|FATAL)\] \[(\d+\.\d+)\] \[([^\]]+)\]: (.*)$")
needs_pty = pytest.mark.skipif(not hasattr(os, "openpty"), reason="os.openpty is not available")


class Console:
    """The lines rcutils wrote to fd 2 since the test began: (level, wall time s, logger, text)."""

    def __init__(self, capfd) -> None:
        self.capfd, self.lines = capfd, []

    def read(self) -> list:
        err = self.capfd.readouterr().err
        for line in err.splitlines():
            m = LINE.match(line)
            if m:
                self.lines.append((m[1], float(m[2]), m[3], m[4]))
        return self.lines

    def matching(self, text: str) -> list:
        return [ln for ln in self.read() if text in ln[3]]


# --------------------------------------------------------------------------- fusion: the NIS band


class _Logger:
    def __init__(self) -> None:
        self.lines: list[tuple[str, str]] = []

    def warning(self, text, **kw):
        self.lines.append(("WARN", text))

    def info(self, text, **kw):
        self.lines.append(("INFO", text))


def test_nis_leaving_its_band_is_said_with_its_value_at_most_every_10_s():
    from imu_array_ros.nodes.fusion_node import NIS_LOG_INTERVAL_S, NIS_WARN_RATIO, FusionNode

    rng = np.random.default_rng()
    clock = [int(rng.integers(10**18, 2 * 10**18))]
    log = _Logger()
    node = SimpleNamespace(_nis_high=False, _nis_logged_at=-1e18, _now=lambda: clock[0], get_logger=lambda: log)

    def second(ratio, seconds=1.0):
        FusionNode._log_nis(node, ratio)
        clock[0] += int(seconds * 1e9)

    for _ in range(3):
        second(float(rng.uniform(0.5, 1.5)))  # in the band: silent
    second(NIS_WARN_RATIO)  # at the edge: still in
    second(float("nan"))  # nothing fused: no verdict
    assert log.lines == []
    high = float(rng.uniform(3.5, 50.0))
    second(high)
    assert len(log.lines) == 1 and log.lines[0][0] == "WARN", log.lines
    text = log.lines[0][1]
    assert f"NIS ratio {high:.3g}" in text and f"up to {NIS_WARN_RATIO:g}" in text and "model does not fit" in text
    # flapping within the interval: nothing more; the change is said at the next chance after it
    for k in range(int(NIS_LOG_INTERVAL_S) - 2):
        second(0.9 if k % 2 else 40.0)
    assert len(log.lines) == 1, log.lines
    second(0.9)
    second(0.8)  # 10 s after the warning: back in the band, said once
    assert [lvl for lvl, _ in log.lines] == ["WARN", "INFO"] and "NIS ratio back in its band: 0.8" in log.lines[1][1]
    for _ in range(30):
        second(0.8)  # staying in: silent
    assert len(log.lines) == 2


# --------------------------------------------------------------------------- driver: port and device


class DriverInProcess:
    """driver_node's node class built in this process (parameters as on the command line), spun on demand."""

    def __init__(self, *params: str) -> None:
        import rclpy
        from rclpy.experimental import EventsExecutor

        from imu_array_ros.nodes.driver_node import DriverNode

        args = ["--ros-args", "-p", f"array_config:={CORNERS}"]
        for p in params:
            args += ["-p", p]
        rclpy.init(args=args)
        try:
            self.node = DriverNode()
        except BaseException:
            rclpy.try_shutdown()
            raise
        self.executor = EventsExecutor()
        self.executor.add_node(self.node)

    def spin(self, seconds: float, until=None) -> bool:
        """Spin for ``seconds`` or until ``until()``; its value."""
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            self.executor.spin_once(timeout_sec=0.005)
            if until is not None and until():
                return True
        return until() if until is not None else True

    def close(self) -> None:
        import rclpy

        try:
            self.node.close()
            self.node.destroy_node()
        finally:
            rclpy.try_shutdown()


@pytest.fixture
def driver(dds):
    made = []

    def make(*params):
        d = DriverInProcess(*params)
        made.append(d)
        return d

    yield make
    for d in made:
        d.close()


@needs_pty
def test_missing_then_lost_port_named_within_2_s_then_reconnect(driver, capfd, tmp_path):
    """The port missing at start, found, lost (unplug), back: each said once, naming the port and the
    problem; missing and lost within 2 s (measured from the log stamps); repeats of the same error silent."""
    from imu_array_ros.io.openshoe.fake_device import FakeArrayDevice, stamps_to_ticks

    console = Console(capfd)
    port = tmp_path / f"port-{np.random.default_rng().integers(1 << 30)}"
    t_start = time.time()
    d = driver(f"port:={port}", "rate_divider:=4")
    assert d.spin(PORT_LINE_S + 1, lambda: console.matching("cannot open")), console.read()
    d.spin(0.3)  # the link retries (backoff 0.2 s): the same error is not said again
    missing = console.matching("cannot open")
    assert len(missing) == 1 and missing[0][0] == "ERROR", missing
    assert f"serial port {port}: cannot open: " in missing[0][3] and "No such file" in missing[0][3], missing
    # pyserial's "could not open port PORT:" prefix is dropped: the port named once, plus the OS error's own
    assert missing[0][3].count(str(port)) <= 2 and "could not open port" not in missing[0][3], missing
    seconds_missing = missing[0][1] - t_start
    assert seconds_missing < PORT_LINE_S, seconds_missing

    n, unplug_at = 500, 1.5  # 4 s at 125 Hz; unplugged 1.5 s after the device is made, for 0.5 s
    ticks = stamps_to_ticks(np.arange(n, dtype=np.int64) * 8_000_000)
    raw = np.random.default_rng(1).integers(-3000, 3000, size=(n, 8, 6)).astype(np.int16)
    t_before = time.time()  # the unplug comes at least unplug_at after this
    with FakeArrayDevice.from_samples(raw, ticks, link=port, unplug_at=unplug_at, unplug_duration=0.5, seed=2):
        assert d.spin(10.0, lambda: console.matching("streaming 8 IMUs")), console.read()
        assert d.spin(10.0, lambda: console.matching(": lost:")), console.read()
        assert d.spin(10.0, lambda: console.matching("again (reconnect 1)")), console.read()
        d.spin(0.1)
    lost = console.matching(": lost:")
    assert len(lost) == 1 and lost[0][0] == "ERROR" and f"serial port {port}: lost: " in lost[0][3], lost
    seconds_lost = lost[0][1] - (t_before + unplug_at)
    assert 0 <= seconds_lost < PORT_LINE_S, seconds_lost
    first = console.matching("streaming 8 IMUs")
    assert f"streaming 8 IMUs from {port}" in first[0][3] and "again" not in first[0][3], first
    back = console.matching("again (reconnect 1)")
    assert len(back) == 1 and f"streaming 8 IMUs from {port} again (reconnect 1)" in back[0][3], back
    # in order, each once; while unplugged the port may also be said missing (another error), once
    said = [ln[3].split(": ")[1] if ln[3].startswith("serial port") else ln[3].split(" from ")[0]
            for ln in console.read() if str(port) in ln[3] and not ln[3].startswith("opening")]
    assert said in (["cannot open", "streaming 8 IMUs", "lost", "streaming 8 IMUs"],
                    ["cannot open", "streaming 8 IMUs", "lost", "cannot open", "streaming 8 IMUs"]), said
    print(f"\nconsole: port missing said {seconds_missing:.3f} s after the node was made, lost "
          f"{seconds_lost:.3f} s after the unplug (at most)")


def _await_start_command(driver_node, master: int) -> None:
    """Spin the driver until the start command (9 bytes or more) has reached the pty's master side."""
    import select

    got = b""
    end = time.monotonic() + 5
    while len(got) < 9 and time.monotonic() < end:
        driver_node.spin(0.02)
        if select.select([master], [], [], 0)[0]:
            got += os.read(master, 4096)
    assert len(got) >= 9, got


@needs_pty
def test_device_restart_said_once_per_restart(driver, capfd):
    """A device whose packet counter steps back (it restarted): one warning per restart naming the port and
    the count so far."""
    import tty

    from imu_array_ros.io.openshoe.framing import encode_packets
    from imu_array_ros.io.openshoe.protocol import START_ACK

    master, slave = os.openpty()
    tty.setraw(slave)
    path = os.ttyname(slave)
    console = Console(capfd)
    rng = np.random.default_rng(3)

    def packets(c0, m, t0):
        return encode_packets((c0 + np.arange(m)) % 65536, (t0 + np.arange(m, dtype=np.int64) * 1_024_000) % (1 << 32),
                              rng.integers(-3000, 3000, size=(m, 8, 6)).astype(np.int16))

    try:
        d = driver(f"port:={path}", "rate_divider:=5")
        _await_start_command(d, master)
        os.write(master, START_ACK + packets(100, 20, 10**6))
        assert d.spin(3.0, lambda: console.matching("streaming 8 IMUs")), console.read()
        for restart in (1, 2):
            os.write(master, packets(0, 10, 500))  # the counter went back: the device restarted
            assert d.spin(3.0, lambda: len(console.matching("restarted")) >= restart), console.read()
            os.write(master, packets(10, 20, 500 + 10 * 1_024_000))  # and streams on
            d.spin(0.2)
        lines = console.matching("restarted")
        assert [ln[0] for ln in lines] == ["WARN", "WARN"], lines
        for k, ln in enumerate(lines, 1):
            assert f"device on {path} restarted" in ln[3] and f"{k} restarts so far" in ln[3], ln
    finally:
        os.close(master)
        os.close(slave)


@needs_pty
def test_a_device_streaming_other_imus_is_said_once(driver, capfd):
    """Bytes arrive but no packet of the description's 8 IMUs parses (a board streaming 4 IMUs, or the launch
    file's default 32-IMU array_config on an 8-IMU board): one warning naming the port, the IMU count and
    array_config, about NO_PACKET_S after streaming began -- before, 'streaming 8 IMUs' and then silence."""
    import tty

    from imu_array_ros.io.openshoe.framing import encode_packets
    from imu_array_ros.io.openshoe.protocol import START_ACK
    from imu_array_ros.nodes.driver_node import NO_PACKET_S

    master, slave = os.openpty()
    tty.setraw(slave)
    path = os.ttyname(slave)
    console = Console(capfd)
    rng = np.random.default_rng(4)
    try:
        d = driver(f"port:={path}", "rate_divider:=5")
        _await_start_command(d, master)
        os.write(master, START_ACK)
        counter = 0

        def four_imus() -> None:  # 5 packets of 4 IMUs: 62.5 Hz for 80 ms
            nonlocal counter
            os.write(master, encode_packets(counter + np.arange(5), 10**6 + (counter + np.arange(5)) * 1_024_000,
                                            rng.integers(-3000, 3000, size=(5, 4, 6)).astype(np.int16)))
            counter += 5

        said = lambda: console.matching("but no packet")  # noqa: E731
        end = time.monotonic() + NO_PACKET_S + 2.0
        while not said() and time.monotonic() < end:
            four_imus()
            d.spin(0.08)
        for _ in range(6):  # more of the same: not said again
            four_imus()
            d.spin(0.08)
        lines = said()
        assert len(lines) == 1 and lines[0][0] == "WARN", console.read()
        text = lines[0][3]
        assert f"serial port {path}: " in text and "no packet of 8 IMUs" in text and str(CORNERS) in text, text
        streaming = console.matching("streaming 8 IMUs")
        # the node times NO_PACKET_S on the monotonic clock read before each line is formatted; the console stamps
        # are the wall clock when the line is logged, so the two lines' stamps may be a few ms closer than
        # NO_PACKET_S (CI: 1.9985 s): 50 ms slack below, still failing a warning given early
        assert streaming and NO_PACKET_S - 0.05 <= lines[0][1] - streaming[0][1] < NO_PACKET_S + 1.0, (streaming, lines)
    finally:
        os.close(master)
        os.close(slave)


# --------------------------------------------------------------------------- QoS: switch and incompatible peers


@pytest.fixture
def ros_node(dds):
    import rclpy
    from rclpy.experimental import EventsExecutor

    context = rclpy.Context()
    rclpy.init(context=context)
    node = rclpy.create_node(f"console_{os.getpid()}", context=context)
    ex = EventsExecutor(context=context)
    ex.add_node(node)

    def spin(seconds, until=None):
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            ex.spin_once(timeout_sec=0.01)
            if until is not None and until():
                return True
        return until() if until is not None else True

    node.spin = spin
    yield node
    node.destroy_node()
    ex.shutdown(timeout_sec=1.0)
    rclpy.try_shutdown(context=context)


def test_best_effort_publisher_switches_the_topic_once_with_one_line(ros_node, capfd):
    from sensor_msgs.msg import Imu

    from imu_array_ros.io.live_queue import CompletionQueue
    from imu_array_ros.nodes.runtime import RAW_DEPTH, RawSubscriptions, qos

    console = Console(capfd)
    topics = [f"/console_test_{os.getpid()}/imu_{k}/data_raw" for k in range(4)]
    timeouts = []
    subs = RawSubscriptions(ros_node, Imu, topics, CompletionQueue(len(topics)), reliable=False, hint="-",
                            sync_timeout=-1.0, set_timeout=timeouts.append)
    pubs = [ros_node.create_publisher(Imu, t, qos(False)) for t in topics[1:3]]  # sensor data: best effort

    def adapted():
        subs.adapt()
        return not all(subs.reliable[1:3])

    assert ros_node.spin(10.0, adapted), "the best-effort publishers were never seen"
    for _ in range(5):
        ros_node.spin(0.05)
        subs.adapt()  # nothing new: nothing said
    assert subs.reliable == [True, False, False, True]
    lines = console.matching("best-effort publisher")
    assert len(lines) == 1 and lines[0][0] == "INFO", console.read()
    assert timeouts == [50_000_000] and len(console.matching("sync_timeout now 0.05 s")) == 1, console.read()
    text = lines[0][3]
    assert "on 2 IMU topic(s)" in text and topics[1] in text and f"keeping the last {RAW_DEPTH}" in text, text
    # the switched topic receives from the best-effort publisher; no incompatible-QoS line
    queue = subs.queue
    assert ros_node.spin(5.0, lambda: pubs[0].publish(Imu()) or bool(queue.payloads)), "nothing received"
    assert not console.matching("cannot connect"), console.read()


def test_incompatible_qos_names_topic_policy_and_fix_at_most_every_10_s(ros_node, capfd):
    from sensor_msgs.msg import Imu

    from imu_array_ros.io.live_queue import CompletionQueue
    from imu_array_ros.nodes.runtime import RawSubscriptions, qos

    console = Console(capfd)
    topics = [f"/console_test_{os.getpid()}/imu_{k}/data_raw" for k in range(3)]
    hint = "set reliable:=true on the publisher too, or false here"
    RawSubscriptions(ros_node, Imu, topics, CompletionQueue(len(topics)), reliable=True, hint=hint)
    ros_node.create_publisher(Imu, topics[0], qos(False))  # best effort: cannot reach a reliable subscription
    assert ros_node.spin(10.0, lambda: console.matching("cannot connect to this subscription")), console.read()
    for t in topics[1:]:
        ros_node.create_publisher(Imu, t, qos(False))  # more of them within 10 s: not said again
    ros_node.spin(1.5)
    lines = console.matching("cannot connect to this subscription")
    assert len(lines) == 1 and lines[0][0] == "WARN", lines
    text = lines[0][3]
    assert "RELIABILITY" in text and hint in text and "publisher" in text, text
    assert topics[0] in text, f"the line does not name the topic: {text}"


def test_publisher_grace_says_only_what_stays_incompatible(ros_node, capfd):
    """The serial driver's best-effort publishers wait ``grace`` before saying a subscriber cannot connect: a
    reliable subscription that goes away (the nodes switch to best effort) is not reported, one that stays is."""
    from sensor_msgs.msg import Imu

    from imu_array_ros.nodes.runtime import qos, qos_events

    console = Console(capfd)
    topics = [f"/console_grace_{os.getpid()}/imu_{k}/data_raw" for k in range(2)]
    for t in topics:
        ros_node.create_publisher(Imu, t, qos(False), event_callbacks=qos_events(
            ros_node, "publisher", "-", t, grace=0.5, own_qos=qos(False)))
    passing = ros_node.create_subscription(Imu, topics[0], lambda m: None, qos(True))
    ros_node.spin(0.3)
    ros_node.destroy_subscription(passing)  # switched away within the grace period: nothing to say
    ros_node.spin(1.5)
    assert not console.matching("cannot connect"), console.read()
    ros_node.create_subscription(Imu, topics[1], lambda m: None, qos(True))  # stays reliable
    assert ros_node.spin(10.0, lambda: console.matching("cannot connect to this publisher")), console.read()
    lines = console.matching("cannot connect to this publisher")
    assert len(lines) == 1 and topics[1] in lines[0][3], lines


def test_publisher_grace_is_quiet_when_the_subscription_switches_to_best_effort(ros_node, capfd):
    """What the fusion and calibration nodes do when the serial driver appears: their reliable keep-all raw
    subscription is replaced by a best-effort one (made first, then the reliable one destroyed,
    :meth:`RawSubscriptions.adapt`). The driver's grace check must then find nothing incompatible: a subscription
    seen in the ROS graph carries concrete deadline and liveliness values, which rmw's compatibility check used to
    call incompatible with the driver's requested profile (default values), so the driver warned after every such
    switch (the README's driver + fusion + calibration node run on the fake device)."""
    from sensor_msgs.msg import Imu

    from imu_array_ros.nodes.runtime import qos, qos_events, raw_subscription_qos

    console = Console(capfd)
    topic = f"/console_switch_{os.getpid()}/imu_0/data_raw"
    ros_node.create_publisher(Imu, topic, qos(False), event_callbacks=qos_events(
        ros_node, "publisher", "-", topic, grace=0.5, own_qos=qos(False)))
    reliable = ros_node.create_subscription(Imu, topic, lambda m: None, raw_subscription_qos(True))
    ros_node.spin(0.3)
    ros_node.create_subscription(Imu, topic, lambda m: None, raw_subscription_qos(False))
    ros_node.destroy_subscription(reliable)
    ros_node.spin(1.5)  # three times the grace
    assert not console.matching("cannot connect"), console.read()
