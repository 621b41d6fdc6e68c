"""Discovery's score passes on one BLAS thread (imu_array_ros/discovery/threads.py)."""

from __future__ import annotations

import pytest

from imu_array_ros.discovery.threads import limiter_available, single_blas_thread


def test_the_score_passes_run_on_one_blas_thread():
    threadpoolctl = pytest.importorskip("threadpoolctl")
    assert limiter_available()
    with single_blas_thread():
        inside = [i["num_threads"] for i in threadpoolctl.threadpool_info() if i["user_api"] == "blas"]
    assert inside and all(n == 1 for n in inside)


def test_discover_runs_whole_on_one_blas_thread():
    threadpoolctl = pytest.importorskip("threadpoolctl")
    from imu_array_ros.discovery.discover import discover
    from imu_array_ros.discovery.threads import on_one_blas_thread

    assert discover.__wrapped__ is not None  # discover is the decorated workflow
    seen = []

    @on_one_blas_thread
    def probe():
        seen.extend(i["num_threads"] for i in threadpoolctl.threadpool_info() if i["user_api"] == "blas")
    probe()
    assert seen and all(n == 1 for n in seen)
