"""calibration_node as a process over real DDS (own ROS_DOMAIN_ID, localhost only):
replay driver -> calibration_node (+ fusion_node) -> the /calibrate_geometry service."""

from __future__ import annotations

import json
import re
import sys
import tempfile
import time
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from conftest import ARRAY32, REPO
from dds_harness import BIN, COME_UP_S

CAL_NODE = "imu_array_calibration"


# --------------------------------------------------------------------------- processes and a test-side node


def _stopped(proc) -> tuple[int, str]:
    """Ctrl-C; (exit status, stdout and stderr)."""
    code, out, err = proc.stop()
    return code, out + err


class Caller:
    """The test's own node: a /calibrate_geometry client and the calibration node's /diagnostics."""

    def __init__(self):
        import rclpy
        from diagnostic_msgs.msg import DiagnosticArray
        from rclpy.experimental import EventsExecutor
        from std_srvs.srv import Trigger

        rclpy.init()
        self.node = rclpy.create_node("calibration_test_caller")
        self.client = self.node.create_client(Trigger, "/calibrate_geometry")
        self.diags: list[tuple[float, dict]] = []  # (arrival, status of the calibration node)
        self.driver: list[tuple[float, int]] = []  # (stamp, samples published) of the driver's diagnostics
        self.node.create_subscription(DiagnosticArray, "/diagnostics", self._on_diag, 50)
        self.executor = EventsExecutor()
        self.executor.add_node(self.node)
        self._request = Trigger.Request

    def _on_diag(self, msg) -> None:
        stamp = msg.header.stamp.sec + msg.header.stamp.nanosec * 1e-9
        for s in msg.status:
            values = {kv.key: kv.value for kv in s.values}
            if s.name.startswith(CAL_NODE):
                self.diags.append((time.monotonic(), {"message": s.message, "level": s.level, "stamp": stamp,
                                                      **values}))
            elif s.name.startswith("imu_array_driver"):
                self.driver.append((stamp, int(values["samples_published"])))

    def driver_stalled_in(self, a: float, b: float) -> bool:
        """The driver (another process) was held up between stamps a and b (s), by its 1 Hz diagnostics: none
        of them stamped in (a, b) (its timer did not run), or two consecutive ones overlapping (a, b) with no
        sample published between them."""
        if not any(a < t < b for t, _ in self.driver):
            return True
        return any(t1 > a and t0 < b and n1 == n0 for (t0, n0), (t1, n1) in zip(self.driver, self.driver[1:]))

    def spin_until(self, cond, timeout=30.0) -> bool:
        end = time.monotonic() + timeout
        while time.monotonic() < end and not cond():
            self.executor.spin_once(timeout_sec=0.02)
        return cond()

    def window_full(self, timeout=COME_UP_S) -> dict:
        ok = self.spin_until(lambda: self.client.service_is_ready() and self.diags
                             and float(self.diags[-1][1]["window_fill"]) >= 1.0, timeout)
        assert ok, ("window never filled / service never came", self.diags[-1:] or "no diagnostics")
        return self.diags[-1][1]

    def call_async(self):
        return self.client.call_async(self._request())

    def call(self, timeout=60.0):
        future = self.call_async()
        assert self.spin_until(future.done, timeout), "no response"
        return future.result()

    def close(self) -> None:
        import rclpy

        self.node.destroy_node()
        rclpy.try_shutdown()


@pytest.fixture
def caller(dds):
    c = Caller()
    try:
        yield c
    finally:
        c.close()


def _simulate(tmp_path, name, *args) -> Path:
    from imu_array_ros.cli import main as cli

    out = tmp_path / name
    assert cli(["simulate", "--array", str(ARRAY32), "--out", str(out), "--duration", "2", "--rate", "500",
                "--start-time", "0", "--quiet", *map(str, args)]) == 0
    return out


def _true_array(tmp_path) -> Path:
    """array32 with every IMU moved by ~0.5 mm per axis (seeded): what the twist recording is made of."""
    from imu_array_ros.model.description import load_description, save_description

    desc = load_description(ARRAY32)
    rng = np.random.default_rng(5)
    true = desc.with_imus([imu.__class__(**{**imu.__dict__, "position": imu.position + rng.normal(0, 5e-4, 3)})
                           for imu in desc.imus])
    save_description(true, tmp_path / "true.yaml")
    return tmp_path / "true.yaml"


def _driver(dds, bag, subscribers):
    return dds.start("driver", BIN / "driver_node", "--ros-args", "-p", f"array_config:={ARRAY32}", "-p", "mode:=replay",
               "-p", f"bag:={bag}", "-p", "loop:=true", "-p", "reliable:=true",
               "-p", f"wait_for_subscribers:={subscribers}")


def _calibration_node(dds, out, *params):
    args = ["-p", f"array_config:={ARRAY32}", "-p", f"output_file:={out}", "-p", "reliable:=true"]  # sync_timeout default
    for p in params:
        args += ["-p", p]
    return dds.start("calibration", BIN / "calibration_node", "--ros-args", *args)


#: the most IMUs a sample may be fused without (messages lost on that many topics at once) that the test tries
MAX_MISSING = 8
#: candidate sets kept per size in the search beyond three missing IMUs
BEAM = 64
#: what a fused sample publishes
FIELDS = ("omega", "omega_dot", "specific_force")


def _distance(got, fused, i) -> np.ndarray:
    """Per row of ``fused``: how far it is from the published sample ``i`` (sum of squared relative errors)."""
    out = np.zeros(len(fused.stamps))
    for n in FIELDS:
        ref = np.asarray(got[n][i])
        out += np.sum((getattr(fused, n) - ref) ** 2, axis=1) / (np.sum(ref ** 2) + 1e-12)
    return out


def _missing_imus(fusion, window, i, exact, distance, seen: list, search: bool = True):
    """The IMUs without which the offline fusion of ``window``'s sample ``i`` is exactly the published one:
    (missing IMU indexes, that fusion as one row), or None.  Tried in turn, each group fused as one
    batch (rows 1 ns apart): the sets that explained earlier rows (``seen``, appended to; topics held back
    together stay so for a few samples; only these when not ``search``), every single IMU, pair and triple, then a beam search (the
    :data:`BEAM` nearest sets of each size grown by one IMU) up to :data:`MAX_MISSING`.  ``exact(fused, j)``:
    row j is the published sample; ``distance(fused)``: per row, how far.  An exact match of nine fused values
    (to 1e-9) is proof whichever way the set was found."""
    from itertools import combinations

    from imu_array_ros.model.samples import ImuSamples

    k = len(window.names)

    def fuse(sets):
        acc = np.repeat(window.accel[i:i + 1], len(sets), axis=0)
        gyr = np.repeat(window.gyro[i:i + 1], len(sets), axis=0)
        for j, missing in enumerate(sets):
            acc[j, list(missing)] = gyr[j, list(missing)] = np.nan
        fused, _ = fusion.fuse(ImuSamples(window.stamps[i] + np.arange(len(sets)), acc, gyr, window.names))
        return fused

    def hit(sets):
        """((missing, row) or None, the fusion of every set)."""
        fused = fuse(sets)
        j = next((j for j in range(len(sets)) if exact(fused, j)), None)
        if j is None:
            return None, fused
        seen.append(sets[j])
        return (sets[j], SimpleNamespace(**{n: getattr(fused, n)[j:j + 1] for n in FIELDS})), fused

    found = hit(list(dict.fromkeys(seen)))[0] if seen else None
    if found is not None or not search:
        return found
    for size in range(1, MAX_MISSING + 1):
        sets = (list(combinations(range(k), size)) if size <= 3 else
                list(dict.fromkeys(tuple(sorted(b + (m,))) for b in beam for m in range(k) if m not in b)))
        found, fused = hit(sets)
        if found is not None:
            return found
        beam = [sets[j] for j in np.argsort(distance(fused))[:BEAM]]
    return None


def _diagnose(got, window, samples, rows, calibrated, nominal, unexplained) -> str:
    """What the unexplained published samples are instead (for the failure message): per sample, how far it is
    from the offline fusion with the calibrated and with the nominal description, and the recording row whose
    calibrated fusion it is closest to (another row: the node fused another sample's readings under this stamp)."""
    from imu_array_ros.model.samples import ImuSamples

    every_cal, _ = calibrated.fuse(ImuSamples(samples.stamps, samples.accel, samples.gyro, samples.names))
    here_cal, _ = calibrated.fuse(window)
    here_nom, _ = nominal.fuse(window)
    notes = []
    for i in unexplained[:8]:
        far = lambda f, j: max(float(np.abs(got[n][i] - getattr(f, n)[j]).max()) for n in FIELDS)  # noqa: E731
        rec = np.max([np.abs(getattr(every_cal, n) - got[n][i]).max(axis=1) for n in FIELDS], axis=0)
        j = int(np.argmin(rec))
        notes.append(f"sample {i} (recording row {rows[i]}): {far(here_cal, i):.3g} from the calibrated fusion, "
                     f"{far(here_nom, i):.3g} from the nominal one; closest calibrated row {j} ({rec[j]:.3g})")
    return "; ".join(notes)


# --------------------------------------------------------------------------- the tests


def test_calibration_reaches_the_fusion_node(dds, caller, tmp_path):
    """Twist with moved IMUs -> the service writes the calibrated description, the fusion node
    reloads it, and what it publishes from then on is the offline fusion with the calibrated
    description -- sample for sample, and measurably not the fusion with the nominal one."""
    from imu_array_ros.workflows import load_array
    from imu_array_ros.workflows import build_fusion
    from imu_array_ros.io.rosbag.recording import read_imu_recording
    from imu_array_ros.model.description import load_description
    from imu_array_ros.model.samples import ImuSamples

    true = _true_array(tmp_path)
    bag = _simulate(tmp_path, "twist", "--true-array", true, "--rms-rate", 900, "--seed", 1)
    out = tmp_path / "calibrated.yaml"
    fusion = dds.start("fusion", BIN / "fusion_node", "--ros-args", "-p", f"array_config:={ARRAY32}",
                 "-p", "reliable:=true", "-p", f"calibration_file:={out}", "-p", "watch_period:=0.1",
                 "-p", "sync_timeout:=5.0")  # a loaded machine can hold a topic back for seconds
    cal = _calibration_node(dds, out, "window:=2.0")
    _driver(dds, bag, subscribers=2)
    caller.window_full()
    t0 = time.monotonic()
    response = caller.call()
    seconds = time.monotonic() - t0
    assert response.success, response.message
    assert "samples used" in response.message and str(out) in response.message and "\n" not in response.message
    print(f"\ncalibration service round trip {seconds:.2f} s: {response.message}")

    nominal, got_true = load_description(ARRAY32), load_description(true)
    calibrated = load_description(out)
    assert calibrated.calibration and calibrated.calibration["reference"] == nominal.names[0]
    assert all(imu.stds["position"].shape == (3,) for imu in calibrated.imus)
    rel = lambda d: d.positions - d.positions[0]  # noqa: E731 - only relative positions are observable
    assert np.abs(rel(calibrated) - rel(nominal)).max() > 1e-3  # they moved (by up to ~2 mm) ...
    assert np.abs(rel(calibrated) - rel(got_true)).max() < 1e-4  # ... to where the IMUs really are

    fusion.wait_line("reloaded calibration", timeout=10, stream="any")
    probe = dds.start("probe", sys.executable, "-m", "imu_array_ros.nodes.probe", "--out", tmp_path / "got.npz",
                "--count", 300, "--timeout", 30, "--reliable")
    assert probe.finish(45)[0] == 0, probe.text()
    got = np.load(tmp_path / "got.npz")
    fusion_diag = next((v for k, v in json.loads(str(got["diagnostics"])).items() if k.startswith("imu_array_fusion")),
                       "no fusion diagnostics")
    assert len(got["stamps"]) >= 300, (len(got["stamps"]), fusion_diag)

    # the raw samples of those stamps: the replay loops the recording with stamps shifted by its period
    samples, _ = read_imu_recording(bag, nominal)
    period = samples.stamps[-1] - samples.stamps[0] + int(np.median(np.diff(samples.stamps)))
    rows = np.searchsorted(samples.stamps, samples.stamps[0] + (got["stamps"] - samples.stamps[0]) % period)
    np.testing.assert_array_equal((got["stamps"] - samples.stamps[rows]) % period, 0)
    window = ImuSamples(got["stamps"], samples.accel[rows], samples.gyro[rows], samples.names)
    calibrated_fusion = build_fusion(load_array(ARRAY32, out)[0])
    want, _ = calibrated_fusion.fuse(window)
    old, _ = build_fusion(nominal).fuse(window)
    np.testing.assert_array_equal(want.stamps, got["stamps"])
    # On a loaded machine DDS can drop messages (a reliable keep-last history overwritten before the fusion
    # node took it), also on several topics at once; the node then fuses that sample without the silent IMUs
    # once its sync timeout passes, and counts it as incomplete.  Such a row must be exactly the offline fusion
    # without some IMUs (_missing_imus finds which), and there are no more of them than the node counted.
    close = lambda f, i, j: all(np.allclose(got[n][i], getattr(f, n)[j], rtol=1e-9, atol=1e-9)  # noqa: E731
                                for n in FIELDS)
    off = [i for i in range(len(want.stamps)) if not close(want, i, i)]
    names = nominal.names
    seen, lost = [], {}
    for search in (True, False):  # again without a search: a row before the one whose search found its set
        for i in [i for i in off if i not in lost]:
            found = _missing_imus(calibrated_fusion, window, i, lambda f, j: close(f, i, j),
                                  lambda f: _distance(got, f, i), seen, search=search)
            if found is not None:
                lost[i] = found
    unexplained = [i for i in off if i not in lost]
    for i, (missing, alone) in sorted(lost.items()):
        for n in FIELDS:
            getattr(want, n)[i] = getattr(alone, n)[0]
        print(f"sample {i}: fused without {', '.join(names[k] for k in missing)} (message(s) lost under load), "
              "as offline")
    assert not unexplained, (f"samples {unexplained} are not the offline fusion without any set of IMUs tried "
                             f"(those of earlier rows, every one up to three, a beam search to {MAX_MISSING}): "
                             f"{_diagnose(got, window, samples, rows, calibrated_fusion, build_fusion(nominal), unexplained)}; "
                             f"fusion node: {fusion_diag}")
    for name in FIELDS:
        np.testing.assert_allclose(got[name], getattr(want, name), rtol=1e-9, atol=1e-9,
                                   err_msg=f"{name}; fusion node: {fusion_diag}")
    # not an accident: every sample tells the two descriptions apart by far more than the tolerance
    apart = np.max(np.abs(np.concatenate([want.omega_dot - old.omega_dot,
                                          want.specific_force - old.specific_force], axis=1)), axis=1)
    assert apart.min() > 1e-5, apart.min()
    print(f"calibrated vs nominal fusion, per sample: at least {apart.min():.3g} apart")

    code, log = _stopped(cal)
    assert code == 0 and "Traceback" not in log and "[FATAL]" not in log and "calibration done" in log, log
    code, log = _stopped(fusion)
    assert code == 0 and "Traceback" not in log and "[FATAL]" not in log, log
    # no more samples fused without an IMU than the node counted incomplete over its whole run (its exit totals:
    # the /diagnostics the probe heard last can be a second or more older than the samples it recorded)
    totals = re.search(r"exiting: fused \d+ samples \(\d+ complete, (\d+) incomplete", log)
    assert totals, log
    assert len(off) <= int(totals.group(1)), (f"{len(off)} samples differ from the offline fusion, the node counted "
                                              f"{totals.group(1)} incomplete: {off}; {totals.group(0)}")


def test_still_window_fails_and_leaves_the_file_alone(dds, caller, tmp_path):
    """No rotation in the window: success false, the message names the missing motion, and the
    calibration on file is not touched (bytes, mtime, no backup)."""
    from imu_array_ros.model.description import load_description, save_description

    bag = _simulate(tmp_path, "still", "--rms-rate", 0.01, "--seed", 2)
    out = tmp_path / "calibrated.yaml"
    desc = load_description(ARRAY32)
    save_description(desc.with_imus([imu.__class__(**{**imu.__dict__, "position": imu.position + 1e-4})
                                     for imu in desc.imus]), out)
    before = (out.read_bytes(), out.stat().st_mtime_ns)
    cal = _calibration_node(dds, out, "window:=1.0")
    _driver(dds, bag, subscribers=1)
    caller.window_full()
    response = caller.call()
    assert not response.success
    assert "too few samples with rotation" in response.message and "twist the array" in response.message, \
        response.message
    assert "\n" not in response.message
    assert (out.read_bytes(), out.stat().st_mtime_ns) == before
    assert not (tmp_path / "calibrated.yaml.bak").exists()
    # the diagnostics report it
    assert caller.spin_until(lambda: caller.diags[-1][1]["calibrations_failed"] == "1", 5)
    assert caller.diags[-1][1]["level"] == b"\x01" and "too few samples" in caller.diags[-1][1]["message"]
    code, log = _stopped(cal)
    assert code == 0 and "Traceback" not in log and "[FATAL]" not in log and "calibration failed" in log, log
    assert log.count("too few samples with rotation") == 1, log  # the refusal said once (issue 24)


def test_unconverged_calibration_is_refused_and_leaves_the_file_alone(dds, caller, tmp_path):
    """One iteration cannot converge: the guards (calibration.guards) refuse it -- success false, the
    reason in one line, the calibration on file untouched (bytes, mtime, no backup)."""
    from imu_array_ros.model.description import load_description, save_description

    bag = _simulate(tmp_path, "twist", "--true-array", _true_array(tmp_path), "--rms-rate", 900, "--seed", 4)
    out = tmp_path / "calibrated.yaml"
    save_description(load_description(ARRAY32), out)
    before = (out.read_bytes(), out.stat().st_mtime_ns)
    cal = _calibration_node(dds, out, "window:=1.0", "max_iterations:=1")
    _driver(dds, bag, subscribers=1)
    caller.window_full()
    response = caller.call()
    assert not response.success
    assert "refused: not converged (1 iterations); nothing written" in response.message, response.message
    assert "\n" not in response.message
    assert (out.read_bytes(), out.stat().st_mtime_ns) == before
    assert not (tmp_path / "calibrated.yaml.bak").exists()
    code, log = _stopped(cal)
    assert code == 0 and "Traceback" not in log and "calibration failed" in log, log
    assert log.count("refused: not converged") == 1, log  # the refusal said once (issue 24)


def test_second_call_refused_while_the_window_keeps_filling(dds, caller, tmp_path):
    """A call while a calibration runs is refused at once; meanwhile the node goes on buffering
    (its 1 Hz diagnostics keep coming during the calibration, with samples received since it started)."""
    bag = _simulate(tmp_path, "twist", "--rms-rate", 900, "--seed", 3, "--duration", 5)
    out = tmp_path / "calibrated.yaml"
    # the BCD solver on 4 s at 500 Hz: a few seconds of calibration (3 s on the CI machine), so that
    # the Ctrl-C below, sent when the 1 Hz diagnostics first say busy, arrives before the file is written.
    # 30 iterations do not converge (~130 would): the first call ends refused (calibration.guards)
    cal = _calibration_node(dds, out, "window:=4.0", "method:=bcd", "max_iterations:=30")
    _driver(dds, bag, subscribers=1)
    caller.window_full()
    first = caller.call_async()
    # the first request has reached the node: its diagnostics say busy (however loaded the machine)
    assert caller.spin_until(lambda: caller.diags[-1][1]["busy"] == "True", COME_UP_S), "first call never started"
    t0 = time.monotonic()
    second = caller.call()
    refused_in = time.monotonic() - t0
    assert not second.success and "already running" in second.message and refused_in < 1.0, \
        (refused_in, second.message)
    assert caller.spin_until(first.done, 60), "the first call never returned"
    assert not first.result().success and "refused: not converged (30 iterations)" in first.result().message, \
        first.result().message
    assert not out.exists()
    busy = [d for _, d in caller.diags if d["busy"] == "True"]
    received = [int(d["samples_received_while_calibrating"]) for d in busy]
    print(f"\nrefused in {refused_in * 1e3:.1f} ms; samples received while calibrating (after s): " + ", ".join(
        f"{r} ({float(d['calibrating_for_s']):.1f})" for r, d in zip(received, busy)))
    assert busy and received[-1] > 0 and all(np.diff(received) >= 0), (received, first.result().message)
    # between two diagnostics the window grew, unless the driver (another process, starved on a loaded
    # machine) was held up meanwhile: an interval without samples received is then not the node's doing
    stamps = [float(d["stamp"]) for d in busy]
    idle = [(round(a - stamps[0], 1), round(b - stamps[0], 1)) for a, b, grew in
            zip(stamps, stamps[1:], np.diff(received) > 0) if not grew and not caller.driver_stalled_in(a, b)]
    assert not idle, ("samples published but none received while calibrating (s after the first diagnostics)",
                      idle, received, caller.driver)
    assert caller.spin_until(lambda: caller.diags[-1][1]["busy"] == "False" and
                             caller.diags[-1][1]["calibrations_failed"] == "1", 30)
    assert caller.diags[-1][1]["calls_refused_busy"] == "1"
    # Ctrl-C during a calibration (from the nominal positions again, as long as the first): it is
    # abandoned at its next iteration, nothing written, clean exit
    caller.call_async()
    assert caller.spin_until(lambda: caller.diags[-1][1]["busy"] == "True", 30), "third call never started"
    t0 = time.monotonic()
    code, log = _stopped(cal)
    print(f"stopped during a calibration in {time.monotonic() - t0:.2f} s")
    assert code == 0 and "Traceback" not in log and "[FATAL]" not in log and "calibration failed" in log and "shutting down" in log, log
    assert not out.exists()
    # each refusal said once (issue 24): the busy one, and the first calibration's
    assert log.count("calibration call refused") == 1 and log.count("refused: not converged (30 iterations)") == 1, log


_OUT = str(Path(tempfile.gettempdir()) / "calibration_node_bad_parameters.yaml")  # never written


@pytest.mark.parametrize("args, fragment", [
    (["-p", "array_config:=/nonexistent/array.yaml", "-p", f"output_file:={_OUT}"], "/nonexistent/array.yaml"),
    (["-p", f"array_config:={ARRAY32}"], "'output_file' is required"),
    (["-p", f"array_config:={ARRAY32}", "-p", "output_file:=/nonexistent/dir/cal.yaml"], "'output_file'"),
    (["-p", f"array_config:={ARRAY32}", "-p", f"output_file:={_OUT}", "-p", "window:=0.0"], "'window'"),
    (["-p", f"array_config:={ARRAY32}", "-p", f"output_file:={_OUT}", "-p", "method:=lbfgs"], "'method'"),
    (["-p", f"array_config:={ARRAY32}", "-p", f"output_file:={_OUT}", "-p", "reference_imu:=imu_99"],
     "'reference_imu'"),
    (["-p", f"array_config:={ARRAY32}", "-p", f"output_file:={REPO / 'config' / 'planar4.yaml'}"],
     "'output_file': "),  # a description of other IMUs: never replaced
])
def test_bad_parameters_one_line(dds, args, fragment):
    code, out, err = dds.start("calibration", BIN / "calibration_node", "--ros-args", *args).finish(60)
    lines = [ln for ln in (out + err).splitlines() if ln.strip()]
    assert code == 2, lines
    assert len(lines) == 1 and lines[0].startswith("calibration_node: error: ") and fragment in lines[0], lines
