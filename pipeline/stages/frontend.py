"""Stage `frontend`: feature tracks from the camera images (skipped when the recording carries tracks)."""

from __future__ import annotations

from pipeline.core.topics import TOPIC_CAM0, TOPIC_FEATURES

from .context import StageContext, StageResult


def run(ctx: StageContext) -> StageResult:
    topics = ctx.reader.topics()
    if TOPIC_FEATURES in topics:
        return StageResult(
            "frontend", f"recording has {topics[TOPIC_FEATURES].count} feature frames; skipped"
        )
    if TOPIC_CAM0 not in topics:
        return StageResult("frontend", "no camera images; skipped")
    from ..frontend import run_frontend

    log = ctx.runlog("frontend")
    try:
        stats = run_frontend(ctx.reader, ctx.dir.file("frontend.mcap"), ctx.config.frontend, log=log)
    finally:
        log.close()
    return StageResult("frontend", str(stats))
