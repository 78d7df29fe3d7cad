"""The range-to-pose clock offset of a recording: UWB ranges often reach the recorder a fixed latency after the
poses they belong to (a driver's filter, a radio link), and a range compared with the pose of the wrong instant
errs by the carrier's speed times that latency.

`estimate_clock` scans the offset tau (ranges re-stamped t + tau) over ``[-max_s, max_s]``: at each tau every
determined anchor's position is refitted (the base family of `evidence.fit_family`, each anchor's deflation kept)
and their deflated robust costs summed; a parabola through the best grid point and its neighbours refines tau, its
curvature gives sigma. The offset enters by the evidence rule of the anchors' optional parameters: its log evidence
(prior N(0, ``prior_s^2``)) must beat no offset by the Bayes factor `evidence.BAYES_FACTOR`.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass, replace

import numpy as np

from uwbcal.pipeline.uwb.evidence import BAYES_FACTOR, FitSpec, fit_anchor, fit_family
from uwbcal.pipeline.uwb.initializer import InitWindow
from uwbcal.pipeline.uwb.search import subsample

PRIOR_S = 0.2  # prior sigma of a UWB message path's latency [s]


@dataclass(frozen=True)
class ClockOffset:
    offset_s: float  # estimated shift of the range stamps (t_pose = t_range + offset)
    sigma_s: float
    used: bool
    log_bayes: float  # log evidence of the offset over none
    anchors: int  # anchors the scan used

    @property
    def applied_s(self) -> float:
        return self.offset_s if self.used else 0.0

    def summary(self) -> dict:
        return {
            "offset_s": round(self.offset_s, 4),
            "sigma_s": round(self.sigma_s, 4),
            "used": self.used,
            "log_bayes_factor": round(self.log_bayes, 2),
            "anchors": self.anchors,
        }

    def message(self) -> str:
        verb = "used" if self.used else "not used (the evidence does not demand it)"
        return (
            f"range clock offset {self.offset_s:+.3f} +- {self.sigma_s:.3f} s (ranges re-stamped by it), {verb}; "
            f"log Bayes factor {self.log_bayes:+.1f} over {self.anchors} anchors"
        )


NO_OFFSET = ClockOffset(0.0, float("inf"), False, float("-inf"), 0)


def _costs(windows_at, fits: Mapping, specs: Mapping, grid: np.ndarray) -> np.ndarray:
    """Summed deflated cost of every anchor's position refitted (from its fit at tau = 0) at each offset of
    ``grid``."""
    out = np.zeros(len(grid))
    for i, tau in enumerate(grid):
        for a, w in windows_at(float(tau)).items():
            s2 = np.full(len(w), specs[a].sigma_range ** 2)
            li = np.zeros(len(w), np.int64)
            m = fits[a]
            out[i] += fit_family(w.tag_xyz, w.d, li, 1, s2, "position", m.p, specs[a], warm=m).cost
    return out


def estimate_clock(
    windows_at: Callable[[float], Mapping[int, InitWindow]],
    spec: FitSpec,
    *,
    max_s: float = 0.5,
    step_s: float = 0.02,
    prior_s: float = PRIOR_S,
    max_ranges: int = 500,
) -> ClockOffset:
    """The clock offset from ``windows_at(tau)``: each anchor's ranges re-stamped by tau (the same ranges at every
    tau). Only anchors the evidence fit determines at tau = 0 take part, each with its deflation."""
    base = windows_at(0.0)
    keep, fits, specs = {}, {}, {}
    for a, w in base.items():
        k = subsample(len(w), max_ranges)
        sub = w.subset(np.isin(np.arange(len(w)), k))
        sr = fit_anchor(sub.tag_xyz, sub.d, t_ns=sub.t_ns, spec=replace(spec, max_ranges=max_ranges))
        if sr.ok:
            keep[a], specs[a] = k, replace(spec, deflate=float(sr.costs.get("kappa", 1.0)))
            s2 = np.full(len(sub), spec.sigma_range**2)
            li = np.zeros(len(sub), np.int64)
            fits[a] = fit_family(sub.tag_xyz, sub.d, li, 1, s2, "position", sr.p, specs[a])
    if not keep:
        return NO_OFFSET

    def sub_at(tau: float) -> dict[int, InitWindow]:
        ws = windows_at(tau)
        return {a: ws[a].subset(np.isin(np.arange(len(ws[a])), k)) for a, k in keep.items()}

    grid = np.arange(-max_s, max_s + 0.5 * step_s, step_s)
    c = _costs(sub_at, fits, specs, grid)
    k = int(np.clip(np.argmin(c), 1, len(grid) - 2))
    a2 = (c[k + 1] - 2 * c[k] + c[k - 1]) / step_s**2  # the cost's curvature
    if not np.isfinite(a2) or a2 <= 0:
        return NO_OFFSET
    tau = float(np.clip(grid[k] - (c[k + 1] - c[k - 1]) / (2 * a2 * step_s), -max_s, max_s))
    c_tau, c0 = _costs(sub_at, fits, specs, np.array([tau, 0.0]))
    info = 0.5 * a2  # -log likelihood = cost / 2
    log_bf = 0.5 * (c0 - c_tau) - 0.5 * tau**2 / prior_s**2 - 0.5 * np.log(1.0 + info * prior_s**2)
    used = bool(log_bf > np.log(BAYES_FACTOR))
    return ClockOffset(tau, float(1.0 / np.sqrt(info)), used, float(log_bf), len(keep))
