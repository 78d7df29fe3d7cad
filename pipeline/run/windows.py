"""The three time windows of the paper: initialisation, refinement, localisation."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from uwbcal.convert.recording import RecordingReader
from uwbcal.pipeline.core.errors import InputError
from uwbcal.pipeline.core.topics import TOPIC_IMU, TOPIC_ODOM, TOPIC_RANGE


@dataclass(frozen=True)
class Windows:
    start_ns: int
    init_end_ns: int
    refine_end_ns: int
    end_ns: int

    def segment_of(self, t_ns):
        """0 init, 1 refine, 2 localize (vectorised over numpy arrays)."""
        t = np.asarray(t_ns)
        return (t >= self.init_end_ns).astype(np.int8) + (t >= self.refine_end_ns).astype(np.int8)

    def as_dict(self) -> dict[str, float]:
        return {
            "start_s": self.start_ns * 1e-9,
            "init_end_s": self.init_end_ns * 1e-9,
            "refine_end_s": self.refine_end_ns * 1e-9,
            "end_s": self.end_ns * 1e-9,
        }


def split_windows(
    start_ns: int, end_ns: int, init_s: float | None, refine_s: float | None, source: str = "recording"
) -> Windows:
    """Default: thirds of the data, as in the paper's NTU-VIRAL experiments."""
    if end_ns <= start_ns:
        raise InputError(f"{source}: empty time span; nothing to run on")
    span = end_ns - start_ns
    init_ns = int(init_s * 1e9) if init_s else span // 3
    refine_ns = int(refine_s * 1e9) if refine_s else span // 3
    init_end = start_ns + init_ns
    refine_end = min(end_ns, init_end + refine_ns)
    if init_end >= end_ns:
        raise InputError(
            f"{source}: the initialisation window ({init_ns * 1e-9:.1f} s) covers the whole "
            f"recording ({span * 1e-9:.1f} s); shorten run.init_window_s"
        )
    return Windows(start_ns, init_end, refine_end, end_ns)


def recording_windows(reader: RecordingReader, init_s: float | None, refine_s: float | None) -> Windows:
    """The windows over the span where the recording has both ranges and a pose source (IMU or odometry)."""
    topics = reader.topics()
    rec = getattr(reader, "path", "recording")
    if TOPIC_RANGE not in topics:
        raise InputError(f"{rec}: no '{TOPIC_RANGE}' topic; UWB calibration needs ranges")
    src = [t for t in (TOPIC_IMU, TOPIC_ODOM) if t in topics]
    if not src:
        raise InputError(f"{rec}: neither '{TOPIC_IMU}' nor '{TOPIC_ODOM}'; no pose source")
    start = max(topics[TOPIC_RANGE].start_ns, min(topics[t].start_ns for t in src))
    end = min(topics[TOPIC_RANGE].end_ns, max(topics[t].end_ns for t in src))
    return split_windows(start, end, init_s, refine_s, str(rec))
