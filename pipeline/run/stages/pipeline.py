"""The staged pipeline: frontend -> vio -> init -> refine -> localize -> evaluate.

`Pipeline` owns one run directory and runs the stages of `stages.REGISTRY` in order; each stage is one module
of `pipeline/run/stages/` (``run(ctx) -> StageResult``), reads the recording and the artefacts of the stage before
(never in-memory state), writes its own artefacts atomically and its own rerun log; a failing stage leaves the
earlier artefacts untouched, and each stage can be re-run alone.
"""

from __future__ import annotations

import dataclasses
import logging
import time
from pathlib import Path

from uwbcal.convert.calibration import parse_calibration
from uwbcal.convert.info import calibration_problems, clock_jumps, nan_problems
from uwbcal.convert.recording import TOPIC_IMU, TOPIC_ODOM, TOPIC_RANGE, RecordingReader
from uwbcal.pipeline.core.atomic import sweep_stale
from uwbcal.pipeline.core.errors import InputError
from uwbcal.pipeline.core.names import STAGES
from uwbcal.pipeline.run import artefacts
from uwbcal.pipeline.run import rundir as rd
from uwbcal.pipeline.run.config import PipelineConfig, load_config
from uwbcal.pipeline.run.context import Evaluator, StageContext, StageResult
from uwbcal.pipeline.run.provenance import claim, record_stage, recording_record
from uwbcal.pipeline.run.resolve import resolve
from uwbcal.pipeline.run.stages import REGISTRY
from uwbcal.pipeline.viz.log_server import start_log_server

_log = logging.getLogger(__name__)


class Pipeline:
    def __init__(self, config: PipelineConfig, run_dir: Path, evaluator: Evaluator | None = None) -> None:
        self.ctx = StageContext(config, run_dir, evaluator)
        self.shown_warnings: set[str] = set()
        self.recording: dict = {}  # provenance.recording_record of this run's recording (set by run)

    @property
    def config(self) -> PipelineConfig:
        return self.ctx.config

    @property
    def dir(self) -> rd.RunDir:
        return self.ctx.dir

    @property
    def results_text(self) -> str:
        return self.ctx.results_text

    def run(
        self, stages: list[str] | None = None, progress=print, overwrite: bool = False
    ) -> list[StageResult]:
        """The stages, under the run-directory lock; config.toml and stages.json are written after each stage
        that succeeds (`provenance`); temporary files of an interrupted earlier run are removed first, and a
        directory of another recording is refused (``overwrite``: its artefacts are removed, `provenance.claim`)."""
        ctx = self.ctx
        stages = list(ctx.config.run.stages) if stages is None else list(stages)
        if not stages:
            raise InputError(f"--stages: no stage given; choose from {', '.join(STAGES)}")
        ctx.stages = list(stages)
        with rd.run_lock(ctx.dir.path) as stale_pid:
            if stale_pid is not None:
                progress(f"note: took over the lock of an interrupted run (pid {stale_pid}, not running)")
            removed = sweep_stale(ctx.dir.path)
            if removed:
                names = ", ".join(p.name for p in removed[:3]) + (" ..." if len(removed) > 3 else "")
                progress(f"note: removed {len(removed)} temporary file(s) of an interrupted run ({names})")
            self.recording = recording_record(ctx.recording)
            stale = claim(ctx.dir, self.recording, stages, overwrite)
            if stale:
                progress(f"note: --overwrite: removed {len(stale)} artefact(s) of another recording")
            ctx.reader.check_schemas()
            parse_calibration(ctx.reader.calibration, f"{ctx.recording}: uwbcal.calibration")
            for w in ctx.reader.warnings:  # once here; the results table leaves them out (run_cli)
                progress(f"warning: {w}")
                self.shown_warnings.add(f"warning: {w}")
            resolved = resolve(ctx.config, ctx.reader)
            ctx.config, ctx.choices = resolved.config, resolved.summary()
            for c in resolved.choices:
                _log.info("%s", c)
            if any(s != "frontend" for s in stages):
                ctx.windows()  # the recording has what the stages need (ranges, a pose source): fail before any
                check_values(ctx)
            results = []
            if ctx.config.run.log and ctx.config.run.log_process:
                ctx.log_server = start_log_server()
            try:
                for name, stage in REGISTRY.items():
                    if name not in stages:
                        continue
                    t0 = time.perf_counter()
                    res = dataclasses.replace(stage(ctx), wall_s=time.perf_counter() - t0)
                    results.append(res)
                    self._record_stage(res)
                    progress(f"[{name}] {res.summary} ({res.wall_s:.1f} s)")
            finally:
                server, ctx.log_server = ctx.log_server, None
                try:
                    if ctx.config.run.log:
                        ctx.dir.merge_rrd(ctx.run_kind(), server)
                finally:
                    if server is not None:
                        server.stop()
        return results

    def _record_stage(self, res: StageResult) -> None:

        entry = {"wall_s": res.wall_s, "summary": res.summary, "warnings": res.warnings}
        res.warnings += record_stage(
            self.dir, res.stage, entry, self.config, self.ctx.stages, self.recording, self.ctx.choices
        )


def check_values(ctx: StageContext) -> None:
    """Refuse NaN/inf or absurd values in the ranges and the pose source's input before any stage (they would
    surface as a numerical failure deep in a filter)."""

    reader = ctx.reader
    topics, problems = reader.topics(), []
    if TOPIC_RANGE in topics:
        r = reader.read_ranges()
        problems += nan_problems(TOPIC_RANGE, r.t_ns, r.distance)
    if ctx.pose_source() == "odometry" and TOPIC_ODOM in topics:
        o = reader.read_odometry()
        problems += nan_problems(TOPIC_ODOM, o.t_ns, o.p, o.q_xyzw)
        problems += clock_jumps(TOPIC_ODOM, reader.read_odometry(file_order=True).t_ns)
    elif TOPIC_IMU in topics:
        m = reader.read_imu(file_order=True)
        problems += nan_problems(TOPIC_IMU, m.t_ns, m.gyro, m.acc) + clock_jumps(TOPIC_IMU, m.t_ns)
    if ctx.pose_source() == "msckf":  # the images against the resolution their intrinsics are for (as info)
        problems += [p for p in calibration_problems(reader, topics) if p.topic]
    if problems:
        fix = (
            ""
            if problems[0].kind == "calibration"
            else "; re-convert the data (uwbcal convert drops such records)"
        )
        raise InputError(f"{ctx.recording}: {problems[0].text}{fix}")


def _resumed_config(output: Path, overrides: dict) -> Path | None:
    """A partial re-run (stages given, VIO not among them) builds on the directory's artefacts: it continues
    with the directory's config.toml (then config.toml keeps reproducing the run; a directory of another
    recording is refused by `provenance.claim`)."""
    stages = overrides["run"].get("stages")
    cfg_path = output / rd.CONFIG
    if not stages or "vio" in stages or not artefacts.present(cfg_path):
        return None
    return cfg_path


def run_cli(
    recording: Path,
    output: Path,
    *,
    config: Path | None,
    init: str | None,
    refine: str | None,
    stages: str | None,
    log: bool,
    evaluator: Evaluator | None = None,
    overwrite: bool = False,
) -> str:
    overrides: dict = {"run": {"recording": str(Path(recording).resolve()), "log": log}}
    if stages is not None:
        overrides["run"]["stages"] = [s.strip() for s in stages.split(",") if s.strip()]
        if not overrides["run"]["stages"]:
            raise InputError(f"--stages {stages!r}: no stage named; choose from {', '.join(STAGES)}")
        unknown = [s for s in overrides["run"]["stages"] if s not in STAGES]
        if unknown:
            raise InputError(
                f"--stages {stages!r}: unknown stage(s) {', '.join(unknown)}; choose from {', '.join(STAGES)}"
            )
    uwb: dict = {}
    if init:
        uwb["init_method"] = init
    if refine:
        uwb["refine_method"] = refine
    if uwb:
        overrides["uwb"] = uwb
    RecordingReader(overrides["run"]["recording"])  # fail early, before the run directory is touched
    cfg = load_config(config or _resumed_config(Path(output), overrides), overrides)
    pipe = Pipeline(cfg, output, evaluator)
    pipe.run(overwrite=overwrite)
    return "\n".join(ln for ln in pipe.results_text.splitlines() if ln not in pipe.shown_warnings)
