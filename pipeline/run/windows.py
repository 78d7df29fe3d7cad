"""The three time windows of the paper: initialisation, refinement, localisation."""

from __future__ import annotations

from dataclasses import dataclass

from uwbcal.pipeline.core.errors import InputError


@dataclass(frozen=True)
class Windows:
    start_ns: int
    init_end_ns: int
    refine_end_ns: int
    end_ns: int

    def segment_of(self, t_ns):
        """0 init, 1 refine, 2 localize (vectorised over numpy arrays)."""
        import numpy as np

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
