"""The range-to-pose clock offset of a recording: UWB ranges often reach the recorder a fixed latency after the
poses they belong to (a driver's filter, a radio link), and a range compared with the pose of the wrong instant
errs by the carrier's speed times that latency.

`estimate_clock` scans the offset tau (ranges re-stamped t + tau) over ``[-max_s, max_s]``: at each tau every
determined anchor is refitted in the family its evidence chose, with its range offset free in any case (each
anchor's deflation kept), and their deflated robust costs summed; a parabola through the best grid point and its
neighbours refines tau. A second scan about that offset takes each anchor's model and deflation there. Sigma is
the sandwich of the offset's score series (correlated in time and across anchors as it is) plus what the poses'
declared error does to it. The offset enters by the evidence rule of the anchors' optional parameters: its log
evidence (prior N(0, ``prior_s^2``)) must beat no offset by the Bayes factor `evidence.BAYES_FACTOR`.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass, field, replace

import numpy as np

from uwbcal.pipeline.core.series import autocorrelation_time, correlated_errors_covariance
from uwbcal.pipeline.uwb.evidence import (
    BAYES_FACTOR,
    FitSpec,
    Model,
    fit_anchor,
    fit_family,
    range_losses,
)
from uwbcal.pipeline.uwb.model import lines_of_sight
from uwbcal.pipeline.uwb.window import InitWindow, subsample

PRIOR_S = 0.2  # prior sigma of a UWB message path's latency [s]
NEAR_S = 0.1  # [s] the second pass scans this far about the first pass's offset


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
    fit: Model  # its chosen family, its offset free, where the scan measured it (`_scan_anchors`)
    chosen: Model  # its chosen family there (what its reported position moves by)


def _costs(windows_at, anchors: Mapping, grid: np.ndarray) -> np.ndarray:
    """(len(grid),): the deflated robust cost of every anchor's ranges with its scan family refitted (from its fit
    where the scan measured it) at each offset of ``grid``."""
    out = np.zeros(len(grid))
    for i, tau in enumerate(grid):
        ws = windows_at(float(tau))
        for a, an in anchors.items():
            m, s2 = _refit(ws[a], an)
            out[i] += float(np.sum(range_losses(m, s2, an.spec)))
    return out


def _offset_variance(windows_at, anchors: Mapping, tau: float, h: float, pose_tau_s: float | None) -> float:
    """The variance of the offset estimate: what the ranges show (the sandwich of its score series, each range's
    weighted residual times the residual's derivative in the offset with the anchors refitted at tau +- h, over
    every anchor's ranges in time order, its long-run variance by the series' integrated autocorrelation time),
    plus what the poses' declared error does to it (`core.series.correlated_errors_covariance`). A pose error that
    differs between a leg driven away from the anchors and one driven back is the offset's own signature: the fit
    takes it, the residuals do not show it."""
    at, hi, lo = (windows_at(float(x)) for x in (tau, tau + h, tau - h))
    stamps, scores, gains, sig2, info = [], [], [], [], 0.0
    for a, an in anchors.items():
        m, s2 = _refit(at[a], an)
        w = at[a].subset(an.keep)
        dr = (_refit(hi[a], an)[0].r - _refit(lo[a], an)[0].r) / (2.0 * h)
        g = m.w * dr / s2
        u = lines_of_sight(m.p, w.tag_xyz)
        scores.append(g * m.r)
        gains.append(g[:, None] * u)  # the offset's response to each tag position error, times info
        sig2.append(np.trace(w.P_pose[:, 3:6, 3:6], axis1=1, axis2=2) / 3.0)
        info += float(np.sum(g * dr))
        stamps.append(w.t_ns)
    if info <= 0:
        return float("inf")
    order = np.argsort(np.concatenate(stamps), kind="stable")
    s = np.concatenate(scores)[order]
    t = np.concatenate(stamps)[order] * 1e-9
    pose = correlated_errors_covariance(
        np.concatenate(gains)[order][:, None], np.concatenate(sig2)[order], t, pose_tau_s
    )[0, 0]
    return (autocorrelation_time(s) * float(np.sum(s**2)) + pose) / info**2


def _refit(window: InitWindow, an: _Anchor, fit: Model | None = None) -> tuple[Model, np.ndarray]:
    """The anchor's scan family (or the family of ``fit``) refitted from its fit on its ranges of ``window``; and
    the ranges' variances."""
    w = window.subset(an.keep)
    li = np.searchsorted(an.links, w.links()).clip(0, len(an.links) - 1)
    s2 = np.full(len(w), an.spec.sigma_range**2)
    m = fit or an.fit
    return fit_family(w.tag_xyz, w.d, li, len(an.links), s2, m.name, m.p, an.spec, warm=m), s2


def _positions(windows_at, anchors: Mapping, tau: float) -> dict:
    """Each anchor's position in its chosen family, refitted with the ranges re-stamped by ``tau``."""
    ws = windows_at(float(tau))
    return {a: _refit(ws[a], an, an.chosen)[0].p for a, an in anchors.items()}


def _vertex(grid: np.ndarray, c: np.ndarray) -> tuple[float, float]:
    """The minimum of ``c`` over ``grid`` refined by the parabola through it and its neighbours, and the
    curvature there (nan when it is not a minimum)."""
    step = grid[1] - grid[0]
    k = int(np.clip(np.argmin(c), 1, len(grid) - 2))
    a2 = (c[k + 1] - 2 * c[k] + c[k - 1]) / step**2
    if not np.isfinite(a2) or a2 <= 0:
        return float(grid[k]), float("nan")
    return float(np.clip(grid[k] - (c[k + 1] - c[k - 1]) / (2 * a2 * step), grid[0], grid[-1])), float(a2)


def _scan_anchors(windows_at, at: float, spec: FitSpec, max_ranges: int) -> dict:
    """The anchors the evidence fit determines on their ranges re-stamped by ``at``: each with the family it chose
    there, its offset free in any case (held at its mean, an offset the model leaves out trades against the clock:
    on a leg driven straight away from the anchor a late range and a long one look alike), and its deflation."""
    anchors = {}
    for a, w in windows_at(at).items():
        keep = subsample(len(w), max_ranges)
        sub = w.subset(keep)
        fit_spec = replace(spec, max_ranges=max_ranges, refine_cov=False)
        sr = fit_anchor(sub.tag_xyz, sub.d, sub.links(), t_ns=sub.t_ns, spec=fit_spec)
        if not sr.ok:
            continue
        sa = replace(spec, deflate=float(sr.costs.get("kappa", 1.0)))
        li = np.searchsorted(sr.links, sub.links()).clip(0, len(sr.links) - 1)
        s2 = np.full(len(sub), spec.sigma_range**2)
        data = (sub.tag_xyz, sub.d, li, len(sr.links), s2)
        chosen = fit_family(*data, sr.costs["evidence"]["model"], sr.p, sa)
        fit = fit_family(*data, "gamma", sr.p, sa) if chosen.name == "position" else chosen
        anchors[a] = _Anchor(keep, sr.links, sa, fit, chosen)
    return anchors


def estimate_clock(
    windows_at: Callable[[float], Mapping[int, InitWindow]],
    spec: FitSpec,
    *,
    max_s: float = 0.5,
    step_s: float = 0.02,
    prior_s: float = PRIOR_S,
    max_ranges: int = 500,
    pose_tau_s: float | None = None,
) -> ClockOffset:
    """The clock offset from ``windows_at(tau)``: each anchor's ranges re-stamped by tau (the same ranges at every
    tau). Only anchors the evidence fit determines take part, each with its chosen family (its offset free) and
    its deflation, measured at 0 and again at the first scan's offset (`_scan_anchors`), whose neighbourhood a
    second scan refines. The offset's own deflation is the variance of its score series over the curvature's
    (`_offset_variance`: the anchors share the pose's error, so their evidence is not independent). ``shift``: each
    anchor's position change per second of offset (central difference over +-sigma), what the offset's error does
    to the anchors. ``pose_tau_s``: the correlation time of the poses' errors (None: they drift, a random walk).
    """
    grid = np.arange(-max_s, max_s + 0.5 * step_s, step_s)
    tau = 0.0
    for near in (None, NEAR_S):
        # the second pass takes each anchor's model and deflation at the first pass's offset: at 0 they are those
        # of ranges compared with the wrong poses (a deflation of 1000 on a late drive, and the model it leaves)
        anchors = _scan_anchors(windows_at, tau, spec, max_ranges)
        if not anchors:
            return NO_OFFSET
        if near is not None:
            grid = grid[np.abs(grid - tau) <= near + 1e-9]
        tau, a2 = _vertex(grid, _costs(windows_at, anchors, grid))
        if not np.isfinite(a2):
            return NO_OFFSET
    info = 0.5 * a2  # -log likelihood = cost / 2
    deflate = max(_offset_variance(windows_at, anchors, tau, step_s, pose_tau_s) * info, 1.0)
    c_tau, c0 = _costs(windows_at, anchors, np.array([tau, 0.0]))
    info /= deflate
    log_bf = 0.5 * (c0 - c_tau) / deflate - 0.5 * tau**2 / prior_s**2 - 0.5 * np.log(1.0 + info * prior_s**2)
    used = bool(log_bf > np.log(BAYES_FACTOR))
    sigma = float(1.0 / np.sqrt(info))
    h = max(min(sigma, max_s), step_s)
    hi, lo = _positions(windows_at, anchors, tau + h), _positions(windows_at, anchors, tau - h)
    shift = {a: (hi[a] - lo[a]) / (2.0 * h) for a in anchors}
    return ClockOffset(tau, sigma, used, float(log_bf), len(anchors), shift)
