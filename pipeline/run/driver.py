"""The one estimator driver: reads the recording, merges its streams in time order, feeds the estimator, logs.

No estimator opens a file. `msckf_from_recording` / `odometry_from_recording` build a pose source from a
recording's calibration; `run_estimator(est, reader, start_ns, end_ns, on_range=, log=)` is how every stage runs
it: the driver reads the span (the IMU for the MSCKF's `feed_imu`, the odometry for the odometry filter's
`feed_odometry`; the estimator checks it and initialises on the first span), interleaves its frames (camera frames, odometry messages) with the UWB ranges — a frame first when both have the same stamp —
hands each range to ``on_range`` through the estimator (which brings its state to the range stamp first; a
handler with ``epoch`` gets all ranges of one stamp at once, `Estimator.process_ranges`), and
logs the span's trajectory, covariance and the estimator's own series.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from uwbcal.pipeline.core.blas import single_blas_thread
from uwbcal.pipeline.core.errors import InputError
from uwbcal.pipeline.core.noise import OdometryFilterConfig
from uwbcal.pipeline.core.state import ImuState
from uwbcal.pipeline.core.topics import TOPIC_FEATURES, TOPIC_IMU, TOPIC_RANGE
from uwbcal.pipeline.vio.camera import Camera
from uwbcal.pipeline.vio.config import VioConfig
from uwbcal.pipeline.vio.estimator import (
    Estimator,
    RangeHandler,
    RangeMeasurement,
    Span,
    epoch_handler,
    same_stamp_end,
)
from uwbcal.pipeline.vio.groundtruth import groundtruth_state
from uwbcal.pipeline.vio.imu import ImuNoise
from uwbcal.pipeline.vio.msckf import MsckfEstimator
from uwbcal.pipeline.vio.odometry_filter import OdometryEstimator
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
        span = open_span(est, reader, start_ns, end_ns, trace=log is not None)
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


def msckf_from_recording(
    reader: RecordingReader,
    config: VioConfig | None = None,
    initial: ImuState | None = None,
    initial_cov: np.ndarray | None = None,
) -> MsckfEstimator:
    """The MSCKF on the recording's calibration (cam0, IMU noise). ``initial`` (and its 15x15 covariance
    ``initial_cov``, e.g. from the static initialiser) replaces the ground-truth initial state; without
    ``initial_cov`` the vio.sigma_*0 settings are used."""
    config = config or VioConfig()
    src = str(getattr(reader, "path", "recording"))
    calib = reader.calibration
    cam = Camera.from_calibration(calib, "cam0", src)
    noise = ImuNoise.from_calibration(calib, src, config.imu_noise_inflation)
    est = MsckfEstimator(config, cam, noise, initial, initial_cov, source=src)
    if initial is None and not config.init_from_groundtruth:
        raise InputError(
            f"{src}: the MSCKF needs an initial IMU state: set vio.init_from_groundtruth (simulation) or "
            "pass one from the static initialiser"
        )
    return est


def odometry_from_recording(
    reader: RecordingReader, config: OdometryFilterConfig | None = None
) -> OdometryEstimator:
    """The external-odometry filter on the recording's odometry topic and calibration."""
    config = config or OdometryFilterConfig()
    src = str(getattr(reader, "path", "recording"))
    topics = reader.topics()
    if config.topic not in topics or topics[config.topic].count == 0:
        have = ", ".join(sorted(topics)) or "none"
        raise InputError(
            f"{src}: no '{config.topic}' messages (topics: {have}); the odometry pose source needs an "
            "external odometry (convert with poses, or use the MSCKF with IMU + camera)"
        )
    return OdometryEstimator(config, src, getattr(reader, "calibration", None))


def open_span(
    est: Estimator, reader: RecordingReader, start_ns: int | None, end_ns: int | None, *, trace: bool
) -> Span | None:
    """Read ``[start_ns, end_ns)`` of ``reader`` for ``est`` and feed it what it propagates with; the span's
    frames and ranges for the merge (None: nothing to do)."""
    if isinstance(est, MsckfEstimator):
        return _msckf_span(est, reader, start_ns, end_ns, trace)
    return _odometry_span(est, reader, start_ns, end_ns)


def _msckf_span(
    est: MsckfEstimator, reader: RecordingReader, start_ns: int | None, end_ns: int | None, trace: bool
) -> Span:
    """The IMU of ``[start_ns, end_ns)`` (with a margin) fed and checked, the state initialised on the first
    call; the span's frames are the camera feature frames, its ranges those from the state time on."""
    src = str(getattr(reader, "path", est.source))
    topics = reader.topics()
    if TOPIC_IMU not in topics:
        raise InputError(f"{src}: no '{TOPIC_IMU}' topic; the MSCKF needs IMU data")
    first_imu = topics[TOPIC_IMU].start_ns
    start = max(start_ns if start_ns is not None else first_imu, first_imu)
    if est.initialized:
        start = max(start, est.t_ns)
    end = end_ns if end_ns is not None else topics[TOPIC_IMU].end_ns + 1
    margin = int(0.5e9)
    imu = reader.read_imu(TOPIC_IMU, (est.t_ns if est.initialized else start) - margin, end + margin)
    first_run = not est.initialized
    t0 = est.feed_imu(imu.t_ns, imu.gyro, imu.acc, first_imu, src, start, end)
    if t0 is not None:
        est.initialize(t0, est.initial if est.initial is not None else groundtruth_state(reader, t0))
    est.begin(trace)
    f_start = start_ns if first_run else start
    frames = reader.iter_features(TOPIC_FEATURES, f_start, end) if TOPIC_FEATURES in topics else iter(())
    ranges = reader.read_ranges(TOPIC_RANGE, est.t_ns, end) if TOPIC_RANGE in topics else None
    return Span(src, end, frames, ranges if ranges is not None and len(ranges) else None, len(est.history()))


def _odometry_span(
    est: OdometryEstimator, reader: RecordingReader, start_ns: int | None, end_ns: int | None
) -> Span | None:
    """The odometry from the state time on fed (no end: the message after ``end_ns`` interpolates ranges just
    before it), the filter initialised on the first call; the span's frames are the messages after the state
    time and before ``end_ns``, its ranges all of ``[start_ns, end_ns)`` (those outside the odometry are
    counted, not silently lost). None: nothing to do."""
    topic = est.config.topic
    src = str(getattr(reader, "path", est.source))
    topics = reader.topics()
    if topic not in topics or topics[topic].count == 0:
        raise InputError(f"{src}: no '{topic}' messages; the odometry pose source needs them")
    info = topics[topic]
    start = max(start_ns if start_ns is not None else info.start_ns, info.start_ns)
    if est.initialized:
        start = max(start, est.t_ns)
    end = end_ns if end_ns is not None else info.end_ns + 1
    if end <= start:
        return None
    od = reader.read_odometry(topic, est.t_ns if est.initialized else start, None)
    first_record = len(est.history())
    first_run = not est.initialized
    frames = est.feed_odometry(od, src, start, end)
    ranges = None
    if TOPIC_RANGE in topics:
        r_lo = start_ns if start_ns is not None else (None if first_run else est.t_ns + 1)
        rd = reader.read_ranges(TOPIC_RANGE, r_lo, end_ns)
        ranges = rd if len(rd) else None
    return Span(src, end, frames, ranges, first_record)


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
