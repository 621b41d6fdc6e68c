"""Fusion of a whole stream of array samples in bounded chunks.

The command line (``imu-array fuse``/``residuals``) calls :func:`fuse_chunked`
and the fusion node :class:`~imu_array_ros.fusion.live.LiveFusion`, both on
the fusion object :func:`~imu_array_ros.fusion.live.build_fusion` makes.
Each sample is fused on its own, so chunking changes a value only by rounding
(a few vectorised sums run in another order for another batch size: within
1e-12 relative on ``bags/twist32_sample``, test_live_fusion.py).
"""

from __future__ import annotations

from dataclasses import fields
from typing import Callable

import numpy as np

from imu_array_ros.fusion.ml_fusion import FusionStats, MLFusion
from imu_array_ros.model.samples import FusedSamples, ImuSamples

__all__ = ["fuse_chunked", "concatenate_fused", "DEFAULT_CHUNK"]

DEFAULT_CHUNK = 200_000
"""Samples fused per call: bounds the temporary memory (~2.3 kB per sample)."""


def concatenate_fused(parts: list[FusedSamples]) -> FusedSamples:
    """One :class:`FusedSamples` from consecutive parts (every field concatenated)."""
    def cat(name):
        values = [getattr(p, name) for p in parts]
        return None if any(v is None for v in values) else np.concatenate(values)

    return FusedSamples(**{f.name: cat(f.name) for f in fields(FusedSamples)})


def fuse_chunked(fusion: MLFusion, samples: ImuSamples, progress: Callable[[int, int], None] | None = None,
                 chunk: int = DEFAULT_CHUNK) -> tuple[FusedSamples, FusionStats]:
    """Fuse ``samples`` ``chunk`` at a time; ``progress(done, total)`` after each chunk.

    Returns the same numbers as one ``fusion.fuse`` call over all samples (up to rounding).
    """
    if chunk < 1:
        raise ValueError("chunk must be >= 1")
    parts, total = [], FusionStats()
    n = len(samples)
    for lo in range(0, max(n, 1), chunk):
        hi = min(lo + chunk, n)
        fused, stats = fusion.fuse(samples.select(slice(lo, hi)))
        parts.append(fused)
        total.merge(stats)
        if progress is not None:
            progress(hi, n)
    return concatenate_fused(parts), total
