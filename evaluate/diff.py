"""Regression diff of metrics (``uwbcal diff BASELINE CURRENT``): exit 1 when CURRENT is worse.

Inputs are a JSON file, or a folder holding ``metrics.json`` (a run directory), else ``summary.json`` (an
experiment), else every ``*.json`` in it (keys prefixed with the file stem). Nested objects are flattened to
dotted keys (``prmse_m.all``); lists of numbers to ``key.0``, ``key.1``; other lists to one string.

Rules, per flattened key:
- *error metrics* (a key part contains ``rmse``, ``error`` or ``deviation``, or has the word ``err``): larger
  magnitude is worse; a regression when ``|current| > |baseline| * (1 + rtol) + atol`` (or current is NaN and
  baseline is not).
- *NEES* (a numeric key with ``nees`` in it, e.g. ``nees_pose.position.mean``): when χ² bounds are stored
  alongside (sibling ``<parent>.bounds`` or ``<key>_bounds`` = [lo, hi], as ``consistency.summarize_nees``
  writes them), a regression when the current value leaves the bounds that the baseline was inside, and also
  when both are inside but the value moved from the baseline by more than ``rtol`` (a seeded experiment whose
  ANEES drops from 5.90 to 3.97 has changed the filter's belief even though 3.97 is still inside [3.96, 6.15]);
  when both are outside, the distance to the nearer bound is compared like an error metric. With only a sibling ``dof`` (``<parent>.dof``/``<key>_dof``), ``|nees / dof - 1|`` is compared
  like an error metric. Without either, NEES is informational.
- timing / provenance keys (a ``_``-separated word ``wall``, ``elapsed``, ``version``, ``seed`` ...) are ignored.
- everything else (estimates, counts, strings) is informational: changes are shown, never a regression.
- a key in the baseline but missing from the current is a regression (except ignored keys); a new key is "new".
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from uwbcal.pipeline.core.errors import InputError
from uwbcal.pipeline.run import artefacts

ATOL = 1e-9
ERROR_WORDS = ("rmse", "error", "err", "deviation")
IGNORED_WORDS = ("wall", "elapsed", "timestamp", "version", "hostname", "date", "created", "seed")
BOUND_LEAVES = ("bounds", "lo", "hi", "lower", "upper", "dof", "n_runs", "inside")


# -- loading -------------------------------------------------------------------------------------------------------
def flatten(obj: Any, prefix: str = "") -> dict[str, Any]:
    """Nested dicts -> ``{"a.b.c": value}``; numeric lists -> indexed keys; other lists -> one string."""
    out: dict[str, Any] = {}
    if isinstance(obj, dict):
        for k, v in obj.items():
            out.update(flatten(v, f"{prefix}.{k}" if prefix else str(k)))
    elif isinstance(obj, list) and obj and all(_is_num(v) or isinstance(v, (list, dict)) for v in obj):
        for i, v in enumerate(obj):
            out.update(flatten(v, f"{prefix}.{i}"))
    elif isinstance(obj, list):
        out[prefix] = "; ".join(map(str, obj))
    else:
        out[prefix] = obj
    return out


def _is_num(v: Any) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool)


def _read_json(path: Path) -> dict:
    """A JSON object (metrics are always one); anything else is an input error naming the file. A run's
    metrics.json is checked against its declared shape (`artefacts.METRICS`)."""
    shape = artefacts.METRICS if path.name == "metrics.json" else dict
    return artefacts.read_json(path, shape, fix="pass a metrics.json or summary.json")


def load_metrics(path: str | Path) -> dict[str, Any]:
    """Flattened metrics of a JSON file or a folder (see the module docstring)."""
    path = Path(path)
    if not path.exists():
        raise InputError(f"{path}: no such file or folder; pass a metrics.json or a run/experiment directory")
    if path.is_file():
        return flatten(_read_json(path))
    for name in ("metrics.json", "summary.json"):
        if (path / name).is_file():
            return flatten(_read_json(path / name))
    files = sorted(path.glob("*.json"))
    if not files:
        raise InputError(f"{path}: no metrics.json, summary.json or *.json inside; is this a run directory?")
    out: dict[str, Any] = {}
    for f in files:
        out.update(flatten(_read_json(f), f.stem))
    return out


# -- classification ------------------------------------------------------------------------------------------------
def _parts(key: str) -> list[str]:
    return key.lower().split(".")


def _tokens(key: str) -> set[str]:
    return {t for p in _parts(key) for t in p.split("_")}


def _is_ignored(key: str) -> bool:
    return bool(_tokens(key) & set(IGNORED_WORDS))


def _is_error(key: str) -> bool:
    # any part naming an error: "prmse_m.all", "anchors.3.error_m", "beta_err", "nees_deviation"
    return "err" in _tokens(key) or any(w in p for p in _parts(key) for w in ERROR_WORDS if w != "err")


def _is_nees_value(key: str) -> bool:
    parts = _parts(key)
    if not any("nees" in p for p in parts):
        return False
    tail = parts[-1:] if not parts[-1].isdigit() else parts[-2:-1]
    return not any(p == w or p.endswith("_" + w) for p in tail for w in BOUND_LEAVES)


def _siblings(key: str, name: str) -> list[str]:
    """Where a NEES value's ``name`` (bounds, dof) may be stored: ``<parent>.<name>`` or ``<key>_<name>``."""
    out = [f"{key.rsplit('.', 1)[0]}.{name}"] if "." in key else []
    return out + [f"{key}_{name}"]


def _bounds(metrics: dict[str, Any], key: str) -> tuple[float, float] | None:
    for pre in _siblings(key, "bounds"):
        lo, hi = metrics.get(pre + ".0"), metrics.get(pre + ".1")
        if _is_num(lo) and _is_num(hi):
            return float(lo), float(hi)
    return None


def _dof(metrics: dict[str, Any], key: str) -> float | None:
    for k in _siblings(key, "dof"):
        if _is_num(metrics.get(k)) and metrics[k] > 0:
            return float(metrics[k])
    return None


def _outside(v: float, b: tuple[float, float]) -> float:
    """Distance of ``v`` outside ``[lo, hi]`` (0 inside)."""
    return max(b[0] - v, v - b[1], 0.0)


# -- diff ------------------------------------------------------------------------------------------------------------
@dataclass
class DiffRow:
    metric: str
    baseline: Any
    current: Any
    status: str  # ok | improved | regressed | new | missing | changed | info | ignored
    note: str = ""

    @property
    def change_pct(self) -> float | None:
        b, c = self.baseline, self.current
        if _is_num(b) and _is_num(c) and b != 0 and math.isfinite(b) and math.isfinite(c):
            return 100.0 * (c - b) / abs(b)
        return None


@dataclass
class DiffReport:
    rows: list[DiffRow] = field(default_factory=list)
    rtol: float = 0.05
    atol: float = ATOL
    baseline: str = ""
    current: str = ""

    @property
    def regressed(self) -> bool:
        return any(r.status in ("regressed", "missing") for r in self.rows)

    def count(self, status: str) -> int:
        return sum(r.status == status for r in self.rows)

    def render(self, all_rows: bool = True) -> str:
        """A Markdown table (metric, baseline, current, change %, status) and a one-line verdict."""
        head = ["metric", "baseline", "current", "change %", "status"]
        rows = [r for r in self.rows if all_rows or r.status not in ("ok", "ignored", "info")]
        cells = [
            [
                r.metric,
                _fmt(r.baseline),
                _fmt(r.current),
                "" if r.change_pct is None else f"{r.change_pct:+.1f}",
                r.status + (f" ({r.note})" if r.note else ""),
            ]
            for r in rows
        ]
        widths = [max([len(h)] + [len(c[i]) for c in cells]) for i, h in enumerate(head)]
        line = lambda cs: "| " + " | ".join(c.ljust(w) for c, w in zip(cs, widths, strict=True)) + " |"  # noqa: E731
        out = [f"baseline: {self.baseline}", f"current:  {self.current}", ""] if self.baseline else []
        out += [line(head), "|" + "|".join("-" * (w + 2) for w in widths) + "|", *(line(c) for c in cells)]
        n_bad = self.count("regressed") + self.count("missing")
        verdict = (
            f"REGRESSED: {n_bad} metric(s) worse than baseline (rtol {self.rtol:g})"
            if self.regressed
            else f"OK: no regression (rtol {self.rtol:g}; {self.count('improved')} improved, {self.count('new')} new)"
        )
        return "\n".join([*out, "", verdict])


def _fmt(v: Any) -> str:
    if v is None:
        return "—"
    if _is_num(v):
        return f"{v:.6g}"
    return str(v)


def _worse(b: float, c: float, rtol: float, atol: float) -> str:
    """Status of a larger-is-worse magnitude (signed errors are compared by their absolute values)."""
    b, c = abs(b), abs(c)
    if math.isnan(c):
        return "ok" if math.isnan(b) else "regressed"
    if math.isnan(b):
        return "improved"
    if c > b * (1.0 + rtol) + atol:
        return "regressed"
    if c < b * (1.0 - rtol) - atol:
        return "improved"
    return "ok"


def _compare(key: str, b: Any, c: Any, base: dict, cur: dict, rtol: float, atol: float) -> tuple[str, str]:
    if _is_ignored(key):
        return "ignored", ""
    if not (_is_num(b) and _is_num(c)):
        return ("ok" if b == c else "changed"), ""
    b, c = float(b), float(c)
    if _is_nees_value(key):
        bb, cb = _bounds(base, key), _bounds(cur, key)
        if cb is not None:
            out_c = _outside(c, cb) if math.isfinite(c) else math.inf
            out_b = _outside(b, bb or cb) if math.isfinite(b) else math.inf
            if out_c == 0.0:
                if out_b > 0.0:
                    return "improved", "back inside χ² bounds"
                if abs(c - b) > rtol * abs(b) + atol:  # a seeded run that moved: the filter's belief changed
                    return (
                        "regressed",
                        f"moved {100 * (c - b) / abs(b):+.0f}% inside χ² bounds; re-baseline if meant",
                    )
                return "ok", "inside χ² bounds"
            if out_b == 0.0:
                return "regressed", f"left χ² bounds [{cb[0]:.3g}, {cb[1]:.3g}]"
            return _worse(out_b, out_c, rtol, atol), "outside χ² bounds in both"
        dof = _dof(cur, key)
        if dof is not None:
            return _worse(b / dof - 1, c / dof - 1, rtol, atol), f"|nees/dof - 1|, dof {dof:g}"
        return ("ok" if b == c else "info"), ""
    if _is_error(key):
        return _worse(b, c, rtol, atol), ""
    return ("ok" if b == c or (math.isnan(b) and math.isnan(c)) else "info"), ""


def diff_metrics(
    baseline: dict[str, Any], current: dict[str, Any], rtol: float = 0.05, atol: float = ATOL
) -> DiffReport:
    """Compare two flattened metric dicts (see :func:`flatten`)."""
    report = DiffReport(rtol=rtol, atol=atol)
    for key in sorted(set(baseline) | set(current), key=_sort_key):
        b, c = baseline.get(key), current.get(key)
        if key not in current:
            status = "ignored" if _is_ignored(key) else "missing"
            report.rows.append(DiffRow(key, b, None, status))
        elif key not in baseline:
            report.rows.append(DiffRow(key, None, c, "new"))
        else:
            status, note = _compare(key, b, c, baseline, current, rtol, atol)
            report.rows.append(DiffRow(key, b, c, status, note))
    return report


def _sort_key(key: str) -> list:
    return [(0, int(p), "") if p.isdigit() else (1, 0, p) for p in key.split(".")]


def diff_paths(baseline: Path, current: Path, rtol: float = 0.05, atol: float = ATOL) -> DiffReport:
    """``uwbcal diff``: compare the metrics of two files/folders; ``report.regressed`` -> exit code 1."""
    if not (math.isfinite(rtol) and rtol >= 0):
        raise InputError(f"--rtol {rtol}: must be a finite number >= 0 (e.g. 0.05)")
    base = load_metrics(baseline)
    if not any(_is_num(v) for k, v in base.items() if not _is_ignored(k)):
        raise InputError(
            f"{baseline}: no numeric metrics in the baseline; it would let anything pass — "
            "pass the metrics.json / summary.json of a finished run"
        )
    report = diff_metrics(base, load_metrics(current), rtol=rtol, atol=atol)
    report.baseline, report.current = str(baseline), str(current)
    return report
