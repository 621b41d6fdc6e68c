"""BLAS threads of discovery: :func:`~.discover.discover` runs on one (:func:`on_one_blas_thread`).

A score pass (:func:`~imu_array_ros.fitting.score.score_blocks` through :func:`.scopes.score_given`) makes
tens of thousands of small matrix products (per 0.5 s block and IMU: 56 x 186 by 186 x 56 with every
candidate term).  OpenBLAS splits each across its threads; on a machine whose cores are busy with other work
the threads wait for one another and each product takes 10-100x longer than on one thread (measured on 2
cores at load ~4: a 60 s score pass of exp_3 44.5 s with the default threads, 3.4 s with one,
ad hoc, ``benchmarks/results/discovery_speed.md``); the refits' (9 n x M) products do the same (one
linearisation of a 120 s window under the clocked model, load ~4: 3.9 s -> 1.0 s, bit-identical).  So
discover runs on one BLAS thread, with threadpoolctl (a dependency; where it is missing the threads are left
as they are).
"""

from __future__ import annotations

import contextlib
import functools
import importlib.util

__all__ = ["single_blas_thread", "limiter_available", "on_one_blas_thread"]


def limiter_available() -> bool:
    """True when the BLAS thread count can be limited (threadpoolctl importable)."""
    return importlib.util.find_spec("threadpoolctl") is not None


def single_blas_thread():
    """Context manager: BLAS on one thread inside (threadpoolctl), a no-op when it cannot be limited."""
    if not limiter_available():
        return contextlib.nullcontext()
    from threadpoolctl import threadpool_limits

    return threadpool_limits(limits=1, user_api="blas")


def on_one_blas_thread(func):
    """Decorator: ``func`` runs inside :func:`single_blas_thread` (the whole of :func:`~.discover.discover`: its
    refits' products are no better off across threads on a busy machine than the score passes')."""
    @functools.wraps(func)
    def wrapper(*args, **kwargs):
        with single_blas_thread():
            return func(*args, **kwargs)
    return wrapper
