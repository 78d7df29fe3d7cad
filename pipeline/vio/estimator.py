"""What every pose source offers the UWB stages (MSCKF VIO and the external-odometry filter)."""

from __future__ import annotations

from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Protocol

import numpy as np

from uwbcal.pipeline.core.geometry import rot_to_quat

if TYPE_CHECKING:
    from uwbcal.convert.recording import RangeData
    from uwbcal.pipeline.core.state import State


@dataclass(frozen=True)
class RangeMeasurement:
    t_ns: int
    tag: int
    antenna: int
    anchor: int
    distance: float


RangeHandler = Callable[["Estimator", RangeMeasurement], None]


def epoch_handler(handler: RangeHandler | None) -> bool:
    """A handler that also takes all ranges of one stamp at once (``handler.epoch(estimator, batch)``, e.g.
    `uwb_filter.UwbUpdater`: one stacked update per epoch)."""
    return callable(getattr(handler, "epoch", None))


def same_stamp_end(t_ns: np.ndarray, j: int) -> int:
    """End (exclusive) of the run of ranges with the stamp of range ``j`` (the ranges are time ordered)."""
    return int(np.searchsorted(t_ns, t_ns[j], side="right"))


@dataclass
class TrajectoryRecord:
    """Pose estimates with 6x6 pose covariance (error [dtheta, dp]), appended during a run."""

    t_ns: list[int] = field(default_factory=list)
    p: list[np.ndarray] = field(default_factory=list)
    R: list[np.ndarray] = field(default_factory=list)  # turned into quaternions in one batch by arrays()
    cov: list[np.ndarray] = field(default_factory=list)

    def append(self, t_ns: int, R: np.ndarray, p: np.ndarray, cov6: np.ndarray) -> None:
        if self.t_ns and t_ns <= self.t_ns[-1]:
            if t_ns == self.t_ns[-1]:  # the same instant twice (a range at a camera stamp): keep the newest
                self.p[-1], self.R[-1], self.cov[-1] = (
                    np.array(p, float),
                    np.array(R, float),
                    np.array(cov6, float),
                )
            return
        self.t_ns.append(int(t_ns))
        self.p.append(np.array(p, float))
        self.R.append(np.array(R, float))
        self.cov.append(np.array(cov6, float))

    def __len__(self) -> int:
        return len(self.t_ns)

    def arrays(self) -> dict[str, np.ndarray]:
        n = len(self.t_ns)
        return {
            "t_ns": np.asarray(self.t_ns, dtype=np.int64),
            "p": np.asarray(self.p, float).reshape(n, 3),
            "q_xyzw": rot_to_quat(np.asarray(self.R, float).reshape(n, 3, 3)).reshape(n, 4),
            "cov": np.asarray(self.cov, float).reshape(n, 6, 6),
        }


@dataclass
class Span:
    """The stretch of the recording the driver processes (`driver.open_span`)."""

    source: str  # the recording, for messages
    end_ns: int
    frames: Iterable[Any]  # the estimator's own measurements in time order (first item: t_ns): camera frames
    # (MSCKF), odometry messages (odometry filter)
    ranges: RangeData | None  # the ranges of the span, in time order
    first_record: int  # len(history()) at the start: the driver logs the span's part of the history


class Estimator(Protocol):
    """Everything the stages and the driver use of a pose source (MSCKF VIO, external-odometry filter).

    The estimator is fed and opens no file: the driver reads what it propagates with (IMU, odometry) and feeds it
    (the estimator checks it and initialises), then merges `Span.frames` and `Span.ranges` in time order and
    calls `process_frame` / `process_range` (a frame first when both have the same stamp), then `close`; a log
    observes it from outside (`viz.observers.log_span`)."""

    state: State
    t_ns: int
    # whether the estimator keeps pose probes (start_probes ... stop_probes) over the initialisation window, so
    # that the anchors' initial covariance gets exact cross-covariances with the poses; False: the probe calls
    # do nothing
    keeps_probes: bool

    @property
    def warnings(self) -> list[str]: ...

    def span_warnings(self, stage: str, start_ns: int | None, end_ns: int | None, t0_ns: int) -> list[str]:
        """What the estimator's own updates over ``[start_ns, end_ns)`` (the stretch ``stage`` ran; the
        estimator may carry earlier stages' records through a checkpoint) say about its consistency, times in s
        after ``t0_ns`` (the MSCKF: its visual updates' chi2 rejection rate; the odometry filter: nothing)."""
        ...

    def propagate_to(self, t_ns: int) -> None: ...

    def process_frame(self, frame: Any) -> None: ...

    def process_range(self, m: RangeMeasurement, on_range: RangeHandler | None) -> None: ...

    def process_ranges(self, batch: list[RangeMeasurement], on_range: RangeHandler) -> None:
        """All ranges of one stamp (more than one) for an epoch handler (`epoch_handler`): propagate to the stamp
        and record once, ``on_range.epoch(self, batch)`` once."""
        ...

    def close(self, span: Span) -> None: ...

    def history(self) -> TrajectoryRecord: ...

    def start_probes(self, period_s: float) -> None: ...

    def add_probe(self) -> None: ...

    def stop_probes(self, remove: bool = True) -> None: ...
