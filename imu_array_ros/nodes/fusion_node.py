"""fusion_node: ML fusion of the array's raw Imu topics into angular velocity,
angular acceleration and specific force with their Cramér-Rao covariance.

Subscribes ``<topic_prefix>/<name>/data_raw`` for every IMU of the description;
publishes ``<topic_prefix>/fused/imu`` (Imu) and ``<topic_prefix>/fused/accel``
(AccelWithCovarianceStamped), exactly as ``imu-array fuse`` writes them, and
``/diagnostics``.  Parameters: :data:`imu_array_ros.nodes.parameters.FUSION_PARAMS`.
All the work is :class:`imu_array_ros.fusion.live.LiveFusion`; the
subscriptions take the serialized messages (``raw=True``) and queue them.

Fusion is event-driven: the callback of the message that completes an array sample
(every IMU's message of its stamp arrived; :class:`~imu_array_ros.io.live_queue.CompletionQueue`,
a dictionary look-up per message, no decoding) decodes, assembles, fuses and publishes
everything queued, at once.  When messages back up (a sample completes later than the
next one's stamp: :class:`~imu_array_ros.io.live_queue.BacklogGate`) it waits for those
already queued behind it, and the ``period`` timer fuses them in one call (as it did every
sample before: batching is what lets a node short of CPU catch up); at most 8 wait.  So does
a node whose fusion calls take more than half the stamp spacing (a running mean): it cannot
keep up one call per sample, and fuses on the timer only, as before.  Otherwise
the timer only sweeps: when no sample has completed for ``sync_timeout``, it fuses the samples
whose timeout has passed (an IMU silent or lost).  The diagnostics (NIS ratio, rates, latency quantiles; 1 Hz) take a
cheap copy on this thread, are computed in a worker thread and published by a 20 Hz
timer, which also polls the session-state and bias trackers (not per fused sample).

QoS: the raw subscriptions are reliable keep-all, and a topic switches to best effort
(keeping the last 1000) when a best-effort publisher appears on it
(:class:`~imu_array_ros.nodes.runtime.RawSubscriptions`), so the replay's reliable
stream loses nothing and the serial driver's sensor-data stream connects;
``reliable``: reliable keep-all throughout.  The fused topics are published
reliable (keeping the last 1000), which every subscriber can take.  A peer whose QoS
cannot connect is logged.  The console also says when the NIS ratio leaves its band
(above :data:`NIS_WARN_RATIO`) and comes back, a calibration reloaded or refused,
and the totals on exit.  Latency in /diagnostics is reported only for live stamps
(within :data:`LIVE_STAMP_S` of the clock): a replay's recorded stamps are not.

With sample clocks in the description or ``stamps:=own``, the session states
(clock phases, common rate, stamp clocks) are tracked by a
:class:`~imu_array_ros.workflows.live_session.SessionTracker`: estimated in a worker
thread from the last ``session_window`` seconds, swapped in between two steps,
reported in /diagnostics.  Without them the node does exactly what it did before.

With ``bias_tracking`` (default true) the gyroscope biases are re-measured on every
still interval by a :class:`~imu_array_ros.workflows.live_session.BiasSessionTracker`
(in a worker thread, the numbers ``imu-array fuse`` finds), applied from then on,
published per IMU and axis in /diagnostics, and an update that moves a bias by more
than 3 sigma is logged.
"""

from __future__ import annotations

if __name__ == "__main__":  # python -m imu_array_ros.nodes.fusion_node: run as the console script, which says
    # in one line when rclpy or a message package is missing (this module imports them below)
    from imu_array_ros.nodes import entry

    raise SystemExit(entry.fusion_node())

import os
import threading
import time
from pathlib import Path

from geometry_msgs.msg import AccelWithCovarianceStamped
from rclpy.node import Node
from sensor_msgs.msg import Imu

from imu_array_ros.errors import ConfigError, ImuArrayError
from imu_array_ros.fusion.live import LiveFusion, summarize
from imu_array_ros.io.live_queue import BacklogGate, CompletionQueue, stamp_ns
from imu_array_ros.io.rosbag.recording import imu_topic
from imu_array_ros.nodes.frames import StaticFramePublisher
from imu_array_ros.nodes.parameters import FUSION_PARAMS, NODE_OPTIONS, declare, sync_timeout_s
from imu_array_ros.nodes.runtime import (OK, WARN, DiagnosticsPublisher, RawSubscriptions, output_qos, qos_events,
                                         run, timer)
from imu_array_ros.workflows import load_array
from imu_array_ros.workflows.live_session import MIN_MOVING_S, BiasSessionTracker, SessionTracker, has_sample_clocks

__all__ = ["FusionNode", "main", "NIS_WARN_RATIO", "LIVE_STAMP_S", "latency_values"]

#: NIS ratio above which the diagnostics say the model no longer fits (WARN).
NIS_WARN_RATIO = 3.0
#: seconds between two console lines about the NIS band
NIS_LOG_INTERVAL_S = 10.0
#: seconds between polls of the session-state and bias trackers (off the fusion path)
TRACK_PERIOD_S = 0.05
#: stamps whose median latency (publish - stamp) lies outside [-LIVE_STAMP_S, LIVE_STAMP_S] are not live
LIVE_STAMP_S = 60.0


def latency_values(p50: float, p99: float) -> dict:
    """/diagnostics latency values: the quantiles (s) when the stamps are live, else a note (a replay of
    recorded stamps measured against the wall clock gives days or years, not a latency)."""
    if p50 == p50 and abs(p50) > LIVE_STAMP_S:
        return {"latency": f"not measured: stamps are {p50:.3g} s from this clock (recorded, not live; "
                           "restamp:=true on a replay gives live stamps)"}
    return {"latency_p50_s": p50, "latency_p99_s": p99}


def _file_id(path: str):
    try:
        st = os.stat(path)
    except OSError:
        return None
    return st.st_mtime_ns, st.st_size, st.st_ino


class FusionNode(Node):
    def __init__(self) -> None:
        super().__init__("imu_array_fusion", **NODE_OPTIONS)
        p = self.p = declare(self, FUSION_PARAMS)
        cal = p.calibration_file or None
        self._cal_id = _file_id(cal) if cal else None
        desc, source = load_array(Path(p.array_config), Path(cal) if self._cal_id else None)
        own = p.stamps == "own"
        if p.reference_imu and p.reference_imu not in desc.names:
            raise ConfigError(f"parameter 'reference_imu': no IMU {p.reference_imu!r} in {source}")
        reference = list(desc.names).index(p.reference_imu) if p.reference_imu else 0
        self.core = LiveFusion(desc, frame_prefix=p.frame_prefix,
                               sync_timeout_s=sync_timeout_s(p.sync_timeout, all_reliable=True), max_batch=p.max_batch,
                               own_stamps=own, reference=reference, timed_batch_s=p.timed_batch)
        self.tracker: SessionTracker | None = None
        self._logged_error: str | None = None
        self._base = self.core.fusion.model  # the description's model (no session states)
        self.biases = BiasSessionTracker(self._base) if p.bias_tracking else None
        self._sinks = [] if self.biases is None else [self.biases.add]
        self.core.sink = self._sink
        grid = f", own stamps paired onto the stamps of {desc.names[reference]!r}" if own else ""
        self.get_logger().info(f"fusing {len(desc.names)} IMUs with {source}{grid}")
        self.frames = StaticFramePublisher(self, p.frame_prefix) if p.publish_frames else None
        if self.frames is not None:
            self.frames.publish(desc)
        self._track_start(self.core.fusion.model)
        self.raw = CompletionQueue(len(desc.names), self._on_complete, own_stamps=own, reference=reference)
        self.gate = BacklogGate()
        self.cost_ns = 0.0  # running mean of a fusion call's duration (the gate's headroom check)
        self._last_event = self._now()
        hint = ("this node subscribes reliable (reliable:=true) and the publisher is best effort (e.g. the serial "
                "driver without reliable:=true): set reliable:=true on the publisher too, or false here")
        self.raw_subs = RawSubscriptions(self, Imu, [imu_topic(n, p.topic_prefix) for n in desc.names],
                                         self.raw, p.reliable, hint, sync_timeout=p.sync_timeout,
                                         set_timeout=self._set_timeout)
        timer(self, 0.25, self.raw_subs.adapt)
        out = f"{p.topic_prefix.rstrip('/')}/fused"
        hint = "check the subscriber's QoS"
        self.pub_imu = self.create_publisher(Imu, out + "/imu", output_qos(),
                                             event_callbacks=qos_events(self, "publisher", hint, out + "/imu"))
        self.pub_accel = self.create_publisher(AccelWithCovarianceStamped, out + "/accel", output_qos(),
                                               event_callbacks=qos_events(self, "publisher", hint, out + "/accel"))
        self._nis_high = False
        self._nis_logged_at = -1e18
        self._t_start = self._now()
        self.diagnostics = DiagnosticsPublisher(self, self.get_name(), p.array_config)
        self._reported: set[str] = set()
        self._foreign: set[str] = set()
        self._diag_worker: threading.Thread | None = None
        self._diag_result = None
        timer(self, p.period, self._sweep)
        timer(self, TRACK_PERIOD_S, self._poll_trackers)
        timer(self, 1.0, self._diagnose)
        if cal:
            timer(self, p.watch_period, self._watch)

    def _now(self) -> int:
        """Arrival time on the system clock, also under ``use_sim_time`` (sync timeouts, latency and rates are
        real-time matters; a simulated clock stops with the replay and would hold the last samples back)."""
        return time.time_ns()

    def _set_timeout(self, timeout_ns: int) -> None:
        self.core.timeout_ns = self.core.intake.assembler.timeout_ns = timeout_ns

    def _on_complete(self, key: bytes) -> None:
        """A sample is complete (called from the subscription callback of its last message): fuse now,
        unless the gate lets it wait for a batch (messages backing up)."""
        now = self._now()
        self._last_event = now
        if self.gate.complete(time.monotonic_ns(), stamp_ns(key), self.cost_ns):
            self._step(now)

    def _sweep(self) -> None:
        """The timer: fuse the samples the gate held back (behind: one batch), and what timed out when no
        sample has completed for a sync timeout (an IMU silent or lost, the end of a stream)."""
        now = self._now()
        core = self.core
        quiet = now - self._last_event
        if self.gate.waiting:  # behind: the samples completed since the last sweep, in one batch
            self.gate.fused()
        elif quiet < core.timeout_ns:
            return
        if len(self.raw) or core.assembler.pending or core.held:
            self._step(now)

    def _step(self, now: int | None = None) -> None:
        t0 = time.perf_counter_ns()
        now = self._now() if now is None else now
        payloads, index = self.raw.drain()
        if payloads:
            self.core.add(payloads, index, now)
        batches = self.core.step(now)
        self._publish(batches)
        if batches:
            self.cost_ns += 0.1 * (time.perf_counter_ns() - t0 - self.cost_ns)

    def _poll_trackers(self) -> None:
        if self._diag_result is not None:
            self._diagnose_publish()
        if self.tracker is not None:
            self._track(self._now())
        if self.biases is not None:
            self._track_biases()

    def _publish(self, batches) -> None:
        for batch in batches:
            for imu, acc in zip(batch.imu_payloads, batch.accel_payloads):
                self.pub_imu.publish(imu.tobytes())
                self.pub_accel.publish(acc.tobytes())
            self.core.record_latency(self._now(), batch.fused.stamps)

    def _log_rejections(self, counts: dict) -> None:
        """Once per kind of rejected message (the counts go to /diagnostics)."""
        for kind in ("undecodable", "wrong_frame_id", "non_finite", "duplicate", "backwards", "late"):
            if counts[kind] and kind not in self._reported:
                self.get_logger().warning(f"skipping {kind.replace('_', ' ')} messages (counted in /diagnostics)")
                self._reported.add(kind)

    def _watch(self) -> None:
        path = self.p.calibration_file
        now_id = _file_id(path)
        if now_id is None or now_id == self._cal_id:
            return
        self._cal_id = now_id
        try:
            desc, _ = load_array(Path(self.p.array_config), Path(path))
            self.core.set_description(desc)
            self._base = self.core.fusion.model
            if self.biases is not None:
                self.biases.rebase(self._base)
            if self.tracker is not None:
                self.tracker.rebase(self._base)
            else:
                self._track_start(self._base)
            self.core.set_model(self._model())
        except ImuArrayError as err:
            self.get_logger().error(f"calibration not reloaded, keeping the one in use: {err}")
            return
        self.get_logger().info(f"reloaded calibration {path}")
        if self.frames is not None:
            self.frames.publish(desc)

    def _diagnose(self) -> None:
        """1 Hz: copy the window (cheap) and compute the summary in a worker thread; published when done."""
        if self._diag_worker is not None and self._diag_worker.is_alive():
            return  # the last one is still being computed (a loaded machine): skip this second
        snap = self.core.snapshot(self._now())

        def work() -> None:
            try:
                self._diag_result = summarize(snap)
            except Exception as err:  # noqa: BLE001 - reported on the node's thread
                self._diag_result = err

        self._diag_worker = threading.Thread(target=work, daemon=True, name="fusion-diagnostics")
        self._diag_worker.start()

    def _diagnose_publish(self) -> None:
        s, self._diag_result = self._diag_result, None
        if s is None:
            return
        if isinstance(s, Exception):
            raise s
        self._log_rejections(s.counts)
        known = {imu_topic(n, self.p.topic_prefix) for n in self.core.names}
        prefix = self.p.topic_prefix.rstrip("/") + "/"
        for topic, _ in self.get_topic_names_and_types():
            if topic.startswith(prefix) and topic.endswith("/data_raw") and topic not in known | self._foreign:
                self._foreign.add(topic)
                self.get_logger().warning(f"ignoring {topic}: its IMU is not in {self.p.array_config}")
        values = {"input_rate_msgs": s.input_rate, "fused_rate_hz": s.fused_rate, "nis_ratio": s.nis_ratio,
                  "nis_samples": s.nis_samples, **latency_values(s.latency_p50, s.latency_p99),
                  "unknown_imu_topics": len(self._foreign), **s.counts}
        self._log_nis(s.nis_ratio)
        if self.tracker is not None:
            values.update(self.tracker.values(self._now()))
        if self.biases is not None:
            values.update(self.biases.values())
        if s.nis_ratio > NIS_WARN_RATIO:
            level, msg = WARN, f"model does not fit: NIS ratio {s.nis_ratio:.3g} over the last second"
        elif s.fused_rate == 0:
            level, msg = WARN, "no fused samples in the last second"
        else:
            level, msg = OK, f"fusing at {s.fused_rate:.1f} Hz, NIS ratio {s.nis_ratio:.3g}"
        if self.tracker is not None and self.tracker.states is None:
            msg += "; session states not estimated yet (fallback)"
        self.diagnostics.publish(level, msg, values)

    def _log_nis(self, ratio: float) -> None:
        """A console line when the NIS ratio leaves its band (above NIS_WARN_RATIO) and when it is back,
        at most one every NIS_LOG_INTERVAL_S (a change in between is said at the next chance)."""
        if ratio != ratio:  # nothing fused in the last second: no verdict
            return
        high = ratio > NIS_WARN_RATIO
        now = self._now()
        if high == self._nis_high or now - self._nis_logged_at < NIS_LOG_INTERVAL_S * 1e9:
            return
        self._nis_high, self._nis_logged_at = high, now
        if high:
            self.get_logger().warning(f"model does not fit the data: NIS ratio {ratio:.3g} over the last second "
                                      f"(band: up to {NIS_WARN_RATIO:g}; 1 = noise level): check the description "
                                      "or calibration, saturation, or a loose IMU")
        else:
            self.get_logger().info(f"NIS ratio back in its band: {ratio:.3g} over the last second")

    def _totals(self) -> str:
        c = self.core.summary(self._now()).counts
        kinds = ("late", "duplicate", "backwards", "undecodable", "wrong_frame_id", "non_finite")
        rejected = ", ".join(f"{c[k]} {k.replace('_', ' ')}" for k in kinds if c.get(k))
        skipped = c.get("skipped_unidentifiable", 0)
        return (f"fused {c.get('fused', 0)} samples ({c.get('complete_samples', 0)} complete, "
                f"{c.get('incomplete_samples', 0)} incomplete"
                + (f"; {skipped} of them skipped: not identifiable" if skipped else "")
                + f") from {c.get('messages', 0)} messages in "
                f"{(self._now() - self._t_start) / 1e9:.1f} s"
                + (f"; rejected messages: {rejected}" if rejected else ""))

    # ------------------------------------------------------------------ session states

    def _track_start(self, model) -> None:
        """Track the session states when the model has sample clocks or the stamps are own (else nothing)."""
        p = self.p
        tracker = SessionTracker(model, own_stamps=self.core.own_stamps, window_s=p.session_window,
                                 interval_s=p.session_interval)
        if not tracker.enabled:
            return
        self.tracker = tracker
        self._sinks.append(tracker.add)
        self.core.set_model(self._model())
        parts = [(w, until) for w, until, on in (
            ("sample-clock phases", "sample clocks at their mean age", has_sample_clocks(model)),
            ("stamp clocks", "own stamps taken as sample times", tracker.own_stamps)) if on]
        self.get_logger().info(f"tracking session states ({' and '.join(w for w, _ in parts)}) from the last "
                               f"{p.session_window:g} s; until they are estimated (>= {MIN_MOVING_S:g} s of motion): "
                               + ", ".join(u for _, u in parts))

    def _track(self, now: int) -> None:
        tracker = self.tracker
        result = tracker.poll(now, self.core.fusion.t0_ns)
        if tracker.error and tracker.error != self._logged_error:
            self._logged_error = tracker.error
            self.get_logger().error(f"session states not estimated, keeping those in use: {tracker.error}")
        if result is None:
            return
        if result.estimated:
            self.core.set_model(self._model())
            if tracker.estimates == 1:
                self.get_logger().info(tracker.line())
            else:
                self.get_logger().info(f"re-estimated: {tracker.line()}", throttle_duration_sec=60.0)
        else:
            self.get_logger().info(f"session states kept: {tracker.last_note}", throttle_duration_sec=60.0)

    # ------------------------------------------------------------------ gyroscope biases

    def _sink(self, samples, fused) -> None:
        for sink in self._sinks:
            sink(samples, fused)

    def _model(self):
        """The model to fuse with: the description's, with the timing states and the gyroscope biases in use."""
        model = self.tracker.model if self.tracker is not None else self._base
        return model if self.biases is None else self.biases.apply(model)

    def _track_biases(self) -> None:
        biases = self.biases
        updates = biases.poll(self.core.fusion.t0_ns)
        if biases.error and biases.error != self._logged_error:
            self._logged_error = biases.error
            self.get_logger().error(f"gyroscope biases not updated, keeping those in use: {biases.error}")
        if not updates:
            return
        self.core.set_model(self._model())
        for u in updates:
            if u.jumps(biases.names) or len(biases.updates) == len(updates):
                self.get_logger().info(biases.line(u))
            else:
                self.get_logger().info(biases.line(u), throttle_duration_sec=60.0)

    def close(self) -> None:
        """Fuse and publish what is still buffered, if the context is still up."""
        try:
            self._step()
            self._poll_trackers()
            self._publish(self.core.step(self._now(), flush=True))
        except Exception:  # noqa: BLE001 - shutting down: the context may already be gone
            pass
        try:
            self.get_logger().info(f"exiting: {self._totals()}")
        except Exception:  # noqa: BLE001 - a summary must not turn a clean exit into a failure
            pass


def main(args=None) -> int:
    return run(FusionNode, args)
