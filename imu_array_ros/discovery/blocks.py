"""Time blocks of discovery's block-robust test and held-out folds, short recordings, and the subsample a long
recording is searched on first.

:func:`short_recording_options`: a recording too short for 2 x folds blocks of the default length is analysed
with shorter blocks (never fewer than :data:`MIN_BLOCK_SAMPLES` samples each) and a note says what that costs,
instead of being refused.

:func:`search_rungs`: a recording of more than ``budget`` readings (samples x IMUs), and of more than
:data:`LADDER_FROM`, is searched first on every k-th time block, evenly spread over it (every regime in its share),
so that the exact refits of its strong effects cost a k-th, then on every (k/2)-th, ... and the whole recording,
each only when the one before runs out of candidates; the blocks are chosen by their place in time alone, so every test on them keeps its false-finding
rate (:func:`~.discover.discover` says how the rate is shared between the rungs).
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from imu_array_ros.errors import CalibrationError

__all__ = ["time_blocks", "short_recording_options", "search_rungs", "MIN_BLOCK_SAMPLES", "SEARCH_READINGS",
           "LADDER_FROM"]

#: fewest samples in a time block when a short recording gets shorter blocks
MIN_BLOCK_SAMPLES = 16
#: a recording of more readings (samples x IMUs) than this is searched on an evenly spread subsample of its blocks
#: first (:func:`search_rungs`); the exact refits' cost grows with the readings (a refit of the clocked model
#: on the whole 10-minute exp_3 capture, 300,000 readings, took 10-25 min)
SEARCH_READINGS = 40_000
#: ... but only a recording of more readings than this: below it the subsamples' extra looks cost more than their
#: smaller refits save, and a subsample's lower evidence can change which of two confounded terms wins
#: (randomised suite, seed 161454, 45 recordings of 40,000-120,000 readings: discover 1.45x slower, 3 of 45
#: answers changed, 2 for the worse; benchmarks/results/discovery_subsample_161454.md)
LADDER_FROM = 150_000


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


def search_rungs(blocks: np.ndarray, n_imus: int, budget: int | None, folds: int, start: int = LADDER_FROM) -> list:
    """The subsamples a long recording is searched on before the whole of it, smallest first: [(sample indexes,
    their blocks renumbered 0 .. nb'-1, k)] of every k-th time block (the first included: the model's drifts and
    clocks count from the first stamp) for k = k0, k0 // 2, ... > 1, k0 the least that brings the readings
    (samples x ``n_imus``) within ``budget``.  Empty when the recording is within ``budget`` or ``start``,
    ``budget`` is None, or a subsample would hold fewer than 2 x ``folds`` blocks (the held-out folds need two)."""
    blocks = np.asarray(blocks)
    if budget is None or len(blocks) * n_imus <= max(budget, start):
        return []
    nb = int(blocks[-1]) + 1
    k = int(np.ceil(len(blocks) * n_imus / budget))
    if -(-nb // k) < 2 * folds:
        return []
    rungs = []
    while k > 1:
        index = np.flatnonzero(blocks % k == 0)
        _, renumbered = np.unique(blocks[index], return_inverse=True)
        rungs.append((index, renumbered.astype(np.int64), k))
        k //= 2
    return rungs
