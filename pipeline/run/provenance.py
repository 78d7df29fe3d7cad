"""What produced a run directory's artefacts: each stage's config (in ``stages.json``) and a ``config.toml`` that
reproduces them.

``config.toml`` is written after each stage that succeeds (never before a stage runs), with ``run.stages`` = every
stage whose artefacts are in the directory, so ``uwbcal run REC -o NEW --config RUN_DIR/config.toml`` redoes the
run. A stage re-run under another config than the stages it builds on is reported (stages.json warnings, hence
metrics.json): then no single config reproduces the directory.
"""

from __future__ import annotations

from typing import Any

from uwbcal.pipeline.core.names import STAGES
from uwbcal.pipeline.run import rundir as rd
from uwbcal.pipeline.run.config import PipelineConfig

# keys that say how a run was invoked, not what it computed
_INVOCATION = {("run", "stages"), ("run", "log")}


def config_record(cfg: PipelineConfig) -> dict[str, Any]:
    """The config as it bears on the artefacts (the invocation keys removed)."""
    d = cfg.model_dump(mode="json")
    for sec, key in _INVOCATION:
        d.get(sec, {}).pop(key, None)
    return d


def _flat(d: Any, prefix: str = "") -> dict[str, Any]:
    if isinstance(d, dict):
        out: dict[str, Any] = {}
        for k, v in d.items():
            out.update(_flat(v, f"{prefix}.{k}" if prefix else str(k)))
        return out
    return {prefix: d}


def differing_keys(a: dict, b: dict) -> list[str]:
    fa, fb = _flat(a), _flat(b)
    return sorted(k for k in fa.keys() | fb.keys() if fa.get(k) != fb.get(k))


def load_stages(run: rd.RunDir) -> dict[str, dict]:
    if not run.exists(rd.STAGES_JSON):
        return {}
    data = run.load_json(rd.STAGES_JSON)
    if not isinstance(data, dict) or not all(isinstance(v, dict) for v in data.values()):
        raise run.corrupt(run.file(rd.STAGES_JSON), "not an object of stages")
    return data


def record_stage(
    run: rd.RunDir,
    stage: str,
    entry: dict,
    cfg: PipelineConfig,
    invocation: list[str],
    choices: list[dict] | None = None,
) -> list[str]:
    """Add ``stage`` (wall_s, summary, warnings) with its config to stages.json, then write config.toml and,
    when this invocation resolved ``"auto"`` keys, resolved.json (each key, its value and why).
    Returns warnings about stages outside this ``invocation`` whose artefacts were made under another config
    (also stored with the stage)."""
    stages = load_stages(run)
    mine = config_record(cfg)
    warns = []
    for other, rec in stages.items():
        if other in invocation or "config" not in rec:
            continue
        keys = differing_keys(rec["config"], mine)
        if keys:
            shown = ", ".join(keys[:4]) + (" ..." if len(keys) > 4 else "")
            warns.append(
                f"{stage} ran with another config than {other} ({shown}); no single config.toml reproduces "
                f"this run directory — re-run every stage to make it consistent"
            )
    entry = dict(entry, warnings=list(entry.get("warnings", [])) + warns, config=mine)
    stages[stage] = entry
    run.save_json(rd.STAGES_JSON, {k: stages[k] for k in STAGES if k in stages})
    done = [k for k in STAGES if k in stages]
    out = cfg.model_copy(deep=True)
    out.run.stages = done
    rd.write_text(run.file(rd.CONFIG), out.to_toml())
    if choices:
        run.save_json(rd.RESOLVED, choices)
    return warns
