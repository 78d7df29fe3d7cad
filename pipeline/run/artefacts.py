"""The one reader of a run directory's artefacts: every problem (missing, unreadable, not UTF-8, not the format,
the wrong shape or type) is an `InputError` that names the file, where in it, and what to do.

Each artefact's shape is declared here once (`ANCHOR_STATES`, `INIT`, `STAGES`, `METRICS`, `TRAJECTORY_ARRAYS`, ...) and
checked as it is read, so a consumer gets what it expects or a clear refusal, never a silently smaller result.
"""

from __future__ import annotations

import csv
import io
import json
import os
import pickle
import re
import tomllib
import zipfile
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Any

import numpy as np
from pydantic import (
    AfterValidator,
    BaseModel,
    ConfigDict,
    TypeAdapter,
    ValidationError,
    field_validator,
    model_validator,
)

from uwbcal.pipeline.core.errors import InputError


def corrupt(p: Path, problem: str, fix: str | None = None) -> InputError:
    """The error for a damaged artefact of a run directory (``fix``: what to do instead of re-running)."""
    p = Path(p)
    fix = (
        fix
        or f"the run directory is damaged — re-run the stage that writes it (uwbcal run REC -o {p.parent} --stages ...)"
    )
    return InputError(f"{p}: {problem}; {fix}")


def present(path: Path) -> bool:
    """Whether an optional artefact is there: False when nothing is at ``path``, True for a regular file, refused
    (naming it) for anything else — a directory or a dangling link in its place is damage, not absence."""
    path = Path(path)
    if not os.path.lexists(path):
        return False
    _regular(path)
    return True


def _regular(path: Path, fix: str | None = None) -> None:
    if not path.is_file():
        raise corrupt(path, "missing" if not os.path.lexists(path) else "not a regular file", fix)


def read_bytes(path: Path, fix: str | None = None) -> bytes:
    path = Path(path)
    _regular(path, fix)
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


def read_log_id(path: Path) -> str:
    """recording_id.txt: the rerun recording id the stages' logs share (32 hex digits)."""
    fix = (
        "delete it (the next stage makes a new one; earlier stage logs then open as another rerun recording)"
    )
    text = read_text(path, fix).strip()
    if not re.fullmatch(r"[0-9a-f]{32}", text):
        raise corrupt(path, f"{text[:40]!r} is not a log id (32 hex digits)", fix)
    return text


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
    inner = "".join(f"[{x}]" if isinstance(x, int) else f".{x}" for x in e["loc"][1:]).lstrip(".")
    msg = re.sub(r" or instance of \w+", "", e["msg"].removeprefix("Value error, "))
    msg = f"{msg[0].lower()}{msg[1:]}" if msg[1:2].islower() else msg  # "Input should ..", not "P[0][0] .."
    return f"{': '.join([' '.join(loc[:1]), inner]).strip(': ') or 'top level'}: {msg}"


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


def read_toml(path: Path, fix: str | None = None, syntax_fix: str | None = None) -> dict:
    """A TOML file; ``fix``: what to do about an unreadable or non-UTF-8 one, ``syntax_fix``: about invalid
    TOML (default ``fix``)."""
    text = read_text(path, fix)
    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise corrupt(path, f"invalid TOML ({exc})", syntax_fix or fix) from None


def read_npz(
    path: Path,
    shapes: dict[str, tuple[int | None, ...]],
    required: tuple[str, ...] = (),
    text: tuple[str, ...] = (),
) -> dict:
    """The arrays of an .npz artefact: ``required`` present, each one named in ``shapes`` numeric (text: those
    named in ``text``) and of its shape (None: the common length n)."""
    path = Path(path)
    _regular(path)  # missing / not a file: named
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


QUAT_TOL = 1e-3  # max | |q| - 1 | of a stored orientation (the filter keeps it unit to ~1e-15)


def read_trajectory(path: Path) -> dict:
    """A pose history (trajectory.npz, vio.npz, refine.npz, localize.npz): the arrays of `TRAJECTORY_ARRAYS`,
    stamps integer ns strictly increasing, every value finite, orientations unit quaternions, segments 0/1/2;
    a problem names the array and its first bad row."""
    path = Path(path)
    z = read_npz(path, TRAJECTORY_ARRAYS, TRAJECTORY_REQUIRED)
    for k, kinds, what in (
        ("t_ns", "iu", "integers"),
        ("segment", "iu", "integers"),
        ("p", "iuf", "numbers"),
    ):
        if k in z and z[k].dtype.kind not in kinds:
            raise corrupt(path, f"'{k}': {z[k].dtype} values, expected {what}")
    for k in ("q_xyzw", "cov"):
        if k in z and z[k].dtype.kind != "f":
            raise corrupt(path, f"'{k}': {z[k].dtype} values, expected floating-point numbers")
    for k in ("p", "q_xyzw", "cov"):
        bad = np.flatnonzero(~np.isfinite(z[k]).all(axis=tuple(range(1, z[k].ndim)))) if k in z else []
        if len(bad):
            raise corrupt(path, f"'{k}' row {bad[0]}: not finite ({len(bad)} row(s))")
    off = np.abs(np.linalg.norm(z["q_xyzw"], axis=1) - 1.0)
    bad = np.flatnonzero(off > QUAT_TOL)
    if len(bad):
        i = bad[0]
        raise corrupt(
            path, f"'q_xyzw' row {i}: not a unit quaternion (|q| off 1 by {off[i]:.3g}; {len(bad)} row(s))"
        )
    back = np.flatnonzero(np.diff(z["t_ns"]) <= 0)
    if len(back):
        i = back[0] + 1
        raise corrupt(
            path,
            f"'t_ns' row {i}: stamp {z['t_ns'][i]} not after row {i - 1}'s {z['t_ns'][i - 1]} (stamps must "
            f"increase; {len(back)} such row(s))",
        )
    if "segment" in z and not np.isin(z["segment"], (0, 1, 2)).all():
        i = int(np.flatnonzero(~np.isin(z["segment"], (0, 1, 2)))[0])
        raise corrupt(
            path, f"'segment' row {i}: {z['segment'][i]}, expected 0 (init), 1 (refine) or 2 (localize)"
        )
    return z


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


STATE_TOL = 1e-5  # anchors.csv keeps 6 decimals of the states anchor_states.json holds


def read_anchor_states(path: Path) -> dict:
    """anchor_states.json (`ANCHOR_STATES`), read together with the refine rows of anchors.csv beside it, which
    the refinement writes from the same states: an anchor estimated there without its state, a state without
    its row, or a state that is not the row's estimate is damage (a consumer would drop σ and NEES, leave out
    an anchor, or take a state of another run)."""
    path = Path(path)
    states = read_json(path, ANCHOR_STATES)
    table = path.parent / "anchors.csv"
    if not present(table):
        return states
    fix = (
        "anchors.csv and anchor_states.json are not of one refinement — re-run it "
        f"(uwbcal run REC -o {path.parent} --stages refine,localize,evaluate)"
    )
    rows = {r["anchor"]: r for r in read_anchor_rows(table) if r["stage"] == "refine"}
    extra = sorted(set(states) - set(rows), key=lambda a: (len(a), a))
    if rows and extra:
        raise corrupt(path, f"anchor {extra[0]}: a state, but no refine row in anchors.csv", fix)
    for aid, r in rows.items():
        row = _row_state(table, r)
        if row is None:
            continue  # not determined (empty or non-finite): no state to hold
        if aid not in states:
            raise corrupt(
                path, f"anchor {aid}: missing (anchors.csv line {r['_line']} has its estimate)", fix
            )
        x = np.asarray(states[aid]["x"][:5], float)
        if np.abs(x - row).max() > STATE_TOL * max(1.0, float(np.abs(row).max())):
            raise corrupt(
                path,
                f"anchor {aid}: x {np.round(x[:3], 6).tolist()} is not anchors.csv line {r['_line']}'s "
                f"{np.round(row[:3], 6).tolist()}",
                fix,
            )
    return states


def _row_state(table: Path, r: dict) -> np.ndarray | None:
    """x, y, z, beta, gamma of an anchors.csv row (None: not determined)."""
    cells = [r.get(c) or "" for c in ANCHOR_COLUMNS[3:]]
    if "" in cells[:3]:
        return None
    try:
        v = np.asarray([float(c) if c else np.nan for c in cells])
    except ValueError:
        raise corrupt(table, f"line {r['_line']}: {cells} are not numbers") from None
    return v if np.isfinite(v).all() else None


# -- the artefacts' shapes ---------------------------------------------------------------------------------------
class _Open(BaseModel):
    model_config = ConfigDict(extra="allow")


def _matrix(v: list[list[float]]) -> list[list[float]]:
    if any(len(r) != len(v) for r in v):
        raise ValueError(f"not a square matrix ({len(v)} rows of {sorted({len(r) for r in v})} columns)")
    return v


class AnchorState(_Open):
    """One anchor in anchor_states.json: its state (position, then beta, gamma per link) and covariance; every
    number finite, the covariance's variances not negative."""

    model_config = ConfigDict(extra="allow", allow_inf_nan=False, strict=True)
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
        neg = [i for i, r in enumerate(self.P) if r[i] < 0]
        if neg:
            raise ValueError(f"P[{neg[0]}][{neg[0]}] = {self.P[neg[0]][neg[0]]:g}, a negative variance")
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
    """init.json: the initialiser the later stages took and every initialiser's result per anchor (and the
    range clock offset the evidence path estimated)."""

    chosen: str
    methods: dict[str, dict[str, InitAnchor]]
    range_clock: dict | None = None

    @model_validator(mode="after")
    def _chosen_ran(self) -> InitInfo:
        if self.chosen not in self.methods:
            ran = ", ".join(self.methods) or "none"
            raise ValueError(f"chosen {self.chosen!r} is not among the methods ({ran})")
        return self


class HealthEntry(_Open):
    """One stage in health.json: whether the pose source's health checks failed (and, if so, which and when)."""

    model_config = ConfigDict(extra="allow", strict=True)
    failed: bool
    reinits: list[dict] = []


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


def _anchor_id(v: str) -> str:
    if not v.isdigit() or int(v) > 2**32 - 1:
        raise ValueError(f"{v!r} is not an anchor id (an integer 0 .. 2^32-1)")
    return v


AnchorId = Annotated[str, AfterValidator(_anchor_id)]
ANCHOR_STATES = Shape(TypeAdapter(dict[AnchorId, AnchorState]), "anchor")
INIT = Shape(TypeAdapter(InitInfo))
STAGES = Shape(TypeAdapter(dict[str, StageEntry]), "stage")
HEALTH = Shape(TypeAdapter(dict[str, HealthEntry]), "stage")
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
