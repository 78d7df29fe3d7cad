"""What produced a run directory's artefacts: each stage's config (in ``stages.json``) and a ``config.toml`` that
reproduces them.

``config.toml`` is written after each stage that succeeds (never before a stage runs), with ``run.stages`` = every
stage whose artefacts are in the directory, so ``uwbcal run REC -o NEW --config RUN_DIR/config.toml`` redoes the
run. A stage re-run under another config than the stages it builds on is reported (stages.json warnings, hence
metrics.json): then no single config reproduces the directory.

A run directory belongs to one recording: each stage's entry carries the id of the recording it ran on
(`recording_id`). A run into a directory holding another recording's artefacts is refused, or with
``overwrite`` the stale artefacts are removed first (config.toml, then stages.json, then the rest: a removal
cut short leaves nothing that reads as a run); `check_recording` refuses to read a directory whose stages ran
on another recording than its config names.
"""

from __future__ import annotations

import contextlib
import hashlib
import shutil
from pathlib import Path
from typing import Any

from uwbcal.pipeline.core.errors import InputError
from uwbcal.pipeline.core.names import STAGES
from uwbcal.pipeline.run import artefacts
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
    return run.load_json(rd.STAGES_JSON, schema=artefacts.STAGES)


def record_stage(
    run: rd.RunDir,
    stage: str,
    entry: dict,
    cfg: PipelineConfig,
    invocation: list[str],
    recording: dict,
    choices: list[dict] | None = None,
) -> list[str]:
    """Add ``stage`` (wall_s, summary, warnings) with its config to stages.json, then write config.toml and,
    when this invocation resolved ``"auto"`` keys, resolved.json (each key, its value and why).
    ``recording``: `recording_record` of the recording the stage ran on. Returns warnings about stages outside this ``invocation`` whose artefacts were made under another config
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
    entry = dict(entry, warnings=list(entry.get("warnings", [])) + warns, config=mine, recording=recording)
    stages[stage] = entry
    run.save_json(rd.STAGES_JSON, {k: stages[k] for k in STAGES if k in stages})
    done = [k for k in STAGES if k in stages]
    out = cfg.model_copy(deep=True)
    out.run.stages = done
    rd.write_text(run.file(rd.CONFIG), out.to_toml())
    if choices:
        run.save_json(rd.RESOLVED, choices)
    return warns


# -- which recording the artefacts belong to -------------------------------------------------------------------
_EDGE = 1 << 20  # bytes hashed at each end of a recording


def recording_id(path: Path) -> str:
    """A recording's identity, cheap for any size: its length and a digest of its first and last MiB (an MCAP's
    header and its summary, whose chunk index carries each chunk's CRC). A copy or a move keeps it; another
    recording, or the same one re-converted differently, does not."""
    path = Path(path)
    size = path.stat().st_size
    h = hashlib.sha256()
    with open(path, "rb") as f:
        h.update(f.read(_EDGE))
        if size > _EDGE:
            f.seek(max(_EDGE, size - _EDGE))
            h.update(f.read())
    return f"{size}-{h.hexdigest()[:16]}"


def recording_record(path: Path) -> dict:
    """What a stage's entry in stages.json says about its recording."""
    return {"id": recording_id(path), "path": str(Path(path).resolve())}


def _held(run: rd.RunDir) -> dict[str, dict]:
    """The recording of each stage recorded in the directory ({} for an entry without one)."""
    return {
        k: v.get("recording") if isinstance(v.get("recording"), dict) else {}
        for k, v in load_stages(run).items()
    }


def claim(run: rd.RunDir, recording: dict, stages: list[str], overwrite: bool) -> list[str]:
    """Make ``run`` a directory of ``recording`` before any stage writes: nothing to do when it holds no
    artefacts or only this recording's; else refused, or with ``overwrite`` (and a run that starts from the VIO)
    the stale artefacts removed. Returns the names removed."""
    present = rd.present_artefacts(run.path)
    if not present:
        return []
    held = _held(run) if run.exists(rd.STAGES_JSON) else {}
    others = {r.get("path", "an unknown recording") for r in held.values() if r.get("id") != recording["id"]}
    if held and not others:
        return []
    what = ", ".join(sorted(others)) if others else "an unknown recording (no stages.json)"
    if "vio" not in stages:
        raise InputError(
            f"{run.path}: holds the artefacts of {what}; re-running only {','.join(stages)} on "
            f"{recording['path']} would mix two recordings — run every stage (with --overwrite to replace "
            "them), or choose another output directory"
        )
    if not overwrite:
        raise InputError(
            f"{run.path}: holds the artefacts of {what}; choose another output directory, or pass "
            "--overwrite to replace them"
        )
    for name in present:  # config.toml and stages.json first (rd.ARTEFACTS' order)
        p = run.file(name)
        with contextlib.suppress(FileNotFoundError):
            shutil.rmtree(p) if p.is_dir() and not p.is_symlink() else p.unlink()
    return present


def check_recording(run: rd.RunDir, recording: Path | None) -> None:
    """Refuse a run directory whose recorded stages ran on several recordings, or on another one than
    ``recording`` (the one its config.toml names; None: not at hand, the stages checked among themselves), or
    whose stages.json records no stage beside the artefacts of stages."""
    if not run.exists(rd.STAGES_JSON):
        return  # no stage recorded (a directory put together by hand): nothing to compare
    held = _held(run)
    path = run.file(rd.STAGES_JSON)
    fix = f"re-run every stage (uwbcal run REC -o {run.path} --overwrite)"
    if not held:
        others = [n for n in rd.present_artefacts(run.path) if n not in (rd.STAGES_JSON, rd.CONFIG)]
        if others:
            raise InputError(f"{path}: records no stage, but {others[0]} is a stage's artefact; {fix}")
        return
    missing = [k for k, r in held.items() if not r.get("id")]
    if missing:
        raise InputError(f"{path}: stage {missing[0]} names no recording (an older uwbcal wrote it); {fix}")
    ids = {r["id"]: k for k, r in held.items()}
    if len(ids) > 1:
        (a, ka), (b, kb) = list(ids.items())[:2]
        raise InputError(
            f"{path}: stage {ka} ran on {held[ka].get('path')}, stage {kb} on {held[kb].get('path')}; the "
            f"directory mixes two recordings — {fix}"
        )
    if recording is None:
        return
    rid = recording_id(recording)
    wrong = {k: r for k, r in held.items() if r["id"] != rid}
    if wrong:
        k, r = next(iter(wrong.items()))
        raise InputError(
            f"{path}: stage {k} ran on {r.get('path')}, not on {recording} (config.toml's recording); the "
            f"directory mixes two recordings — {fix}"
        )
