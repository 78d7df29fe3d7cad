"""Typed, validated run configuration; the resolved config is written into every run directory."""

from __future__ import annotations

import tomllib
from pathlib import Path
from typing import Any, Literal

import tomli_w
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator

from pipeline.core.errors import InputError
from pipeline.core.names import STAGES

from .core.noise import OdometryFilterConfig
from .frontend import FrontendConfig
from .msckf import VioConfig
from .uwb_filter import UwbConfig


class RunSection(BaseModel):
    model_config = ConfigDict(extra="forbid")

    recording: str = ""
    pose_source: Literal["auto", "msckf", "odometry"] = "auto"
    stages: list[str] = Field(default_factory=lambda: list(STAGES))
    init_window_s: float | None = Field(
        None, gt=0, description="length of paper stage 1; default 1/3 of the data"
    )
    refine_window_s: float | None = Field(None, gt=0, description="length of paper stage 2; default 1/3")
    align: Literal["auto", "none", "posyaw", "se3", "sim3"] = "auto"
    log: bool = True
    vio_extent: Literal["auto", "full", "init"] = Field(
        "auto",
        description="auto: the VIO-only pass stops at the end of the initialisation window when refine runs in "
        "the same invocation (refine and localize carry the filter on); full: always to the end of the data "
        "(a VIO-only baseline beside the UWB-aided estimate, ~1.6x the VIO cost); init: always stop there",
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


def load_config(path: Path | None = None, overrides: dict | None = None) -> PipelineConfig:
    """Defaults <- TOML file <- overrides (nested dicts). Errors name the file and the bad key."""
    data: dict = {}
    if path is not None:
        path = Path(path)
        if not path.is_file():
            raise InputError(f"{path}: config file not found")
        try:
            data = tomllib.loads(path.read_text())
        except tomllib.TOMLDecodeError as exc:
            raise InputError(f"{path}: not valid TOML ({exc})") from None
    if overrides:
        data = merge_dicts(data, overrides)
    try:
        return PipelineConfig.model_validate(data)
    except ValidationError as exc:
        err = exc.errors()[0]
        where = ".".join(str(x) for x in err["loc"])
        src = str(path) if path else "config"
        raise InputError(f"{src}: {where}: {err['msg']} ({len(exc.errors())} problem(s) in total)") from None
