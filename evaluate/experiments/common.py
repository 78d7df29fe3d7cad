"""What the experiments share: the paper's initialisation settings and ``--param overrides=`` parsing."""

from __future__ import annotations

import json

from uwbcal.pipeline.core.errors import InputError

# The paper's initialisation (its multi-start, global windows): the experiments reproduce the paper; an
# experiment records what a (possibly diverged, deliberately mis-told) VIO gives: its health checks only warn
PAPER_INIT: dict = {"uwb": {"search": False}, "vio": {"on_failure": "warn"}}


def parse_overrides(text: str) -> dict:
    """``"vio.max_clones=30;uwb.chi2_quantile=0.99"`` -> nested config overrides (values parsed as JSON when
    they are JSON: numbers, true/false, null; else kept as strings)."""
    out: dict = {}
    for item in (t.strip() for t in text.split(";")):
        if not item:
            continue
        key, sep, value = item.partition("=")
        parts = [k.strip() for k in key.split(".")]
        if not sep or len(parts) < 2 or not all(parts):
            raise InputError(f"overrides: {item!r}: expected SECTION.KEY=VALUE (e.g. vio.max_clones=30)")
        try:
            v = json.loads(value)
        except json.JSONDecodeError:
            v = value.strip()
        node = out
        for k in parts[:-1]:
            node = node.setdefault(k, {})
        node[parts[-1]] = v
    return out
