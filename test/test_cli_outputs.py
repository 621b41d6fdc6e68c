"""Outputs never destroy data (issue 5 §3): check_output, atomic_path, and every writing command.

``--force`` replaces only what is itself an output of the kind being written
(an MCAP file, a rosbag2 directory holding only its own files, a YAML/JSON
file); it never replaces an input, something containing or inside an input,
a directory holding other files, the current directory, or through a symlink.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import pytest

from imu_array_ros.cli import main
from imu_array_ros.errors import OutputError
from imu_array_ros.util import files as atomic
from imu_array_ros.io.outputs import check_output
from imu_array_ros.util.files import atomic_path, atomic_write_text
from imu_array_ros.io.rosbag.recording import read_fused_recording, read_imu_recording
from imu_array_ros.model.description import load_description

from conftest import ARRAY32, REPO, START, assert_user_error, cli



def snapshot(root: Path) -> dict:
    """Every path under ``root`` (hidden ones too) with its bytes: what must not change."""
    return {str(p.relative_to(root)): (p.read_bytes() if p.is_file() else None) for p in sorted(root.rglob("*"))}


def leftovers(*dirs: Path) -> list[Path]:
    return [p for d in dirs for p in d.iterdir() if p.name.endswith((".tmp", ".old"))]


@pytest.fixture(scope="module")
def bag(tmp_path_factory):
    """A small simulated rosbag2 directory recording (read-only for the tests: they copy it)."""
    out = tmp_path_factory.mktemp("bag") / "sb"
    assert main(["simulate", "--array", str(ARRAY32), "--out", str(out), "--duration", "0.05", "--rate", "200",
                 "--start-time", START, "-q"]) == 0
    return out


def copy_bag(bag: Path, dest: Path) -> Path:
    """A copy of the bag under a new directory name (metadata lists the data file by its original name)."""
    dest.mkdir(parents=True)
    for p in bag.iterdir():
        (dest / p.name).write_bytes(p.read_bytes())
    return dest


# --------------------------------------------------------------------------- the cases of issue 5 §3, through the CLI


def test_simulate_force_does_not_delete_a_directory_of_other_files(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    victim = tmp_path / "victim"
    victim.mkdir()
    (victim / "thesis.tex").write_text("x\n")
    before = snapshot(tmp_path)
    assert_user_error(cli(capsys, "simulate", "--array", ARRAY32, "--out", "victim", "--duration", 0.1, "--force"),
            "victim", "not a rosbag2 recording", "not replaced")
    assert snapshot(tmp_path) == before
    # a rosbag2 directory with a stranger inside is not replaced either
    (victim / "metadata.yaml").write_text("rosbag2_bagfile_information:\n  relative_file_paths: [victim_0.mcap]\n")
    before = snapshot(tmp_path)
    assert_user_error(cli(capsys, "simulate", "--array", ARRAY32, "--out", "victim", "--duration", 0.1, "--force"),
            "thesis.tex", "not part of its recording")
    assert snapshot(tmp_path) == before


def test_fuse_never_touches_its_input(bag, tmp_path, capsys):
    sb1 = copy_bag(bag, tmp_path / "sb1")
    data = sb1 / "sb_0.mcap"
    before = snapshot(tmp_path)
    # the output directory holds the input file
    assert_user_error(cli(capsys, "fuse", data, "--array", ARRAY32, "--out", sb1, "--force"), "contains the input")
    # the output is the input bag's data file
    assert_user_error(cli(capsys, "fuse", sb1, "--array", ARRAY32, "--out", data, "--force"), "lies inside the input")
    # a new file inside the input bag is refused too (the bag would no longer hold only its own files)
    assert_user_error(cli(capsys, "fuse", sb1, "--array", ARRAY32, "--out", sb1 / "fused.mcap", "--force"), "lies inside the input")
    # the output is the input, directly, through a symlink, through a hard link
    assert_user_error(cli(capsys, "fuse", sb1, "--array", ARRAY32, "--out", sb1, "--force"), "overwrite the input")
    link = tmp_path / "link"
    link.symlink_to(sb1)
    assert_user_error(cli(capsys, "fuse", sb1, "--array", ARRAY32, "--out", link, "--force"), "overwrite the input")
    assert_user_error(cli(capsys, "fuse", link, "--array", ARRAY32, "--out", sb1, "--force"), "overwrite the input")
    hard = tmp_path / "hard.mcap"
    os.link(data, hard)
    assert_user_error(cli(capsys, "fuse", data, "--array", ARRAY32, "--out", hard, "--force"), "overwrite the input")
    # the output is the array description (an input as well)
    assert_user_error(cli(capsys, "fuse", sb1, "--array", ARRAY32, "--out", ARRAY32, "--force"), "overwrite the input")
    after = {k: v for k, v in snapshot(tmp_path).items() if not k.startswith(("link", "hard.mcap"))}
    assert after == before
    assert not leftovers(tmp_path, sb1)


def test_out_dot_and_the_current_directory_are_assert_user_error(bag, tmp_path, monkeypatch, capsys):
    work = tmp_path / "work"
    copy_bag(bag, work)
    monkeypatch.chdir(work)
    before = snapshot(tmp_path)
    for out in (".", "..", str(work), "./", str(tmp_path)):
        assert_user_error(cli(capsys, "fuse", REPO / "bags" / "twist32_sample", "--array", ARRAY32, "--out", out, "--force"))
        assert_user_error(cli(capsys, "simulate", "--array", ARRAY32, "--out", out, "--duration", 0.05, "--force"))
    assert snapshot(tmp_path) == before  # nothing removed, no '..<random>.old' or '.tmp' left behind
    assert_user_error(cli(capsys, "simulate", "--array", ARRAY32, "--out", str(work), "--force"), "current directory")


def test_an_existing_file_named_mcap_that_is_not_mcap_is_kept(tmp_path, capsys):
    fake = tmp_path / "notes.mcap"
    fake.write_text("my notes, not a recording\n")
    assert_user_error(cli(capsys, "simulate", "--array", ARRAY32, "--out", fake, "--duration", 0.05, "--force"),
            "not an MCAP file")
    assert fake.read_text() == "my notes, not a recording\n"
    # a directory recording named like a file, and a file where a directory recording is written
    assert_user_error(cli(capsys, "simulate", "--array", ARRAY32, "--out", tmp_path, "--duration", 0.05, "--force"))
    plain = tmp_path / "thesis.tex"
    plain.write_text("x")
    assert_user_error(cli(capsys, "simulate", "--array", ARRAY32, "--out", plain, "--duration", 0.05, "--force"),
            "not a directory")
    assert plain.read_text() == "x"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["notes.mcap", "thesis.tex"]


def test_symlinked_output_is_assert_user_error(bag, tmp_path, capsys):
    target = tmp_path / "real.mcap"
    assert main(["fuse", str(bag), "--array", str(ARRAY32), "--out", str(target), "-q"]) == 0
    before = target.read_bytes()
    link = tmp_path / "link.mcap"
    link.symlink_to(target)
    assert_user_error(cli(capsys, "fuse", bag, "--array", ARRAY32, "--out", link, "--force"), "symbolic link")
    assert link.is_symlink() and target.read_bytes() == before
    dangling = tmp_path / "dangling.mcap"
    dangling.symlink_to(tmp_path / "nowhere.mcap")
    assert_user_error(cli(capsys, "fuse", bag, "--array", ARRAY32, "--out", dangling), "symbolic link")
    assert not (tmp_path / "nowhere.mcap").exists()


def test_force_replaces_a_recording_of_the_same_kind(bag, tmp_path, capsys):
    """The positive side: with --force an MCAP file and a rosbag2 directory of our own are replaced."""
    out_dir = tmp_path / "sim"
    assert main(["simulate", "--array", str(ARRAY32), "--out", str(out_dir), "--duration", "0.05", "--rate", "200",
                 "--seed", "1", "--start-time", "0", "-q"]) == 0
    assert_user_error(cli(capsys, "simulate", "--array", ARRAY32, "--out", out_dir, "--duration", 0.1, "--rate", 200),
            "already exists", "--force")
    code, _, err = cli(capsys, "simulate", "--array", ARRAY32, "--out", out_dir, "--duration", 0.1, "--rate", 200,
                       "--seed", 2, "--start-time", 0, "--force")
    assert code == 0, err
    samples, _ = read_imu_recording(out_dir, load_description(ARRAY32))
    assert len(samples) == 20  # the new recording, not the old 10-sample one
    assert sorted(p.name for p in out_dir.iterdir()) == ["metadata.yaml", "sim_0.mcap"]
    out_file = tmp_path / "f.mcap"
    for _ in range(2):
        code, _, err = cli(capsys, "fuse", bag, "--array", ARRAY32, "--out", out_file, "--force")
        assert code == 0, err
    assert len(read_fused_recording(out_file)) == 10
    assert not leftovers(tmp_path)


def test_residuals_json_is_not_overwritten_without_force(bag, tmp_path, capsys):
    report = tmp_path / "report.json"
    report.write_text('{"mine": true}\n')
    assert_user_error(cli(capsys, "residuals", bag, "--array", ARRAY32, "--json", report), "already exists", "--force")
    assert report.read_text() == '{"mine": true}\n'
    code, _, err = cli(capsys, "residuals", bag, "--array", ARRAY32, "--json", report, "--force")
    assert code == 0, err
    assert set(json.loads(report.read_text())) == {"recording", "gyroscope_biases"}  # biases tracked by default
    thesis = tmp_path / "thesis.json"
    thesis.write_text("\\documentclass{article}\n")
    assert_user_error(cli(capsys, "residuals", bag, "--array", ARRAY32, "--json", thesis, "--force"), "not a JSON file")
    assert thesis.read_text() == "\\documentclass{article}\n"
    assert_user_error(cli(capsys, "residuals", bag, "--array", ARRAY32, "--json", bag / "metadata.yaml", "--force"),
            "inside the input")
    assert not leftovers(tmp_path)


def test_truth_array_out_is_checked_like_any_output(tmp_path, capsys):
    base = ["simulate", "--array", ARRAY32, "--duration", 0.05, "--rate", 200, "--error-seed", 1]
    array_copy = tmp_path / "array.yaml"
    array_copy.write_bytes(ARRAY32.read_bytes())
    assert_user_error(cli(capsys, *base, "--array", array_copy, "--out", tmp_path / "r.mcap", "--truth-array-out", array_copy,
                "--force"), "--truth-array-out", "overwrite the input")
    assert array_copy.read_bytes() == ARRAY32.read_bytes()
    assert_user_error(cli(capsys, *base, "--out", tmp_path / "r", "--truth-array-out", tmp_path / "r" / "t.yaml"), "overlaps")
    notes = tmp_path / "notes.yaml"
    notes.write_text("just a sentence, not a mapping\n")
    assert_user_error(cli(capsys, *base, "--out", tmp_path / "r.mcap", "--truth-array-out", notes, "--force"), "not a YAML file")
    assert notes.read_text() == "just a sentence, not a mapping\n"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["array.yaml", "notes.yaml"]  # nothing written on refusal
    truth = tmp_path / "truth.yaml"
    code, _, err = cli(capsys, *base, "--out", tmp_path / "r.mcap", "--truth-array-out", truth)
    assert code == 0, err
    assert_user_error(cli(capsys, *base, "--out", tmp_path / "r2.mcap", "--truth-array-out", truth), "already exists")
    code, _, err = cli(capsys, *base, "--out", tmp_path / "r2.mcap", "--truth-array-out", truth, "--force")
    assert code == 0, err


def test_import_openshoe_never_overwrites_its_capture(tmp_path, capsys):
    capture = tmp_path / "exp.bin"
    capture.write_bytes(b"\x00" * 64)
    assert_user_error(cli(capsys, "import-openshoe", capture, "--array", REPO / "config" / "mimu4444bt_corners.yaml",
                "--out", capture, "--force"), "overwrite the input")
    assert capture.read_bytes() == b"\x00" * 64


# --------------------------------------------------------------------------- check_output directly


def test_check_output_rules(bag, tmp_path):
    new = tmp_path / "new" / "deeper" / "out.mcap"
    assert check_output(new, [bag]) == new  # parents are created later, by the writer
    assert check_output(bag, [], "recording", force=True) == bag  # a rosbag2 directory of its own files
    with pytest.raises(OutputError, match="already exists"):
        check_output(bag, [], "recording", force=False)
    with pytest.raises(OutputError, match="is a directory"):
        check_output(bag, [], "json", force=True)
    afile = tmp_path / "afile"
    afile.write_text("x")
    with pytest.raises(OutputError, match="not a directory"):
        check_output(afile / "out.mcap", [])
    yml = tmp_path / "ok.yaml"
    yml.write_text("imu_array: {}\n")
    assert check_output(yml, [], "yaml", force=True) == yml
    js = tmp_path / "ok.json"
    js.write_text("[1, 2]")
    assert check_output(js, [], "json", force=True) == js
    sub = tmp_path / "withdir"
    copy_bag(bag, sub)
    (sub / "extra").mkdir()
    with pytest.raises(OutputError, match="not part of its recording"):
        check_output(sub, [], "recording", force=True)
    with pytest.raises(ValueError, match="unknown output kind"):
        check_output(yml, [], "csv")


# --------------------------------------------------------------------------- atomic_path


def test_atomic_path_refuses_dot_and_leaves_nothing(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "keep.txt").write_text("k")
    for target in (".", "..", "sub/.."):
        with pytest.raises(OutputError, match="not a name"):
            with atomic_path(target, directory=True):
                pytest.fail("must not get here")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["keep.txt"]
    assert not leftovers(tmp_path.parent)


def _old_dir(tmp_path: Path) -> Path:
    target = tmp_path / "rec"
    target.mkdir()
    (target / "old.bin").write_bytes(b"old")
    return target


def test_atomic_directory_is_replaced_only_when_complete(tmp_path):
    target = _old_dir(tmp_path)
    with atomic_path(target, directory=True) as tmp:
        (tmp / "new.bin").write_bytes(b"new")
        assert snapshot(target) == {"old.bin": b"old"}  # still the old one while the new one is being written
    assert snapshot(target) == {"new.bin": b"new"}
    assert sorted(p.name for p in tmp_path.iterdir()) == ["rec"]
    # an error while writing: the old directory stays, the partial new one goes
    with pytest.raises(RuntimeError):
        with atomic_path(target, directory=True) as tmp:
            (tmp / "partial.bin").write_bytes(b"p")
            raise RuntimeError("disk full")
    assert snapshot(target) == {"new.bin": b"new"}
    assert sorted(p.name for p in tmp_path.iterdir()) == ["rec"]


@pytest.mark.parametrize("failing", ["move old aside", "move new in"])
def test_atomic_directory_rename_failure_restores_and_leaves_nothing(tmp_path, monkeypatch, failing):
    """A directory that cannot be renamed (here: os.rename made to fail) keeps its content; no .old/.tmp stay."""
    target = _old_dir(tmp_path)
    real_rename = os.rename

    def rename(src, dst):
        src, dst = Path(src), Path(dst)
        moving_old = src == target and dst.parent.name.endswith(".old")
        moving_new = src.name.endswith(".tmp") and dst == target
        if (failing == "move old aside" and moving_old) or (failing == "move new in" and moving_new):
            raise OSError(16, "Device or resource busy", str(src))
        return real_rename(src, dst)

    monkeypatch.setattr(atomic.os, "rename", rename)
    with pytest.raises(OSError, match="busy"):
        with atomic_path(target, directory=True) as tmp:
            (tmp / "new.bin").write_bytes(b"new")
    assert snapshot(target) == {"old.bin": b"old"}
    assert sorted(p.name for p in tmp_path.iterdir()) == ["rec"]


def test_atomic_file_failure_leaves_nothing(tmp_path):
    target = tmp_path / "adir"
    target.mkdir()
    with pytest.raises(OSError):
        atomic_write_text(target, "cannot replace a directory with a file")
    assert target.is_dir() and sorted(p.name for p in tmp_path.iterdir()) == ["adir"]
    f = tmp_path / "f.json"
    atomic_write_text(f, "1")
    atomic_write_text(f, "2")
    assert f.read_text() == "2" and oct(f.stat().st_mode & 0o777) == "0o644"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["adir", "f.json"]


@pytest.mark.parametrize("command", [["calibrate", m] for m in ("noise", "geometry", "static", "all", "bayes")]
                         + [["calibrate", "fit", "--terms", "gyroscope_bias"], ["discover"]])
def test_an_out_holding_other_imus_is_refused_before_the_work(bag, tmp_path, capsys, monkeypatch, command):
    """--out (--apply for discover) holding a description of other IMUs is refused, with --force too, before
    any calibration or discovery runs; the file is kept as it was."""
    from imu_array_ros import workflows

    def never(*args, **kwargs):
        raise AssertionError("the work ran before the output was checked")

    monkeypatch.setattr(workflows, "calibrate", never)
    monkeypatch.setattr(workflows, "discover", never)
    other = tmp_path / "other.yaml"
    other.write_bytes((REPO / "config" / "mimu4444bt_corners.yaml").read_bytes())
    before = other.read_bytes()
    target = ["--apply", other, "--report", tmp_path / "report"] if command == ["discover"] else ["--out", other]
    assert_user_error(cli(capsys, *command, bag, "--array", ARRAY32, *target, "--force", "-q"),
                      "description of other IMUs", str(other))
    assert other.read_bytes() == before
