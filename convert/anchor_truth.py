"""Surveyed / published anchor positions -> the ``uwbcal.truth`` record of a real recording.

Input: a CSV ``anchor,x,y,z`` (metres, in the frame of the recording's poses), optionally with a ``site`` column
(NTU-VIRAL's ``published_anchors.csv``: ``site,anchor,x,y,z``; the rows of one site are taken). Anchor ids are
integers (as in the ranges). Bad files raise `InputError` naming the file, the line and what to fix.

The record (beside the simulator's ``uwbcal.truth``)::

    {"kind": "surveyed" | "published" | "simulated",
     "anchors": {"<id>": {"position": [x, y, z]}},          # no beta/gamma: unknown on real data
     "anchors_file": {"path": ..., "sha256": ...},          # real data only
     "anchors_frame": "odometry" | "world" | "<other>"}     # odometry/world: the recording's pose frame

``anchors_frame`` other than ``odometry``/``world`` (e.g. NTU-VIRAL's SLICT frame in a bag converted without
SLICT poses) tells the evaluator that only frame-free figures (inter-anchor distances) are meaningful.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from uwbcal.convert.sources import read_csv_strings, sha256_file, to_float, to_int
from uwbcal.pipeline.core.errors import InputError

TRUTH_KINDS = ("surveyed", "published", "simulated")
POSE_FRAMES = ("odometry", "world")  # anchor truth expressed in the recording's own pose frame
COLUMNS = ("anchor", "x", "y", "z")


def read_anchor_truth(path: str | Path, site: str | None = None) -> dict[str, dict]:
    """``{"<id>": {"position": [x, y, z]}}`` from an ``anchor,x,y,z`` CSV (optional ``site`` column: with
    ``site`` given, only that site's rows; without, the file must hold one site)."""
    import polars as pl

    path = Path(path)
    df = read_csv_strings(path, COLUMNS, what="anchor truth CSV (anchor,x,y,z)")
    full = pl.read_csv(path, has_header=True, infer_schema_length=0)
    full.columns = [c.strip() for c in full.columns]
    if df.height == 0:
        raise InputError(f"{path}: no anchor rows; expected lines 'anchor,x,y,z'")
    line = np.arange(df.height) + 2  # file line of each row (header = line 1)
    ids = to_int(path, df, "anchor")  # every row must parse, whatever its site
    xyz = np.column_stack([to_float(path, df, c) for c in COLUMNS[1:]])
    if "site" in full.columns:
        sites = full["site"].cast(pl.Utf8).str.strip_chars().fill_null("").to_numpy().astype(str)
        if site is None:
            uniq = sorted(set(sites.tolist()))
            if len(uniq) > 1:
                raise InputError(
                    f"{path}: column 'site' holds several sites ({', '.join(uniq)}); give the site "
                    "(the sequence name starts with it) or split the file"
                )
        else:
            keep = sites == site
            if not keep.any():
                raise InputError(
                    f"{path}: no rows for site '{site}' (sites: {', '.join(sorted(set(sites.tolist())))}); "
                    "add the site's anchors or give another file"
                )
            ids, xyz, line = ids[keep], xyz[keep], line[keep]
    bad = ~np.isfinite(xyz).all(1)
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        raise InputError(
            f"{path}: line {line[i]}: anchor {ids[i]}: non-finite position {xyz[i].tolist()}; give x,y,z in metres"
        )
    uniq, counts = np.unique(ids, return_counts=True)
    if (counts > 1).any():
        a = int(uniq[counts > 1][0])
        rows = line[ids == a].tolist()
        raise InputError(
            f"{path}: lines {rows}: anchor {a} listed {len(rows)} times; keep one position per anchor"
        )
    return {str(int(a)): {"position": xyz[i].tolist()} for i, a in enumerate(ids.tolist())}


def truth_record(
    anchors: dict[str, dict], kind: str, path: str | Path | None = None, frame: str = "odometry"
) -> dict:
    """The ``uwbcal.truth`` record of a real recording (see the module docstring)."""
    if kind not in TRUTH_KINDS:
        raise ValueError(f"truth kind {kind!r}; expected one of {TRUTH_KINDS}")
    out: dict = {"kind": kind, "anchors": anchors, "anchors_frame": frame}
    if path is not None:
        out["anchors_file"] = {"path": str(path), "sha256": sha256_file(path)}
    return out


def truth_note(anchors: dict[str, dict], ranged: np.ndarray, path: Path) -> str:
    """A conversion note: how many anchors have truth, which ranged anchors have none and vice versa."""
    have = set(anchors)
    seen = {str(int(a)) for a in np.unique(ranged)}
    parts = [f"{path.name}: truth for {len(have)} anchors"]
    if seen - have:
        parts.append(f"ranged without truth: {', '.join(sorted(seen - have, key=lambda s: (len(s), s)))}")
    if have - seen:
        parts.append(f"truth without ranges: {', '.join(sorted(have - seen, key=lambda s: (len(s), s)))}")
    return "; ".join(parts)


def find_published_anchors(path: Path) -> Path | None:
    """NTU-VIRAL: ``published_anchors.csv`` in the sequence folder (or beside the bag), else its parent."""
    base = path if path.is_dir() else path.parent
    for cand in (base / "published_anchors.csv", base.parent / "published_anchors.csv"):
        if cand.is_file():
            return cand
    return None
