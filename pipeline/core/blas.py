"""OpenBLAS thread control for the OpenBLAS copies bundled with numpy and scipy (threadpoolctl would do the same
but is not a dependency). The filters make many small LAPACK calls, for which more than one BLAS thread is
10-100x slower on a loaded 2-core machine, and parallel Monte Carlo workers must not each start one BLAS thread
per core (oversubscription)."""

from __future__ import annotations

import ctypes
import functools
import glob
import os
from collections.abc import Iterator
from contextlib import contextmanager

THREAD_ENV = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")


@functools.cache
def _openblas_functions(*names: str) -> tuple:
    """Per bundled OpenBLAS library, the first of ``names`` it exports (symbol names differ between builds)."""
    fns = []
    for mod in ("numpy", "scipy"):
        try:
            base = os.path.dirname(__import__(mod).__file__)
            libs = glob.glob(os.path.join(base, os.pardir, f"{mod}.libs", "*openblas*.so*"))
        except (ImportError, TypeError):
            continue
        for so in libs:
            try:
                lib = ctypes.CDLL(so)
            except OSError:
                continue
            for name in names:
                fn = getattr(lib, name, None)
                if fn is not None:
                    fn.argtypes = [ctypes.c_int]
                    fn.restype = ctypes.c_int if name.endswith("_local") else None
                    fns.append(fn)
                    break
    return tuple(fns)


@contextmanager
def single_blas_thread() -> Iterator[None]:
    """One OpenBLAS thread for the calling thread inside the block (OpenBLAS' thread-local setter); a no-op
    when the libraries are not found."""
    setters = _openblas_functions("openblas_set_num_threads_local")
    prev = [fn(1) for fn in setters]
    try:
        yield
    finally:
        for fn, n in zip(setters, prev, strict=True):
            fn(max(n, 1))


def limit_blas_threads(n: int = 1) -> None:
    """Process-wide: ``n`` BLAS/OpenMP threads from now on, also for child processes (environment)."""
    for key in THREAD_ENV:
        os.environ[key] = str(n)
    names = (
        "openblas_set_num_threads",
        "scipy_openblas_set_num_threads64_",
        "scipy_openblas_set_num_threads",
    )
    for fn in _openblas_functions(*names):
        fn(n)
