"""Heights flagged unobservable at initialisation, regained when the motion later reveals them.

The initialisation window may be near-planar (a ground stretch, a flight at one height) while the vehicle
moves vertically later. Refinement leaves a flagged height alone (`UwbUpdater.fixed_height`: no z column, so
a tilting tag's lever arm cannot walk it to either side of the motion plane), so on its own it never gets it.
`HeightRegain` keeps each flagged anchor's ranges since initialisation with the filter's pose (and covariance)
at their stamps, and whenever their count has grown by ``growth`` x since the last attempt re-runs the search
(`anchor_search.search_anchor` through the configured `uwb_filter.search_window`: the same height verdict,
spread along the normal against the pose and lever-arm corruption, mirror test) on the initialisation window
plus those ranges. When the search now finds the height observable, the anchor is re-initialised from all of
them (the configured initialiser with that search); the refinement then replaces the anchor's variable by the
new one (`UwbUpdater._regain`), whose ranges so far are all in the new estimate (none counted twice).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from uwbcal.pipeline.uwb.initializer import InitResult, InitWindow
from uwbcal.pipeline.uwb.search import SearchResult


@dataclass
class _Buffer:
    rows: list[tuple] = field(default_factory=list)  # (t_ns, d, link, p_T, R, p, P6)
    next_n: int = 0  # attempt when the window holds this many ranges


@dataclass
class Regained:
    t_ns: int  # stamp of the range that completed the window
    n_ranges: int
    z_before: float
    result: InitResult


def _concat(w: InitWindow, rows: list[tuple]) -> InitWindow:
    t, d, lk, pT, R, p, P6 = (np.asarray(v) for v in zip(*rows, strict=True))
    t0 = w.t_ns if w.t_ns is not None else np.zeros(len(w), np.int64)
    return InitWindow(
        np.r_[w.d, d],
        np.concatenate([w.p_T, pT.reshape(-1, 3)]),
        np.concatenate([w.R, R.reshape(-1, 3, 3)]),
        np.concatenate([w.p, p.reshape(-1, 3)]),
        np.concatenate([w.P_pose, P6.reshape(-1, 6, 6)]),
        np.r_[t0, t.astype(np.int64)],
        np.r_[w.links(), lk.astype(np.int64)],
    )


class HeightRegain:
    """Watches the anchors of ``results`` whose height initialisation flagged unobservable (see module doc).

    ``search`` (InitWindow -> SearchResult) and ``initialise`` (anchor, InitWindow, SearchResult -> InitResult)
    are the configured search and initialiser; ``growth``: attempt whenever the window has grown by this factor
    since the last attempt (a few searches over a run, not one per range)."""

    def __init__(
        self,
        results: dict[Any, InitResult],
        search: Callable[[InitWindow], SearchResult],
        initialise: Callable[[Any, InitWindow, SearchResult], InitResult],
        growth: float = 1.5,
    ) -> None:
        self.search = search
        self.initialise = initialise
        self.growth = float(growth)
        self.watch = {
            a: r
            for a, r in results.items()
            if r.ok and r.window is not None and not r.verdict.get("height_observable", True)
        }
        self.buffers = {
            a: _Buffer(next_n=int(np.ceil(len(r.window) * self.growth))) for a, r in self.watch.items()
        }
        self.regained: dict[Any, Regained] = {}

    def __contains__(self, anchor: Any) -> bool:
        return anchor in self.watch

    def record(
        self,
        anchor: Any,
        t_ns: int,
        d: float,
        link: int,
        p_T: np.ndarray,
        R: np.ndarray,
        p: np.ndarray,
        P6: np.ndarray,
        z_now: float,
    ) -> InitResult | None:
        """Keep one range of a watched anchor; the new initialisation when this range completes a window whose
        search finds the height observable (the anchor is then no longer watched), else None."""
        r = self.watch.get(anchor)
        if r is None:
            return None
        buf = self.buffers[anchor]
        buf.rows.append(
            (
                int(t_ns),
                float(d),
                int(link),
                np.array(p_T, float),
                np.array(R, float),
                np.array(p, float),
                np.array(P6, float),
            )
        )
        n = len(r.window) + len(buf.rows)
        if n < buf.next_n:
            return None
        buf.next_n = int(np.ceil(n * self.growth))
        w = _concat(r.window, buf.rows)
        sr = self.search(w)
        if not (sr.ok and sr.height_observable):
            return None
        new = self.initialise(anchor, w, sr)
        if not new.ok or not new.verdict.get("height_observable", False):
            return None
        self.regained[anchor] = Regained(int(t_ns), n, float(z_now), new)
        del self.watch[anchor]
        del self.buffers[anchor]
        return new

    def summary(self) -> dict[str, dict]:
        """Per regained anchor: when, from how many ranges, the height before and after with its sigma."""
        return {
            str(a): {
                "t_s": g.t_ns * 1e-9,
                "n_ranges": g.n_ranges,
                "z_before_m": g.z_before,
                "z_m": float(g.result.x[2]),
                "sigma_z_m": float(np.sqrt(max(g.result.cov[2, 2], 0.0))),
            }
            for a, g in self.regained.items()
        }
