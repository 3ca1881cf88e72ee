"""Thread counts set deliberately: one compute thread per process where one is enough.

The planner's work is small dense and sparse algebra (a few hundred variables); BLAS threads
only spin on it, and beside a second benchmark worker on two cores they double the CPU time of
a step (5.79 ms CPU for 2.83 ms wall with the default pools, 2.81 for 2.71 with
one, as issue 22 measured). :func:`limit_threads` caps every pool a process may use:

- the BLAS / OpenMP pools NumPy and SciPy loaded (through ``threadpoolctl``, at run time);
- the ``OMP_NUM_THREADS`` / ``OPENBLAS_NUM_THREADS`` / ``MKL_NUM_THREADS`` environment, for
  libraries loaded later and for child processes;
- Open3D's pool (``open3d.utility.set_max_threads``, the ESDF's depth integration), when
  Open3D is already imported;
- PyTorch's intra-op pool (``torch.set_num_threads``), when torch is already imported.

OSQP (QDLDL) and the compiled step data are single-threaded already. Library code never calls
this on import; entry points do (the benchmark workers, ``experiments/bench_planner.py``).
"""

from __future__ import annotations

import logging
import os
import sys

__all__ = ["limit_threads", "thread_report"]

logger = logging.getLogger(__name__)

_ENV = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMEXPR_NUM_THREADS")
_limiter = None  # keeps the threadpoolctl limits alive for the process


def limit_threads(n: int = 1) -> dict:
    """Cap every compute thread pool of this process at ``n`` (>= 1); returns :func:`thread_report`."""
    global _limiter
    if isinstance(n, bool) or not isinstance(n, int) or n < 1:
        raise ValueError(f"thread count must be an int >= 1, got {n!r}")
    for name in _ENV:
        os.environ[name] = str(n)
    try:
        from threadpoolctl import threadpool_limits

        _limiter = threadpool_limits(limits=n)
    except ImportError:  # pragma: no cover - a declared dependency
        logger.warning("threadpoolctl missing: BLAS pools already loaded keep their size")
    o3d = sys.modules.get("open3d")
    if o3d is not None and hasattr(o3d.utility, "set_max_threads"):
        o3d.utility.set_max_threads(n)
    torch = sys.modules.get("torch")
    if torch is not None:
        torch.set_num_threads(n)
    return thread_report()


def thread_report() -> dict:
    """Current pool sizes: ``{"blas": {api: threads}, "env": {...}, "open3d": n, "torch": n}``."""
    out: dict = {"env": {k: os.environ.get(k) for k in _ENV}}
    try:
        from threadpoolctl import threadpool_info

        out["blas"] = {f"{i['internal_api']}:{i.get('prefix', '')}": i["num_threads"] for i in threadpool_info()}
    except ImportError:  # pragma: no cover
        out["blas"] = {}
    o3d = sys.modules.get("open3d")
    if o3d is not None and hasattr(o3d.utility, "get_max_threads"):
        out["open3d"] = int(o3d.utility.get_max_threads())
    torch = sys.modules.get("torch")
    if torch is not None:
        out["torch"] = int(torch.get_num_threads())
    return out
