"""Thread pools of the BLAS libraries, limited where they measurably get in each other's way.

numpy and scipy each carry an OpenBLAS whose worker threads keep spinning for a while after a
call, and MKL (PARDISO's solves, the fast extra) runs its own threads: on a 2-core machine the
100-mode eigen-solve of the OpenHELP liver spends 3.3 s in PARDISO solves beside spinning
OpenBLAS threads and 2.1 s without them (benchmarks/eigen.py). The limits need threadpoolctl
(part of rtfem[fast]); without it nothing is limited.
"""

from __future__ import annotations

import contextlib
import os

__all__ = ["blas_limits", "usable_cores"]


def usable_cores() -> int:
    """The cores this process may run on."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # macOS, Windows
        return os.cpu_count() or 1


def blas_limits(threads: int, internal_api: str | None = None):
    """A context manager holding the BLAS thread pools (only those of ``internal_api``, e.g.
    "openblas", when given) to ``threads``; it does nothing without threadpoolctl."""
    try:
        from threadpoolctl import ThreadpoolController
    except ImportError:
        return contextlib.nullcontext()
    controller = ThreadpoolController()
    if internal_api is not None:
        controller = controller.select(internal_api=internal_api)
    return controller.limit(limits=int(threads))
