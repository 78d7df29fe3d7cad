"""Simulated recordings with one data-preparation fault each (for `uwbcal check`): an anchor-id swap in the truth,
a mirrored lever arm in the calibration, ranges stamped 0.2 s late."""

from __future__ import annotations

import copy
from pathlib import Path

import numpy as np

from uwbcal.convert.recording import META_CALIBRATION, META_TRUTH
from uwbcal.convert.simulator import SimConfig, simulate, write_recording

LEVER = (0.3, 0.2, 0.1)
FAULTS = ("none", "swap", "mirror", "clock")


def fault_recording(fault: str, path: Path, duration: float = 40.0, seed: int = 3) -> Path:
    cfg = SimConfig(
        duration=duration, camera=False, n_anchors=4, tag_lever_arm=LEVER, beta=1.0, gamma=0.1, seed=seed
    )
    data = simulate(cfg)
    meta = copy.deepcopy(data.metadata)
    if fault == "swap":
        a = meta[META_TRUTH]["anchors"]
        a["1"], a["2"] = a["2"], a["1"]
    elif fault == "mirror":
        meta[META_CALIBRATION]["uwb"]["tags"][str(cfg.tag_id)]["antennas"] = [(-np.asarray(LEVER)).tolist()]
    elif fault == "clock":
        data.ranges.t_ns = data.ranges.t_ns + 200_000_000  # stamped 0.2 s after the range was taken
    data.metadata = meta
    write_recording(data, path)
    return path
