"""One line for a pydantic validation error: the file, the key path, the problem and the fix.

The fix is the field's description (every field of a validated model has one: it says what is expected), or, for
an unknown key, the known keys and the closest one ("did you mean ...").
"""

from __future__ import annotations

import difflib
import re
import typing
from typing import Any

from pydantic import BaseModel, ValidationError


def _models_in(annotation: Any) -> list[type[BaseModel]]:
    """The model classes an annotation holds (X, X | None, dict[str, X], list[X], ...)."""
    if isinstance(annotation, type) and issubclass(annotation, BaseModel):
        return [annotation]
    out: list[type[BaseModel]] = []
    for arg in typing.get_args(annotation):
        out += _models_in(arg)
    return out


def _walk(model: type[BaseModel], loc: tuple) -> tuple[type[BaseModel] | None, str | None, str | None]:
    """Along ``loc``: (the model holding the last named field, that field's name, its description)."""
    cur: type[BaseModel] | None = model
    holder, name, desc = None, None, None
    for part in loc:
        if cur is not None and isinstance(part, str) and part in cur.model_fields:
            f = cur.model_fields[part]
            holder, name, desc = cur, part, f.description
            inner = _models_in(f.annotation)
            cur = inner[0] if inner else None
        elif cur is not None and isinstance(part, str) and part not in cur.model_fields and holder is None:
            holder = cur  # an unknown key at the top level
    return holder, name, desc


def _unknown_key_fix(model: type[BaseModel], loc: tuple) -> str:
    parent: type[BaseModel] | None = model
    for part in loc[:-1]:
        if parent is not None and isinstance(part, str) and part in parent.model_fields:
            inner = _models_in(parent.model_fields[part].annotation)
            parent = inner[0] if inner else None
    known = sorted(parent.model_fields) if parent is not None else []
    close = difflib.get_close_matches(str(loc[-1]), known, n=1)
    hint = f"did you mean '{close[0]}'? " if close else ""
    return f"unknown key: {hint}known keys: {', '.join(known)}" if known else "unknown key; remove it"


def _problem(err: dict) -> str:
    msg = str(err.get("msg", "invalid"))
    for prefix in ("Value error, ", "Assertion failed, "):
        if msg.startswith(prefix):
            msg = msg[len(prefix) :]
    msg = re.sub(r" or instance of \w+", "", msg)  # "a valid dictionary", not the model class behind it
    if err.get("type") in ("missing",):
        return "missing"
    got = err.get("input")
    if err.get("type") not in ("value_error", "assertion_error") and not isinstance(got, (dict, list)):
        shown = repr(got)
        msg += f" (got {shown if len(shown) <= 40 else shown[:37] + '...'})"
    first = msg.split(" ", 1)[0]
    return msg[:1].lower() + msg[1:] if first[1:].islower() else msg


def validation_message(
    exc: ValidationError, model: type[BaseModel], source: str, keys: dict[str, str] | None = None
) -> str:
    """``<source>: <key.path>: <problem>; <fix>`` for the first error of ``exc`` (the count when more);
    ``keys``: the model's top-level key -> the key as the file spells it (a file of another layout)."""
    errors = exc.errors()
    err = errors[0]
    loc = tuple(err.get("loc", ()))
    shown = [(keys or {}).get(str(p), str(p)) if i == 0 else str(p) for i, p in enumerate(loc)]
    where = ".".join(shown) or "(top level)"
    problem = _problem(err)
    if err.get("type") == "extra_forbidden":
        return f"{source}: {where}: {_unknown_key_fix(model, loc)}" + _more(errors)
    _, _, desc = _walk(model, loc)
    if "; " in problem or desc is None:  # a validator's message states its own fix
        return f"{source}: {where}: {problem}" + _more(errors)
    return f"{source}: {where}: {problem}; expected {desc}" + _more(errors)


def _more(errors: list) -> str:
    return f" ({len(errors)} problems in total)" if len(errors) > 1 else ""
