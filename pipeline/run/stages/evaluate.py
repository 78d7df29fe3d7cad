"""Stage `evaluate`: metrics of the run directory. The evaluation itself lives a layer above the stages
(`evaluate.evaluation.evaluate_stage`); whoever builds the pipeline hands it in (`Pipeline(..., evaluator=)`)."""

from __future__ import annotations

from uwbcal.pipeline.core.errors import InputError
from uwbcal.pipeline.run import rundir as rd
from uwbcal.pipeline.run.context import StageContext, StageResult


def run(ctx: StageContext) -> StageResult:
    if ctx.evaluator is None:
        raise InputError(
            "the evaluate stage needs an evaluator: build the pipeline with "
            "Pipeline(config, run_dir, evaluator=evaluate.evaluation.evaluate_stage), or run 'uwbcal evaluate RUN_DIR'"
        )
    align = None if ctx.config.run.align == "auto" else ctx.config.run.align
    ctx.results_text = ctx.evaluator(ctx.dir.path, align, lambda: ctx.runlog("evaluate"))
    m = ctx.dir.load_json(rd.METRICS)
    parts = []
    if "prmse_m" in m:
        parts.append(f"PRMSE {m['prmse_m'].get('all', float('nan')):.3f} m")
    if "anchor_error_m" in m:
        parts.append(f"anchor error {m['anchor_error_m']:.3f} m")
    if m.get("groundtruth_glitches"):
        parts.append(f"{m['groundtruth_glitches']} ground-truth glitch samples dropped")
    return StageResult("evaluate", ", ".join(parts) or "metrics written")
