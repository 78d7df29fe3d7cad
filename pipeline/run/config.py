"""Typed, validated run configuration; the resolved config is written into every run directory."""

from __future__ import annotations

import difflib
import math
import re
from pathlib import Path
from typing import Any, Literal

import tomli_w
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator

from uwbcal.pipeline.core.errors import InputError
from uwbcal.pipeline.core.names import STAGES
from uwbcal.pipeline.core.noise import OdometryFilterConfig
from uwbcal.pipeline.run import artefacts
from uwbcal.pipeline.uwb.config import UwbConfig
from uwbcal.pipeline.vio.config import FrontendConfig, VioConfig


class RunSection(BaseModel):
    model_config = ConfigDict(extra="forbid")

    recording: str = Field("", description="the recording (.mcap) the run is of; set by `uwbcal run REC`")
    pose_source: Literal["auto", "msckf", "odometry"] = Field(
        "auto",
        description="msckf: our VIO on IMU + camera; odometry: the filter on /odometry; auto: msckf when the recording has IMU and camera",
    )
    stages: list[str] = Field(
        default_factory=lambda: list(STAGES), description="the stages to run, in run order"
    )
    init_window_s: float | None = Field(
        None, gt=0, description="length of paper stage 1; default 1/3 of the data"
    )
    refine_window_s: float | None = Field(None, gt=0, description="length of paper stage 2; default 1/3")
    align: Literal["auto", "none", "posyaw", "se3", "sim3"] = Field(
        "auto",
        description="trajectory alignment of the evaluation; auto: posyaw for a VIO started by the static initialiser (its own frame), none for a simulation, se3 otherwise (a real ground truth in another frame)",
    )
    log: bool = Field(True, description="write the rerun recording run.rrd (--no-log: false)")
    log_process: bool = Field(
        True,
        description="rerun logging in a helper process that overlaps with the computation (false: in-process)",
    )
    vio_extent: Literal["auto", "full", "init"] = Field(
        "auto",
        description="auto: the VIO-only pass stops at the end of the initialisation window when refine runs in "
        "the same invocation (refine and localize carry the filter on); full: always to the end of the data "
        "(a VIO-only baseline beside the UWB-aided estimate, at extra VIO cost); init: always stop there",
    )

    schedule: Literal["auto", "windows", "per-anchor"] = Field(
        "auto",
        description="anchor initialisation schedule: windows = the paper's (every anchor from the first window); "
        "per-anchor = each anchor as soon as its own ranges determine it, joining the refinement then (refine "
        "runs to the end); auto: per-anchor when some anchor is ranged mostly after the first window or the poses "
        "have a bounded error (odometry error_model bounded), else windows",
    )
    coupling: Literal["tight", "loose"] = Field(
        "tight",
        description="MSCKF pose source: tight = the anchors join the MSCKF state (the paper's filter); loose = "
        "the UWB stages run on the VIO output (the MSCKF over all data, its trajectory as odometry with a drift "
        "model fitted to its covariance growth; the anchors never join the MSCKF state)",
    )

    @field_validator("stages")
    @classmethod
    def _known_stages(cls, v: list[str]) -> list[str]:
        bad = [s for s in v if s not in STAGES]
        if bad:
            raise ValueError(f"unknown stage(s) {bad}; known: {', '.join(STAGES)}")
        return [s for s in STAGES if s in v]


class PipelineConfig(BaseModel):
    model_config = ConfigDict(extra="forbid")

    run: RunSection = Field(default_factory=RunSection)
    frontend: FrontendConfig = Field(default_factory=FrontendConfig)
    vio: VioConfig = Field(default_factory=VioConfig)
    odometry: OdometryFilterConfig = Field(default_factory=OdometryFilterConfig)
    uwb: UwbConfig = Field(default_factory=UwbConfig)

    def to_toml(self) -> str:
        return tomli_w.dumps(_drop_none(self.model_dump(mode="json")))


def _drop_none(d: Any) -> Any:
    if isinstance(d, dict):
        return {k: _drop_none(v) for k, v in d.items() if v is not None}
    if isinstance(d, list):
        return [_drop_none(v) for v in d]
    return d


def merge_dicts(base: dict, over: dict) -> dict:
    """``base`` with ``over`` merged in, recursively for nested dicts (``over`` wins)."""
    out = dict(base)
    for k, v in over.items():
        out[k] = merge_dicts(out[k], v) if isinstance(v, dict) and isinstance(out.get(k), dict) else v
    return out


# No configuration number is this large: a sigma of 1e300 m, a window of 1e12 s are typos, not settings.
PLAUSIBLE_MAX = 1e6


def check_numbers(data: Any, src: str, where: str = "") -> None:
    """Every number finite and within +-PLAUSIBLE_MAX (InputError naming the file and the key)."""
    if isinstance(data, dict):
        for k, v in data.items():
            check_numbers(v, src, f"{where}.{k}" if where else str(k))
    elif isinstance(data, list):
        for i, v in enumerate(data):
            check_numbers(v, src, f"{where}[{i}]")
    elif isinstance(data, (int, float)) and not isinstance(data, bool):
        if not math.isfinite(data):
            raise InputError(f"{src}: {where} = {data}: must be a finite number")
        if abs(data) > PLAUSIBLE_MAX:
            raise InputError(
                f"{src}: {where} = {data:g}: implausibly large (> {PLAUSIBLE_MAX:g}); fix the value"
            )


def read_toml(path: Path) -> dict:
    """A TOML file as a dict; InputError naming the file on anything unreadable."""
    return artefacts.read_toml(
        path,
        fix="save it as UTF-8 TOML (uwbcal config prints the defaults)",
        syntax_fix="fix the TOML at that line (a key or a [section] given twice, a missing value or quote; "
        "uwbcal config prints a valid config)",
    )


def load_config(path: Path | None = None, overrides: dict | None = None) -> PipelineConfig:
    """Defaults <- TOML file <- overrides (nested dicts). Errors name the file and the bad key.

    Strict: values must have the key's type (no "10" for 10), be finite and plausible; unknown keys refused."""
    data: dict = read_toml(path) if path is not None else {}
    src = str(path) if path else "config"
    check_numbers(data, src)
    if path is not None:  # the file on its own: its errors name it, even for keys the command line overrides
        _validate(data, src)
    if overrides:
        check_numbers(overrides, "overrides")
        data = merge_dicts(data, overrides)
    return _validate(data, src)


def run_config(run_dir: Path) -> PipelineConfig:
    """The config a run directory's stages ran under (its ``config.toml``), validated like any config."""
    path = Path(run_dir) / "config.toml"
    if not path.exists():
        raise InputError(f"{path}: missing; is {run_dir} a run directory?")
    return load_config(path)


def _validate(data: dict, src: str) -> PipelineConfig:
    try:
        return PipelineConfig.model_validate(data, strict=True)
    except ValidationError as exc:
        n = len(exc.errors())
        more = f" ({n} problems in total)" if n > 1 else ""
        raise InputError(f"{src}: {config_problem(exc.errors()[0])}{more}") from None


def config_problem(err: dict) -> str:
    """One validation error of the config as ``key = value: problem; fix`` (a near key or choice named)."""
    loc = [str(x) for x in err["loc"]]
    where = ".".join(loc)
    msg = re.sub(r" or instance of \w+", "", err["msg"].removeprefix("Value error, "))
    msg = (msg[0].lower() + msg[1:]).replace("input should be", "must be")
    if err["type"] == "extra_forbidden":
        known = _keys_at(loc[:-1])
        near = difflib.get_close_matches(loc[-1], known, n=1, cutoff=0.6)
        hint = f"did you mean '{'.'.join(loc[:-1] + near)}'?" if near else f"valid here: {', '.join(known)}"
        return f"{where}: unknown key; {hint} (uwbcal config --reference lists every key)"
    got = err.get("input")
    shown = f"{where} = {got!r}" if isinstance(got, (str, int, float, bool)) else where
    if err["type"] == "literal_error":
        near = difflib.get_close_matches(str(got), re.findall(r"'([^']*)'", msg), n=1, cutoff=0.5)
        return f"{shown}: {msg}" + (f"; did you mean '{near[0]}'?" if near else "")
    return f"{shown}: {msg}; fix the value (uwbcal config --reference: each key's type and range)"


def _keys_at(path: list[str]) -> list[str]:
    """The keys the config model accepts under ``path`` (a section)."""
    model: Any = PipelineConfig
    for part in path:
        field = getattr(model, "model_fields", {}).get(part)
        model = field.annotation if field is not None else None
    fields = getattr(model, "model_fields", None)
    return sorted(fields) if isinstance(fields, dict) else []
