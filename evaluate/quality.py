"""Data-quality checks of a run's ranges, reported as warnings in metrics.json: degenerate anchors (every range
zero or constant: a dead or stuck radio) and anchors whose ranges are biased against the calibrated model
(median residual far beyond the range noise, or a ranging offset γ far outside its prior).

A constant bias on all ranges of an anchor is exactly a ranging offset γ: it is only detectable against the γ
prior the calibration declares. With a loose prior (the simulator declares σ = 1 m) a +2 m bias is a 2σ offset,
which no test can call anomalous; with an informative one (NTU-VIRAL: 0.75 ± 0.01 m) it is flagged."""

from __future__ import annotations

import numpy as np

from uwbcal.convert.recording import TOPIC_RANGE
from uwbcal.pipeline.core.geometry import quat_to_rot
from uwbcal.pipeline.uwb.updater import range_lever_arms

MIN_RANGES = 10  # fewer ranges of an anchor: no verdict
BIAS_SIGMAS = 3.0  # |median residual| > max(3 sigma_range, BIAS_FLOOR_M): biased
BIAS_FLOOR_M = 0.3
PRIOR_SIGMAS = 3.0  # |gamma - prior mean| > 3 prior sigmas: prior-data conflict (chi2(1) at 99.7 %)


def degenerate_anchors(anchor: np.ndarray, distance: np.ndarray) -> list[str]:
    out = []
    for a in np.unique(anchor).tolist():
        d = distance[anchor == a]
        if len(d) < 2 or np.ptp(d) > 1e-6:
            continue
        what = "zero" if np.abs(d).max() < 1e-9 else f"equal ({d[0]:g} m)"
        out.append(
            f"anchor {a}: all {len(d)} ranges are {what}: degenerate ranging (dead or stuck radio); its "
            "calibration is meaningless — fix the ranging or drop the anchor"
        )
    return out


def biased_anchors(
    ranges, traj_t: np.ndarray, traj_p: np.ndarray, traj_q: np.ndarray, est: dict, cal: dict
) -> list[str]:
    """Median residual of each calibrated anchor's ranges against its estimate over the run's trajectory."""
    if len(traj_t) < 2 or not est:
        return []
    uwb = cal.get("uwb") or {}
    sigma = float(uwb.get("sigma_range") or 0.1)
    inside = (ranges.t_ns >= traj_t[0]) & (ranges.t_ns <= traj_t[-1])
    out = []
    for aid, e in est.items():
        try:
            a = int(aid)
        except ValueError:
            continue
        m = inside & (ranges.anchor == a)
        if m.sum() < MIN_RANGES:
            continue
        i = np.clip(np.searchsorted(traj_t, ranges.t_ns[m]), 0, len(traj_t) - 1)
        R = quat_to_rot(traj_q[i])
        tag_w = traj_p[i] + np.einsum(
            "nij,nj->ni", R, range_lever_arms(cal, ranges.tag[m], ranges.antenna[m])
        )
        pred = e["beta"] * np.linalg.norm(np.asarray(e["position"]) - tag_w, axis=1) + e["gamma"]
        med = float(np.median(ranges.distance[m] - pred))
        if abs(med) > max(BIAS_SIGMAS * sigma, BIAS_FLOOR_M):
            out.append(
                f"anchor {a}: range residuals biased by {med:+.2f} m (median of {int(m.sum())}, sigma_range "
                f"{sigma:g} m): NLOS, a wrong ranging offset or a moved anchor — check this anchor"
            )
        gp = uwb.get("gamma_prior") or {}
        mean, s = gp.get("mean"), gp.get("sigma")
        if mean is not None and s and abs(e["gamma"] - float(mean)) > PRIOR_SIGMAS * float(s):
            out.append(
                f"anchor {a}: ranging offset gamma {e['gamma']:+.2f} m is {abs(e['gamma'] - mean) / s:.0f} "
                f"sigma from its prior ({mean:g} +- {s:g} m): the ranges are biased — check this anchor"
            )
    return out


def range_quality(reader, traj, est: dict) -> list[str]:
    """All range-quality warnings of a run (reader: the recording; traj: RunTrajectory; est: final anchors)."""
    if TOPIC_RANGE not in reader.topics():
        return []
    r = reader.read_ranges()
    out = degenerate_anchors(r.anchor, r.distance)
    if len(traj):
        out += biased_anchors(r, traj.t_ns, traj.p, traj.q_xyzw, est, reader.calibration)
    return out
