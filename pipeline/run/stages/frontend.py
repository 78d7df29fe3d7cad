"""Stage `frontend`: feature tracks from the camera images (skipped when the recording carries tracks)."""

from __future__ import annotations

from uwbcal.pipeline.core.topics import TOPIC_CAM0, TOPIC_FEATURES
from uwbcal.pipeline.run.context import StageContext, StageResult
from uwbcal.pipeline.vio.frontend import run_frontend
from uwbcal.pipeline.viz import observers


def run(ctx: StageContext) -> StageResult:
    topics = ctx.reader.topics()
    if TOPIC_FEATURES in topics:
        return StageResult(
            "frontend", f"recording has {topics[TOPIC_FEATURES].count} feature frames; skipped"
        )
    if TOPIC_CAM0 not in topics:
        return StageResult("frontend", "no camera images; skipped")
    log = ctx.runlog("frontend")
    try:
        on_frame = observers.frame_logger(log) if log.enabled else None
        stats = run_frontend(ctx.reader, ctx.dir.file("frontend.mcap"), ctx.config.frontend, on_frame)
    finally:
        log.close()
    return StageResult("frontend", str(stats))
