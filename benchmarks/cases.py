"""Benchmark cases. Run one as ``python -m benchmarks.cases NAME [--quick]``: it prints one JSON line with its
own wall time, peak memory and the data seconds it processed. Add a case by registering a function here."""

from __future__ import annotations

import json
import resource
import sys
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path


@dataclass(frozen=True)
class Case:
    fn: Callable[[Path, bool], tuple[float | None, dict]]  # (workdir, quick) -> (data seconds, extra)
    baseline: str | None = None
    help: str = ""


def _calibration(work: Path, quick: bool) -> tuple[float | None, dict]:
    """A fixed numpy + Python workload: the yardstick for cases without a natural baseline."""
    import numpy as np

    rng = np.random.default_rng(0)
    A = rng.normal(size=(120, 120))
    acc = 0.0
    for _ in range(300 if quick else 3000):
        B = A @ A.T
        acc += float(np.linalg.cholesky(B + 120 * np.eye(120))[0, 0])
    return None, {}


def _simulate_mh01(work: Path, quick: bool) -> tuple[float | None, dict]:
    from convert.simulator import SimConfig, simulate_to_file

    duration = 30.0 if quick else None
    cfg = SimConfig(trajectory="MH_01_easy", duration=duration, seed=0)
    simulate_to_file(cfg, work / "mh01.mcap")
    from convert.recording import RecordingReader

    topics = RecordingReader(work / "mh01.mcap").topics()
    info = topics["/imu"]
    return (info.end_ns - info.start_ns) / 1e9, {"imu_msgs": info.count}


def _convert_bag(work: Path, quick: bool) -> tuple[float | None, dict]:
    """Ours vs rosbags-convert on the same synthesised EuRoC-like bag (1 GB; 0.05 GB with --quick)."""
    from .convert_bag import run

    res = run(0.05 if quick else 1.0, work)
    return None, {
        "bag_gb": round(res["bag_bytes"] / 1e9, 3),
        "ours_s": res["uwbcal"]["wall_s"],
        "ours_peak_mb": res["uwbcal"]["peak_rss_mb"],
        "rosbags_convert_s": res["rosbags_convert_sqlite3"]["wall_s"],
        "time_ratio": res["time_ratio_vs_sqlite3"],
    }


CASES: dict[str, Case] = {
    "calibration": Case(_calibration, None, "fixed numpy/Python workload (machine yardstick)"),
    "simulate_mh01": Case(_simulate_mh01, "calibration", "simulate the 182 s of MH_01_easy"),
    "convert_bag": Case(_convert_bag, None, "ROS1 bag -> MCAP beside rosbags-convert (ratio in extra)"),
}


def _main(argv: list[str]) -> int:
    name = argv[0]
    quick = "--quick" in argv
    with tempfile.TemporaryDirectory(prefix=f"uwbcal-bench-{name}-") as tmp:
        t0 = time.perf_counter()
        data_s, extra = CASES[name].fn(Path(tmp), quick)
        wall = time.perf_counter() - t0
    self_kb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    child_kb = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss
    print(
        json.dumps(
            {"wall_s": wall, "peak_rss_mb": max(self_kb, child_kb) / 1024, "data_s": data_s, "extra": extra}
        )
    )
    return 0


if __name__ == "__main__":
    sys.exit(_main(sys.argv[1:]))
