"""The staged pipeline (DESIGN §4): frontend -> vio -> init -> refine -> localize -> evaluate.

`Pipeline` owns one run directory and runs the stages of `stages.REGISTRY` in order; each stage is one module
of `pipeline/stages/` (``run(ctx) -> StageResult``), reads the recording and the artefacts of the stage before
(never in-memory state), writes its own artefacts atomically and its own rerun log; a failing stage leaves the
earlier artefacts untouched, and each stage can be re-run alone.
"""

from __future__ import annotations

import dataclasses
import time
from pathlib import Path

from convert.recording import RecordingReader
from pipeline.core.names import STAGES

from . import rundir as rd
from .config import PipelineConfig, load_config
from .stages import REGISTRY, Evaluator, StageContext, StageResult


class Pipeline:
    def __init__(self, config: PipelineConfig, run_dir: Path, evaluator: Evaluator | None = None) -> None:
        self.ctx = StageContext(config, run_dir, evaluator)

    @property
    def config(self) -> PipelineConfig:
        return self.ctx.config

    @property
    def dir(self) -> rd.RunDir:
        return self.ctx.dir

    @property
    def results_text(self) -> str:
        return self.ctx.results_text

    def run(self, stages: list[str] | None = None, progress=print) -> list[StageResult]:
        ctx = self.ctx
        stages = stages or list(ctx.config.run.stages)
        ctx.stages = list(stages)
        ctx.resolve_auto()
        ctx.dir.path.mkdir(parents=True, exist_ok=True)
        rd.write_text(ctx.dir.file(rd.CONFIG), ctx.config.to_toml())
        results = []
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
            if ctx.config.run.log:
                ctx.dir.merge_rrd(ctx.run_kind())
        return results

    def _record_stage(self, res: StageResult) -> None:
        path = "stages.json"
        stages = self.dir.load_json(path) if self.dir.exists(path) else {}
        stages[res.stage] = {"wall_s": res.wall_s, "summary": res.summary, "warnings": res.warnings}
        self.dir.save_json(path, {k: stages[k] for k in STAGES if k in stages})


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
) -> str:
    overrides: dict = {"run": {"recording": str(Path(recording).resolve()), "log": log}}
    if stages:
        overrides["run"]["stages"] = [s.strip() for s in stages.split(",") if s.strip()]
    uwb: dict = {}
    if init:
        uwb["init_method"] = init
    if refine:
        uwb["refine_method"] = refine
    if uwb:
        overrides["uwb"] = uwb
    cfg = load_config(config, overrides)
    RecordingReader(cfg.run.recording)  # fail early, before the run directory is touched
    pipe = Pipeline(cfg, output, evaluator)
    pipe.run()
    return pipe.results_text
