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

from imu_array_ros.errors import ImuArrayError

__all__ = ["run", "qos", "timer", "DiagnosticsPublisher", "RawQueue", "OK", "WARN", "ERROR"]

OK, WARN, ERROR = b"\x00", b"\x01", b"\x02"


def qos(reliable: bool, keep_all: bool = False):
    """Sensor-data profile (best effort, keep last 5), or reliable keeping the last 1000
    (``keep_all``: every message until acknowledged / taken -- DDS then never drops one)."""
    from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy, qos_profile_sensor_data

    if not reliable:
        return qos_profile_sensor_data
    if keep_all:
        return QoSProfile(history=HistoryPolicy.KEEP_ALL, reliability=ReliabilityPolicy.RELIABLE)
    return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1000, reliability=ReliabilityPolicy.RELIABLE)


def timer(node, period: float, callback):
    """``node.create_timer(period, callback)``, except that the callback is skipped once the node's
    context is shut down, and an exception it raises while the context goes down is dropped: on
    Ctrl-C rclpy invalidates the context before the executor stops, and a timer firing in between
    would otherwise log ``[FATAL] Exception in 'timers' callback`` (its publishers are gone)."""
    context = node.context

    def guarded() -> None:
        if not context.ok():
            return
        try:
            callback()
        except Exception:
            if context.ok():
                raise

    return node.create_timer(period, guarded)


class RawQueue:
    """Serialized messages the raw (``raw=True``) subscriptions queue, drained in one batch by a timer
    of the same executor thread; ``receiver(k)`` is the callback of IMU k's topic."""

    def __init__(self) -> None:
        self.payloads: list = []
        self.index: list = []

    def receiver(self, k: int):
        payloads, index = self.payloads, self.index

        def receive(payload: bytes) -> None:
            payloads.append(payload)
            index.append(k)

        return receive

    def drain(self) -> tuple[list, list]:
        """(payloads, imu indexes) queued since the last call, in arrival order."""
        payloads, index = self.payloads[:], self.index[:]
        del self.payloads[:], self.index[:]
        return payloads, index


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

    prog = os.path.basename(sys.argv[0]) or node_class.__name__
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
