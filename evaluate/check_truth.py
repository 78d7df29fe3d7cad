"""`uwbcal check` against the anchors' truth: measured vs predicted ranges, the anchor-id assignment, the lever arms
and the range-to-pose clock offset, each judged by how well the ranges fit.

The fit measure is the robust scatter of the ranges about their prediction after a per-link line d = b |.| + g
(1.4826 x MAD, pooled over the links): a per-link scale and offset (which every UWB link has) do not count
against a hypothesis, a wrong anchor, lever arm or clock does.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from uwbcal.evaluate.check_data import CheckData
from uwbcal.pipeline.core.robust import mad_sigma

MAX_ROWS = 20_000  # the truth tests use an even subsample of the ranges (their precision is ~1/sqrt(n))
CLOCK_SCAN_S = 1.0  # offsets scanned: +-1 s
CLOCK_STEP_S = 0.02
CLOCK_MIN_S = 0.015  # an offset found below this is not named (the scan's resolution, refined by a parabola)
BETTER = 1.05  # a hypothesis is named when the one given scatters this much more (and by > MIN_GAIN_M)
MIN_GAIN_M = 0.003
FITTED_BETTER = 1.25  # a fitted lever arm (3 free parameters) must gain more to be named
SWAP_RATIO = 0.5  # an anchor's ranges fit another anchor's truth with under half the scatter
MISFIT_FRAC = 0.5  # an anchor with more of its ranges > 1 m off the prediction fits its truth not at all


def line_residuals(pred: np.ndarray, meas: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Residuals of ``meas`` about a robust line b * pred + g (least squares, refit without > 3 sigma), and [b, g]."""
    A = np.column_stack([pred, np.ones_like(pred)])
    keep = np.ones(len(pred), bool)
    coef = np.array([1.0, 0.0])
    for _ in range(2):
        if keep.sum() >= 3 and np.ptp(pred[keep]) > 1e-6:
            coef = np.linalg.lstsq(A[keep], meas[keep], rcond=None)[0]
        else:
            coef = np.array([1.0, float(np.median(meas - pred))])
        r = meas - A @ coef
        s = max(mad_sigma(r), 1e-6)
        keep = np.abs(r - np.median(r)) < 3 * s
    return meas - A @ coef, coef


@dataclass
class Sample:
    """The (sub)sampled ranges the truth tests share: indices into the recording's ranges and their link keys."""

    idx: np.ndarray
    link: np.ndarray  # link index per row


def sample(data: CheckData, shift_s: float = 0.0) -> Sample:
    r = data.ranges
    margin = round(shift_s * 1e9)
    ok = data.covered(r.t_ns - margin) & data.covered(r.t_ns + margin) & np.isin(r.anchor, list(data.truth))
    idx = np.flatnonzero(ok)
    if len(idx) > MAX_ROWS:
        idx = idx[np.linspace(0, len(idx) - 1, MAX_ROWS).astype(int)]
    key = np.column_stack([r.tag[idx], r.antenna[idx], r.anchor[idx]])
    link = np.unique(key, axis=0, return_inverse=True)[1].ravel() if len(idx) else np.zeros(0, int)
    return Sample(idx, link)


def scatter(
    data: CheckData, s: Sample, anchors: dict[int, np.ndarray] | None = None, shift_s=0.0, levers=None
) -> float:
    """Pooled robust scatter [m] of the sampled ranges about their per-link lines."""
    if not len(s.idx):
        return float("nan")
    anchors = data.truth if anchors is None else anchors
    x, _ = data.tag_positions(s.idx, shift_s, levers)
    a = np.array([anchors[int(k)] for k in data.ranges.anchor[s.idx]])
    pred = np.linalg.norm(a - x, axis=1)
    meas = data.ranges.distance[s.idx]
    res = np.empty(len(pred))
    for k in np.unique(s.link):
        m = s.link == k
        res[m] = line_residuals(pred[m], meas[m])[0]
    return mad_sigma(res)


# -- measured vs predicted ----------------------------------------------------------------------------------------
@dataclass
class LinkFit:
    anchor: int
    tag: int
    antenna: int
    n: int
    median_m: float  # of measured - predicted
    mad_m: float
    frac_over_1m: float


def predicted_vs_measured(data: CheckData, s: Sample) -> list[LinkFit]:
    r = data.ranges
    x, _ = data.tag_positions(s.idx)
    a = np.array([data.truth[int(k)] for k in r.anchor[s.idx]])
    e = r.distance[s.idx] - np.linalg.norm(a - x, axis=1)
    out = []
    for k in np.unique(s.link):
        m = s.link == k
        i = s.idx[m][0]
        ek = e[m]
        out.append(
            LinkFit(
                int(r.anchor[i]),
                int(r.tag[i]),
                int(r.antenna[i]),
                int(m.sum()),
                float(np.median(ek)),
                mad_sigma(ek),
                float(np.mean(np.abs(ek) > 1.0)),
            )
        )
    return out


# -- anchor ids -------------------------------------------------------------------------------------------------------
@dataclass
class IdCheck:
    ranged: list[int]
    truth_ids: list[int]
    cost: np.ndarray  # [ranged, truth] scatter of ranged anchor i's ranges at truth anchor j
    best: dict[int, int]  # ranged id -> truth id, the assignment of least scatter
    swapped: list[tuple[int, int, float, float]]  # (ranged, truth it fits, scatter there, scatter at its own)


def anchor_ids(data: CheckData) -> IdCheck:
    from scipy.optimize import linear_sum_assignment

    r = data.ranges
    ranged = [int(a) for a in np.unique(r.anchor)]
    truth_ids = sorted(data.truth)
    ok = data.covered(r.t_ns)
    cost = np.full((len(ranged), len(truth_ids)), np.inf)
    for i, a in enumerate(ranged):
        idx = np.flatnonzero(ok & (r.anchor == a))
        if len(idx) > MAX_ROWS // 4:
            idx = idx[np.linspace(0, len(idx) - 1, MAX_ROWS // 4).astype(int)]
        if len(idx) < 10:
            continue
        key = np.column_stack([r.tag[idx], r.antenna[idx]])
        s = Sample(idx, np.unique(key, axis=0, return_inverse=True)[1].ravel())
        for j, b in enumerate(truth_ids):
            cost[i, j] = scatter(data, s, {a: data.truth[b]})
    finite = np.where(np.isfinite(cost), cost, 1e6)
    rows, cols = linear_sum_assignment(finite)
    best = {ranged[i]: truth_ids[j] for i, j in zip(rows, cols, strict=True) if np.isfinite(cost[i, j])}
    swapped = []
    for a, b in best.items():
        if a == b or a not in data.truth:
            continue
        i, j, jj = ranged.index(a), truth_ids.index(b), truth_ids.index(a)
        if cost[i, j] < SWAP_RATIO * cost[i, jj]:
            swapped.append((a, b, float(cost[i, j]), float(cost[i, jj])))
    return IdCheck(ranged, truth_ids, cost, best, swapped)


# -- lever arms ---------------------------------------------------------------------------------------------------
@dataclass
class LeverCheck:
    tag: int
    antenna: int
    given: np.ndarray
    fitted: np.ndarray
    scatter: dict[str, float]  # given / zero / mirrored / fitted -> scatter [m]

    @property
    def best(self) -> str:
        return min(self.scatter, key=self.scatter.get)


def _fit_lever(
    data: CheckData, s: Sample, key: tuple[int, int], start: np.ndarray, shift_s: float
) -> np.ndarray:
    """Gauss-Newton on one antenna's lever arm, the per-link lines refitted each step (robust: 3-sigma trim)."""
    r = data.ranges
    mine = (r.tag[s.idx] == key[0]) & (r.antenna[s.idx] == key[1])
    idx, link = s.idx[mine], s.link[mine]
    a = np.array([data.truth[int(k)] for k in r.anchor[idx]])
    arm = start.copy()
    for _ in range(8):
        x, R = data.tag_positions(idx, shift_s, levers={**data.levers, key: arm})
        diff = a - x
        pred = np.linalg.norm(diff, axis=1)
        u = diff / np.maximum(pred, 1e-9)[:, None]
        res, J = np.empty(len(idx)), np.empty((len(idx), 3))
        for k in np.unique(link):
            m = link == k
            res[m], (b, _) = line_residuals(pred[m], r.distance[idx][m])
            J[m] = -b * np.einsum("ni,nij->nj", -u[m], R[m])  # d pred / d arm = -u^T R
        keep = np.abs(res) < 3 * max(mad_sigma(res), 1e-6)
        step = np.linalg.lstsq(J[keep], res[keep], rcond=None)[0]
        arm = arm - step
        if np.linalg.norm(step) < 1e-4:
            break
    return arm


def lever_arms(data: CheckData, s: Sample, shift_s: float = 0.0) -> list[LeverCheck]:
    if data.poses is None or data.poses.q_xyzw is None:
        return []
    r = data.ranges
    out = []
    keys = sorted({(int(t), int(a)) for t, a in zip(r.tag[s.idx], r.antenna[s.idx], strict=True)})
    for key in keys:
        mine = (r.tag[s.idx] == key[0]) & (r.antenna[s.idx] == key[1])
        sk = Sample(s.idx[mine], s.link[mine])
        given = data.levers.get(key, np.zeros(3))
        hyp = {"given": given, "zero": np.zeros(3)}
        if np.linalg.norm(given) > 0:
            hyp["mirrored"] = -given
        fitted = _fit_lever(data, s, key, given, shift_s)
        hyp["fitted"] = fitted
        sc = {
            name: scatter(data, sk, shift_s=shift_s, levers={**data.levers, key: arm})
            for name, arm in hyp.items()
        }
        out.append(LeverCheck(key[0], key[1], given, fitted, sc))
    return out


# -- clock offset -------------------------------------------------------------------------------------------------
@dataclass
class ClockCheck:
    offsets_s: np.ndarray
    scatter: np.ndarray
    best_s: float  # the shift of the poses that fits best: ranges stamped |best| late when negative
    at_zero: float
    at_best: float

    @property
    def found(self) -> bool:
        return abs(self.best_s) >= CLOCK_MIN_S and significant(self.at_zero, self.at_best)


def clock_offset(data: CheckData, s: Sample, levers=None) -> ClockCheck | None:
    if len(s.idx) < 30:
        return None
    taus = np.round(np.arange(-CLOCK_SCAN_S, CLOCK_SCAN_S + 1e-9, CLOCK_STEP_S), 6)
    sc = np.array([scatter(data, s, shift_s=float(t), levers=levers) for t in taus])
    k = int(np.nanargmin(sc))
    best = float(taus[k])
    if 0 < k < len(taus) - 1:  # parabola through the minimum and its neighbours
        y0, y1, y2 = sc[k - 1], sc[k], sc[k + 1]
        den = y0 - 2 * y1 + y2
        if den > 0:
            best += float(0.5 * (y0 - y2) / den * CLOCK_STEP_S)
    at_best = scatter(data, s, shift_s=best, levers=levers)
    return ClockCheck(taus, sc, best, float(sc[np.argmin(np.abs(taus))]), at_best)


def significant(given: float, best: float, ratio: float = BETTER) -> bool:
    """The best hypothesis scatters ``ratio`` times less than the given one, and by more than MIN_GAIN_M."""
    return bool(
        np.isfinite(given) and np.isfinite(best) and given > ratio * best and given - best > MIN_GAIN_M
    )
