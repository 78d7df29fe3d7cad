"""Error metrics over associated (and, if wanted, aligned) arrays.

- PRMSE [m] = sqrt(mean ||p_hat - p||^2)
- ORMSE [deg] = sqrt(mean ||Log(R_hat^T R)||^2) * 180 / pi
- anchor error [m] = mean over anchors of ||p_hat_a - p_a||, with beta and gamma errors alongside; horizontal
  error ||(p_hat_a - p_a)_xy|| (z up); mean and max of both.
- inter-anchor distance error [m] = ||p_hat_i - p_hat_j|| - ||p_i - p_j|| over all pairs (frame-free: unchanged by
  any rigid motion of the estimate), mean |.| and max |.|.
Segments are boolean masks keyed by name (``init``, ``refine``, ``localize``, ``all``).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np

from uwbcal.pipeline.core.geometry import log_so3
from uwbcal.pipeline.core.names import SEGMENT_IDS


def position_errors(p_est: np.ndarray, p_gt: np.ndarray) -> np.ndarray:
    """Per-sample Euclidean position error [m], shape (N,)."""
    return np.linalg.norm(np.asarray(p_est, float) - np.asarray(p_gt, float), axis=-1)


def rotation_errors(R_est: np.ndarray, R_gt: np.ndarray) -> np.ndarray:
    """Per-sample rotation error angle [rad] ``||Log(R_hat^T R)||``, shape (N,)."""
    R_est = np.asarray(R_est, float).reshape(-1, 3, 3)
    R_gt = np.asarray(R_gt, float).reshape(-1, 3, 3)
    return np.linalg.norm(log_so3(np.swapaxes(R_est, -1, -2) @ R_gt), axis=-1)


def rms(x: np.ndarray) -> float:
    x = np.asarray(x, float)
    return float(np.sqrt(np.mean(x * x))) if x.size else float("nan")


def prmse(p_est: np.ndarray, p_gt: np.ndarray) -> float:
    """Position RMSE [m]."""
    return rms(position_errors(p_est, p_gt))


def ormse_deg(R_est: np.ndarray, R_gt: np.ndarray) -> float:
    """Orientation RMSE [deg]."""
    return float(np.degrees(rms(rotation_errors(R_est, R_gt))))


def segment_masks_from_ids(
    segment: np.ndarray, ids: Mapping[str, int] = SEGMENT_IDS
) -> dict[str, np.ndarray]:
    """Masks per named segment from per-sample segment ids (0 init, 1 refine, 2 localize), plus ``all``."""
    segment = np.asarray(segment)
    masks = {name: segment == i for name, i in ids.items()}
    masks["all"] = np.ones(len(segment), bool)
    return masks


def segment_masks_from_bounds(
    t_ns: np.ndarray, bounds: Mapping[str, tuple[int, int]]
) -> dict[str, np.ndarray]:
    """Masks per named segment from ``{name: (start_ns, end_ns)}`` (end exclusive), plus ``all``."""
    t_ns = np.asarray(t_ns, np.int64)
    masks = {name: (t_ns >= lo) & (t_ns < hi) for name, (lo, hi) in bounds.items()}
    masks["all"] = np.ones(len(t_ns), bool)
    return masks


def rmse_by_segment(
    errors: np.ndarray, masks: Mapping[str, np.ndarray], scale: float = 1.0
) -> dict[str, float]:
    """RMSE of per-sample errors within each mask; segments without samples are absent (never faked)."""
    errors = np.asarray(errors, float)
    return {name: rms(errors[m]) * scale for name, m in masks.items() if np.any(m)}


def prmse_by_segment(
    p_est: np.ndarray, p_gt: np.ndarray, masks: Mapping[str, np.ndarray]
) -> dict[str, float]:
    return rmse_by_segment(position_errors(p_est, p_gt), masks)


def ormse_deg_by_segment(
    R_est: np.ndarray, R_gt: np.ndarray, masks: Mapping[str, np.ndarray]
) -> dict[str, float]:
    return rmse_by_segment(rotation_errors(R_est, R_gt), masks, scale=180.0 / np.pi)


@dataclass
class AnchorErrors:
    """Per-anchor errors (estimate - truth) and their means; ``missing`` lists true anchors not estimated."""

    per_anchor: dict[str, dict[str, float]] = field(default_factory=dict)
    mean_m: float = float("nan")
    max_m: float = float("nan")
    mean_horizontal_m: float = float("nan")
    max_horizontal_m: float = float("nan")
    mean_abs_beta: float = float("nan")
    mean_abs_gamma: float = float("nan")
    missing: list[str] = field(default_factory=list)


def _anchor_pos(a: Mapping | np.ndarray) -> np.ndarray:
    if isinstance(a, Mapping):
        a = a.get("position", a.get("estimate"))
    return np.asarray(a, float).reshape(3)


def anchor_errors(estimates: Mapping, truth: Mapping) -> AnchorErrors:
    """Anchor errors for anchors present in both mappings.

    Both map anchor id -> ``{"position": [x, y, z], "beta": b, "gamma": g}`` (beta/gamma optional) or a plain
    3-vector; ids are compared as strings. Keys of ``per_anchor[id]``: ``error_m``, ``error_horizontal_m``,
    ``error_xyz`` (3 floats) and, when both sides have them, ``beta_error``, ``gamma_error``.
    """
    est = {str(k): v for k, v in estimates.items()}
    tru = {str(k): v for k, v in truth.items()}
    out = AnchorErrors(missing=sorted(set(tru) - set(est)))
    errs, beta_err, gamma_err = [], [], []
    for aid in sorted(set(est) & set(tru), key=lambda s: (len(s), s)):
        d = _anchor_pos(est[aid]) - _anchor_pos(tru[aid])
        row: dict = {
            "error_m": float(np.linalg.norm(d)),
            "error_horizontal_m": float(np.linalg.norm(d[:2])),
            "error_xyz": d.tolist(),
        }
        errs.append(row["error_m"])
        for key, acc in (("beta", beta_err), ("gamma", gamma_err)):
            e, t = est[aid], tru[aid]
            if (
                isinstance(e, Mapping)
                and isinstance(t, Mapping)
                and e.get(key) is not None
                and t.get(key) is not None
            ):
                row[f"{key}_error"] = float(e[key]) - float(t[key])
                acc.append(abs(row[f"{key}_error"]))
        out.per_anchor[aid] = row
    if errs:
        out.mean_m, out.max_m = float(np.mean(errs)), float(np.max(errs))
        horiz = [r["error_horizontal_m"] for r in out.per_anchor.values()]
        out.mean_horizontal_m, out.max_horizontal_m = float(np.mean(horiz)), float(np.max(horiz))
    if beta_err:
        out.mean_abs_beta = float(np.mean(beta_err))
    if gamma_err:
        out.mean_abs_gamma = float(np.mean(gamma_err))
    return out


@dataclass
class DistanceErrors:
    """Inter-anchor distance errors: ``per_pair["i-j"]`` = estimated - true distance [m] (i < j by id order)."""

    per_pair: dict[str, float] = field(default_factory=dict)
    mean_abs_m: float = float("nan")
    max_abs_m: float = float("nan")


def inter_anchor_distance_errors(estimates: Mapping, truth: Mapping) -> DistanceErrors:
    """Distance errors over all pairs of anchors present in both mappings (same forms as `anchor_errors`).
    Frame-free: a rotation, translation or reflection of the estimates leaves them unchanged."""
    est = {str(k): v for k, v in estimates.items()}
    tru = {str(k): v for k, v in truth.items()}
    ids = sorted(set(est) & set(tru), key=lambda s: (len(s), s))
    out = DistanceErrors()
    if len(ids) < 2:
        return out
    E = np.stack([_anchor_pos(est[a]) for a in ids])
    T = np.stack([_anchor_pos(tru[a]) for a in ids])
    i, j = np.triu_indices(len(ids), 1)
    err = np.linalg.norm(E[i] - E[j], axis=1) - np.linalg.norm(T[i] - T[j], axis=1)
    out.per_pair = {f"{ids[a]}-{ids[b]}": float(e) for a, b, e in zip(i, j, err, strict=True)}
    out.mean_abs_m, out.max_abs_m = float(np.mean(np.abs(err))), float(np.max(np.abs(err)))
    return out
