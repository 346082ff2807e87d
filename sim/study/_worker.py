"""Worker-process set-up for the study's process pool.

This module must not import numpy (directly or through a package ``__init__``): a spawned worker unpickles
``init`` before anything else, so the BLAS thread limit set here is in place when numpy is first imported.
With 2 cores and one worker per core, more BLAS threads only oversubscribe the machine. A forked worker
(``engine.start_method``: only from a single-threaded parent, whose BLAS runs one thread already) inherits the
parent's numpy; the limit then only reaches what the worker starts itself.
"""

from __future__ import annotations

import os

_SINGLE_THREAD_ENV = ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS")


def init() -> None:
    """Limit BLAS/OpenMP thread pools of this worker process to one thread each."""
    for name in _SINGLE_THREAD_ENV:
        os.environ[name] = "1"
