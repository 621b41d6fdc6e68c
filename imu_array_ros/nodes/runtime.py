"""What every node shares: the Jazzy-correct ``main``, QoS, /diagnostics.

``run(NodeClass)``: ``rclpy.init``, build the node, spin it, and on Ctrl-C
(SIGINT), SIGTERM or an external shutdown close it (its ``close()``, while the
context is still valid), destroy it and ``try_shutdown``.  A user mistake (a bad
parameter or file: :class:`~imu_array_ros.errors.ImuArrayError`) ends the node
with one line ``<node>: error: ...`` and exit status 2, no traceback.

The executor is rclpy's ``EventsExecutor`` driven by ``spin_once`` (about 1.5x
the message rate of the ``SingleThreadedExecutor`` on this machine; its
``spin()`` does not return on shutdown in Jazzy, so it is not used).
"""

from __future__ import annotations

import os
import signal
import sys
import threading
from typing import Callable

from imu_array_ros.errors import ImuArrayError
from imu_array_ros.io.live_queue import CompletionQueue
from imu_array_ros.nodes.parameters import sync_timeout_s

__all__ = ["run", "qos", "raw_subscription_qos", "output_qos", "qos_events", "timer", "DiagnosticsPublisher",
           "RawSubscriptions", "OK", "WARN", "ERROR", "RAW_DEPTH"]

OK, WARN, ERROR = b"\x00", b"\x01", b"\x02"

#: messages a best-effort raw subscription (and every reliable keep-last publisher) keeps per topic
RAW_DEPTH = 1000


def qos(reliable: bool, keep_all: bool = False):
    """Sensor-data profile (best effort, keep last 5), or reliable keeping the last 1000
    (``keep_all``: every message until acknowledged / taken -- DDS then never drops one)."""
    from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy, qos_profile_sensor_data

    if not reliable:
        return qos_profile_sensor_data
    if keep_all:
        return QoSProfile(history=HistoryPolicy.KEEP_ALL, reliability=ReliabilityPolicy.RELIABLE)
    return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=RAW_DEPTH, reliability=ReliabilityPolicy.RELIABLE)


def raw_subscription_qos(reliable: bool):
    """A raw subscription's QoS: reliable keep-all, or (``reliable`` False) best effort keeping the
    last :data:`RAW_DEPTH` per topic, which receives from best-effort and reliable publishers alike."""
    from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy

    if reliable:
        return qos(True, keep_all=True)
    return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=RAW_DEPTH, reliability=ReliabilityPolicy.BEST_EFFORT)


class RawSubscriptions:
    """The raw IMU subscriptions of the fusion and calibration nodes (serialized messages into ``queue``).

    ``reliable`` True: reliable keep-all throughout (a best-effort publisher cannot connect: logged).
    False (adaptive): each topic starts reliable keep-all, so a reliable publisher (the replay) loses
    nothing even on a loaded machine; :meth:`adapt` (a timer of the node) switches a topic to best
    effort, keeping the last :data:`RAW_DEPTH`, as soon as a best-effort publisher (the live serial
    driver) appears on it, once, with one console line for all topics switched together.

    ``sync_timeout`` (the node's parameter) -1 = by QoS: when the first topic turns best effort,
    ``set_timeout(ns)`` gets the best-effort timeout (:func:`~imu_array_ros.nodes.parameters.sync_timeout_s`),
    said in one line."""

    def __init__(self, node, msg_type, topics: list[str], queue: CompletionQueue, reliable: bool, hint: str, *,
                 sync_timeout: float = 0.0, set_timeout: Callable[[int], None] | None = None) -> None:
        self.node, self.msg_type, self.topics, self.queue = node, msg_type, list(topics), queue
        self.adaptive = not reliable
        self.reliable = [True] * len(self.topics)
        self.hint = hint
        self.sync_timeout, self.set_timeout = sync_timeout, set_timeout
        self.subs = [self._subscribe(k, True) for k in range(len(self.topics))]

    def _subscribe(self, k: int, reliable: bool):
        if self.adaptive and reliable:
            # no event handlers: a best-effort publisher is what makes adapt() switch this subscription (said
            # then), and an event still queued for it when adapt() destroys it would raise InvalidHandle in
            # the executor (rclpy's EventsExecutor takes the event of a destroyed handler)
            from rclpy.event_handler import SubscriptionEventCallbacks

            events = SubscriptionEventCallbacks(use_default_callbacks=False)
        else:
            events = qos_events(self.node, "subscription", self.hint, self.topics[k])
        return self.node.create_subscription(self.msg_type, self.topics[k], self.queue.receiver(k),
                                             raw_subscription_qos(reliable), raw=True, event_callbacks=events)

    def adapt(self) -> None:
        """Switch to best effort every reliable topic that has a best-effort publisher (adaptive only)."""
        if not self.adaptive or not any(self.reliable):
            return
        from rclpy.qos import ReliabilityPolicy

        first = all(self.reliable)  # no topic switched before
        switched = []
        for k, topic in enumerate(self.topics):
            if self.reliable[k] and any(info.qos_profile.reliability == ReliabilityPolicy.BEST_EFFORT
                                        for info in self.node.get_publishers_info_by_topic(topic)):
                new = self._subscribe(k, False)  # before the old one goes: no gap
                self.node.destroy_subscription(self.subs[k])
                self.subs[k], self.reliable[k] = new, False
                switched.append(topic)
        if switched:
            self.node.get_logger().info(
                f"best-effort publisher(s) on {len(switched)} IMU topic(s) (e.g. {switched[0]}): subscribing "
                f"them best effort, keeping the last {RAW_DEPTH} messages")
        if switched and first and self.sync_timeout < 0 and self.set_timeout is not None:  # sync_timeout -1 follows
            seconds = sync_timeout_s(self.sync_timeout, all_reliable=False)
            self.set_timeout(int(round(seconds * 1e9)))
            self.node.get_logger().info(f"sync_timeout now {seconds:g} s (a best-effort topic: a missing message "
                                        "is lost, not late)")


def output_qos():
    """Publishers that every subscriber can take from: reliable, keeping the last :data:`RAW_DEPTH`
    (a best-effort subscriber receives from a reliable publisher; the reverse does not connect)."""
    return qos(True)


def qos_events(node, kind: str, hint: str, topic: str | None = None, *, grace: float = 0.0, own_qos=None):
    """Event callbacks of a publisher (``kind`` 'publisher') or subscription ('subscription') on ``topic`` that
    log, at most every 10 s (one line for all of a node's publishers or subscriptions), a peer whose QoS cannot
    connect: the topic, the policy, and ``hint`` (the fix).

    ``grace`` (s, publishers with ``own_qos`` only): say it only if a subscription on ``topic`` is still
    incompatible with ``own_qos`` that long after the event -- the fusion and calibration nodes start their raw
    subscriptions reliable and switch to best effort within a fraction of a second when they see a best-effort
    publisher (the serial driver's default), which is not a problem to report."""
    from rclpy.event_handler import PublisherEventCallbacks, SubscriptionEventCallbacks
    from rclpy.qos import QoSCompatibility, QoSPolicyKind, ReliabilityPolicy, qos_check_compatible

    logger = node.get_logger()
    pending: list = []

    def still_incompatible() -> bool:
        # both sides as the ROS graph sees them: a discovered profile has concrete deadline and liveliness values,
        # which rmw's check calls incompatible with a requested profile's defaults (every subscription would be)
        mine = [info.qos_profile for info in node.get_publishers_info_by_topic(topic)
                if info.node_name == node.get_name() and info.node_namespace == node.get_namespace()]
        if not mine:  # not in the graph (yet): the policy the nodes switch is the only one compared
            return any(info.qos_profile.reliability == ReliabilityPolicy.RELIABLE
                       for info in node.get_subscriptions_info_by_topic(topic)) \
                and own_qos.reliability == ReliabilityPolicy.BEST_EFFORT
        return any(qos_check_compatible(mine[0], info.qos_profile)[0] == QoSCompatibility.ERROR
                   for info in node.get_subscriptions_info_by_topic(topic))

    def later(event) -> None:
        if pending:
            return  # a check is due already

        def check() -> None:
            pending.pop().cancel()
            if still_incompatible():
                say(event)

        pending.append(timer(node, grace, check))

    def incompatible(event) -> None:
        if grace > 0 and own_qos is not None and topic and kind == "publisher":
            later(event)
        else:
            say(event)

    def say(event) -> None:
        try:
            policy = QoSPolicyKind(event.last_policy_kind).name
        except ValueError:
            policy = str(event.last_policy_kind)
        peer = "subscriber" if kind == "publisher" else "publisher"
        where = f" on {topic}" if topic else ""
        logger.warning(f"a {peer} with incompatible QoS ({policy}) cannot connect to this {kind}{where} "
                       f"({event.total_count} so far); no messages pass between them: {hint}",
                       throttle_duration_sec=10.0)

    if kind == "publisher":
        return PublisherEventCallbacks(incompatible_qos=incompatible)
    return SubscriptionEventCallbacks(incompatible_qos=incompatible)


def timer(node, period: float, callback):
    """``node.create_timer(period, callback)``, except that the callback is skipped once the node's
    context is shut down, and an exception it raises while the context goes down is dropped: on
    Ctrl-C rclpy invalidates the context before the executor stops, and a timer firing in between
    would otherwise log ``[FATAL] Exception in 'timers' callback`` (its publishers are gone). The timer runs
    on the steady clock, also under ``use_sim_time``."""
    from rclpy.clock import Clock, ClockType

    context = node.context

    def guarded() -> None:
        if not context.ok():
            return
        try:
            callback()
        except Exception:
            if context.ok():
                raise

    # on the steady clock: with use_sim_time the node's clock follows /clock, which stops with the replay
    # and would stop the sweeps that fuse what is left (a node's work is paced by real time, not sim time)
    return node.create_timer(period, guarded, clock=Clock(clock_type=ClockType.STEADY_TIME))


class DiagnosticsPublisher:
    """Publishes one ``diagnostic_msgs/DiagnosticStatus`` on /diagnostics each call."""

    def __init__(self, node, name: str, hardware_id: str) -> None:
        from diagnostic_msgs.msg import DiagnosticArray

        self._node, self._name, self._hw = node, name, hardware_id
        self._pub = node.create_publisher(DiagnosticArray, "/diagnostics", 10)

    def publish(self, level: bytes, message: str, values: dict) -> None:
        from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue

        status = DiagnosticStatus(level=level, name=self._name, message=message, hardware_id=self._hw,
                                  values=[KeyValue(key=str(k), value=_fmt(v)) for k, v in values.items()])
        msg = DiagnosticArray(status=[status])
        msg.header.stamp = self._node.get_clock().now().to_msg()
        self._pub.publish(msg)


def _fmt(value) -> str:
    return f"{value:.6g}" if isinstance(value, float) else str(value)


def run(node_class, args=None) -> int:
    """Run ``node_class()`` until shutdown; returns the exit status (see module docstring)."""
    import rclpy
    from rclpy.executors import ExternalShutdownException
    from rclpy.experimental import EventsExecutor
    from rclpy.signals import SignalHandlerOptions

    prog = os.path.basename(sys.argv[0]).removesuffix(".py") or node_class.__name__  # also under python -m
    # SIGINT / SIGTERM only set a flag the spin loop reads: rclpy's own handlers invalidate the
    # context at once and Python's raises KeyboardInterrupt inside whichever callback runs, so a
    # Ctrl-C would log "[FATAL] Exception in ... callback" and could cut a file write or a service
    # response short.  The node is closed and destroyed first, the context shut down last.  A second
    # Ctrl-C interrupts as usual (KeyboardInterrupt).
    stop = threading.Event()
    previous = {}

    def on_signal(signum, frame) -> None:
        stop.set()
        signal.signal(signal.SIGINT, signal.default_int_handler)

    rclpy.init(args=args, signal_handler_options=SignalHandlerOptions.NO)
    if threading.current_thread() is threading.main_thread():
        for sig in (signal.SIGINT, signal.SIGTERM):
            previous[sig] = signal.signal(sig, on_signal)
    node, status = None, 0
    try:
        node = node_class()
        executor = EventsExecutor()
        executor.add_node(node)
        while not stop.is_set() and rclpy.ok() and not getattr(node, "finished", False):
            executor.spin_once(timeout_sec=0.1)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except ImuArrayError as err:
        print(f"{prog}: error: {err}", file=sys.stderr)
        status = 2
    finally:
        try:
            if node is not None:
                close = getattr(node, "close", None)
                if close is not None:
                    close()
                node.destroy_node()
        finally:
            rclpy.try_shutdown()
            for sig, handler in previous.items():
                signal.signal(sig, handler)
    return status
