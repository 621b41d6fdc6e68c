"""Short recordings are analysed with the power they have (issue 23, item 8), not refused."""

from __future__ import annotations

import json

import numpy as np
import pytest

from imu_array_ros.discovery.blocks import MIN_BLOCK_SAMPLES, short_recording_options, time_blocks
from imu_array_ros.discovery.discover import DiscoveryOptions
from imu_array_ros.errors import CalibrationError

from conftest import REPO, cli


def stamps(seconds: float, rate: float) -> np.ndarray:
    return (np.arange(int(round(seconds * rate))) * (1e9 / rate)).astype(np.int64)


def test_long_recordings_keep_their_blocks_short_ones_get_shorter_blocks():
    opts, notes = DiscoveryOptions(), []
    assert short_recording_options(stamps(30, 100), opts, notes, print) is opts and notes == []
    short = short_recording_options(stamps(2, 500), opts, notes, lambda text: None)
    blocks = time_blocks(stamps(2, 500), short.block_s)
    counts = np.bincount(blocks)
    assert len(counts) == 2 * opts.folds and counts.min() >= MIN_BLOCK_SAMPLES  # two blocks per fold
    assert short.block_s < opts.block_s and short.folds == opts.folds and len(notes) == 1
    assert "short recording" in notes[0] and "less power" in notes[0]


def test_a_recording_too_short_even_for_short_blocks_is_refused_in_one_line():
    with pytest.raises(CalibrationError,
                       match=r"too short for discovery: 100 samples \(0.99 s\); at least 8 blocks of 16 samples"):
        short_recording_options(stamps(1, 100), DiscoveryOptions(), [], lambda text: None)


def test_the_shipped_sample_is_analysed(tmp_path, capsys):
    report = tmp_path / "report"
    code, _, err = cli(capsys, "discover", REPO / "bags" / "twist32_sample", "--array", REPO / "config" / "array32.yaml",
                       "--report", report, "--no-plots", "--no-empirical")
    assert code == 0, err
    assert "short recording (2 s)" in err
    data = json.loads((report / "report.json").read_text())
    assert any("short recording" in n for n in data["notes"])


def test_apply_inside_the_report_directory_is_refused(tmp_path, capsys):
    from conftest import assert_user_error

    report = tmp_path / "report"
    assert_user_error(cli(capsys, "discover", REPO / "bags" / "twist32_sample", "--array",
                          REPO / "config" / "array32.yaml", "--report", report, "--apply", report / "cal.yaml"),
                      "--apply overlaps --report")
    assert not report.exists()
