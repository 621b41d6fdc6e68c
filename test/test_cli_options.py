"""Bad input, the rest (issue 5 §4): validated options, strict JSON, -q, identifiability
naming the file, start times, and the README's commands (run twice, CI in step, shipped bag)."""

from __future__ import annotations

import calendar
import json
import os
import re
import shlex
import time
from pathlib import Path

import numpy as np
import pytest
import yaml

from imu_array_ros.cli import build_parser, main
from imu_array_ros.io.openshoe.framing import encode_packets
from imu_array_ros.io.rosbag.recording import read_fused_recording, read_imu_recording, read_truth
from imu_array_ros.model.description import load_description

from conftest import ARRAY32, REPO, assert_user_error, cli

CORNERS = REPO / "config" / "mimu4444bt_corners.yaml"
README = (REPO / "README.md").read_text(encoding="utf-8")
NOV21_10H_NS = calendar.timegm((2026, 11, 21, 10, 0, 0)) * 10**9  # 2026-11-21T10:00:00Z


def strict_json(text: str):
    """json.loads that refuses NaN / Infinity (Python's default accepts them; JSON does not)."""
    def bad_constant(name):
        raise AssertionError(f"not valid JSON: bare {name}")
    return json.loads(text, parse_constant=bad_constant)


@pytest.fixture(scope="module")
def spinning(tmp_path_factory):
    """Random motion at |omega| = 600 deg/s: no sample is 'still' (|omega| < 0.2 rad/s)."""
    out = tmp_path_factory.mktemp("spin") / "spin.mcap"
    assert main(["simulate", "--array", str(ARRAY32), "--out", str(out), "--motion", "random", "--duration", "0.1",
                 "--rate", "500", "--start-time", "0", "-q"]) == 0
    return out


# --------------------------------------------------------------------------- every numeric option is validated


SIM = ["simulate", "--array", ARRAY32]
BAD_OPTIONS = [
    (SIM + ["--duration", "0"], "--duration", "positive"),
    (SIM + ["--duration", "-1"], "--duration", "positive"),
    (SIM + ["--duration", "nan"], "--duration", "finite"),
    (SIM + ["--duration", "inf"], "--duration", "finite"),
    (SIM + ["--duration", "two"], "--duration", "expected a number"),
    (SIM + ["--rate", "-5"], "--rate", "positive"),
    (SIM + ["--rate", "0"], "--rate", "positive"),
    (SIM + ["--rate", "nan"], "--rate", "finite"),
    (SIM + ["--rate", "2e9"], "--rate", "at most"),
    (SIM + ["--rms-rate", "-1"], "--rms-rate", "positive"),
    (SIM + ["--rms-rate", "0"], "--rms-rate", "positive"),
    (SIM + ["--angular-accel", "-1"], "--angular-accel", "negative"),
    (SIM + ["--angular-accel", "nan"], "--angular-accel", "finite"),
    (SIM + ["--seed", "-1"], "--seed", "negative"),
    (SIM + ["--seed", "1.5"], "--seed", "whole number"),
    (SIM + ["--error-seed", "-3"], "--error-seed", "negative"),
    (SIM + ["--error-seed", "1", "--position-error-std", "-1"], "--position-error-std", "negative"),
    (SIM + ["--error-seed", "1", "--position-error-std", "inf"], "--position-error-std", "finite"),
    (SIM + ["--start-time", "yesterday"], "--start-time", "ISO 8601"),
    (SIM + ["--start-time", "nan"], "--start-time", "finite"),
    (SIM + ["--start-time", "-1"], "--start-time", "between"),
    (SIM + ["--start-time", "2040-01-01T00:00:00Z"], "--start-time", "between"),
    (SIM + ["--start-time", "1e20"], "--start-time", "between"),
    (SIM + ["--motion", "spin"], "--motion", "invalid choice"),
    (["residuals", "REC", "--array", ARRAY32, "--still-threshold", "-0.1"], "--still-threshold", "negative"),
    (["residuals", "REC", "--array", ARRAY32, "--still-threshold", "nan"], "--still-threshold", "finite"),
    (["residuals", "REC", "--array", ARRAY32, "--seed", "-2"], "--seed", "negative"),
    (["import-openshoe", "C.bin", "--array", CORNERS, "--start-time", "21/11/2026"], "--start-time", "ISO 8601"),
    (["fuse", "REC", "--array", ARRAY32], "--out", "required"),
]


@pytest.mark.parametrize("argv, option, problem", BAD_OPTIONS, ids=[f"{a[0][0]} {a[1]} {a[0][-1]}" for a in BAD_OPTIONS])
def test_bad_option_values_are_one_line_errors(tmp_path, capsys, argv, option, problem):
    argv = list(argv)
    if argv[0] in ("simulate", "import-openshoe"):
        argv += ["--out", tmp_path / "out.mcap"]
    err = assert_user_error(cli(capsys, *argv), option, problem)
    assert f"'imu-array {argv[0]} --help'" in err
    assert not list(tmp_path.iterdir())


def test_duration_and_rate_must_give_samples(tmp_path, capsys):
    assert_user_error(cli(capsys, *SIM, "--out", tmp_path / "r", "--duration", "0.001", "--rate", "100"), "gives no sample")
    assert_user_error(cli(capsys, *SIM, "--out", tmp_path / "r", "--duration", "1e9", "--rate", "1000"), "more than")
    assert_user_error(cli(capsys, *SIM, "--out", tmp_path / "r", "--position-error-std", "1e-4"), "needs --error-seed")
    assert_user_error(cli(capsys, *SIM, "--out", tmp_path / "r", "--start-time", "2038-01-19T03:14:07Z", "--duration", "2"),
               "2038")
    assert not list(tmp_path.iterdir())


def test_start_time_parsing():
    parse = build_parser().parse_args
    base = ["simulate", "--array", "a.yaml", "--out", "o"]
    assert parse(base + ["--start-time", "2026-11-21T10:00:00Z"]).start_ns == NOV21_10H_NS
    assert parse(base + ["--start-time", "2026-11-21T11:30:00+01:30"]).start_ns == NOV21_10H_NS
    assert parse(base + ["--start-time", "2026-11-21T10:00:00"]).start_ns == NOV21_10H_NS  # no offset: UTC
    assert parse(base + ["--start-time", "2026-11-21T10:00:00.250000Z"]).start_ns == NOV21_10H_NS + 250_000_000
    # seconds since the epoch, exact to the nanosecond (no float rounding)
    assert parse(base + ["--start-time", str(NOV21_10H_NS // 10**9)]).start_ns == NOV21_10H_NS
    assert parse(base + ["--start-time", "1795255200.123456789"]).start_ns == 1795255200_123456789
    assert parse(base + ["--start-time", "0"]).start_ns == 0
    assert parse(base).start_ns is None


# --------------------------------------------------------------------------- -q and JSON


def test_quiet_silences_stderr_but_not_the_requested_result(spinning, tmp_path, capsys):
    code, helptext, _ = cli(capsys, "residuals", "--help")
    assert code == 0 and "no progress or summary lines on stderr" in " ".join(helptext.split())
    code, out, err = cli(capsys, "fuse", spinning, "--array", ARRAY32, "--out", tmp_path / "f.mcap", "-q")
    assert (code, out, err) == (0, "", "")
    assert len(read_fused_recording(tmp_path / "f.mcap")) == 50
    # without -q: progress and summary lines on stderr, stdout empty (nothing was asked for there)
    code, out, err = cli(capsys, "residuals", spinning, "--array", ARRAY32)
    assert code == 0 and out == ""
    assert "## recording, still: 0 samples" in err and "## recording, moving: 50 samples, NIS ratio" in err
    # -q: nothing at all unless a result was asked for
    assert cli(capsys, "residuals", spinning, "--array", ARRAY32, "-q") == (0, "", "")
    code, out, err = cli(capsys, "residuals", spinning, "--array", ARRAY32, "-q", "--tables")
    assert code == 0 and err == ""
    assert "## recording, moving: NIS ratio by IMU and axis" in out and "| imu_31 |" in out
    assert "still" not in out  # no table for a regime without samples
    code, out, err = cli(capsys, "residuals", spinning, "--array", ARRAY32, "-q", "--json", "-")
    assert code == 0 and err == ""
    assert strict_json(out)["recording"]["moving"]["samples"] == 50


def test_residuals_json_has_null_not_nan_for_a_regime_without_samples(spinning, tmp_path, capsys):
    report = tmp_path / "r.json"
    code, out, err = cli(capsys, "residuals", spinning, "--array", ARRAY32, "--compare-simulated", "--json", report)
    assert code == 0, err
    assert out == "" and f"wrote {report}" in err
    text = report.read_text()
    assert "NaN" not in text and "Infinity" not in text
    result = strict_json(text)
    for name in ("recording", "simulated_same_motion"):
        still, moving = result[name]["still"], result[name]["moving"]
        assert still["samples"] == 0
        assert still["ratio_all"] is None and still["ratio_accelerometers"] is None and still["ratio_gyroscopes"] is None
        assert set(still["by_imu"].values()) == {None} and set(still["by_axis"].values()) == {None}
        assert still["worst"] == []
        # the moving regime holds every sample and real numbers: the simulated recording fits its own model
        assert moving["samples"] == 50
        assert 0.8 < moving["ratio_all"] < 1.2


# --------------------------------------------------------------------------- identifiability names the file


def test_non_identifiable_arrays_are_refused_naming_the_file(spinning, tmp_path, capsys):
    data = yaml.safe_load(ARRAY32.read_text())
    for i, imu in enumerate(data["imu_array"]["imus"]):
        imu["position"] = [0.001 * i, 0.0, 0.0]
    line = tmp_path / "line.yaml"
    line.write_text(yaml.safe_dump(data))
    expected = f"imu-array: error: {line}: accelerometer triads are collinear"
    for argv in (["simulate", "--array", line, "--out", tmp_path / "s.mcap"],
                 ["fuse", spinning, "--array", line, "--out", tmp_path / "f.mcap"],
                 ["residuals", spinning, "--array", line]):
        assert assert_user_error(cli(capsys, *argv)).startswith(expected)
    # with --calibration the geometry comes from the calibration file: that is the file named
    err = assert_user_error(cli(capsys, "fuse", spinning, "--array", ARRAY32, "--calibration", line, "--out", tmp_path / "c.mcap"))
    assert err.startswith(f"imu-array: error: {line}: "), err
    two = yaml.safe_load(ARRAY32.read_text())
    del two["imu_array"]["imus"][2:]
    two_path = tmp_path / "two.yaml"
    two_path.write_text(yaml.safe_dump(two))
    assert_user_error(cli(capsys, "simulate", "--array", two_path, "--out", tmp_path / "s.mcap"), str(two_path), "at least 3")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["line.yaml", "two.yaml"]


# --------------------------------------------------------------------------- start times


def test_simulate_start_time(tmp_path, capsys):
    desc = load_description(ARRAY32)
    common = ["simulate", "--array", ARRAY32, "--duration", 0.05, "--rate", 200, "--seed", 4, "-q"]
    assert cli(capsys, *common, "--out", tmp_path / "a.mcap", "--start-time", "2026-11-21T10:00:00Z")[0] == 0
    assert cli(capsys, *common, "--out", tmp_path / "b.mcap", "--start-time", "0")[0] == 0
    before = time.time_ns()
    assert cli(capsys, *common, "--out", tmp_path / "c.mcap")[0] == 0
    after = time.time_ns()
    a, _ = read_imu_recording(tmp_path / "a.mcap", desc)
    b, _ = read_imu_recording(tmp_path / "b.mcap", desc)
    c, _ = read_imu_recording(tmp_path / "c.mcap", desc)
    np.testing.assert_array_equal(a.stamps, NOV21_10H_NS + 5_000_000 * np.arange(10))
    np.testing.assert_array_equal(b.stamps, 5_000_000 * np.arange(10))
    assert before <= c.stamps[0] <= after  # default: now
    np.testing.assert_array_equal(c.stamps - c.stamps[0], b.stamps)
    # only the stamps move: the measurements and the truth are the same
    for x in (a, c):
        np.testing.assert_array_equal(x.accel, b.accel)
        np.testing.assert_array_equal(x.gyro, b.gyro)
    np.testing.assert_array_equal(read_truth(tmp_path / "a.mcap").omega, read_truth(tmp_path / "b.mcap").omega)
    np.testing.assert_array_equal(read_truth(tmp_path / "a.mcap").stamps, a.stamps)


def _capture(path: Path, n_imus: int, packets: int) -> None:
    """A valid OpenShoe capture: one packet per 16 ms (1,024,000 ticks of the 64 MHz clock)."""
    rng = np.random.default_rng(0)
    raw = rng.integers(-200, 200, size=(packets, n_imus, 6)).astype(np.int16)
    path.write_bytes(encode_packets(np.arange(packets), 5000 + 1_024_000 * np.arange(packets), raw))


def test_import_openshoe_start_time(tmp_path, capsys):
    desc = load_description(CORNERS)
    capture = tmp_path / "exp.bin"
    _capture(capture, len(desc.imus), 40)
    mtime_ns = NOV21_10H_NS + 123_456_789
    os.utime(capture, ns=(mtime_ns, mtime_ns))
    assert cli(capsys, "import-openshoe", capture, "--array", CORNERS, "--out", tmp_path / "d.mcap", "-q")[0] == 0
    d, _ = read_imu_recording(tmp_path / "d.mcap", desc)
    # default: the capture ends at the file's modification time
    assert d.stamps[-1] == mtime_ns
    np.testing.assert_array_equal(np.diff(d.stamps), 16_000_000)
    assert len(d) == 40
    assert cli(capsys, "import-openshoe", capture, "--array", CORNERS, "--out", tmp_path / "e.mcap", "-q",
               "--start-time", "2026-11-21T10:00:00Z")[0] == 0
    e, _ = read_imu_recording(tmp_path / "e.mcap", desc)
    np.testing.assert_array_equal(e.stamps, NOV21_10H_NS + 16_000_000 * np.arange(40))
    np.testing.assert_array_equal(e.accel, d.accel)


# --------------------------------------------------------------------------- the README's commands


def _readme_section(title: str) -> str:
    m = re.search(rf"^## {re.escape(title)}\n(.*?)(?=^## )", README, flags=re.S | re.M)
    assert m, title
    return m.group(1)


def _args_after(line: str, program: str = "imu-array") -> list[str]:
    words = shlex.split(line)
    i = next(i for i, w in enumerate(words) if w.endswith(program))
    return words[i + 1:]


def test_quickstart_fuse_runs_twice_in_a_row(tmp_path, monkeypatch, capsys):
    """README step 1's command (inputs taken from the repository, output in a scratch directory)."""
    line = next(l for l in _readme_section("Quickstart").splitlines() if "imu-array fuse" in l)
    args = _args_after(line.split("&&")[-1])
    out = args[args.index("--out") + 1]
    assert not os.path.isabs(out)
    monkeypatch.chdir(tmp_path)
    argv = [str(REPO / a) if a != out and (REPO / a).exists() else a for a in args]
    for _ in range(2):
        code, _, err = cli(capsys, *argv)
        assert code == 0, err
    assert len(read_fused_recording(tmp_path / out)) == 1000
    assert sorted(p.name for p in tmp_path.iterdir()) == [out]


def test_ci_runs_the_readme_step_1_command():
    readme = _args_after(next(l for l in _readme_section("Quickstart").splitlines() if "imu-array fuse" in l)
                         .split("&&")[-1])
    ci_line = next(l for l in (REPO / ".ci" / "run").read_text().splitlines() if "imu-array fuse" in l)
    ci = _args_after(ci_line)
    i = readme.index("--out")
    assert ci[:i + 1] == readme[:i + 1] and ci[i + 2:] == readme[i + 2:], (ci, readme)
    assert Path(ci[i + 1]).name == readme[i + 1]


def test_shipped_sample_recording_is_reproduced_by_its_documented_command(tmp_path, capsys):
    """README "The command line" gives the command that made bags/twist32_sample; it reproduces it exactly."""
    spans = re.findall(r"`([^`]*--out bags/twist32_sample[^`]*)`", _readme_section("The command line"))
    assert len(spans) == 1, spans
    args = _args_after(spans[0])
    args[args.index("--out") + 1] = str(tmp_path / "again")
    args = [str(REPO / a) if a.endswith(".yaml") else a for a in args]
    code, _, err = cli(capsys, *args)
    assert code == 0, err
    desc = load_description(ARRAY32)
    shipped, _ = read_imu_recording(REPO / "bags" / "twist32_sample", desc)
    again, _ = read_imu_recording(tmp_path / "again", desc)
    np.testing.assert_array_equal(again.stamps, shipped.stamps)
    np.testing.assert_array_equal(again.accel, shipped.accel)
    np.testing.assert_array_equal(again.gyro, shipped.gyro)
    t_shipped, t_again = read_truth(REPO / "bags" / "twist32_sample"), read_truth(tmp_path / "again")
    np.testing.assert_array_equal(t_again.omega, t_shipped.omega)
    np.testing.assert_array_equal(t_again.specific_force, t_shipped.specific_force)


# --------------------------------------------------------------------------- core errors told with the user's flags


def test_core_errors_naming_a_parameter_are_told_with_its_flag():
    """The core names what it was given (``chains 1: ...``, ``(n_draws)``); the command line says the flag."""
    from imu_array_ros.cli.calibrate.bayes import FLAGS
    from imu_array_ros.cli.options import as_flags
    from imu_array_ros.errors import CalibrationError

    cases = [("chains 1: at least 2 are needed for R-hat", "--chains 1: at least 2 are needed for R-hat"),
             ("scheduler tcp://h:9: cannot connect", "--scheduler tcp://h:9: cannot connect"),
             ("widen the noise (accel_std), or give the draws (n_draws)", "widen the noise (--accel-std), or give "
                                                                          "the draws (--draws)"),
             ("too few samples with rotation: the chains stop", "too few samples with rotation: the chains stop")]
    for core, told in cases:
        with pytest.raises(CalibrationError) as caught:
            with as_flags(FLAGS):
                raise CalibrationError(core)
        assert str(caught.value) == told
