"""The configuration reference (docs/configuration.md), generated from the typed config."""

from __future__ import annotations

import json
import typing

from pydantic import BaseModel
from pydantic.fields import FieldInfo

from uwbcal.pipeline.run.config import PipelineConfig


def _type_name(annotation: object) -> str:
    if isinstance(annotation, type):
        return annotation.__name__
    origin = typing.get_origin(annotation)
    if origin is typing.Literal:
        return " \\| ".join(f"`{a!r}`".replace("'", '"') for a in typing.get_args(annotation))
    text = str(annotation).replace("typing.", "")
    return text.replace("|", "\\|")


def _bounds(info: FieldInfo) -> str:
    out = []
    for m in info.metadata:
        for attr, sym in (("gt", ">"), ("ge", "≥"), ("lt", "<"), ("le", "≤")):
            v = getattr(m, attr, None)
            if v is not None:
                out.append(f"{sym} {v}")
    return ", ".join(out)


def _default(info: FieldInfo) -> str:
    if info.default_factory is not None:
        value = info.default_factory()
    else:
        value = info.default
    if isinstance(value, BaseModel):
        return ""
    return f"`{json.dumps(value)}`" if value is not None else "unset"


def section_table(name: str, model: type[BaseModel]) -> list[str]:
    lines = [f"## `[{name}]`", ""]
    doc = (model.__doc__ or "").strip()
    if doc and not doc.startswith("!!!") and "Usage docs" not in doc:
        lines += [doc, ""]
    lines += ["| key | type | default | allowed | what it does |", "|---|---|---|---|---|"]
    for key, info in model.model_fields.items():
        desc = (info.description or "").replace("\n", " ").replace("|", "\\|")
        lines.append(
            f"| `{key}` | {_type_name(info.annotation)} | {_default(info)} | {_bounds(info)} | {desc} |"
        )
    return lines + [""]


def reference_markdown(root: type[BaseModel] = PipelineConfig) -> str:
    lines = [
        "# Configuration reference",
        "",
        "Generated from the typed configuration (`uwbcal config --reference`); do not edit by hand. A run reads",
        "the defaults, then `--config FILE.toml`, then the command-line options; unknown keys, values of the wrong",
        'type and out-of-range numbers are refused with the key named. A key set to `"auto"` is resolved from the',
        "recording when the run starts; the run directory's `config.toml` holds the resolved values and",
        "`resolved.json` why each was chosen.",
        "",
    ]
    for key, info in root.model_fields.items():
        lines += section_table(key, info.annotation)  # type: ignore[arg-type]
    return "\n".join(lines).rstrip() + "\n"
