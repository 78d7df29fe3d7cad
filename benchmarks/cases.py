"""Benchmark cases. Run one as ``python -m uwbcal.benchmarks.cases NAME [--quick]``: it prints one JSON line with its
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

from uwbcal.benchmarks import convert_bag
from uwbcal.convert.recording import RecordingReader
from uwbcal.convert.simulator import SimConfig, simulate_to_file
from uwbcal.evaluate.evaluation import evaluate_stage
from uwbcal.evaluate.experiments.table1 import experiment as _table1
from uwbcal.pipeline.run import artefacts
from uwbcal.pipeline.run.config import load_config
from uwbcal.pipeline.run.stages.pipeline import Pipeline


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


def _calibration_x2(work: Path, quick: bool) -> tuple[float | None, dict]:
    """The calibration workload in two processes at once: the machine's own ceiling for two jobs (ratio to
    ``calibration`` 1.0 = two independent cores; a ``--jobs 2`` speed-up cannot exceed 2 / this ratio)."""
    import multiprocessing as mp

    procs = [mp.get_context("fork").Process(target=_calibration, args=(work, quick)) for _ in range(2)]
    for proc in procs:
        proc.start()
    for proc in procs:
        proc.join()
    return None, {}


def _simulate_mh01(work: Path, quick: bool) -> tuple[float | None, dict]:

    duration = 30.0 if quick else None
    cfg = SimConfig(trajectory="MH_01_easy", duration=duration, seed=0)
    simulate_to_file(cfg, work / "mh01.mcap")

    topics = RecordingReader(work / "mh01.mcap").topics()
    info = topics["/imu"]
    return (info.end_ns - info.start_ns) / 1e9, {"imu_msgs": info.count}


def _convert_bag(work: Path, quick: bool) -> tuple[float | None, dict]:
    """Ours vs rosbags-convert on the same synthesised EuRoC-like bag (1 GB; 0.05 GB with --quick)."""

    res = convert_bag.run(0.05 if quick else 1.0, work)
    return None, {
        "bag_gb": round(res["bag_bytes"] / 1e9, 3),
        "ours_s": res["uwbcal"]["wall_s"],
        "ours_peak_mb": res["uwbcal"]["peak_rss_mb"],
        "rosbags_convert_s": res["rosbags_convert_sqlite3"]["wall_s"],
        "time_ratio": res["time_ratio_vs_sqlite3"],
        "ours_cpu_s": res["uwbcal"]["cpu_s"],
        "rosbags_convert_cpu_s": res["rosbags_convert_sqlite3"]["cpu_s"],
        "cpu_ratio": res["cpu_ratio_vs_sqlite3"],
    }


def _simulate(work: Path, name: str, **kw) -> Path:

    rec = work / f"{name}.mcap"
    simulate_to_file(SimConfig(**kw), rec)
    return rec


_TIMED_CPU: list[float] = []  # CPU seconds of a case's timed part (this process and its finished children)


def _cpu_s() -> float:
    """User + system CPU of this process and of its children that have finished (workers, the log helper)."""
    me, ch = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    return me.ru_utime + me.ru_stime + ch.ru_utime + ch.ru_stime


def _pipeline(rec: Path, out: Path, log: bool, stages: list[str] | None = None) -> float:
    """Run the pipeline on a recording; returns the timed seconds (simulation excluded)."""

    over: dict = {"run": {"recording": str(rec), "log": log}}
    if stages:
        over["run"]["stages"] = stages
    t0, c0 = time.perf_counter(), _cpu_s()
    Pipeline(load_config(None, over), out, evaluate_stage).run(progress=lambda *_: None)
    _TIMED_CPU.append(_cpu_s() - c0)
    return time.perf_counter() - t0


def _vio_mh01(work: Path, quick: bool) -> tuple[float | None, dict]:
    dur = 30.0 if quick else None
    rec = _simulate(work, "mh01", trajectory="MH_01_easy", duration=dur, seed=0)
    timed = _pipeline(rec, work / "run", log=False, stages=["vio"])
    data_s = _span(rec)
    frames = artefacts.read_json(work / "run" / "stages.json", artefacts.STAGES)
    return data_s, {
        "timed_s": round(timed, 2),
        "ms_per_camera_update": round(1e3 * timed / (20 * data_s), 2),
        "summary": frames["vio"]["summary"],
    }


def _span(rec: Path) -> float:

    a, b = RecordingReader(rec).time_span()
    return (b - a) * 1e-9


def _full_run(log: bool):
    def case(work: Path, quick: bool) -> tuple[float | None, dict]:
        dur = 40.0 if quick else None
        rec = _simulate(work, "mh01", trajectory="MH_01_easy", duration=dur, seed=0)
        timed = _pipeline(rec, work / "run", log=log)
        return _span(rec), {"timed_s": round(timed, 2)}

    return case


def _table1_jobs(jobs: int):
    def case(work: Path, quick: bool) -> tuple[float | None, dict]:

        t0, c0 = time.perf_counter(), _cpu_s()
        _table1(work, 2, jobs, None, 0, trajectory=None, duration=30.0 if quick else 60.0)
        _TIMED_CPU.append(_cpu_s() - c0)
        return None, {"timed_s": round(time.perf_counter() - t0, 2), "runs": 2}

    return case


def _growth(anchors: int, length: float):
    def case(work: Path, quick: bool) -> tuple[float | None, dict]:
        base = 10.0 if quick else 25.0  # 4x must fit in the 120 s built-in trajectory
        rec = _simulate(work, "g", trajectory=None, duration=base * length, seed=0, n_anchors=anchors)
        timed = _pipeline(rec, work / "run", log=False)
        return _span(rec), {"timed_s": round(timed, 2), "anchors": anchors, "length_x": length}

    return case


CASES: dict[str, Case] = {
    "calibration": Case(_calibration, None, "fixed numpy/Python workload (machine yardstick)"),
    "calibration_x2": Case(
        _calibration_x2, "calibration", "the yardstick twice at once (ratio: 1.0 = two free cores)"
    ),
    "simulate_mh01": Case(_simulate_mh01, "calibration", "simulate the 182 s of MH_01_easy"),
    "convert_bag": Case(_convert_bag, None, "ROS1 bag -> MCAP beside rosbags-convert (ratio in extra)"),
    "vio_mh01": Case(_vio_mh01, "calibration", "MSCKF VIO on simulated MH_01_easy"),
    "run_log_off": Case(_full_run(False), None, "full pipeline on simulated MH_01_easy, --no-log"),
    "run_log_on": Case(_full_run(True), "run_log_off", "full pipeline with rerun logging (ratio = overhead)"),
    "table1_jobs1": Case(_table1_jobs(1), None, "table1, 2 seeds, 60 s, --jobs 1"),
    "table1_jobs2": Case(
        _table1_jobs(2), "table1_jobs1", "table1, 2 seeds, 60 s, --jobs 2 (ratio = 1/speed-up)"
    ),
    "growth_a1_x1": Case(_growth(1, 1), None, "full pipeline, 1 anchor, 1x length"),
    "growth_a4_x1": Case(_growth(4, 1), "growth_a1_x1", "4 anchors"),
    "growth_a16_x1": Case(_growth(16, 1), "growth_a1_x1", "16 anchors"),
    "growth_a4_x2": Case(_growth(4, 2), "growth_a4_x1", "4 anchors, 2x length"),
    "growth_a4_x4": Case(_growth(4, 4), "growth_a4_x1", "4 anchors, 4x length"),
}


def _main(argv: list[str]) -> int:
    name = argv[0]
    quick = "--quick" in argv
    with tempfile.TemporaryDirectory(prefix=f"uwbcal-bench-{name}-") as tmp:
        t0, c0 = time.perf_counter(), _cpu_s()
        data_s, extra = CASES[name].fn(Path(tmp), quick)
        # a case may time only its own part (e.g. without simulating its input)
        wall = extra.pop("timed_s", None) or (time.perf_counter() - t0)
        cpu = _TIMED_CPU[-1] if _TIMED_CPU else _cpu_s() - c0
    self_kb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    child_kb = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss
    print(
        json.dumps(
            {
                "wall_s": wall,
                "cpu_s": cpu,
                "peak_rss_mb": max(self_kb, child_kb) / 1024,
                "data_s": data_s,
                "extra": extra,
            }
        )
    )
    return 0


if __name__ == "__main__":
    sys.exit(_main(sys.argv[1:]))
