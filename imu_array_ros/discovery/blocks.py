"""Time blocks of discovery's block-robust test and held-out folds, and short recordings.

:func:`short_recording_options`: a recording too short for 2 x folds blocks of the default length is analysed
with shorter blocks (never fewer than :data:`MIN_BLOCK_SAMPLES` samples each) and a note says what that costs,
instead of being refused.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from imu_array_ros.errors import CalibrationError

__all__ = ["time_blocks", "short_recording_options", "MIN_BLOCK_SAMPLES"]

#: fewest samples in a time block when a short recording gets shorter blocks
MIN_BLOCK_SAMPLES = 16


def time_blocks(stamps: np.ndarray, block_s: float) -> np.ndarray:
    """(N,) index of the ``block_s``-long time block of every stamp, counted from the first."""
    t = (np.asarray(stamps, dtype=np.int64) - int(stamps[0])) * 1e-9
    return np.floor(t / block_s).astype(np.int64)


def short_recording_options(stamps: np.ndarray, opts, notes: list, say):
    """``opts`` with shorter time blocks when the recording holds fewer than 2 x folds blocks of
    ``opts.block_s`` (the held-out folds need two blocks each): the recording is analysed with the power it has
    and a note says so.  CalibrationError when even blocks of ``MIN_BLOCK_SAMPLES`` samples are too few."""
    need = 2 * opts.folds
    duration = (int(stamps[-1]) - int(stamps[0])) / 1e9 if len(stamps) > 1 else 0.0
    if int(time_blocks(stamps, opts.block_s)[-1]) + 1 >= need:
        return opts
    dt = float(np.median(np.diff(stamps))) / 1e9 if len(stamps) > 1 else 0.0
    block = duration / (need - 0.5)  # need blocks, the last one half as long
    if len(stamps) < need * MIN_BLOCK_SAMPLES or block <= 0:
        raise CalibrationError(f"recording too short for discovery: {len(stamps)} samples ({duration:.3g} s); at "
                               f"least {need} blocks of {MIN_BLOCK_SAMPLES} samples are needed "
                               f"({need * MIN_BLOCK_SAMPLES * dt:.3g} s at this rate); record longer")
    note = (f"short recording ({duration:.3g} s): time blocks of {block:.3g} s instead of {opts.block_s:g} s, so "
            f"that the {opts.folds} held-out folds get two blocks each; residual correlation longer than a block "
            "makes the block-robust test less conservative, and a short recording has less power: a weak effect "
            "may go unfound")
    notes.append(note)
    say(note)
    return replace(opts, block_s=block)
