"""Thread pools of the numeric libraries, set deliberately.

On 2 cores OpenBLAS's default threads spin after each matrix product and made plain numpy code
several times slower next to other work (measured: p90 80 ms for a 10 ms deprojection). Every
hapticloud process therefore runs BLAS/OpenMP single-threaded unless told otherwise; the work is
parallel across cameras and processes, not inside a matrix product.
"""

from __future__ import annotations

import os

_VARS = ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS", "BLIS_NUM_THREADS")


def set_environment(threads: int = 1) -> None:
    """Set the thread-count variables for this process (effective before numpy is imported)."""
    for var in _VARS:
        os.environ.setdefault(var, str(threads))


def limit_blas_threads(threads: int = 1) -> object:
    """Limit already-loaded BLAS/OpenMP pools to ``threads``; returns the threadpoolctl handle."""
    from threadpoolctl import threadpool_limits

    return threadpool_limits(limits=threads)
