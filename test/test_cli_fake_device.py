"""``imu-array fake-device``: one-line errors in-process, and real runs as a process driven by the serial link."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time

import pytest

from conftest import REPO, SHARED_DATA, assert_user_error, cli

CORNERS = REPO / "config" / "mimu4444bt_corners.yaml"
needs_pty = pytest.mark.skipif(not hasattr(os, "openpty"), reason="os.openpty is not available")


def test_link_path_that_is_a_user_file_is_refused(capsys, tmp_path):
    mine = tmp_path / "port"
    mine.write_bytes(b"not a port")
    assert_user_error(cli(capsys, "fake-device", "--array", CORNERS, "--link", mine),
                      str(mine), "exists and is not a symlink")
    assert mine.read_bytes() == b"not a port"


def test_link_in_missing_directory(capsys, tmp_path):
    assert_user_error(cli(capsys, "fake-device", "--array", CORNERS, "--link", tmp_path / "no" / "tty"),
                      "does not exist")


def test_unknown_capture(capsys, tmp_path):
    assert_user_error(cli(capsys, "fake-device", "--array", CORNERS, "--capture", tmp_path / "none.bin",
                          "--link", tmp_path / "tty"), "none.bin", "cannot read capture")
    assert not os.path.lexists(tmp_path / "tty")


@pytest.mark.skipif(not (SHARED_DATA / "exp_1.bin").is_file(), reason="real capture not found")
def test_capture_with_wrong_imu_count(capsys, tmp_path):
    assert_user_error(cli(capsys, "fake-device", "--array", REPO / "config" / "planar4.yaml",
                          "--capture", SHARED_DATA / "exp_1.bin"), "4-IMU", "8-IMU")


@pytest.mark.parametrize("args, fragments", [
    (["--capture", "x.bin", "--duration", "2"], ["--duration", "not with --capture"]),
    (["--rate", "100"], ["--rate", "1000, 500, 250, 125, 62.5, 31.25, 15.625", "'100'"]),
    (["--bit-error-rate", "1.5"], ["--bit-error-rate", "[0, 1)"]),
    (["--drop-byte-rate", "-0.1"], ["--drop-byte-rate"]),
    (["--speed", "-1"], ["--speed"]),
    (["--unplug-at", "0"], ["--unplug-at"]),
])
def test_bad_options(capsys, args, fragments):
    assert_user_error(cli(capsys, "fake-device", "--array", CORNERS, *args), *fragments)


def _start(tmp_path, *args):
    link = tmp_path / "tty"
    proc = subprocess.Popen([sys.executable, "-m", "imu_array_ros", "fake-device", "--array", str(CORNERS),
                             "--link", str(link), *args], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            cwd=tmp_path, env={**os.environ, "PYTHONPATH": str(REPO)})
    port = proc.stdout.readline().strip()
    assert port == str(link), proc.stderr.read()
    return proc, port


@needs_pty
def test_simulated_run_to_the_end(tmp_path):
    from imu_array_ros.io.openshoe.serial_link import SerialArrayLink

    proc, port = _start(tmp_path, "--duration", "0.5", "--speed", "0", "--seed", "4")
    assert os.readlink(port).startswith("/dev/")
    link = SerialArrayLink(port, 8)
    n = 0
    deadline = time.monotonic() + 20
    while proc.poll() is None and time.monotonic() < deadline:
        n += len(link.poll())
        time.sleep(0.002)
    n += len(link.poll())
    link.close()
    out, err = proc.communicate(timeout=5)
    assert proc.returncode == 0, err
    assert out == "" and "Traceback" not in err and "sent 32 packets" in err  # 0.5 s at 62.5 Hz
    assert n == 32 and link.stats.bad_checksums == 0
    assert not os.path.lexists(port)


@needs_pty
@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
def test_interrupt_exits_cleanly(tmp_path, sig):
    proc, port = _start(tmp_path, "--duration", "1", "--loop", "-q")
    assert os.path.islink(port)
    proc.send_signal(sig)
    out, err = proc.communicate(timeout=10)
    assert proc.returncode == 0 and out == "" and err == ""
    assert not os.path.lexists(port)


@needs_pty
def test_host_stop_is_said_and_the_device_waits(tmp_path):
    """A host that stops the stream is named on the console; the device waits for the next start, as one would."""
    from imu_array_ros.io.openshoe.serial_link import SerialArrayLink

    proc, port = _start(tmp_path, "--duration", "2", "--loop")
    link = SerialArrayLink(port, 8)
    n, deadline = 0, time.monotonic() + 10
    while n < 5 and time.monotonic() < deadline:
        n += len(link.poll())
        time.sleep(0.005)
    link.close()  # sends the stop command
    time.sleep(0.6)
    assert proc.poll() is None  # still waiting for a start
    proc.send_signal(signal.SIGINT)
    out, err = proc.communicate(timeout=10)
    assert n >= 5 and proc.returncode == 0, err
    assert "the host started the stream" in err
    assert "the host stopped the stream" in err and "waiting for the next start" in err
