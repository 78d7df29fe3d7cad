"""When each anchor is initialised: the paper's global windows, or per anchor as soon as its own data allow.

- ``windows`` (the paper): every anchor is initialised from the ranges of the first window and joins the
  refinement at its start; an anchor the window does not determine is reported "not determined".
- ``per-anchor``: an anchor determined by the first window joins at the refinement's start as before; any
  other is re-tried on growing prefixes of its own ranges (at fractions of its range count) and joins the
  refinement at the first prefix that determines it, however late in the run; one never determined is
  reported with the reason of its last attempt.

`choose_schedule` picks between them from the range stamps alone (before any pose is estimated): windows when
every anchor is ranged enough inside the first window, per-anchor otherwise.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from uwbcal.pipeline.uwb.evidence import AnchorFit
from uwbcal.pipeline.uwb.window import InitWindow


def choose_schedule(
    t_ns: np.ndarray,
    anchor: np.ndarray,
    init_end_ns: int,
    *,
    min_ranges: int = 30,
    min_fraction: float = 0.2,
) -> tuple[str, str]:
    """("windows" | "per-anchor", why). An anchor ranged at least ``min_ranges`` times in the recording is
    "late" when fewer than ``min_ranges`` or fewer than ``min_fraction`` of its ranges fall before
    ``init_end_ns``; any late anchor -> per-anchor."""
    t_ns = np.asarray(t_ns, np.int64)
    anchor = np.asarray(anchor)
    late = []
    for a in np.unique(anchor):
        m = anchor == a
        n = int(m.sum())
        if n < min_ranges:
            continue
        early = int(np.sum(t_ns[m] < init_end_ns))
        if early < min_ranges or early < min_fraction * n:
            late.append(f"{a} ({early}/{n})")
    if late:
        return "per-anchor", f"anchors ranged mostly after the first window: {', '.join(late)}"
    return "windows", "every anchor is ranged within the first window"


@dataclass
class Join:
    join_ns: int | None  # None: never determined
    window: InitWindow  # the ranges its initialisation uses
    search: AnchorFit


def candidate_ends(t_ns: np.ndarray, init_end_ns: int, steps: int = 8) -> list[int]:
    """The first window's end, then the stamps after it at which the anchor's own range count reaches k /
    ``steps`` of its total (k = 1..steps; the last one takes every range)."""
    t = np.sort(np.asarray(t_ns, np.int64))
    ends = [int(init_end_ns)]
    if not len(t):
        return ends
    for k in range(1, steps + 1):
        i = int(np.ceil(k / steps * len(t))) - 1
        te = int(t[i]) + 1  # strictly after the k-th fraction's last range
        if te > ends[-1]:
            ends.append(te)
    return ends


def join_time(
    window: InitWindow,
    init_end_ns: int,
    search: Callable[[InitWindow], AnchorFit],
    *,
    per_anchor: bool = True,
    steps: int = 8,
    min_ranges: int = 30,
    join_sigma: float | None = None,
    join_ratio: float = 0.02,
) -> Join:
    """When ``window``'s anchor (all its ranges, time-stamped) becomes determined: the first candidate end
    (`candidate_ends`) whose prefix ``search`` accepts with a horizontal sigma <= min(``join_sigma``,
    ``join_ratio`` x its median range) (None: any), else all its ranges if ``search`` accepts them;
    ``per_anchor`` False: the first window only. The bar is relative to the range too: the refinement keeps
    the anchor's Jacobians at its first estimate (FEJ), whose direction error is sigma / range."""
    assert window.t_ns is not None, "join_time needs time-stamped ranges"
    ends = candidate_ends(window.t_ns, init_end_ns, steps) if per_anchor else [int(init_end_ns)]
    for te in ends:  # the last end is never passed over: it ends the search
        m = window.t_ns < te
        if int(m.sum()) < min_ranges and te != ends[-1]:
            continue
        sub = window.subset(m)
        sr = search(sub)
        bar = None if join_sigma is None else min(join_sigma, join_ratio * float(np.median(sub.d)))
        if te == ends[-1] or (sr.ok and (bar is None or sr.sigma_horizontal <= bar)):
            break
    return Join(te if sr.ok else None, sub, sr)
