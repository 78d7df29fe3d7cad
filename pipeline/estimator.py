"""What every pose source offers the UWB stages (MSCKF VIO and the external-odometry filter)."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Protocol

import numpy as np

from .core.geometry import rot_to_quat

if TYPE_CHECKING:
    from convert.recording import RecordingReader

    from .runlog import RunLog
    from .state import State


@dataclass(frozen=True)
class RangeMeasurement:
    t_ns: int
    tag: int
    antenna: int
    anchor: int
    distance: float


RangeHandler = Callable[["Estimator", RangeMeasurement], None]


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


class Estimator(Protocol):
    """Everything the stages use of a pose source (MSCKF VIO, external-odometry filter)."""

    state: State
    t_ns: int
    # whether the estimator keeps pose probes (start_probes ... stop_probes) over the initialisation window, so
    # that the anchors' initial covariance gets exact cross-covariances with the poses; False: the probe calls
    # do nothing
    keeps_probes: bool

    @property
    def warnings(self) -> list[str]: ...

    def start_probes(self, period_s: float) -> None: ...

    def add_probe(self) -> None: ...

    def stop_probes(self, remove: bool = True) -> None: ...

    def run(
        self,
        reader: RecordingReader,
        start_ns: int | None,
        end_ns: int | None,
        *,
        on_range: RangeHandler | None = None,
        log: RunLog | None = None,
    ) -> None: ...

    def history(self) -> TrajectoryRecord: ...
