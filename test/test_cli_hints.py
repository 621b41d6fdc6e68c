"""Mistakes a new user makes get a line that says what to do (issue 24's smaller defects)."""

from __future__ import annotations

import yaml

from conftest import REPO, assert_user_error, cli

ARRAY32 = REPO / "config" / "array32.yaml"
SAMPLE = REPO / "bags" / "twist32_sample"
CORNERS = REPO / "config" / "mimu4444bt_corners.yaml"


def test_a_raw_capture_given_as_a_recording_points_to_import_openshoe(tmp_path, capsys):
    capture = tmp_path / "exp_9.bin"
    capture.write_bytes(bytes([0xA0, 0x28, 0x00, 0xC8]) + bytes([0xAA, 0, 1, 100]) * 40)
    assert_user_error(cli(capsys, "fuse", capture, "--array", CORNERS, "--out", tmp_path / "f.mcap"),
                      "not an MCAP file", "imu-array import-openshoe")
    assert not (tmp_path / "f.mcap").exists()
    other = tmp_path / "notes.mcap"
    other.write_text("hello\n")  # not MCAP, not a capture: no hint
    line = assert_user_error(cli(capsys, "fuse", other, "--array", CORNERS, "--out", tmp_path / "f.mcap"),
                             "not an MCAP file")
    assert "import-openshoe" not in line


def test_positions_written_in_millimetres_are_refused(tmp_path, capsys):
    doc = yaml.safe_load(ARRAY32.read_text())
    for imu in doc["imu_array"]["imus"]:
        imu["position"] = [1000 * x for x in imu["position"]]
    mm = tmp_path / "array_mm.yaml"
    mm.write_text(yaml.safe_dump(doc))
    assert_user_error(cli(capsys, "fuse", SAMPLE, "--array", mm, "--out", tmp_path / "f.mcap"),
                      str(mm), "span", "millimetres")
    assert not (tmp_path / "f.mcap").exists()


def test_progress_lines_off_a_terminal_are_few(capsys, monkeypatch):
    """Off a terminal: a quick job says 100 % once; a slow one also 25/50/75 % (at most one line a second)."""
    from imu_array_ros.cli import progress

    clock = iter([0.0] + [0.1 * i for i in range(1, 200)])
    monkeypatch.setattr(progress.time, "perf_counter", lambda: next(clock))
    p = progress.Progress("fast")
    for i in range(101):
        p(i, 100)
    err = capsys.readouterr().err.splitlines()
    assert err == ["fast: 100%  (0.5 s)"], err  # five buckets, 0.1 s apart: one line
    slow = iter([0.0] + [2.0 * i for i in range(1, 200)])
    monkeypatch.setattr(progress.time, "perf_counter", lambda: next(slow))
    p = progress.Progress("slow")
    for i in range(101):
        p(i, 100)
    err = capsys.readouterr().err.splitlines()
    assert [line.split(":")[1].split("%")[0].strip() for line in err] == ["0", "25", "50", "75", "100"], err
    quick = iter([0.0] + [0.001 * i for i in range(1, 200)])
    monkeypatch.setattr(progress.time, "perf_counter", lambda: next(quick))
    p = progress.Progress("quick")
    for i in range(101):
        p(i, 100)
    assert capsys.readouterr().err.splitlines() == ["quick: 100%  (0.0 s)"]


def test_samples_that_did_not_converge_point_to_the_description_even_with_q(tmp_path, capsys, monkeypatch):
    """A one-digit position typo fused a real capture with exit 0 and 59 'not converged' in a count line (helper-31's
    trial): the user is told what it likely means and how to see which IMU, also with -q."""
    from imu_array_ros.cli import fuse as fuse_cli
    from imu_array_ros.fusion.ml_fusion import FusionStats

    real = fuse_cli.read_and_fuse

    def with_unconverged(*args, **kwargs):
        desc, f = real(*args, **kwargs)
        f.stats = FusionStats(**{**f.stats.__dict__, "not_converged": 7})
        return desc, f

    monkeypatch.setattr(fuse_cli, "read_and_fuse", with_unconverged)
    code, _, err = cli(capsys, "fuse", SAMPLE, "--array", ARRAY32, "--out", tmp_path / "f.mcap", "-q")
    assert code == 0
    assert "7 samples did not converge" in err and "imu-array residuals" in err and str(ARRAY32) in err, err
    monkeypatch.setattr(fuse_cli, "read_and_fuse", real)
    code, _, err = cli(capsys, "fuse", SAMPLE, "--array", ARRAY32, "--out", tmp_path / "g.mcap", "-q")
    assert code == 0 and "did not converge" not in err, err


def test_discover_help_states_the_default_terms(capsys):
    """--terms' default is the candidate terms, not every registered one (the clock terms are the timing stage's)."""
    from imu_array_ros.model.terms import candidate_names, term_names

    code, helptext, _ = cli(capsys, "discover", "--help")
    text = " ".join(helptext.split())
    assert code == 0 and "every registered term)" not in text
    assert f"default: the {len(candidate_names())} candidate terms, every registered term but " in text
    clocks = [t for t in term_names() if t not in candidate_names()]
    assert clocks and all(t in text for t in clocks)
    assert "which the timing stage searches for instead" in text


def test_a_mistyped_term_names_the_option_and_the_close_match(tmp_path, capsys):
    """Not the engine's parameter name ('in free'): the option given, and the registry name meant."""
    for option, command in (("--moving-terms", "all"), ("--terms", "fit")):
        line = assert_user_error(cli(capsys, "calibrate", command, SAMPLE, "--array", ARRAY32, option, "positon",
                                     "--out", tmp_path / "c.yaml"),
                                 f"{option}: unknown term 'positon'; did you mean 'position'?")
        assert "in free" not in line
    line = assert_user_error(cli(capsys, "discover", SAMPLE, "--array", ARRAY32, "--terms", "gyroscope_gian",
                                 "--report", tmp_path / "d"), "--terms: unknown term 'gyroscope_gian'; did you mean "
                                                              "'gyroscope_gain'?")
    line = assert_user_error(cli(capsys, "calibrate", "fit", SAMPLE, "--array", ARRAY32, "--terms", "warp_drive",
                                 "--out", tmp_path / "c.yaml"), "--terms: unknown term 'warp_drive' (known: position")
    assert "did you mean" not in line and not (tmp_path / "c.yaml").exists()


def test_discover_on_a_window_of_the_recording(tmp_path, capsys):
    """discover --start/--duration: the samples of calibrate geometry's window (the same helper), named in the
    report; a window without samples is one line, as in calibrate geometry."""
    import json

    from imu_array_ros import workflows

    desc, _ = workflows.load_array(ARRAY32)
    expected = len(workflows.read_imu_recording(SAMPLE, desc)[0].window(0.5, 0.5))
    report = tmp_path / "report"
    code, out, err = cli(capsys, "discover", SAMPLE, "--array", ARRAY32, "--start", "0.5", "--duration", "0.5",
                         "--report", report, "--no-plots", "--no-empirical", "--terms", "position,accelerometer_bias",
                         "--max-findings", "1")
    assert code == 0 and out == "", err
    assert f"window: {expected} samples from 0.5 s" in err and 0 < expected < 1000
    assert json.loads((report / "report.json").read_text())["recording"] == f"{SAMPLE}, 0.5 s to 1 s"
    assert (report / "report.md").read_text().startswith(f"# Mismatch discovery: {SAMPLE}, 0.5 s to 1 s\n")
    for command in (["discover", SAMPLE, "--array", ARRAY32, "--report", tmp_path / "none", "--no-plots"],
                    ["calibrate", "geometry", SAMPLE, "--array", ARRAY32, "--out", tmp_path / "g.yaml"]):
        assert_user_error(cli(capsys, *command, "--start", "100", "-q"),
                          f"{SAMPLE}: no samples from 100 s on (the recording spans 1.998 s)")
        assert_user_error(cli(capsys, *command, "--start", "50", "--duration", "2", "-q"),
                          f"{SAMPLE}: no samples between 50 s and 52 s (the recording spans 1.998 s)")
    assert not (tmp_path / "g.yaml").exists() and not (tmp_path / "none" / "report.json").exists()
