"""The one estimator driver: merges the recording's streams in time order, feeds the estimator, logs.

`run_estimator(est, reader, start_ns, end_ns, on_range=, log=)` is how every stage runs a pose source: the
estimator opens the span (reads and checks what it propagates with, initialises), the driver interleaves its
frames (camera frames, odometry messages) with the UWB ranges — a frame first when both have the same stamp —
hands each range to ``on_range`` through the estimator (which brings its state to the range stamp first; a
handler with ``epoch`` gets all ranges of one stamp at once, `Estimator.process_ranges`), and
logs the span's trajectory, covariance and the estimator's own series.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from uwbcal.pipeline.core.blas import single_blas_thread
from uwbcal.pipeline.vio.estimator import (
    Estimator,
    RangeHandler,
    RangeMeasurement,
    epoch_handler,
    same_stamp_end,
)
from uwbcal.pipeline.viz import observers

if TYPE_CHECKING:
    from uwbcal.convert.recording import RecordingReader
    from uwbcal.pipeline.viz.runlog import RunLog


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
        epochs = epoch_handler(on_range)  # dense ranging: the ranges of one stamp in one update
        for frame in span.frames:
            t_frame = frame[0]
            while j < nr and rng.t_ns[j] < t_frame:
                j = _deliver(est, rng, j, on_range, epochs)
            est.process_frame(frame)
        while j < nr:
            j = _deliver(est, rng, j, on_range, epochs)
        est.close(span)
    if log is not None:
        observers.log_span(log, est, span)


def _deliver(est: Estimator, rng, j: int, on_range: RangeHandler | None, epochs: bool) -> int:
    """Range ``j`` (with an epoch handler: every range of its stamp) to the estimator; returns the next index."""
    k = same_stamp_end(rng.t_ns, j) if epochs else j + 1
    if k - j == 1:
        est.process_range(_range(rng, j), on_range)
    else:
        est.process_ranges([_range(rng, i) for i in range(j, k)], on_range)
    return k


def _range(rng, j: int) -> RangeMeasurement:
    return RangeMeasurement(
        int(rng.t_ns[j]), int(rng.tag[j]), int(rng.antenna[j]), int(rng.anchor[j]), float(rng.distance[j])
    )
