"""Time association of an estimate with ground truth by interpolation (not nearest neighbour).

Ground truth is interpolated at the estimate's stamps: positions linearly, orientations by slerp. Estimate stamps
outside the ground-truth span, or inside a ground-truth gap longer than ``max_gap_ns``, are dropped and counted.

Ground-truth glitches (:func:`glitch_mask`) are dropped before interpolating, and counted: a short run of samples
that jumps away from the sample before it and back to the sample after it by more than any carrier can rotate or
move in those sample intervals, while the samples either side agree with each other, is a measurement fault (a
motion-capture marker swap fits the rigid body 10-150 deg off for 1-4 samples), not motion.

Ground truth of a point on the body (NTU-VIRAL Leica prism: ``p_prism = p_body + R_body @ lever``) is compared
with the estimate moved to the same point (:func:`lever_point`), never the other way round, because position-only
ground truth has no orientation to move it back with.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from uwbcal.pipeline.core.errors import InputError
from uwbcal.pipeline.core.geometry import quat_slerp, quat_to_rot
from uwbcal.pipeline.core.series import bracket

# A gap in the ground truth longer than this many median sampling intervals is not interpolated across.
AUTO_GAP_FACTOR = 10

# Ground-truth glitch bounds: what no carrier this tool meets (hand-held rigs, MAVs, ground robots, cars) performs:
# 1000 deg/s is 5-15x the fastest turns of the hand-held rig and the MAV flights here and half a usual
# MEMS gyro range, 50 m/s (180 km/h) beyond every carrier here (docs/results/measurements.md: the carriers' rates
# and the samples dropped per dataset). A sample interval counts at least the median ground-truth interval:
# arrival-stamped motion capture bunches samples 0.1 ms apart (their motion took a full interval).
GLITCH_MAX_RATE_RAD_S = np.radians(1000.0)
GLITCH_MAX_SPEED_M_S = 50.0
GLITCH_MAX_SAMPLES = 5  # longest run judged (motion capture's marker swaps on INRoL asc1 last 1-4 samples)


@dataclass
class Association:
    """Ground truth at the kept estimate stamps. ``idx`` indexes the estimate arrays that were kept."""

    idx: np.ndarray  # int64 [M], indices into the estimate
    t_ns: np.ndarray  # int64 [M]
    p: np.ndarray  # [M, 3] ground-truth positions
    q_xyzw: np.ndarray | None  # [M, 4] ground-truth orientations (None for position-only ground truth)
    n_outside: int  # estimate stamps outside the ground-truth span
    n_gap: int  # estimate stamps inside a ground-truth gap > max_gap_ns
    max_gap_ns: int
    n_gt_glitches: int = 0  # ground-truth samples dropped as glitches (glitch_mask)

    @property
    def n_dropped(self) -> int:
        return self.n_outside + self.n_gap

    def __len__(self) -> int:
        return len(self.idx)


def _clean_gt(
    t_gt: np.ndarray, p_gt: np.ndarray, q_gt: np.ndarray | None
) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """Sort by stamp and drop repeated stamps (first kept) and non-finite samples."""
    t_gt = np.asarray(t_gt, np.int64).reshape(-1)
    p_gt = np.asarray(p_gt, float).reshape(-1, 3)
    if len(p_gt) != len(t_gt):
        raise InputError(f"ground truth: {len(t_gt)} stamps but {len(p_gt)} positions; lengths must match")
    ok = np.isfinite(p_gt).all(axis=1)
    if q_gt is not None:
        q_gt = np.asarray(q_gt, float).reshape(-1, 4)
        if len(q_gt) != len(t_gt):
            raise InputError(
                f"ground truth: {len(t_gt)} stamps but {len(q_gt)} orientations; lengths must match"
            )
        ok &= np.isfinite(q_gt).all(axis=1) & (np.linalg.norm(q_gt, axis=1) > 0)
    order = np.argsort(t_gt[ok], kind="stable")
    keep = np.flatnonzero(ok)[order]
    t = t_gt[keep]
    first = np.concatenate([[True], np.diff(t) > 0])
    keep = keep[first]
    return t_gt[keep], p_gt[keep], (None if q_gt is None else q_gt[keep])


def _reachable(
    t: np.ndarray, p: np.ndarray, q: np.ndarray | None, i: np.ndarray, j: np.ndarray, dt_min: float
) -> np.ndarray:
    """Whether a carrier can go from sample ``i`` to sample ``j`` (index arrays) within the bounds."""
    dt = np.maximum(np.abs(t[j] - t[i]) * 1e-9, dt_min)
    ok = np.linalg.norm(p[j] - p[i], axis=1) <= GLITCH_MAX_SPEED_M_S * dt
    if q is not None:
        qi = q[i] / np.linalg.norm(q[i], axis=1, keepdims=True)
        qj = q[j] / np.linalg.norm(q[j], axis=1, keepdims=True)
        angle = 2.0 * np.arccos(np.clip(np.abs(np.sum(qi * qj, axis=1)), 0.0, 1.0))
        ok &= angle <= GLITCH_MAX_RATE_RAD_S * dt
    return ok


def glitch_mask(t_gt: np.ndarray, p_gt: np.ndarray, q_gt: np.ndarray | None) -> np.ndarray:
    """Ground-truth samples (sorted, unique stamps) that are measurement glitches: a run of at most
    ``GLITCH_MAX_SAMPLES`` whose first sample no carrier can reach from the sample before it, whose last sample
    cannot reach the sample after it, while the samples either side of the run can reach each other (the
    ``GLITCH_*`` bounds). A sample without a neighbour on both sides (the ends) is never judged."""
    n = len(t_gt)
    bad = np.zeros(n, bool)
    if n < 3:
        return bad
    dt_min = float(np.median(np.diff(t_gt))) * 1e-9
    step = np.arange(n - 1)
    jumps = np.flatnonzero(~_reachable(t_gt, p_gt, q_gt, step, step + 1, dt_min))
    is_jump = np.zeros(n, bool)
    is_jump[jumps] = True  # is_jump[k]: sample k cannot reach sample k + 1
    last_end = -1
    for i in jumps:  # i: the last good sample before a jump away
        if i <= last_end:
            continue
        for end in range(i + 1, min(i + GLITCH_MAX_SAMPLES, n - 2) + 1):  # end: the run's last sample
            if is_jump[end] and _reachable(t_gt, p_gt, q_gt, np.array([i]), np.array([end + 1]), dt_min)[0]:
                bad[i + 1 : end + 1] = True
                last_end = end
                break
    return bad


def auto_max_gap_ns(t_gt: np.ndarray) -> int:
    """Default gap limit: ``AUTO_GAP_FACTOR`` times the median ground-truth sampling interval."""
    dt = np.diff(np.asarray(t_gt, np.int64))
    return int(AUTO_GAP_FACTOR * np.median(dt)) if len(dt) else 0


def associate(
    t_est: np.ndarray,
    t_gt: np.ndarray,
    p_gt: np.ndarray,
    q_gt: np.ndarray | None = None,
    *,
    max_gap_ns: int | None = None,
) -> Association:
    """Ground truth interpolated at the estimate stamps ``t_est`` (int64 ns).

    ``max_gap_ns``: a query whose bracketing ground-truth samples are further apart than this is dropped;
    ``None`` means ``AUTO_GAP_FACTOR`` x the median ground-truth interval.
    """
    t_est = np.asarray(t_est, np.int64).reshape(-1)
    t_gt, p_gt, q_gt = _clean_gt(t_gt, p_gt, q_gt)
    glitch = glitch_mask(t_gt, p_gt, q_gt)
    if glitch.any():
        t_gt, p_gt = t_gt[~glitch], p_gt[~glitch]
        q_gt = None if q_gt is None else q_gt[~glitch]
    if len(t_gt) < 2:
        raise InputError(
            f"ground truth: {len(t_gt)} valid sample(s); at least 2 are needed to interpolate at the estimate"
        )
    gap = auto_max_gap_ns(t_gt) if max_gap_ns is None else int(max_gap_ns)
    inside = (t_est >= t_gt[0]) & (t_est <= t_gt[-1])
    cand = np.flatnonzero(inside)
    i0, i1, s = bracket(t_gt, t_est[cand])
    exact = s == 0.0
    exact |= s == 1.0
    # a query that hits a ground-truth stamp exactly is never inside a gap
    ok = exact | ((t_gt[i1] - t_gt[i0]) <= gap)
    idx = cand[ok]
    i0, i1, s = i0[ok], i1[ok], s[ok]
    p = p_gt[i0] + s[:, None] * (p_gt[i1] - p_gt[i0])
    q = None if q_gt is None else quat_slerp(q_gt[i0], q_gt[i1], s)
    return Association(
        idx=idx.astype(np.int64),
        t_ns=t_est[idx],
        p=p,
        q_xyzw=q,
        n_outside=int(len(t_est) - len(cand)),
        n_gap=int(len(cand) - len(idx)),
        max_gap_ns=gap,
        n_gt_glitches=int(glitch.sum()),
    )


def lever_point(p: np.ndarray, q_xyzw: np.ndarray, lever: np.ndarray | None) -> np.ndarray:
    """Position of the body point ``lever`` (body frame): ``p + R(q) @ lever`` for (N, 3)/(N, 4) poses."""
    p = np.asarray(p, float)
    if lever is None or not np.any(np.asarray(lever, float)):
        return p.copy()
    R = quat_to_rot(np.asarray(q_xyzw, float))
    return p + R @ np.asarray(lever, float).reshape(3)
