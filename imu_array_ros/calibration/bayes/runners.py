"""Where the chains run: worker processes, a Dask cluster, or this process.

Each round is one task per chain carrying the chain's state (theta, random numbers, generator,
proposals), so the same code runs anywhere and a chain's draws do not depend on where it ran.
``scheduler``: None or "processes" (worker processes, one BLAS thread each), "local" (a new Dask
``LocalCluster``), "serial" (this process), or the address of a running Dask scheduler.
"""

from __future__ import annotations

import contextlib
import os

from imu_array_ros.calibration.bayes.chain import ChainState, ChunkResult, run_chunk
from imu_array_ros.calibration.bayes.problem import BayesProblem
from imu_array_ros.errors import CalibrationError
from imu_array_ros.util.extras import require

__all__ = ["ChainRunner", "dask_client", "one_thread_blas"]


def _run_task(problem, state, n_iter):  # a top-level function: picklable for processes and Dask
    return run_chunk(problem, state, n_iter)


_INSTALLED: dict = {}


def _install(problem) -> None:
    _INSTALLED["problem"] = problem


def _run_installed(state, n_iter):
    return run_chunk(_INSTALLED["problem"], state, n_iter)


def _noop(_):
    return None


@contextlib.contextmanager
def one_thread_blas():
    """Worker processes inherit one BLAS/OpenMP thread each (chains, not threads, use the cores)."""
    keys = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")
    old = {k: os.environ.get(k) for k in keys}
    os.environ.update({k: "1" for k in keys})
    try:
        yield
    finally:
        for k, v in old.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v


class ChainRunner:
    """Runs one round (a chunk per chain) at a time, where ``scheduler`` says (module docstring).

    Use as a context manager; :meth:`run` (states, n_iter) -> ChunkResults in order.
    """

    def __init__(self, problem: BayesProblem, scheduler: str | None = None, workers: int | None = None,
                 chains: int = 2):
        self.problem = problem
        self.scheduler = scheduler
        self.workers = 1 if scheduler == "serial" else max(1, min(chains, workers or os.cpu_count() or 1))
        self._stack = contextlib.ExitStack()
        self._pool = self._client = self._problem_future = None

    @property
    def kind(self) -> str:
        if self.scheduler in (None, "processes"):
            return "serial" if self.workers == 1 else "processes"
        return "serial" if self.scheduler == "serial" else "dask"

    def __enter__(self) -> "ChainRunner":
        kind = self.kind
        if kind == "processes":
            import multiprocessing
            from concurrent.futures import ProcessPoolExecutor

            with one_thread_blas():
                self._pool = self._stack.enter_context(ProcessPoolExecutor(
                    self.workers, mp_context=multiprocessing.get_context("spawn"), initializer=_install,
                    initargs=(self.problem,)))
                # start the workers now, while the environment says one thread
                list(self._pool.map(_noop, range(self.workers)))
        elif kind == "dask":
            self._client = self._stack.enter_context(dask_client(self.scheduler, self.workers))
            self._problem_future = self._client.scatter(self.problem, broadcast=True)
        return self

    def __exit__(self, *exc) -> None:
        self._stack.close()

    def run(self, states: list[ChainState], n_iter: int) -> list[ChunkResult]:
        kind = self.kind
        if kind == "serial":
            return [run_chunk(self.problem, s, n_iter) for s in states]
        if kind == "processes":
            futures = [self._pool.submit(_run_installed, s, n_iter) for s in states]
            return [f.result() for f in futures]
        futures = [self._client.submit(_run_task, self._problem_future, s, n_iter, pure=False) for s in states]
        return self._client.gather(futures)


@contextlib.contextmanager
def dask_client(scheduler: str, workers: int):
    """A ``dask.distributed`` client: a new LocalCluster of ``workers`` single-threaded processes for
    ``"local"``, else the scheduler at that address (a one-line error when it cannot be reached, or when
    dask.distributed, of the ``[bayes]`` extra, is not installed)."""
    distributed = require("distributed", "bayes", f"scheduler {scheduler}")
    import logging

    logging.getLogger("distributed").setLevel(logging.ERROR)
    if scheduler == "local":
        with one_thread_blas():
            cluster = distributed.LocalCluster(n_workers=workers, threads_per_worker=1, processes=True,
                                               dashboard_address=None, silence_logs=logging.ERROR)
        with cluster, distributed.Client(cluster) as client:
            yield client
        return
    try:
        client = distributed.Client(scheduler, timeout=10)
    except (OSError, ValueError, TimeoutError) as err:
        raise CalibrationError(f"scheduler {scheduler}: cannot connect to a Dask scheduler: {err}") from None
    with client:
        yield client
