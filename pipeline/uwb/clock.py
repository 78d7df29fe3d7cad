"""The range-to-pose clock offset of a recording: UWB ranges often reach the recorder a fixed latency after the
poses they belong to (a driver's filter, a radio link), and a range compared with the pose of the wrong instant
errs by the carrier's speed times that latency.

`estimate_clock` scans the offset tau (ranges re-stamped t + tau) over ``[-max_s, max_s]``: at each tau every
determined anchor is refitted in the family its evidence chose, with its range offset free in any case (each
anchor's deflation kept), and their deflated robust costs summed; a parabola through the best grid point and its neighbours refines tau, its
curvature gives sigma. The offset enters by the evidence rule of the anchors' optional parameters: its log evidence
(prior N(0, ``prior_s^2``)) must beat no offset by the Bayes factor `evidence.BAYES_FACTOR`.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass, field, replace

import numpy as np

from uwbcal.pipeline.uwb.evidence import BAYES_FACTOR, FitSpec, Model, fit_anchor, fit_family, range_losses
from uwbcal.pipeline.uwb.window import InitWindow, subsample

PRIOR_S = 0.2  # prior sigma of a UWB message path's latency [s]


@dataclass(frozen=True)
class ClockOffset:
    offset_s: float  # estimated shift of the range stamps (t_pose = t_range + offset)
    sigma_s: float
    used: bool
    log_bayes: float  # log evidence of the offset over none
    anchors: int  # anchors the scan used
    shift: Mapping = field(default_factory=dict)  # anchor -> d position / d offset [m/s] (3,)

    @property
    def applied_s(self) -> float:
        return self.offset_s if self.used else 0.0

    def position_cov(self, anchor) -> np.ndarray:
        """(3, 3) what the clock's error about the applied offset does to the anchor's position, through the
        anchor's shift per second: the offset's mean squared error under the two models weighted by their
        evidence (no offset; the estimate +- sigma)."""
        if anchor not in self.shift:
            return np.zeros((3, 3))
        p1 = float(1.0 / (1.0 + np.exp(-np.clip(self.log_bayes, -50.0, 50.0))))
        a = self.applied_s
        err2 = (1.0 - p1) * a**2 + p1 * (self.sigma_s**2 + (self.offset_s - a) ** 2)
        g = np.asarray(self.shift[anchor], float)
        return err2 * np.outer(g, g)

    def summary(self) -> dict:
        return {
            "offset_s": round(self.offset_s, 4),
            "sigma_s": round(self.sigma_s, 4),
            "used": self.used,
            "log_bayes_factor": round(self.log_bayes, 2),
            "anchors": self.anchors,
            "anchor_shift_m_per_s": {str(a): np.round(g, 3).tolist() for a, g in self.shift.items()},
        }

    def message(self) -> str:
        verb = "used" if self.used else "not used (the evidence does not demand it)"
        return (
            f"range clock offset {self.offset_s:+.3f} +- {self.sigma_s:.3f} s (ranges re-stamped by it), {verb}; "
            f"log Bayes factor {self.log_bayes:+.1f} over {self.anchors} anchors"
        )


NO_OFFSET = ClockOffset(0.0, float("inf"), False, float("-inf"), 0)


@dataclass(frozen=True)
class _Anchor:
    keep: np.ndarray  # indices of the scanned ranges in the anchor's window
    links: np.ndarray  # the fit's link ids
    spec: FitSpec  # with the anchor's deflation
    fit: Model  # its chosen family (its offset free) at tau = 0
    block: np.ndarray  # the time block of each scanned range (blocks common to every anchor)


def _block_costs(windows_at, anchors: Mapping, grid: np.ndarray, blocks: int) -> np.ndarray:
    """(len(grid), blocks): the deflated robust cost of each time block's ranges (over every anchor) with each
    anchor's chosen family refitted (from its fit at tau = 0) at each offset of ``grid``."""
    out = np.zeros((len(grid), blocks))
    for i, tau in enumerate(grid):
        ws = windows_at(float(tau))
        for a, an in anchors.items():
            m, s2 = _refit(ws[a], an)
            out[i] += np.bincount(an.block, range_losses(m, s2, an.spec), minlength=blocks)
    return out


def _refit(window: InitWindow, an: _Anchor) -> tuple[Model, np.ndarray]:
    """The anchor's family refitted from its fit on its ranges of ``window``; and the ranges' variances."""
    w = window.subset(an.keep)
    li = np.searchsorted(an.links, w.links()).clip(0, len(an.links) - 1)
    s2 = np.full(len(w), an.spec.sigma_range**2)
    return fit_family(w.tag_xyz, w.d, li, len(an.links), s2, an.fit.name, an.fit.p, an.spec, warm=an.fit), s2


def _positions(windows_at, anchors: Mapping, tau: float) -> dict:
    """Each anchor's position refitted (its family, from its fit) with the ranges re-stamped by ``tau``."""
    ws = windows_at(float(tau))
    return {a: _refit(ws[a], an)[0].p for a, an in anchors.items()}


def _vertex(grid: np.ndarray, c: np.ndarray) -> tuple[float, float]:
    """The minimum of ``c`` over ``grid`` refined by the parabola through it and its neighbours, and the
    curvature there (nan when it is not a minimum)."""
    step = grid[1] - grid[0]
    k = int(np.clip(np.argmin(c), 1, len(grid) - 2))
    a2 = (c[k + 1] - 2 * c[k] + c[k - 1]) / step**2
    if not np.isfinite(a2) or a2 <= 0:
        return float(grid[k]), float("nan")
    return float(np.clip(grid[k] - (c[k + 1] - c[k - 1]) / (2 * a2 * step), grid[0], grid[-1])), float(a2)


def estimate_clock(
    windows_at: Callable[[float], Mapping[int, InitWindow]],
    spec: FitSpec,
    *,
    max_s: float = 0.5,
    step_s: float = 0.02,
    prior_s: float = PRIOR_S,
    max_ranges: int = 500,
    blocks: int = 10,
) -> ClockOffset:
    """The clock offset from ``windows_at(tau)``: each anchor's ranges re-stamped by tau (the same ranges at every
    tau). Only anchors the evidence fit determines at tau = 0 take part, each with its chosen family (its offset
    free) and its deflation. The offset's own deflation is measured by a block jackknife over time (the anchors share the pose's
    error, so their evidence is not independent): the scatter of the offsets with each time block left out over
    the curvature's variance. ``shift``: each anchor's position change per second of offset (central difference
    over +-sigma), what the offset's error does to the anchors."""
    anchors = {}
    base = windows_at(0.0)
    stamps = np.concatenate([w.t_ns for w in base.values()]) if base else np.zeros(0, np.int64)
    edges = np.quantile(stamps, np.linspace(0.0, 1.0, blocks + 1)[1:-1]) if len(stamps) else np.zeros(0)
    for a, w in base.items():
        keep = subsample(len(w), max_ranges)
        sub = w.subset(keep)
        sr = fit_anchor(
            sub.tag_xyz,
            sub.d,
            sub.links(),
            t_ns=sub.t_ns,
            spec=replace(spec, max_ranges=max_ranges, refine_cov=False),
        )
        if not sr.ok:
            continue
        sa = replace(spec, deflate=float(sr.costs.get("kappa", 1.0)))
        li = np.searchsorted(sr.links, sub.links()).clip(0, len(sr.links) - 1)
        s2 = np.full(len(sub), spec.sigma_range**2)
        # the offset is a nuisance of the scan: held at its mean, an offset the anchor's model leaves out trades
        # against the clock (on a leg driven straight away from the anchor a late range and a long one look alike)
        name = sr.costs["evidence"]["model"]
        name = "gamma" if name == "position" else name
        fit = fit_family(sub.tag_xyz, sub.d, li, len(sr.links), s2, name, sr.p, sa)
        anchors[a] = _Anchor(keep, sr.links, sa, fit, np.searchsorted(edges, sub.t_ns))
    if not anchors:
        return NO_OFFSET
    grid = np.arange(-max_s, max_s + 0.5 * step_s, step_s)
    C = _block_costs(windows_at, anchors, grid, blocks)
    tau, a2 = _vertex(grid, C.sum(axis=1))
    if not np.isfinite(a2):
        return NO_OFFSET
    loo = np.array([_vertex(grid, C.sum(axis=1) - C[:, b])[0] for b in range(blocks)])
    var_jk = (blocks - 1) / blocks * float(np.sum((loo - loo.mean()) ** 2))
    info = 0.5 * a2  # -log likelihood = cost / 2
    deflate = max(var_jk * info, 1.0)
    c_tau, c0 = _block_costs(windows_at, anchors, np.array([tau, 0.0]), blocks).sum(axis=1)
    info /= deflate
    log_bf = 0.5 * (c0 - c_tau) / deflate - 0.5 * tau**2 / prior_s**2 - 0.5 * np.log(1.0 + info * prior_s**2)
    used = bool(log_bf > np.log(BAYES_FACTOR))
    sigma = float(1.0 / np.sqrt(info))
    h = max(min(sigma, max_s), step_s)
    hi, lo = _positions(windows_at, anchors, tau + h), _positions(windows_at, anchors, tau - h)
    shift = {a: (hi[a] - lo[a]) / (2.0 * h) for a in anchors}
    return ClockOffset(tau, sigma, used, float(log_bf), len(anchors), shift)
