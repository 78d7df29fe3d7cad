"""The one reader of a run directory's artefacts: every problem (missing, unreadable, not UTF-8, not the format,
the wrong shape or type) is an `InputError` that names the file, where in it, and what to do.

Each artefact's shape is declared here once (`ANCHOR_STATES`, `INIT`, `STAGES`, `METRICS`, `TRAJECTORY_ARRAYS`, ...) and
checked as it is read, so a consumer gets what it expects or a clear refusal, never a silently smaller result.
"""

from __future__ import annotations

import csv
import io
import json
import pickle
import re
import tomllib
import zipfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from pydantic import BaseModel, ConfigDict, TypeAdapter, ValidationError, field_validator, model_validator

from uwbcal.pipeline.core.errors import InputError


def corrupt(p: Path, problem: str, fix: str | None = None) -> InputError:
    """The error for a damaged artefact of a run directory (``fix``: what to do instead of re-running)."""
    p = Path(p)
    fix = (
        fix
        or f"the run directory is damaged — re-run the stage that writes it (uwbcal run REC -o {p.parent} --stages ...)"
    )
    return InputError(f"{p}: {problem}; {fix}")


def read_bytes(path: Path, fix: str | None = None) -> bytes:
    path = Path(path)
    if not path.is_file():
        raise corrupt(path, "missing" if not path.exists() else "not a regular file", fix)
    try:
        return path.read_bytes()
    except OSError as exc:
        raise corrupt(path, f"unreadable ({exc.strerror})", fix) from None


def read_text(path: Path, fix: str | None = None) -> str:
    data = read_bytes(path, fix)
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise corrupt(path, f"byte {exc.start}: not UTF-8 text", fix) from None


@dataclass(frozen=True)
class Shape:
    """An artefact's JSON shape; ``item``: what its top-level keys are (for the messages: "anchor 7: x: ...")."""

    adapter: TypeAdapter
    item: str = ""


def _where(err: ValidationError, item: str) -> str:
    e = err.errors()[0]
    loc = [str(x) for x in e["loc"]]
    if item and loc:
        loc[0] = f"{item} {loc[0]}"
    msg = re.sub(r" or instance of \w+", "", e["msg"].removeprefix("Value error, "))
    return f"{': '.join([' '.join(loc[:1]), '.'.join(loc[1:])]).strip(': ') or 'top level'}: {msg[0].lower()}{msg[1:]}"


def read_json(path: Path, schema: Shape | type = dict, fix: str | None = None) -> Any:
    """A JSON artefact checked against ``schema`` (its `Shape`, or a plain type for the top level); returns the
    data as parsed (the consumers read it as plain JSON)."""
    text = read_text(path, fix)
    try:
        data = json.loads(text)
    except json.JSONDecodeError as exc:
        raise corrupt(path, f"line {exc.lineno}: not valid JSON ({exc.msg})", fix) from None
    if isinstance(schema, type):
        if not isinstance(data, schema):
            raise corrupt(path, f"a JSON {_json_kind(data)}, expected a JSON {_json_kind(schema())}", fix)
        return data
    try:
        schema.adapter.validate_python(data)
    except ValidationError as exc:
        raise corrupt(path, _where(exc, schema.item), fix) from None
    return data


def _json_kind(v: Any) -> str:
    return {dict: "object", list: "array", str: "string"}.get(type(v), type(v).__name__)


def read_toml(path: Path, fix: str | None = None) -> dict:
    text = read_text(path, fix)
    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise corrupt(path, f"invalid TOML ({exc})", fix) from None


def read_npz(
    path: Path,
    shapes: dict[str, tuple[int | None, ...]],
    required: tuple[str, ...] = (),
    text: tuple[str, ...] = (),
) -> dict:
    """The arrays of an .npz artefact: ``required`` present, each one named in ``shapes`` numeric (text: those
    named in ``text``) and of its shape (None: the common length n)."""
    path = Path(path)
    read_bytes(path)  # missing / not a file: named
    try:
        with np.load(path, allow_pickle=False) as z:
            out = {k: z[k] for k in z.files}
    except (OSError, ValueError, EOFError, KeyError, zipfile.BadZipFile) as exc:
        raise corrupt(path, f"unreadable array file ({type(exc).__name__})") from None
    absent = [k for k in required if k not in out]
    if absent:
        raise corrupt(path, f"no '{absent[0]}' array (has {', '.join(sorted(out)) or 'none'})")
    n = None
    for k, shape in shapes.items():
        if k not in out:
            continue
        a = out[k]
        n = a.shape[0] if n is None and a.ndim else n
        if k in text:
            if a.size and a.dtype.kind != "U":
                raise corrupt(path, f"'{k}': {a.dtype} values, expected text")
        elif not (np.issubdtype(a.dtype, np.number) or a.dtype == bool):
            raise corrupt(path, f"'{k}': {a.dtype} values, expected numbers")
        want = tuple(n if s is None else s for s in shape)
        if a.shape != want:
            shown = "(" + ", ".join("n" if s is None else str(s) for s in shape) + ")"
            raise corrupt(path, f"'{k}': shape {a.shape}, expected {shown} with n = {n}")
    return out


def read_pickle(path: Path) -> Any:
    data = read_bytes(path)
    try:
        return pickle.loads(data)
    except Exception as exc:  # noqa: BLE001 - a damaged pickle can fail in any way
        raise corrupt(path, f"unreadable checkpoint ({type(exc).__name__})") from None


ANCHOR_COLUMNS = ("anchor", "method", "stage", "x", "y", "z", "beta", "gamma")


def read_anchor_rows(path: Path) -> list[dict]:
    """The rows of anchors.csv (each with its line number as ``_line``); the columns checked."""
    text = read_text(path)
    try:
        reader = csv.DictReader(io.StringIO(text, newline=""))
        missing = [c for c in ANCHOR_COLUMNS if c not in (reader.fieldnames or [])]
        if missing:
            raise corrupt(path, f"header: missing column(s) {', '.join(missing)}")
        return [dict(r, _line=str(i)) for i, r in enumerate(reader, start=2)]
    except csv.Error as exc:
        raise corrupt(path, f"not a CSV ({exc})") from None


# -- the artefacts' shapes ---------------------------------------------------------------------------------------
class _Open(BaseModel):
    model_config = ConfigDict(extra="allow")


def _matrix(v: list[list[float]]) -> list[list[float]]:
    if any(len(r) != len(v) for r in v):
        raise ValueError(f"not a square matrix ({len(v)} rows of {sorted({len(r) for r in v})} columns)")
    return v


class AnchorState(_Open):
    """One anchor in anchor_states.json: its state (position, then beta, gamma per link) and covariance."""

    x: list[float]
    P: list[list[float]]
    noise_inflation: float = 1.0
    link_offsets: dict[str, float] = {}

    @field_validator("x")
    @classmethod
    def _x(cls, v: list[float]) -> list[float]:
        if len(v) < 5:
            raise ValueError(f"{len(v)} components, expected position (3) and beta, gamma")
        return v

    @field_validator("P")
    @classmethod
    def _p(cls, v: list[list[float]]) -> list[list[float]]:
        return _matrix(v)

    @model_validator(mode="after")
    def _p_of_x(self) -> AnchorState:
        if len(self.P) != len(self.x):
            raise ValueError(
                f"the covariance P is {len(self.P)} x {len(self.P)}, x has {len(self.x)} components"
            )
        return self


class Verdict(_Open):
    """An initialiser's verdict on one anchor (what the report reads of it)."""

    height_observable: bool = True
    model: str | dict | None = None
    bias: dict = {}


class InitAnchor(_Open):
    """One anchor of one initialiser in init.json."""

    status: str
    x: list[float] | None = None
    cov: list[list[float]] | None = None
    reason: str | None = None
    warnings: list[str] = []
    model: str | dict | None = None
    verdict: Verdict = Verdict()


class InitInfo(_Open):
    chosen: str | None = None
    methods: dict[str, dict[str, InitAnchor]] = {}


class StageEntry(_Open):
    wall_s: float = 0.0
    summary: str = ""
    warnings: list[str] = []
    recording: dict[str, str] = {}
    config: dict = {}


def _xyz(v: list[float] | None) -> list[float] | None:
    if v is not None and len(v) != 3:
        raise ValueError(f"{len(v)} components, expected x, y, z")
    return v


class MetricAnchor(_Open):
    """One anchor in metrics.json (what the report and the summaries read)."""

    estimate: list[float] | None = None
    sigma_xyz: list[float] | None = None
    determined: bool = True
    error_m: float | None = None
    method: str | None = None
    reason: str = ""

    @field_validator("estimate", "sigma_xyz")
    @classmethod
    def _three(cls, v: list[float] | None) -> list[float] | None:
        return _xyz(v)


class Metrics(_Open):
    anchors: dict[str, MetricAnchor] = {}
    warnings: list[str] = []


ANCHOR_STATES = Shape(TypeAdapter(dict[str, AnchorState]), "anchor")
INIT = Shape(TypeAdapter(InitInfo))
STAGES = Shape(TypeAdapter(dict[str, StageEntry]), "stage")
# trajectory.npz and the stages' histories (vio.npz, refine.npz, localize.npz): a pose per stamp, its covariance
TRAJECTORY_ARRAYS = {
    "t_ns": (None,),
    "p": (None, 3),
    "q_xyzw": (None, 4),
    "cov": (None, 6, 6),
    "segment": (None,),
}
TRAJECTORY_REQUIRED = ("t_ns", "p", "q_xyzw")
METRICS = Shape(TypeAdapter(Metrics))
# range_updates.npz: every range of the refinement (its anchor as text)
RANGE_UPDATES_ARRAYS = {
    "t_ns": (None,),
    "anchor": (None,),
    "residual": (None,),
    "nis": (None,),
    "rejected": (None,),
}
RANGE_UPDATES_TEXT = ("anchor",)
