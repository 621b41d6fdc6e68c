"""A listener for tests, benchmarks and quick checks: records the fused topics.

``python -m imu_array_ros.nodes.probe --out FILE.npz [--count N] [--timeout S] [--reliable]``
subscribes ``<prefix>/fused/imu`` and ``<prefix>/fused/accel`` (serialized, as
published) and ``/diagnostics``; prints ``ready`` once the fused publishers are
matched, and on exit (N fused samples seen, timeout, or Ctrl-C) writes the
decoded samples (:func:`imu_array_ros.io.messages.decode_fused`), their arrival
times (ns, this machine's ROS clock) and the last diagnostics per node to FILE.npz.
"""

from __future__ import annotations

import argparse
import json
import sys
import time

import numpy as np

__all__ = ["main"]


def main(argv=None) -> int:
    from imu_array_ros.nodes.entry import ros_missing

    try:
        import rclpy
        from diagnostic_msgs.msg import DiagnosticArray
        from geometry_msgs.msg import AccelWithCovarianceStamped
        from rclpy.executors import ExternalShutdownException
        from rclpy.experimental import EventsExecutor
        from sensor_msgs.msg import Imu
    except ImportError as err:  # a core install without ROS 2: one line, not a traceback
        why = ros_missing(err)
        if why is None:
            raise
        print(f"imu_array_ros.nodes.probe: error: {why}", file=sys.stderr)
        return 2

    from imu_array_ros.util.files import atomic_write_bytes
    from imu_array_ros.io.messages import concat_payloads, decode_fused
    from imu_array_ros.io.rosbag.cdr_columns import decode_accel_with_covariance_stamped, decode_imu
    from imu_array_ros.nodes.runtime import qos

    ap = argparse.ArgumentParser(prog="imu_array_ros.nodes.probe")
    ap.add_argument("--out", required=True)
    ap.add_argument("--count", type=int, default=0, help="exit after this many fused samples (0: run until timeout)")
    ap.add_argument("--timeout", type=float, default=60.0)
    ap.add_argument("--reliable", action="store_true")
    ap.add_argument("--topic-prefix", default="/imu_array")
    args = ap.parse_args(argv)

    rclpy.init()
    node = rclpy.create_node("imu_array_probe")
    imu, acc, arrival, diags = [], [], [], {}
    q = qos(args.reliable, keep_all=args.reliable)
    base = args.topic_prefix.rstrip("/") + "/fused"
    clock = node.get_clock()
    node.create_subscription(Imu, base + "/imu", lambda m: (imu.append(m), arrival.append(clock.now().nanoseconds)),
                             q, raw=True)
    node.create_subscription(AccelWithCovarianceStamped, base + "/accel", acc.append, q, raw=True)

    def on_diag(msg):
        for s in msg.status:
            diags[s.name] = {"level": int.from_bytes(s.level, "little") if isinstance(s.level, bytes) else int(s.level),
                             "message": s.message, **{kv.key: kv.value for kv in s.values}}

    node.create_subscription(DiagnosticArray, "/diagnostics", on_diag, 50)
    executor = EventsExecutor()
    executor.add_node(node)
    end = time.monotonic() + args.timeout
    ready = False
    try:
        while time.monotonic() < end and not (args.count and min(len(imu), len(acc)) >= args.count):
            executor.spin_once(timeout_sec=0.05)
            if not ready and node.count_publishers(base + "/imu") and node.count_publishers(base + "/accel"):
                ready = True
                print("ready", flush=True)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    # pair the two topics by stamp (one may have lost a message under overload)
    imu_stamps = decode_imu(*concat_payloads(imu), fields=()).stamps
    acc_stamps = decode_accel_with_covariance_stamped(*concat_payloads(acc), fields=()).stamps
    _, keep, pair = np.intersect1d(imu_stamps, acc_stamps, assume_unique=True, return_indices=True)
    fused = decode_fused([imu[i] for i in keep], [acc[j] for j in pair])
    arrival = [arrival[i] for i in keep]
    n = len(keep)
    import io

    buf = io.BytesIO()
    np.savez(buf, stamps=fused.stamps, omega=fused.omega, omega_dot=fused.omega_dot,
             specific_force=fused.specific_force, covariance=fused.covariance,
             arrival_ns=np.asarray(arrival[:n], dtype=np.int64), diagnostics=json.dumps(diags))
    atomic_write_bytes(args.out, buf.getvalue())
    print(f"received {n} fused samples ({len(imu)} Imu and {len(acc)} Accel messages); wrote {args.out}",
          file=sys.stderr, flush=True)
    node.destroy_node()
    rclpy.try_shutdown()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
