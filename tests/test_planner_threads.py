"""Thread counts set deliberately: the planner's pools and the benchmark workers'."""

from __future__ import annotations

import concurrent.futures as cf
import logging
import multiprocessing as mp

import pytest

from onfly.bench.runner import BenchConfigError, _worker_init, worker_threads
from planning.threads import limit_threads, thread_report


def _report_after_import() -> dict:
    import open3d  # noqa: F401  (the ESDF's library, loaded by an episode)

    from planning.threads import thread_report as report

    return report()


def test_limit_threads_caps_blas_and_the_environment():
    import numpy  # noqa: F401

    rep = limit_threads(1)
    assert rep["blas"] and set(rep["blas"].values()) == {1}
    assert rep["env"]["OMP_NUM_THREADS"] == "1" and rep["env"]["OPENBLAS_NUM_THREADS"] == "1"
    with pytest.raises(ValueError, match="thread count"):
        limit_threads(0)


def test_benchmark_workers_start_with_one_thread_per_pool():
    ctx = mp.get_context("spawn")
    with cf.ProcessPoolExecutor(1, mp_context=ctx, initializer=_worker_init, initargs=(logging.WARNING, 1)) as pool:
        rep = pool.submit(_report_after_import).result(timeout=300)
    assert set(rep["blas"].values()) == {1}
    assert rep["open3d"] == 1  # imported after the limit: OpenMP read OMP_NUM_THREADS = 1
    assert rep["env"]["OMP_NUM_THREADS"] == "1"


def test_worker_thread_count_from_the_environment(monkeypatch):
    monkeypatch.delenv("ONFLY_WORKER_THREADS", raising=False)
    assert worker_threads() == 1
    monkeypatch.setenv("ONFLY_WORKER_THREADS", "2")
    assert worker_threads() == 2
    monkeypatch.setenv("ONFLY_WORKER_THREADS", "two")
    with pytest.raises(BenchConfigError, match="ONFLY_WORKER_THREADS"):
        worker_threads()
