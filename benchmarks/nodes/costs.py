"""Per-call CPU costs of the nodes' work in this process, without DDS (the driver's encode, rclpy's
deserialization, the fusion node's decode, step and diagnostics)."""

from __future__ import annotations

import time
from pathlib import Path

from benchmarks.nodes.procs import ARRAY, N_IMUS



def in_process_costs(bag: Path) -> list[tuple[str, float, float]]:
    """Per-call CPU costs of the node's work, in this process without DDS: (what, us per call, us per message).

    Best of a few repeats of ``time.process_time`` loops."""
    import numpy as np
    from rclpy.serialization import deserialize_message
    from sensor_msgs.msg import Imu

    from imu_array_ros.fusion.live import LiveFusion
    from imu_array_ros.io.messages import decode_raw_imu, raw_imu_payloads
    from imu_array_ros.io.rosbag.recording import read_imu_recording
    from imu_array_ros.model.description import load_description

    desc = load_description(ARRAY)
    samples, _ = read_imu_recording(bag, desc)

    def timed(fn, reps: int) -> float:
        best_t = float("inf")
        for _ in range(3):
            t0 = time.process_time()
            for _ in range(reps):
                fn()
            best_t = min(best_t, (time.process_time() - t0) / reps)
        return best_t

    out = []
    for n in (1, 10, 100):
        sub = samples.select(slice(0, n))
        t = timed(lambda: raw_imu_payloads(sub, desc), max(20, 400 // n))
        out.append((f"driver: `raw_imu_payloads` (encode) of {n} array sample{'s' if n > 1 else ''} "
                    f"({32 * n} messages)", 1e6 * t, 1e6 * t / (32 * n)))
    per_imu = raw_imu_payloads(samples.select(slice(0, 100)), desc)
    msgs = [(k, per_imu[k][1][i].tobytes()) for i in range(100) for k in range(N_IMUS)]
    one = msgs[0][1]
    t = timed(lambda: deserialize_message(one, Imu), 5000)
    out.append(("bare subscriber: rclpy `deserialize_message(Imu)` of one message", 1e6 * t, 1e6 * t))
    for n in (1, 10, 100):
        payloads = [m for _, m in msgs[:32 * n]]
        index = np.array([k for k, _ in msgs[:32 * n]])
        t = timed(lambda: decode_raw_imu(payloads, index, desc.names), max(20, 400 // n))
        out.append((f"fusion: `decode_raw_imu` of {32 * n} messages", 1e6 * t, 1e6 * t / (32 * n)))
    for n in (1, 10, 100):
        payloads = [m for _, m in msgs[:32 * n]]
        index = np.array([k for k, _ in msgs[:32 * n]])
        live = LiveFusion(desc)
        clock = [10**12]

        def step():  # one fusion-node step: add n array samples, fuse and encode them (fresh stamps each time)
            live.assembler = type(live.assembler)(N_IMUS, timeout_ns=live.assembler.timeout_ns)
            live.add(payloads, index, clock[0])
            live.step(clock[0])
            clock[0] += 10**6

        t = timed(step, max(20, 200 // n))
        out.append((f"fusion: `LiveFusion.add` + `step` of {n} array sample{'s' if n > 1 else ''}",
                    1e6 * t, 1e6 * t / (32 * n)))
    for rate in (200, 1000):  # the diagnostics, once a second, over a full 1 s window
        n = min(rate, len(samples))
        live = LiveFusion(desc)
        per_imu = raw_imu_payloads(samples.select(slice(0, n)), desc)
        every = max(1, rate // 200)  # 5 ms steps
        t0 = int(samples.stamps[0])
        for lo in range(0, n, every):
            hi = min(n, lo + every)
            payloads = [per_imu[k][1][i].tobytes() for i in range(lo, hi) for k in range(N_IMUS)]
            index = [k for _ in range(lo, hi) for k in range(N_IMUS)]
            now = t0 + int((hi - 1) * 1e9 / rate) + 1
            live.add(payloads, index, now)
            live.step(now)
        t = timed(lambda: live.summary(now), 5)
        out.append((f"fusion: `LiveFusion.summary` (the 1 s diagnostics) with a full window at {rate} Hz",
                    1e6 * t, 1e6 * t / (32 * n)))
    return out
