"""The stages, one module each, listed once: `REGISTRY` maps every name of `core.names.STAGES` (run order) to its
``run(ctx) -> StageResult``."""

from __future__ import annotations

from collections.abc import Callable

from uwbcal.pipeline.core.names import STAGES
from uwbcal.pipeline.run.context import Evaluator, StageContext, StageResult
from uwbcal.pipeline.run.stages import evaluate, frontend, init, localize, refine, vio

REGISTRY: dict[str, Callable[[StageContext], StageResult]] = {
    "frontend": frontend.run,
    "vio": vio.run,
    "init": init.run,
    "refine": refine.run,
    "localize": localize.run,
    "evaluate": evaluate.run,
}
assert tuple(REGISTRY) == STAGES, "the registry lists the stages in run order"

__all__ = ["REGISTRY", "Evaluator", "StageContext", "StageResult"]
