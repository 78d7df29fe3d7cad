"""Tables: one polars frame rendered as Markdown, CSV or LaTeX (booktabs), and the paper's numbers.

Floats are printed with 3 decimals (``digits``); missing values as an em dash in Markdown/LaTeX and empty in CSV.
"""

from __future__ import annotations

import io
import math
from collections.abc import Sequence
from pathlib import Path

import polars as pl

from uwbcal.pipeline.core.atomic import write_text_atomic
from uwbcal.pipeline.core.errors import InputError

FORMATS = {"md": ".md", "csv": ".csv", "latex": ".tex"}

# Paper Table 1 (simulation, EuRoC MH_01 trajectory): PRMSE [m] and anchor error [m] per (sigma_I, sigma_U).
PAPER_TABLE1 = pl.DataFrame(
    {
        "sigma_i": [0.1, 0.1, 0.3, 0.3, 0.3, 0.3, 0.5, 0.5],
        "sigma_u": [1.0, 1.0, 1.0, 1.0, 0.9, 0.9, 0.9, 0.9],
        "method": ["skf", "ekf"] * 4,
        "prmse_m": [0.452, 0.379, 0.487, 0.466, 0.489, 0.546, 0.495, 0.679],
        "anchor_error_m": [0.312, 0.271, 0.346, 0.349, 0.352, 0.408, 0.422, 0.771],
    }
)

# Paper Table 2 (NTU-VIRAL): PRMSE [m], ORMSE [deg] and anchor error [m]. VIRO = LSI + EKF.
PAPER_TABLE2 = pl.DataFrame(
    {
        "sequence": ["eee_01"] * 3 + ["eee_03"] * 3 + ["nya_01"] * 3,
        "method": ["viro", "ri+ekf", "ri+skf"] * 3,
        "init": ["lsi", "ri", "ri"] * 3,
        "refine": ["ekf", "ekf", "skf"] * 3,
        "prmse_m": [0.351, 0.300, 0.287, 0.329, 0.289, 0.325, 0.326, 0.319, 0.301],
        "ormse_deg": [5.725, 5.723, 5.626, 4.867, 4.865, 4.871, 4.652, 4.674, 4.600],
        "anchor_error_m": [0.485, 0.408, 0.346, 0.425, 0.422, 0.429, 0.412, 0.388, 0.375],
    }
)


def _cell(v, digits: int | None, missing: str) -> str:
    if v is None or (isinstance(v, float) and math.isnan(v)):
        return missing
    if isinstance(v, float):
        return repr(v) if digits is None else f"{v:.{digits}f}"
    if isinstance(v, bool):
        return "yes" if v else "no"
    return str(v)


def format_rows(df: pl.DataFrame, digits: int | None = 3, missing: str = "—") -> list[list[str]]:
    """Rows of strings (floats to ``digits`` decimals, ``None`` keeps full precision)."""
    return [[_cell(v, digits, missing) for v in row] for row in df.iter_rows()]


def _is_numeric(df: pl.DataFrame, col: str) -> bool:
    return df.schema[col].is_numeric()


def to_markdown(df: pl.DataFrame, digits: int | None = 3) -> str:
    rows = format_rows(df, digits)
    head = [str(c) for c in df.columns]
    widths = [max([len(h)] + [len(r[i]) for r in rows]) for i, h in enumerate(head)]
    right = [_is_numeric(df, c) for c in df.columns]

    def line(cells: Sequence[str]) -> str:
        return (
            "| "
            + " | ".join(
                c.rjust(w) if r else c.ljust(w) for c, w, r in zip(cells, widths, right, strict=True)
            )
            + " |"
        )

    rule = (
        "|"
        + "|".join(
            ("-" * (w + 1) + ":") if r else ("-" * (w + 2)) for w, r in zip(widths, right, strict=True)
        )
        + "|"
    )
    return "\n".join([line(head), rule, *(line(r) for r in rows)]) + "\n"


def to_csv(df: pl.DataFrame, digits: int | None = 3) -> str:
    import csv

    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(df.columns)
    w.writerows(format_rows(df, digits, missing=""))
    return buf.getvalue()


_LATEX_ESCAPES = {
    "\\": r"\textbackslash{}",
    "&": r"\&",
    "%": r"\%",
    "$": r"\$",
    "#": r"\#",
    "_": r"\_",
    "{": r"\{",
    "}": r"\}",
    "~": r"\textasciitilde{}",
    "^": r"\textasciicircum{}",
}


def latex_escape(s: str) -> str:
    return "".join(_LATEX_ESCAPES.get(ch, ch) for ch in s)


def to_latex(
    df: pl.DataFrame, digits: int | None = 3, caption: str | None = None, label: str | None = None
) -> str:
    """A booktabs ``tabular`` (wrapped in ``table`` when a caption or label is given)."""
    rows = format_rows(df, digits, missing="--")
    spec = "".join("r" if _is_numeric(df, c) else "l" for c in df.columns)
    body = [
        f"\\begin{{tabular}}{{{spec}}}",
        "\\toprule",
        " & ".join(latex_escape(str(c)) for c in df.columns) + " \\\\",
        "\\midrule",
        *(" & ".join(latex_escape(c) for c in r) + " \\\\" for r in rows),
        "\\bottomrule",
        "\\end{tabular}",
    ]
    if caption is None and label is None:
        return "\n".join(body) + "\n"
    out = ["\\begin{table}", "\\centering"]
    if caption is not None:
        out.append(f"\\caption{{{latex_escape(caption)}}}")
    if label is not None:
        out.append(f"\\label{{{label}}}")
    return "\n".join([*out, *body, "\\end{table}"]) + "\n"


def render(df: pl.DataFrame, fmt: str = "md", digits: int | None = 3) -> str:
    """``fmt`` in ``md``, ``csv``, ``latex``."""
    if fmt == "md":
        return to_markdown(df, digits)
    if fmt == "csv":
        return to_csv(df, digits)
    if fmt == "latex":
        return to_latex(df, digits)
    raise InputError(f"table format '{fmt}' unknown; use one of {', '.join(FORMATS)}")


def write_tables(
    df: pl.DataFrame,
    stem: str | Path,
    formats: Sequence[str] = ("md", "csv", "latex"),
    digits: int | None = 3,
) -> list[Path]:
    """Write ``stem.md``, ``stem.csv``, ``stem.tex`` atomically; returns the paths written."""
    stem = Path(stem)
    out = []
    for fmt in formats:
        path = stem.with_name(stem.name + FORMATS[fmt])
        write_text_atomic(path, render(df, fmt, digits))
        out.append(path)
    return out


def side_by_side(
    ours: pl.DataFrame,
    paper: pl.DataFrame,
    on: Sequence[str],
    metrics: Sequence[str] | None = None,
    suffixes: tuple[str, str] = ("ours", "paper"),
) -> pl.DataFrame:
    """Our numbers next to the paper's: for each metric ``m`` the columns ``m_ours``, ``m_paper`` (left join on
    ``on``, keeping our rows and order; a metric the paper lacks is null)."""
    if metrics is None:
        metrics = [c for c in ours.columns if c not in on and c in paper.columns]
    missing = [c for c in on if c not in ours.columns or c not in paper.columns]
    if missing:
        raise InputError(f"side_by_side: key column(s) {missing} missing in one of the tables")
    a, b = suffixes
    left = ours.select([*on, *[pl.col(m).alias(f"{m}_{a}") for m in metrics if m in ours.columns]])
    right = paper.select([*on, *[pl.col(m).alias(f"{m}_{b}") for m in metrics if m in paper.columns]])
    # join keys of float type (sigma grids) are compared after rounding, so 0.30000000000000004 == 0.3
    keys = []
    for k in on:
        if ours.schema[k].is_float():
            left = left.with_columns(pl.col(k).round(9))
            right = right.with_columns(pl.col(k).cast(pl.Float64).round(9))
        elif paper.schema[k] != ours.schema[k]:
            right = right.with_columns(pl.col(k).cast(ours.schema[k]))
        keys.append(k)
    joined = left.join(right, on=keys, how="left", maintain_order="left")
    cols = list(on)
    for m in metrics:
        cols += [c for c in (f"{m}_{a}", f"{m}_{b}") if c in joined.columns]
    return joined.select(cols)
