"""The one estimator driver: merges the recording's streams in time order, feeds the estimator, logs.

`run_estimator(est, reader, start_ns, end_ns, on_range=, log=)` is how every stage runs a pose source: the
estimator opens the span (reads and checks what it propagates with, initialises), the driver interleaves its
frames (camera frames, odometry messages) with the UWB ranges — a frame first when both have the same stamp —
hands each range to ``on_range`` through the estimator (which brings its state to the range stamp first), and
logs the span's trajectory, covariance and the estimator's own series.
"""

from __future__ import annotations

import ctypes
import glob
import os
from contextlib import contextmanager
from typing import TYPE_CHECKING

import numpy as np

from .estimator import Estimator, RangeHandler, RangeMeasurement

if TYPE_CHECKING:
    from convert.recording import RecordingReader

    from .runlog import RunLog


def run_estimator(
    est: Estimator,
    reader: RecordingReader,
    start_ns: int | None,
    end_ns: int | None,
    *,
    on_range: RangeHandler | None = None,
    log: RunLog | None = None,
) -> None:
    """Process ``[start_ns, end_ns)`` of ``reader`` with ``est`` (None: from the state time / to the end)."""
    with single_blas_thread():
        span = est.open(reader, start_ns, end_ns, trace=log is not None)
        if span is None:
            return
        rng = span.ranges
        nr = len(rng) if rng is not None else 0
        j = 0
        for frame in span.frames:
            t_frame = frame[0]
            while j < nr and rng.t_ns[j] < t_frame:
                est.process_range(_range(rng, j), on_range)
                j += 1
            est.process_frame(frame)
        while j < nr:
            est.process_range(_range(rng, j), on_range)
            j += 1
        est.close(span)
    if log is not None:
        log_history(log, est.history().arrays(), span.first_record)
        est.log_span(log, span)


def _range(rng, j: int) -> RangeMeasurement:
    return RangeMeasurement(
        int(rng.t_ns[j]), int(rng.tag[j]), int(rng.antenna[j]), int(rng.anchor[j]), float(rng.distance[j])
    )


def log_history(log: RunLog, hist: dict[str, np.ndarray], first: int) -> None:
    """world/vio: the poses from index ``first`` on, their position covariance and 3-sigma series."""
    from . import runlog as rl

    t, p, q, cov = (hist[k][first:] for k in ("t_ns", "p", "q_xyzw", "cov"))
    if not len(t):
        return
    sig3 = 3.0 * np.sqrt(np.maximum(np.diagonal(cov, axis1=1, axis2=2), 0))
    step = max(1, len(t) // 500)
    log.trajectory(rl.VIO, t, p, q)
    log.ellipsoid_series(rl.VIO_COV, t[::step], p[::step], cov[::step, 3:6, 3:6])
    log.scalars(f"{rl.SIGMA}/vio_p3sigma", t, sig3[:, 3:6], ["x", "y", "z"])
    log.scalars(f"{rl.SIGMA}/vio_theta3sigma_deg", t, np.degrees(sig3[:, 0:3]), ["x", "y", "z"])


@contextmanager
def single_blas_thread():
    """Run the filter's many small LAPACK calls on one OpenBLAS thread (this thread only).

    Multi-threaded OpenBLAS on small matrices (QRs of a few hundred rows) is much slower on a loaded machine
    than one thread (docs/results/measurements.md). Uses OpenBLAS' thread-local setter of the libraries bundled with numpy/scipy;
    a no-op when they are not found. (threadpoolctl would do the same but is not a dependency.)
    """
    setters = []
    for mod in ("numpy", "scipy"):
        try:
            base = os.path.dirname(__import__(mod).__file__)
            for so in glob.glob(os.path.join(base, os.pardir, f"{mod}.libs", "*openblas*.so*")):
                fn = ctypes.CDLL(so).openblas_set_num_threads_local
                fn.restype, fn.argtypes = ctypes.c_int, [ctypes.c_int]
                setters.append(fn)
        except (OSError, AttributeError, ImportError, TypeError):
            continue
    prev = [fn(1) for fn in setters]
    try:
        yield
    finally:
        for fn, n in zip(setters, prev, strict=True):
            fn(max(n, 1))
