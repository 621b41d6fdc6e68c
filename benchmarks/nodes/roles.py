"""The benchmark's helper processes, each started in an interpreter of its own by the measurements:

* ``bare-sub``: a plain rclpy subscriber of the 32 raw topics whose callbacks only count;
* ``pub``: a synthetic source publishing payloads encoded beforehand, as fast as possible;
* ``diag``: records every /diagnostics status with its arrival time.

    python -m benchmarks.nodes.roles {bare-sub,pub,diag} --out FILE [options]
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

from benchmarks.nodes.procs import ARRAY, N_IMUS



def _topics(n_topics: int) -> list[str]:
    """The 32 raw topics, or one topic (``n_topics`` 1: all Imu messages; 0: one array message per sample)."""
    from imu_array_ros.io.rosbag.recording import imu_topic
    from imu_array_ros.model.description import load_description

    names = load_description(ARRAY).names
    if n_topics == N_IMUS:
        return [imu_topic(n) for n in names]
    return ["/bench/one_topic/data_raw" if n_topics == 1 else "/bench/array_samples"]


def _msg_type(n_topics: int):
    if n_topics == 0:  # one message per array sample: the 32 IMUs' 6 values, float64
        from std_msgs.msg import Float64MultiArray

        return Float64MultiArray
    from sensor_msgs.msg import Imu

    return Imu


def bare_sub(args) -> int:
    """Plain rclpy subscriber: deserializing callbacks (``--raw``: serialized) that count."""
    import rclpy
    from rclpy.executors import ExternalShutdownException
    from rclpy.experimental import EventsExecutor

    from imu_array_ros.nodes.runtime import qos

    topics = _topics(args.topics)
    msg_type = _msg_type(args.topics)
    rclpy.init()
    node = rclpy.create_node("bare_subscriber")
    counts = [0] * len(topics)
    total = [0]
    last = [None]
    q = qos(True, keep_all=True)  # the fusion node's input QoS with reliable:=true

    stamps_cb = [None, None]  # drain mode: wall time of the first and the last callback

    def make(k):
        def cb(msg):
            counts[k] += 1
            total[0] += 1
            last[0] = msg

        def cb_timed(msg):
            counts[k] += 1
            total[0] += 1
            stamps_cb[1] = time.time_ns()
            if stamps_cb[0] is None:
                stamps_cb[0] = stamps_cb[1]

        return cb_timed if args.hold_until else cb

    for k, topic in enumerate(topics):
        node.create_subscription(msg_type, topic, make(k), q, raw=args.raw)
    executor = EventsExecutor()
    executor.add_node(node)
    print("ready", flush=True)
    if args.hold_until:  # let the source fill the queues first (DDS receives in its own threads), then drain
        limit = time.monotonic() + args.timeout
        while not Path(args.hold_until).exists() and time.monotonic() < limit:
            time.sleep(0.05)
    t_first = t_last = None
    seen = 0
    end = time.monotonic() + args.timeout
    idle_ns = int(args.idle * 1e9) if args.idle else None
    try:
        while time.monotonic() < end and total[0] < args.count:
            executor.spin_once(timeout_sec=0.05)
            if total[0] != seen:
                seen = total[0]
                t_last = time.time_ns()
                if t_first is None:
                    t_first = t_last
            elif idle_ns and t_last is not None and time.time_ns() - t_last > idle_ns:
                break  # the source has stopped
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    if args.hold_until:
        t_first, t_last = stamps_cb
    stamp = None
    if last[0] is not None and not args.raw and hasattr(last[0], "header"):
        s = last[0].header.stamp
        stamp = s.sec * 1_000_000_000 + s.nanosec
    Path(args.out).write_text(json.dumps({"total": total[0], "per_topic": counts, "t_first_ns": t_first,
                                          "t_last_ns": t_last, "last_stamp_ns": stamp}))
    node.destroy_node()
    rclpy.try_shutdown()
    return 0


def pub(args) -> int:
    """Synthetic source: the Imu payloads of ``--bag`` (as the driver encodes them), encoded beforehand and
    published as fast as possible, reliable, keep last 1000 (``--keep-all``: keep all), on the 32 topics, all
    on one topic, or (``--topics 0``) one Float64MultiArray of the 32 IMUs' values per array sample (repeated
    up to ``--count`` messages); writes ``--out`` once every subscriber has acknowledged everything."""
    import numpy as np
    import rclpy
    from rclpy.duration import Duration
    from rclpy.experimental import EventsExecutor
    from rclpy.serialization import serialize_message

    from imu_array_ros.io.messages import raw_imu_payloads
    from imu_array_ros.io.rosbag.recording import read_imu_recording
    from imu_array_ros.model.description import load_description
    from imu_array_ros.nodes.runtime import qos

    desc = load_description(ARRAY)
    samples, _ = read_imu_recording(args.bag, desc)
    msg_type = _msg_type(args.topics)
    if args.topics == 0:
        values = np.concatenate([samples.accel, samples.gyro], axis=2).reshape(len(samples), -1)
        msgs = [(0, serialize_message(msg_type(data=row.tolist()))) for row in values]
        msgs = (msgs * (args.count // len(msgs) + 1))[:args.count] if args.count else msgs
    else:
        if args.count:
            samples = samples.select(slice(0, -(-args.count // N_IMUS)))
        per_imu = raw_imu_payloads(samples, desc)
        msgs = [(k, per_imu[k][1][i].tobytes()) for i in range(len(samples)) for k in range(len(per_imu))]
        msgs = msgs[:args.count or len(msgs)]
    topics = _topics(args.topics)
    rclpy.init()
    node = rclpy.create_node("bench_publisher")
    q = qos(True, keep_all=args.keep_all)  # keep last 1000 (the driver's reliable:=true) or keep all
    pubs = [node.create_publisher(msg_type, t, q) for t in topics]
    executor = EventsExecutor()
    executor.add_node(node)
    while any(p.get_subscription_count() < 1 for p in pubs):
        executor.spin_once(timeout_sec=0.01)
    time.sleep(0.5)  # let the reliable endpoints settle
    fns = [p.publish for p in pubs] if len(pubs) > 1 else [pubs[0].publish] * N_IMUS
    t0 = time.time_ns()
    for k, data in msgs:
        fns[k](data)
    t1 = time.time_ns()
    acked = all(p.wait_for_all_acked(Duration(seconds=30.0)) for p in pubs)
    t2 = time.time_ns()
    Path(args.out).write_text(json.dumps({"published": len(msgs), "t_start_ns": t0, "t_published_ns": t1,
                                          "t_acked_ns": t2, "acked": acked}))
    node.destroy_node()
    rclpy.try_shutdown()
    return 0


def diag(args) -> int:
    """Records every /diagnostics status (with its arrival time) until Ctrl-C."""
    import rclpy
    from diagnostic_msgs.msg import DiagnosticArray
    from rclpy.executors import ExternalShutdownException
    from rclpy.experimental import EventsExecutor

    rclpy.init()
    node = rclpy.create_node("bench_diag_monitor")
    records = []

    def on_diag(msg):
        now = time.time_ns()
        for s in msg.status:
            records.append({"t_ns": now, "name": s.name, "message": s.message,
                            **{kv.key: kv.value for kv in s.values}})

    node.create_subscription(DiagnosticArray, "/diagnostics", on_diag, 100)
    executor = EventsExecutor()
    executor.add_node(node)
    print("ready", flush=True)
    try:
        while rclpy.ok():
            executor.spin_once(timeout_sec=0.1)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    Path(args.out).write_text(json.dumps(records))
    node.destroy_node()
    rclpy.try_shutdown()
    return 0


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description="a helper process of benchmarks.bench_nodes")
    ap.add_argument("role", choices=("bare-sub", "pub", "diag"))
    ap.add_argument("--out", required=True, help="where the role writes its JSON record")
    ap.add_argument("--count", type=int, default=0,
                    help="bare-sub: stop after this many messages; pub: publish this many")
    ap.add_argument("--timeout", type=float, default=60.0, help="bare-sub: give up after this many seconds")
    ap.add_argument("--topics", type=int, default=N_IMUS, help="32 topics, 1 (every Imu on one topic) or 0 (one array "
                    "message per sample)")
    ap.add_argument("--raw", action="store_true", help="bare-sub: serialized callbacks")
    ap.add_argument("--bag", help="pub: the recording whose payloads are published")
    ap.add_argument("--idle", type=float, default=0.0, help="bare-sub: stop after this many seconds without a message")
    ap.add_argument("--hold-until", help="bare-sub: do not spin until this file exists (queues fill meanwhile)")
    ap.add_argument("--keep-all", action="store_true", help="pub: keep-all publishers (default keep last 1000)")
    args = ap.parse_args(argv)
    return {"bare-sub": bare_sub, "pub": pub, "diag": diag}[args.role](args)


if __name__ == "__main__":
    raise SystemExit(main())
