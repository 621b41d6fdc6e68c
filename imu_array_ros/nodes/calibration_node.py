"""calibration_node: geometry calibration of the array on demand, from the live raw topics.

Subscribes ``<topic_prefix>/<name>/data_raw`` for every IMU of the description
and keeps the latest ``window`` seconds (or ``window_samples``) of array samples
(:class:`imu_array_ros.io.window.SampleWindow`).  The service
``calibrate_geometry`` (``std_srvs/srv/Trigger``; ``/calibrate_geometry`` unless
the node runs in a namespace) calibrates the accelerometer positions on a copy of
that window (:func:`imu_array_ros.workflows.calibrate` ``"geometry"``, installed by its one install path) and
writes ``output_file``, the calibrated description ``fusion_node`` watches
(its ``calibration_file``).  Response: success and the calibration's one-line
summary, or success false and a one-line reason; the file is only ever replaced
by a successful calibration that fits the window at least as well as the one on
file (the previous one kept as ``<output_file>.bak``).  Publishes ``/diagnostics``
at 1 Hz.  Parameters: :data:`imu_array_ros.nodes.parameters.CALIBRATION_PARAMS`.

Threads: the subscriptions and timers run on the main node in the process's
``EventsExecutor`` (:func:`imu_array_ros.nodes.runtime.run`); the service lives
on a second node, ``<node name>_service`` in the same namespace, spun by a
``MultiThreadedExecutor`` in a thread of its own, so the calibration (seconds)
runs off the executor thread and the window keeps filling meanwhile.  One
calibration at a time: a call while one runs is refused at once.
(rclpy's EventsExecutor cannot run coroutine service callbacks, and an
awaiting callback on a single-threaded executor starves the subscriptions.)
"""

from __future__ import annotations

if __name__ == "__main__":  # python -m imu_array_ros.nodes.calibration_node: run as the console script, which says
    # in one line when rclpy or a message package is missing (this module imports them below)
    from imu_array_ros.nodes import entry

    raise SystemExit(entry.calibration_node())

import threading
import time
import traceback
from pathlib import Path

from rclpy.node import Node
from sensor_msgs.msg import Imu

from imu_array_ros.errors import ConfigError, ImuArrayError
from imu_array_ros.io.live_queue import CompletionQueue
from imu_array_ros.io.rosbag.recording import imu_topic
from imu_array_ros.io.window import SampleWindow
from imu_array_ros.model.description import load_description
from imu_array_ros.nodes.parameters import CALIBRATION_PARAMS, NODE_OPTIONS, declare, sync_timeout_s
from imu_array_ros.nodes.runtime import OK, WARN, DiagnosticsPublisher, RawSubscriptions, run, timer
from imu_array_ros.workflows import calibrate, load_array

__all__ = ["CalibrationNode", "main", "SERVICE"]

#: the service, a relative name: /calibrate_geometry in the root namespace
SERVICE = "calibrate_geometry"


class _Cancelled(Exception):
    """The node is shutting down: the calibration stops at its next iteration, or before it writes."""


class CalibrationNode(Node):
    def __init__(self) -> None:
        super().__init__("imu_array_calibration", **NODE_OPTIONS)
        p = self.p = declare(self, CALIBRATION_PARAMS)
        self.desc, _ = load_array(Path(p.array_config), None)
        if p.reference_imu and p.reference_imu not in self.desc.names:
            raise ConfigError(f"parameter 'reference_imu': unknown IMU {p.reference_imu!r} "
                              f"(the IMUs of {p.array_config} are {', '.join(self.desc.names[:4])}...)")
        self.out = Path(p.output_file)
        self._check_output()
        self.window = SampleWindow(self.desc, p.frame_prefix, sync_timeout_s(p.sync_timeout, all_reliable=True),
                                   p.window, p.window_samples)
        self.raw = CompletionQueue(len(self.desc.names))  # a plain queue: the window is buffered by a timer
        hint = ("this node subscribes reliable (reliable:=true) and the publisher is best effort (e.g. the serial "
                "driver without reliable:=true): set reliable:=true on the publisher too, or false here")
        self.raw_subs = RawSubscriptions(self, Imu, [imu_topic(n, p.topic_prefix) for n in self.desc.names],
                                         self.raw, p.reliable, hint, sync_timeout=p.sync_timeout,
                                         set_timeout=self._set_timeout)
        timer(self, 0.25, self.raw_subs.adapt)
        self.diagnostics = DiagnosticsPublisher(self, self.get_name(), p.array_config)
        timer(self, p.period, self._step)
        timer(self, 1.0, self._diagnose)
        # the calibration's state, shared with the service thread
        self._busy = threading.Lock()  # held while a calibration runs
        self._state = threading.Lock()  # guards the fields below
        self._started: float | None = None
        self._received_at_start = 0  # samples the window had received when the running calibration started
        self._last = ("none yet", True, 0.0)  # (message, success, seconds)
        self._ok = self._failed = self._refused = 0
        self._closing = threading.Event()
        try:
            from_file = self._starting_point()[1]
        except ConfigError as err:
            raise ConfigError(f"parameter 'output_file': {err}") from None
        if self.out.exists() and not from_file:
            self.get_logger().warning(f"{self.out} is not a readable description: the first calibration replaces "
                                      f"it (its bytes kept in {self.out.name}.bak)")
        where = f"{self.out} (starting from it)" if from_file else str(self.out)
        self._start_service()  # last: nothing after it may fail (run() only closes a node it got)
        self.get_logger().info(f"buffering {len(self.desc.names)} IMUs; service "
                               f"{self._service_node.resolve_service_name(SERVICE)} writes {where}")

    # ------------------------------------------------------------------ set-up

    def _check_output(self) -> None:
        out = self.out
        if out.is_symlink() or (out.exists() and not out.is_file()):
            raise ConfigError(f"parameter 'output_file': {out} is not a regular file")
        if not out.parent.is_dir():
            raise ConfigError(f"parameter 'output_file': {out.parent} is not a directory")

    def _start_service(self) -> None:
        """The service on a node of its own, spun by a MultiThreadedExecutor in its own thread."""
        from rclpy.callback_groups import ReentrantCallbackGroup
        from rclpy.executors import MultiThreadedExecutor
        from std_srvs.srv import Trigger

        ns = self.get_namespace()
        # process-wide remappings still apply (e.g. of the service name); the node's name and
        # namespace are set here so that a global __node remap does not give both nodes one name
        self._service_node = Node(f"{self.get_name()}_service", namespace=ns, context=self.context,
                                  cli_args=["--ros-args", "-r", f"__node:={self.get_name()}_service",
                                            "-r", f"__ns:={ns}"],
                                  start_parameter_services=False)
        self._service = self._service_node.create_service(Trigger, SERVICE, self._calibrate,
                                                          callback_group=ReentrantCallbackGroup())
        self._executor = MultiThreadedExecutor(num_threads=2, context=self.context)
        self._executor.add_node(self._service_node)
        self._spinning = True
        self._thread = threading.Thread(target=self._spin_service, name="calibration_service", daemon=True)
        self._thread.start()

    def _spin_service(self) -> None:
        while self._spinning and self.context.ok():
            try:
                self._executor.spin_once(timeout_sec=0.1)
            except Exception as err:  # noqa: BLE001 - the service must outlive one bad call
                if self._spinning and self.context.ok():
                    self.get_logger().error(f"service executor: {type(err).__name__}: {err}")

    # ------------------------------------------------------------------ buffering (main thread)

    def _now(self) -> int:
        return self.get_clock().now().nanoseconds

    def _set_timeout(self, timeout_ns: int) -> None:
        self.window.assembler.timeout_ns = timeout_ns

    def _step(self) -> None:
        now = self._now()
        payloads, index = self.raw.drain()
        if payloads:
            self.window.add(payloads, index, now)
        self.window.step(now)

    def _diagnose(self) -> None:
        w = self.window.counts()
        with self._state:
            started, (last, last_ok, last_s) = self._started, self._last
            since = w.received - self._received_at_start if started is not None else 0
            ok, failed, refused = self._ok, self._failed, self._refused
        busy = started is not None
        values = {"window_fill": w.fill, "window_s": w.span_s, "samples_buffered": w.buffered,
                  "samples_received": w.received, "busy": busy,
                  "calibrating_for_s": time.monotonic() - started if busy else 0.0,
                  "samples_received_while_calibrating": since,
                  "calibrations_ok": ok, "calibrations_failed": failed, "calls_refused_busy": refused,
                  "last_result": last, "last_duration_s": last_s, **w.counts}
        if busy:
            level, msg = OK, f"calibrating for {values['calibrating_for_s']:.1f} s"
        elif w.buffered == 0:
            level, msg = WARN, "no array samples buffered"
        elif not last_ok:
            level, msg = WARN, f"last calibration failed: {last}"
        else:
            level, msg = OK, f"window {100 * w.fill:.0f} % full ({w.buffered} samples, {w.span_s:.1f} s)"
        self.diagnostics.publish(level, msg, values)

    # ------------------------------------------------------------------ the service (service thread)

    def _starting_point(self):
        """(description to start from, True when it is output_file's).  output_file when it is a
        description of the array; the array's when it is absent or unreadable (it is then replaced,
        its bytes kept in the backup); ConfigError when it describes other IMUs."""
        if not self.out.exists():
            return self.desc, False
        try:
            return load_array(Path(self.p.array_config), self.out)[0], True
        except ConfigError:
            try:
                load_description(self.out)
            except ConfigError:
                return self.desc, False  # unreadable: not a calibration to start from
            raise

    def _progress(self, iteration: int = 0, loglik: float = 0.0) -> None:
        if self._closing.is_set():
            raise _Cancelled

    def _calibrate(self, request, response):
        if not self._busy.acquire(blocking=False):
            with self._state:
                self._refused += 1
                age = time.monotonic() - self._started if self._started is not None else 0.0
            response.success = False
            response.message = (f"a calibration is already running (for {age:.1f} s); "
                                "call again when it has finished")
            self.get_logger().warning(f"calibration call refused: {response.message}", throttle_duration_sec=5.0)
            return response
        t0 = time.monotonic()
        received = self.window.counts().received
        with self._state:
            self._started, self._received_at_start = t0, received
        try:
            response.success, response.message = self._run_calibration()
        finally:
            seconds = time.monotonic() - t0
            response.message = " ".join(str(response.message).split())  # one line
            with self._state:
                self._started = None
                self._last = (response.message, bool(response.success), seconds)
                if response.success:
                    self._ok += 1
                else:
                    self._failed += 1
            self._busy.release()
        # (rclpy loggers refuse a second severity from one call site: one call per severity)
        if response.success:
            self.get_logger().info(f"calibration done in {seconds:.2f} s: {response.message}")
        else:
            self.get_logger().warning(f"calibration failed after {seconds:.2f} s: {response.message}")
        return response

    def _run_calibration(self) -> tuple[bool, str]:
        p = self.p
        try:
            try:
                desc, from_file = self._starting_point()
            except ConfigError as err:
                return False, f"output_file {err}; not replaced"
            cal = calibrate("geometry", self.window.snapshot(), desc, reference=p.reference_imu or None,
                            method=p.method, max_iterations=p.max_iterations or None,
                            min_excitation=p.min_excitation, progress=self._progress)
            self._progress()  # shutting down: abandon it before anything is written
            installed = cal.install(desc, self.out)
        except _Cancelled:
            return False, "the node is shutting down; calibration abandoned, nothing written"
        except ImuArrayError as err:
            return False, str(err)
        except Exception as err:  # noqa: BLE001 - a bug must not take the service down; the log has the trace
            self.get_logger().error(traceback.format_exc())
            return False, f"internal error: {type(err).__name__}: {err}"
        start = "from the calibration on file" if from_file else "from the array's nominal positions"
        kept = f", previous kept as {installed.backup}" if installed.backup else ""
        return True, f"{cal.summary()}; started {start}; wrote {installed.out}{kept}"

    # ------------------------------------------------------------------ shutdown

    def close(self) -> None:
        """Stop the service thread (a running calibration stops at its next iteration), destroy its node."""
        with self._state:
            ok, failed, refused = self._ok, self._failed, self._refused
        self.get_logger().info(f"exiting: {self.window.counts().received} samples received, calibrations: {ok} ok, "
                               f"{failed} failed, {refused} refused while busy")
        self._closing.set()
        if self._busy.acquire(timeout=30.0):  # the callback runs in the executor's pool: let it end
            self._busy.release()
        # the response goes out after the callback returns; Jazzy's Executor.shutdown() does not wait
        # for running handlers (its check is inverted), so wait for them here before destroying the node
        tracker = getattr(self._executor, "_work_tracker", None)
        if tracker is not None:
            tracker.wait(5.0)
        self._spinning = False
        self._thread.join(timeout=5.0)
        try:
            self._executor.shutdown(timeout_sec=1.0)
        except Exception:  # noqa: BLE001 - shutting down: the context may already be gone
            pass
        self._service_node.destroy_node()


def main(args=None) -> int:
    return run(CalibrationNode, args)
