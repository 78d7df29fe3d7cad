"""Sample-series helpers shared by the converters, the run log and the evaluator."""

from __future__ import annotations

import numpy as np

from uwbcal.pipeline.core.geometry import quat_slerp


def sliding_mean(x: np.ndarray, k: int) -> np.ndarray:
    """Mean of every ``k`` consecutive samples along axis 0 (``len(x) - k + 1`` of them; none when ``len(x) < k``),
    from one cumulative sum."""
    x = np.asarray(x, dtype=np.float64)
    if len(x) < k:
        return x[:0]
    c = np.concatenate([np.zeros((1, *x.shape[1:])), np.cumsum(x, axis=0)])
    return (c[k:] - c[:-k]) / k


def bracket(t_gt: np.ndarray, t_query: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Indices ``i0, i1 = i0 + 1`` of the ground-truth samples around each query stamp and the fraction ``s``.

    Requires ``len(t_gt) >= 2`` and queries inside ``[t_gt[0], t_gt[-1]]``.
    """
    i1 = np.clip(np.searchsorted(t_gt, t_query, side="left"), 1, len(t_gt) - 1)
    i0 = i1 - 1
    # integer differences first: float64 seconds since the epoch would lose the nanoseconds
    s = (t_query - t_gt[i0]).astype(float) / (t_gt[i1] - t_gt[i0]).astype(float)
    return i0, i1, s


def interpolate_positions(t_gt: np.ndarray, p_gt: np.ndarray, t_query: np.ndarray) -> np.ndarray:
    """Linear interpolation of (N, 3) positions at stamps inside the ground-truth span."""
    i0, i1, s = bracket(np.asarray(t_gt, np.int64), np.asarray(t_query, np.int64))
    p_gt = np.asarray(p_gt, float)
    return p_gt[i0] + s[:, None] * (p_gt[i1] - p_gt[i0])


def interpolate_quats(t_gt: np.ndarray, q_gt: np.ndarray, t_query: np.ndarray) -> np.ndarray:
    """Slerp of (N, 4) xyzw quaternions at stamps inside the ground-truth span."""
    i0, i1, s = bracket(np.asarray(t_gt, np.int64), np.asarray(t_query, np.int64))
    q_gt = np.asarray(q_gt, float)
    return quat_slerp(q_gt[i0], q_gt[i1], s)
