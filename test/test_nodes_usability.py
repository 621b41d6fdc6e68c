"""Issue 24: the nodes' parameter-name check, console lines, replay latency note, fake-device speed."""

from __future__ import annotations

import time

import numpy as np
import pytest

from conftest import ARRAY32, REPO
from dds_harness import BIN
from imu_array_ros.nodes.parameters import FUSION_PARAMS, unknown_parameters


def test_unknown_parameter_names_and_their_nearest_known_name():
    assert unknown_parameters(["sync_timeout", "use_sim_time", "qos_overrides./x.publisher.depth"],
                              FUSION_PARAMS) is None
    assert unknown_parameters(["sync_timout"], FUSION_PARAMS) == \
        "unknown parameter 'sync_timout' (did you mean 'sync_timeout'?)"
    text = unknown_parameters(["zzz", "perod"], FUSION_PARAMS)
    assert text == "unknown parameters 'perod' (did you mean 'period'?), 'zzz'"


@pytest.mark.parametrize("exe, typo, meant", [("fusion_node", "sync_timout", "sync_timeout"),
                                               ("driver_node", "poll_perod", "poll_period"),
                                               ("calibration_node", "windw", "window")])
def test_misspelt_parameter_refused_by_name(dds, exe, typo, meant, tmp_path):
    args = ["-p", f"array_config:={ARRAY32}", "-p", f"{typo}:=2.0", "-p", "use_sim_time:=false"]
    if exe == "calibration_node":
        args += ["-p", f"output_file:={tmp_path}/cal.yaml"]
    code, _, err = dds.start(exe, BIN / exe, "--ros-args", *args).finish(60)
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert code == 2, err
    assert lines == [f"{exe}: error: unknown parameter '{typo}' (did you mean '{meant}'?)"], lines


def test_known_parameters_and_ros_own_ones_still_start(dds):
    """A node given only known names (and use_sim_time) runs; the value given is the value used."""
    proc = dds.start("driver", BIN / "driver_node", "--ros-args", "-p", f"array_config:={ARRAY32}",
                     "-p", "port:=/dev/ttyNOPE_issue24", "-p", "use_sim_time:=false", "-p", "poll_period:=0.01")
    proc.wait_line("cannot open", stream="err")
    code, _, err = proc.stop(20)
    lines = err.splitlines()
    text = "\n".join(lines)
    opened = next(i for i, ln in enumerate(lines) if "opening /dev/ttyNOPE_issue24" in ln)
    error = next(i for i, ln in enumerate(lines) if "cannot open" in ln)
    # the console names the port and the problem, and says it within 2 s of opening it
    t = [float(lines[i].split("[")[2].split("]")[0]) for i in (opened, error)]
    assert "/dev/ttyNOPE_issue24" in lines[error] and "No such file" in lines[error], text
    assert t[1] - t[0] < 2.0, t
    assert "exiting after" in text and "0 samples (0 messages) published" in text, text
    assert code == 0 and "Traceback" not in text


def test_replay_latency_is_not_reported_against_the_wall_clock():
    from imu_array_ros.nodes.fusion_node import latency_values

    assert "latency" in latency_values(1.8e9, 1.8e9) and "latency_p50_s" not in latency_values(1.8e9, 1.8e9)
    assert "not live" in latency_values(-5e3, 1.0)["latency"]
    assert latency_values(0.004, 0.009) == {"latency_p50_s": 0.004, "latency_p99_s": 0.009}
    nan = latency_values(float("nan"), float("nan"))
    assert set(nan) == {"latency_p50_s", "latency_p99_s"}


def test_fake_device_speed_keeps_the_device_clock_real_time():
    from imu_array_ros.cli.fake_device import real_time_ticks
    from imu_array_ros.io.openshoe.framing import TICK_HZ, TickUnwrapper

    ticks = (np.arange(5000, dtype=np.int64) * (TICK_HZ // 1000) + (1 << 32) - 64_000 * 7) % (1 << 32)
    got = TickUnwrapper().unwrap(real_time_ticks(ticks.astype(np.uint32), 4.0))
    np.testing.assert_array_equal(np.diff(got), TICK_HZ // 4000)  # across the 32-bit wrap too
    assert got[0] == ticks[0]


def _stamps_from_fake_device(tmp_path, speed: float, real_time: bool, seconds: float = 2.0):
    from imu_array_ros.cli.fake_device import real_time_ticks
    from imu_array_ros.io.openshoe.fake_device import FakeArrayDevice, samples_to_counts, stamps_to_ticks
    from imu_array_ros.io.openshoe.serial_link import SerialArrayLink
    from imu_array_ros.model.description import load_description
    from imu_array_ros.simulation.simulator import simulate_twist

    desc = load_description(REPO / "config" / "mimu4444bt_corners.yaml")
    samples, _ = simulate_twist(desc, 20.0, 1000.0, np.random.default_rng(1))
    counts, ticks = samples_to_counts(samples.accel, samples.gyro), stamps_to_ticks(samples.stamps)
    kw = dict(link=tmp_path / f"port{speed}{real_time}", speed=speed)
    if real_time:
        ticks, kw["speed"] = real_time_ticks(ticks, speed), 1.0
    stamps, arrivals = [], []
    with FakeArrayDevice.from_samples(counts, ticks, **kw) as device, \
            SerialArrayLink(device.port, len(desc.names), rate_divider=4) as link:
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            batch = link.poll()
            if len(batch):
                stamps.append(batch.stamps_ns)
                arrivals.append(np.full(len(batch), time.time_ns()))
            time.sleep(0.005)
    return np.concatenate(stamps), np.concatenate(arrivals)


def test_fake_device_speed_4_gives_increasing_stamps_near_host_time(tmp_path):
    """--speed 4 as the command builds it: stamps strictly increasing and within 0.1 s of their arrival;
    the device clock at 4x real time (the defect) steps stamps back."""
    stamps, arrivals = _stamps_from_fake_device(tmp_path, 4.0, real_time=True)
    assert len(stamps) > 150
    assert np.all(np.diff(stamps) > 0)
    lag = (arrivals - stamps) / 1e9
    assert np.all(lag > -0.01) and np.all(lag < 0.1), (lag.min(), lag.max())
    bad, _ = _stamps_from_fake_device(tmp_path, 4.0, real_time=False)
    assert np.any(np.diff(bad) <= 0), "the unscaled device clock no longer steps stamps back: drop this contrast"


def test_default_replay_into_the_fusion_node_fuses_every_sample(dds, tmp_path):
    """The README's live example with defaults only (issue 24: 10-22 % before): the fusion node and the
    replay started one right after the other; >= 99 % of the samples fused complete (all 32 IMUs),
    the replay's end and the totals said on the console."""
    from benchmarks.bench_default_replay import run_once

    domain = dds.domain
    r = run_once(domain, tmp_path, 1000)
    logs = {k: (tmp_path / f"{k}_{domain}.log").read_text() for k in ("fusion", "driver")}
    assert r["finished"] and r["complete"] >= 990, (r, logs)
    assert "replay finished: 1000 samples (32000 messages) published" in logs["driver"], logs
    assert "exiting: fused" in logs["fusion"] and not r["switched"] and not r["incompatible"], logs
