"""driver_node: one ``sensor_msgs/Imu`` per IMU per array sample, from an OpenShoe
serial array (``mode: serial``) or a recording (``mode: replay``).  A replay
republishes every message with its own recorded stamp, also when the IMUs of the
recording stamp their messages with their own clocks (``restamp`` moves each
message's stamp with its array sample's, keeping the IMUs' recorded offsets).

QoS: a replay publishes reliable (keeping the last 1000; ``rate: 0`` keep-all), so
best-effort and reliable subscribers both receive it, and by default waits until
every IMU topic has a subscriber (``wait_for_subscribers`` -1, at most
``wait_timeout``) before it starts; the serial stream publishes sensor-data
(best effort) unless ``reliable``.  The console says when the port is missing or
lost, the reconnect, a device restart, the end of a replay, and the totals on exit.

Topics: ``<topic_prefix>/<name>/data_raw`` for every IMU of ``array_config``
(recording contract, :mod:`imu_array_ros.io.messages`), ``/diagnostics``; the IMU frames on
``/tf_static`` (``publish_frames``, :mod:`imu_array_ros.nodes.frames`); in replay ``/clock``
(``publish_clock``): the time of the replayed stamps, published before the samples of that time, so
that nodes run with ``use_sim_time`` see the recording's time.  The replay itself is paced by the
system clock (a ``use_sim_time`` given to the driver is turned off, with one line: it is the clock).
Parameters: :data:`imu_array_ros.nodes.parameters.DRIVER_PARAMS`.
The serial protocol, reconnection and the device clock live in
:mod:`imu_array_ros.io.openshoe.serial_link`; replay timing in
:mod:`imu_array_ros.io.replay`; this file only moves bytes.
"""

from __future__ import annotations

if __name__ == "__main__":  # python -m imu_array_ros.nodes.driver_node: run as the console script, which says
    # in one line when rclpy or a message package is missing (this module imports them below)
    from imu_array_ros.nodes import entry

    raise SystemExit(entry.driver_node())

import re
import time

import numpy as np
from rclpy.node import Node
from sensor_msgs.msg import Imu

from imu_array_ros.errors import ConfigError
from imu_array_ros.io.rosbag.recording import imu_payloads, imu_topic
from imu_array_ros.model.description import load_description
from imu_array_ros.model.samples import ImuSamples
from imu_array_ros.nodes.frames import StaticFramePublisher
from imu_array_ros.nodes.parameters import DRIVER_PARAMS, NODE_OPTIONS, declare
from imu_array_ros.nodes.runtime import OK, WARN, DiagnosticsPublisher, qos, qos_events, run, timer

__all__ = ["DriverNode", "main", "replay_clock_ns"]


def replay_clock_ns(first_ns: int, last_ns: int, elapsed_ns: int, rate: float, *, loop: bool = False,
                    restamp_ns: int | None = None) -> int:
    """The replay's time ``elapsed_ns`` after its start, for /clock: the recording's first stamp plus
    ``elapsed * rate``, at most its last stamp unless it loops; restamped (``restamp_ns``: the start's
    wall time), the publish time the samples are stamped with.  -1 for ``rate`` 0 (no time, as fast as
    possible: the node uses the stamps handed out).  Every sample :class:`~imu_array_ros.io.replay.Replay`
    hands out by then has a stamp at most this, every later one at least this."""
    if rate <= 0:
        return -1
    local = elapsed_ns * rate if loop else min(elapsed_ns * rate, last_ns - first_ns)
    return restamp_ns + int(local / rate) if restamp_ns is not None else first_ns + int(local)


#: seconds a subscriber must stay incompatible before the driver says so (the nodes' raw subscriptions start
#: reliable and switch to the serial driver's best effort within ~0.35 s on a quiet machine; the calibration
#: node took 2.5-3 s beside the fusion node and a fake device at load ~3, stop 33's README walk-through)
QOS_GRACE_S = 6.0
#: start_delay -1 in replay: a downstream subscriber (of the fused topics) needs the fusion node to discover it
#: too, which took 0.7-1.6 s after the fusion node's start in 5 of 9 runs (helper-31's trial, load 2-5)
START_DELAY_S = 2.0
#: seconds of bytes without a single packet of the description's IMUs before the serial driver says so (at
#: 62.5 Hz a matching device sends ~120 packets by then)
NO_PACKET_S = 2.0


class DriverNode(Node):
    def __init__(self) -> None:
        super().__init__("imu_array_driver", **NODE_OPTIONS)
        p = self.p = declare(self, DRIVER_PARAMS)
        self.desc = load_description(p.array_config)
        replay = p.mode == "replay"
        flat_out = replay and p.rate == 0  # as fast as possible without loss: DDS flow control
        q = qos(p.reliable or replay, keep_all=flat_out)
        hint = ("the subscriber asks for reliable delivery: set reliable:=false on it (a best-effort subscription "
                "receives from every publisher) or reliable:=true here")
        self.pubs = [self.create_publisher(Imu, imu_topic(n, p.topic_prefix), q,
                                           event_callbacks=qos_events(self, "publisher", hint,
                                                                      imu_topic(n, p.topic_prefix),
                                                                      grace=QOS_GRACE_S, own_qos=q))
                     for n in self.desc.names]
        self.wait_for = p.wait_for_subscribers if p.wait_for_subscribers >= 0 else int(replay)
        self.start_delay = p.start_delay if p.start_delay >= 0 else (START_DELAY_S if replay and self.wait_for else 0.0)
        self.diagnostics = DiagnosticsPublisher(self, f"{self.get_name()}: {p.mode}", p.port if p.mode == "serial" else p.bag)
        self.published = 0
        self.finished = False
        self._start = None
        self._wait_started: float | None = None
        self._matched: float | None = None  # when the awaited subscribers had matched
        self._t_start = time.monotonic()
        self._last_diag = (time.monotonic(), 0)
        self._link_seen = ("", "disconnected", 0, 0)  # (last_error, state, reconnects, device_restarts) logged
        self._streaming_from = None  # (monotonic s, packets, bytes_in) when streaming began; None once said
        self._error_logged_at = -1e9
        self._ended = False
        self._clock_pub = None
        if p.mode == "replay":
            from imu_array_ros.io.replay import Replay

            if not p.bag:
                raise ConfigError("parameter 'bag' is required in replay mode")
            self.source = Replay(p.bag, self.desc, rate=p.rate, loop=p.loop, topic_prefix=p.topic_prefix)
            self.link = None
            self.get_logger().info(f"replaying {p.bag}: {len(self.source.samples)} samples at rate {p.rate:g}")
            if p.publish_clock:
                self._clock_source()
        else:
            from imu_array_ros.io.openshoe.serial_link import SerialArrayLink

            self.source = None
            try:
                self.link = SerialArrayLink(p.port, len(self.desc.names), baud=p.baud, imu_mask=p.imu_mask or None,
                                            rate_divider=p.rate_divider, now=self._now)
            except ValueError as err:
                raise ConfigError(f"parameter 'imu_mask': {err} (the IMUs of {p.array_config})") from None
            self.get_logger().info(f"opening {p.port} for {len(self.desc.names)} IMUs")
        self.frames = StaticFramePublisher(self, p.frame_prefix) if p.publish_frames else None
        if self.frames is not None:
            self.frames.publish(self.desc)
        timer(self, p.poll_period, self._tick)
        timer(self, 1.0, self._diagnose)

    def _now(self) -> int:
        return self.get_clock().now().nanoseconds

    def _clock_source(self) -> None:
        """Publish /clock from the replay (``publish_clock``); the driver's own clock stays the system's."""
        from rclpy.parameter import Parameter
        from rclpy.qos import QoSProfile, ReliabilityPolicy
        from rosgraph_msgs.msg import Clock

        if self.get_parameter("use_sim_time").value:
            self.set_parameters([Parameter("use_sim_time", Parameter.Type.BOOL, False)])
            self.get_logger().info("use_sim_time ignored: this replay publishes /clock and runs on the system clock")
        # reliable keep-last 1: every time source (best effort, depth 1 in rclpy and rclcpp) connects
        self._clock_msg = Clock()
        self._clock_pub = self.create_publisher(Clock, "/clock",
                                                QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE))
        self._clock_ns = -1  # last published
        self._clock_wall = 0.0

    def _tick(self) -> None:
        if self._waiting():
            return
        if self.link is not None:
            batch = self.link.poll()
            self._log_link()
            samples = ImuSamples(batch.stamps_ns, batch.accel, batch.gyro, self.desc.names)
        else:
            samples = self._replay_step()
            if samples is None:
                return
        self._publish(samples)

    def _waiting(self) -> bool:
        """Before the first sample: wait for ``wait_for_subscribers`` on every topic, at most ``wait_timeout``."""
        if self._start is not None:
            return False
        p, log, mono = self.p, self.get_logger(), time.monotonic()
        missing = sum(pub.get_subscription_count() < self.wait_for for pub in self.pubs)
        what = "the replay" if self.link is None else "streaming"
        if missing:
            if self._wait_started is None:
                self._wait_started = mono
                limit = f"at most {p.wait_timeout:g} s" if p.wait_timeout > 0 else "without a time limit"
                log.info(f"waiting for {self.wait_for} subscriber(s) on each of the {len(self.pubs)} IMU topics "
                         f"({limit}; wait_for_subscribers, wait_timeout) before starting {what}")
            waited = mono - self._wait_started
            if p.wait_timeout == 0 or waited < p.wait_timeout:
                return True
            log.warning(f"{missing} of {len(self.pubs)} IMU topics still lack {self.wait_for} subscriber(s) after "
                        f"{waited:.1f} s: starting {what} anyway (what they miss is lost)")
        else:
            if self._matched is None:
                self._matched = mono
                delay = f" in {self.start_delay:g} s (start_delay)" if self.start_delay > 0 else ""
                after = f" after {mono - self._wait_started:.2f} s" if self._wait_started is not None else ""
                if after or delay:
                    log.info(f"subscribers matched{after}: starting {what}{delay}")
            if mono - self._matched < self.start_delay:
                return True  # the fusion node's own subscribers discover it meanwhile
        self._start = self._now()
        return False

    def _log_link(self) -> None:
        """Console lines for the link's changes: port missing or lost (a repeat of the same error at most
        every 30 s), streaming (again), device restarts."""
        st, log, port = self.link.stats, self.get_logger(), self.p.port
        last_error, state, _, restarts = self._link_seen
        mono = time.monotonic()
        if st.last_error and st.state == "disconnected" and (
                st.last_error != last_error or state != "disconnected" or mono - self._error_logged_at >= 30.0):
            lost = "lost" if state == "streaming" else "cannot open"
            # pyserial says "[Errno 2] could not open port PORT: [Errno 2] ...: 'PORT'": name the port once
            err = re.sub(r"^\[Errno \d+\] could not open port [^:]*: ", "", st.last_error.removeprefix(f"{port}: "))
            log.error(f"serial port {port}: {lost}: {err}; retrying (backoff up to {self.link.backoff[1]:g} s)")
            self._error_logged_at = mono
        if st.state == "streaming" and state != "streaming":
            again = f" again (reconnect {st.reconnects})" if st.connects > 1 else ""
            log.info(f"streaming {len(self.desc.names)} IMUs from {port}{again}")
            self._streaming_from = (mono, st.packets, st.bytes_in)
        if st.state == "streaming" and self._streaming_from is not None:
            since, packets, bytes_in = self._streaming_from
            if st.packets > packets:
                self._streaming_from = None  # the device speaks the description's packets
            elif mono - since >= NO_PACKET_S and st.bytes_in > bytes_in:
                k = len(self.desc.names)
                log.warning(f"serial port {port}: {st.bytes_in - bytes_in} bytes in {mono - since:.1f} s but no "
                            f"packet of {k} IMUs ({st.bad_checksums} bad checksums): does the device stream the "
                            f"IMUs of array_config {self.p.array_config} ({k}; imu_mask)? Nothing is published")
                self._streaming_from = None
        if st.device_restarts > restarts:
            log.warning(f"device on {port} restarted (its packet counter went back; {st.device_restarts} restarts "
                        f"so far): stamps re-anchored")
        self._link_seen = (st.last_error, st.state, st.reconnects, st.device_restarts)

    def _replay_step(self) -> ImuSamples | None:
        p, src = self.p, self.source
        if src.done:
            if not self._ended:
                self._ended = True
                self.get_logger().info(f"replay finished: {self._totals()} in "
                                       f"{(self._now() - self._start) / 1e9:.2f} s")
            if p.exit_at_end and self._acknowledged():
                self.finished = True
            return None
        elapsed = self._now() - self._start
        samples = src.due(elapsed, self._start if p.restamp else None)
        if self._clock_pub is not None:
            self._publish_clock(elapsed, samples)
        return samples

    def _publish_clock(self, elapsed: int, samples: ImuSamples) -> None:
        """/clock at the replay's time ``elapsed`` ns after its start (rate 0: the last stamp handed out), never
        behind a stamp about to be published nor going back; sent with every batch, else at least every 10 ms."""
        p, st = self.p, self.source.samples.stamps
        now = replay_clock_ns(int(st[0]), int(st[-1]), elapsed, p.rate, loop=p.loop,
                              restamp_ns=self._start if p.restamp else None)
        t = max(now, int(samples.stamps.max()) if len(samples) else -1, self._clock_ns)
        mono = time.monotonic()
        if t < 0 or (not len(samples) and (t == self._clock_ns or mono - self._clock_wall < 0.01)):
            return
        self._clock_msg.clock.sec, self._clock_msg.clock.nanosec = divmod(t, 1_000_000_000)
        self._clock_pub.publish(self._clock_msg)
        self._clock_ns, self._clock_wall = t, mono

    def _acknowledged(self) -> bool:
        from rclpy.duration import Duration

        return all(pub.wait_for_all_acked(Duration(seconds=5.0)) for pub in self.pubs)

    def _publish(self, samples: ImuSamples) -> None:
        if not len(samples):
            return
        # every message with its own stamp (a replay of IMUs with their own clocks keeps them)
        per_imu = imu_payloads(samples, self.desc, self.p.frame_prefix)
        # sample-major order: the subscriber completes array samples one after another (own stamps: in stamp order)
        key = np.concatenate([r if samples.own_stamps is None else st for r, st, _ in per_imu])
        which = np.concatenate([np.full(len(r), k) for k, (r, _, _) in enumerate(per_imu)])
        pos = np.concatenate([np.arange(len(r)) for r, _, _ in per_imu])
        for i in np.lexsort((which, key)):
            self.pubs[which[i]].publish(per_imu[which[i]][2][pos[i]].tobytes())
        self.published += len(samples)

    def _diagnose(self) -> None:
        t, n = time.monotonic(), self.published
        rate = (n - self._last_diag[1]) / max(t - self._last_diag[0], 1e-9)
        self._last_diag = (t, n)
        values = {"samples_published": n, "sample_rate_hz": rate}
        if self.link is not None:
            st = self.link.stats
            values.update(st.__dict__)
            level = OK if st.state == "streaming" else WARN
            message = f"{st.state}; {st.packets} packets, {st.bad_checksums} bad checksums, {st.reconnects} reconnects"
        else:
            values.update(bad_messages=self.source.read_stats.bad_messages,
                          incomplete_samples=self.source.read_stats.incomplete_samples)
            level, message = OK, ("finished" if self.source.done else "replaying")
        self.diagnostics.publish(level, message, values)

    def _totals(self) -> str:
        return f"{self.published} samples ({self.published * len(self.pubs)} messages) published"

    def close(self) -> None:
        totals = self._totals()
        if self.link is not None:
            st = self.link.stats
            totals += (f"; {st.packets} packets, {st.bad_checksums} bad checksums, {st.garbage_bytes} garbage bytes, "
                       f"{st.counter_gaps} counter gaps, {st.reconnects} reconnects, {st.device_restarts} device "
                       f"restarts")
            self.link.close()
        self.get_logger().info(f"exiting after {time.monotonic() - self._t_start:.1f} s: {totals}")


def main(args=None) -> int:
    return run(DriverNode, args)
