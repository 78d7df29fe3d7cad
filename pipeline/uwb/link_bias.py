"""The range offset model of an anchor ranged over several links (``uwb.bias = "auto"``): per-link or per-anchor.

Per-link offsets (one gamma per (anchor, tag antenna) link) are the right model when the links' offsets differ by
a constant, as a per-antenna delay does. Two things must hold, and both are tested on the global search's fit
(`anchor_search.SearchResult`: position, beta, one offset per link, their covariance) and the anchor's ranges:

1. The offsets differ beyond their uncertainty: `link_offset_contrast`, one joint Wald test of the L - 1 contrasts
   (every offset minus the first) against their own covariance. The offsets share the anchor's range error (a
   radial shift moves them all), so their differences are far better determined than each offset alone, and one
   joint test keeps its false-alarm rate whatever the number of links.
2. The difference is a constant of the link, i.e. it predicts ranges it was not fitted to: `link_offset_cv_gains`,
   blocked cross-validation with the robust (Cauchy) loss over contiguous time blocks and over the sides of the
   carrier that face the anchor (`bearing_sectors`); both gains must be positive. Differences that come from the
   geometry rather than the link (an antenna pattern, the body shadowing the far antenna, NLOS seen by one antenna
   for a while) change with the part of the run or the side that faces the anchor, and a per-link model would
   bake the run's geometry into the offsets. NTU-VIRAL nya_01 anchor 102: contrast chi2 24.9 (3 dof), but a link's
   median residual runs -0.70, -0.38, +0.12, -0.08 m over the flight's quarters (time gain -0.18); per-link moved
   it 0.078 -> 0.122 m from its published position. eee_01 anchor 102: chi2 116, time gain +0.35 (the loops
   repeat), bearing gain -1.25 (the antenna on the side away from the anchor reads long). cuhksz_mid: tag 0
   reads ~0.05 m long on every anchor (gains +0.14..+0.21 where the contrast test passes): a delay.

Pure functions of arrays; `uwb_filter.initialize_anchors` applies the decision and writes its evidence into the
anchor's verdict (``verdict.bias``).
"""

from __future__ import annotations

import numpy as np

from uwbcal.pipeline.core.state import chi2_ppf
from uwbcal.pipeline.uwb.planar_levers import carrier_heading
from uwbcal.pipeline.uwb.search import SearchResult, subsample

FALSE_ALARM = (
    0.0027  # the two-sided 3-sigma level: equal offsets switch 0.27 % of anchors on the contrast test
)
CV_FOLDS = 4
CV_MIN_RANGES = 10  # a link with fewer ranges in the training blocks is predicted by the common offset
CV_MAX_RANGES = 8000  # ranges used by the cross-validation (evenly subsampled)


def link_offset_contrast(sr: SearchResult) -> tuple[float, int]:
    """(chi2, dof) of the hypothesis that all of an anchor's link offsets are equal: c = C gamma (L - 1 contrasts)
    against C P C^T (P the search's residual-scaled, correlation-inflated offset covariance). (nan, 0) when there
    is nothing to test."""
    L = len(sr.gamma)
    if not sr.ok or L < 2:
        return float("nan"), 0
    C = np.eye(L)[1:] - np.eye(L)[0]
    c = C @ np.asarray(sr.gamma, float)
    S = C @ np.asarray(sr.cov, float)[3:, 3:] @ C.T
    if not (np.all(np.isfinite(c)) and np.all(np.isfinite(S))):
        return float("nan"), 0
    return float(c @ np.linalg.lstsq(S, c, rcond=1e-12)[0]), L - 1


def _cv_gain(e: np.ndarray, link: np.ndarray, fold: np.ndarray, c2: float) -> float:
    """Relative held-out Cauchy-cost reduction of per-link medians over the common median, each fold held out
    in turn (folds with fewer than CV_MIN_RANGES training ranges are not scored)."""
    per_link = common = 0.0
    for f in np.unique(fold):
        train, test = fold != f, fold == f
        if train.sum() < CV_MIN_RANGES:
            continue
        g0 = float(np.median(e[train]))
        pred = np.full(int(test.sum()), g0)
        for lid in np.unique(link[test]):
            m = train & (link == lid)
            if m.sum() >= CV_MIN_RANGES:
                pred[link[test] == lid] = np.median(e[m])
        per_link += float(np.sum(np.log1p((e[test] - pred) ** 2 / c2)))
        common += float(np.sum(np.log1p((e[test] - g0) ** 2 / c2)))
    return (common - per_link) / common if common > 0 else float("nan")


def bearing_sectors(R: np.ndarray, xyz: np.ndarray, p: np.ndarray, sectors: int = 4) -> np.ndarray:
    """The side of the carrier that faces the anchor at each range: the anchor's direction in the body frame,
    as ``sectors`` equal sectors of azimuth about the carrier's yaw axis in the body frame: the body axis the
    world's up is on average, or, when the attitude has none (poses whose attitude is in another convention than
    the world's: it spins about an in-plane axis), the body axis it spins about (`planar_levers.carrier_heading`)."""
    R = np.asarray(R, float)
    up = np.mean(R[:, 2, :], axis=0)  # world z in the body frame, R^T e_z, averaged
    if np.linalg.norm(up) < 0.5:
        up = carrier_heading(R, np.array([0.0, 0.0, 1.0])).axis
    up = up / np.linalg.norm(up)
    a1 = np.cross(up, [1.0, 0.0, 0.0] if abs(up[0]) < 0.9 else [0.0, 1.0, 0.0])
    a1 /= np.linalg.norm(a1)
    a2 = np.cross(up, a1)
    v = np.einsum("nji,nj->ni", R, p - xyz)
    az = np.arctan2(v @ a2, v @ a1)
    return np.floor((az + np.pi) / (2 * np.pi / sectors)).astype(np.int64).clip(0, sectors - 1)


def link_offset_cv_gains(
    sr: SearchResult,
    xyz: np.ndarray,
    d: np.ndarray,
    link: np.ndarray,
    t_ns: np.ndarray | None = None,
    R: np.ndarray | None = None,
) -> dict[str, float]:
    """Do the per-link offsets predict ranges they were not fitted to? Relative reduction of the held-out robust
    cost when each link's offset is its own median instead of the median over all links (> 0: they do), at the
    search's position and range scale, Cauchy loss at 3 x the search's inlier sigma (its second pass's scale, so
    NLOS junk cannot decide), in two blocked cross-validations: ``time`` over CV_FOLDS contiguous time blocks
    (errors that come and go with the part of the run), ``bearing`` over the sides of the carrier that face the
    anchor (`bearing_sectors`, given the attitudes ``R``: an antenna pattern or the body shadowing the far
    antenna; a delay is the same from every side)."""
    xyz = np.asarray(xyz, float).reshape(-1, 3)
    d = np.asarray(d, float).reshape(-1)
    link = np.asarray(link).reshape(-1)
    t = np.arange(len(d)) if t_ns is None else np.asarray(t_ns)
    fin = np.isfinite(d) & np.all(np.isfinite(xyz), axis=1) & (d > 0)
    idx = np.flatnonzero(fin)
    idx = idx[np.argsort(t[idx], kind="stable")]
    idx = idx[subsample(len(idx), CV_MAX_RANGES)]
    if not sr.ok or len(idx) < CV_FOLDS * CV_MIN_RANGES:
        return {}
    e = d[idx] - sr.beta * np.linalg.norm(xyz[idx] - sr.p, axis=1)  # offset + noise, in time order
    lk = link[idx]
    c2 = (3.0 * max(float(sr.scale), 1e-3)) ** 2
    out = {"time": _cv_gain(e, lk, np.arange(len(e)) * CV_FOLDS // len(e), c2)}
    if R is not None:
        out["bearing"] = _cv_gain(e, lk, bearing_sectors(np.asarray(R)[idx], xyz[idx], sr.p), c2)
    return out


def per_link_supported(
    sr: SearchResult,
    xyz: np.ndarray | None = None,
    d: np.ndarray | None = None,
    link: np.ndarray | None = None,
    t_ns: np.ndarray | None = None,
    R: np.ndarray | None = None,
    false_alarm: float = FALSE_ALARM,
) -> bool:
    """The per-link model is supported: the offsets differ (`link_offset_contrast` above the chi2 quantile of
    ``false_alarm``) and, given the ranges (``xyz``, ``d``, ``link``, ``t_ns``, attitudes ``R``), the differences
    predict held-out ranges in every cross-validation (`link_offset_cv_gains` > 0)."""
    return bias_evidence(sr, xyz, d, link, t_ns, R, false_alarm)["model"] == "per-link"


def bias_evidence(
    sr: SearchResult,
    xyz: np.ndarray | None = None,
    d: np.ndarray | None = None,
    link: np.ndarray | None = None,
    t_ns: np.ndarray | None = None,
    R: np.ndarray | None = None,
    false_alarm: float = FALSE_ALARM,
) -> dict:
    """The decision of `per_link_supported` with its evidence, for the anchor's verdict: ``model``, and where
    there are several links ``link_contrast_chi2``/``_dof``/``_threshold`` and (when the contrast test passes)
    ``link_cv_gain`` {time, bearing}."""
    chi2, dof = link_offset_contrast(sr)
    if dof == 0:
        return {"model": "per-anchor"}
    out = {
        "link_contrast_chi2": chi2,
        "link_contrast_dof": dof,
        "link_contrast_threshold": chi2_ppf(1.0 - false_alarm, dof),
    }
    differ = chi2 > out["link_contrast_threshold"]
    if differ and xyz is not None and d is not None and link is not None:
        out["link_cv_gain"] = gains = link_offset_cv_gains(sr, xyz, d, link, t_ns, R)
        differ = bool(gains) and all(g > 0 for g in gains.values())
    return {"model": "per-link" if differ else "per-anchor"} | out
