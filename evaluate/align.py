"""Trajectory alignment, kept apart from the metrics (as in evo).

An :class:`Alignment` maps estimate coordinates onto ground truth: ``p_gt ~= s R p_est + t`` and
``R_gt ~= R R_est``. Methods: ``none``, ``posyaw`` (4-DoF: yaw about world z + translation; the unobservable
directions of VIO), ``se3`` and ``sim3`` (Umeyama, 1991). :func:`initial_pose` is the gauge of a filter that
starts in its own gravity-aligned frame (yaw and position of its first pose), not a fit.

Alignment is fitted on associated positions (`evaluate.association`) and then applied to everything estimated in
the same frame: the trajectory and the anchors get the same :class:`Alignment`.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from uwbcal.pipeline.core.errors import InputError

METHODS = ("none", "posyaw", "se3", "sim3")


@dataclass(frozen=True)
class Alignment:
    R: np.ndarray = field(default_factory=lambda: np.eye(3))
    t: np.ndarray = field(default_factory=lambda: np.zeros(3))
    s: float = 1.0
    method: str = "none"

    def apply_positions(self, p: np.ndarray) -> np.ndarray:
        return self.s * (np.asarray(p, float) @ self.R.T) + self.t

    def apply_rotations(self, R_est: np.ndarray) -> np.ndarray:
        return self.R @ np.asarray(R_est, float)

    def matrix(self) -> np.ndarray:
        """4x4 ``[[s R, t], [0, 1]]``."""
        T = np.eye(4)
        T[:3, :3] = self.s * self.R
        T[:3, 3] = self.t
        return T


def apply(al: Alignment, p: np.ndarray, R: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray | None]:
    """Aligned positions (N, 3) and, when given, rotations (N, 3, 3)."""
    return al.apply_positions(p), (None if R is None else al.apply_rotations(R))


def _check(x: np.ndarray, y: np.ndarray, need: int, method: str) -> tuple[np.ndarray, np.ndarray]:
    x = np.asarray(x, float).reshape(-1, 3)
    y = np.asarray(y, float).reshape(-1, 3)
    if x.shape != y.shape:
        raise InputError(f"alignment '{method}': {len(x)} estimate vs {len(y)} ground-truth positions")
    if len(x) < need:
        raise InputError(
            f"alignment '{method}': {len(x)} associated position(s), at least {need} needed; "
            "check that the estimate overlaps the ground truth in time"
        )
    return x, y


def umeyama(x: np.ndarray, y: np.ndarray, with_scale: bool = False) -> Alignment:
    """Least-squares ``R, t, s`` minimising ``sum ||y_i - (s R x_i + t)||^2`` (Umeyama 1991)."""
    method = "sim3" if with_scale else "se3"
    x, y = _check(x, y, 3, method)
    mx, my = x.mean(axis=0), y.mean(axis=0)
    xc, yc = x - mx, y - my
    n = len(x)
    cov = yc.T @ xc / n
    U, d, Vt = np.linalg.svd(cov)
    if d[1] <= 1e-12 * max(d[0], 1e-300):
        raise InputError(
            f"alignment '{method}': degenerate (collinear or static) trajectory; use --align none"
        )
    S = np.eye(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        S[2, 2] = -1.0
    R = U @ S @ Vt
    var_x = np.sum(xc * xc) / n
    s = float(np.trace(np.diag(d) @ S) / var_x) if with_scale else 1.0
    t = my - s * R @ mx
    return Alignment(R=R, t=t, s=s, method=method)


def posyaw(x: np.ndarray, y: np.ndarray) -> Alignment:
    """Closed-form yaw (about world z) + translation minimising ``sum ||y_i - (Rz x_i + t)||^2``."""
    x, y = _check(x, y, 1, "posyaw")
    mx, my = x.mean(axis=0), y.mean(axis=0)
    xc, yc = x - mx, y - my
    # y . Rz(psi) x = cos(psi) (x1 y1 + x2 y2) + sin(psi) (x1 y2 - x2 y1) + x3 y3
    c = np.sum(xc[:, 0] * yc[:, 0] + xc[:, 1] * yc[:, 1])
    s = np.sum(xc[:, 0] * yc[:, 1] - xc[:, 1] * yc[:, 0])
    psi = np.arctan2(s, c) if (c != 0.0 or s != 0.0) else 0.0
    cp, sp = np.cos(psi), np.sin(psi)
    R = np.array([[cp, -sp, 0.0], [sp, cp, 0.0], [0.0, 0.0, 1.0]])
    return Alignment(R=R, t=my - R @ mx, s=1.0, method="posyaw")


def initial_pose(R_est0: np.ndarray, p_est0: np.ndarray, R_gt0: np.ndarray, p_gt0: np.ndarray) -> Alignment:
    """The yaw rotation and offset that put the first estimated pose on the ground truth's (the gauge of a
    filter that starts in its own gravity-aligned frame)."""
    D = R_gt0 @ R_est0.T
    yaw = np.arctan2(D[1, 0], D[0, 0])
    c, s = np.cos(yaw), np.sin(yaw)
    Rz = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    return Alignment(R=Rz, t=p_gt0 - Rz @ p_est0, method="initial-pose")


def align(p_est: np.ndarray, p_gt: np.ndarray, method: str = "none") -> Alignment:
    """Alignment of associated estimate positions onto ground truth by ``method`` (see :data:`METHODS`)."""
    if method == "none":
        return Alignment()
    if method == "posyaw":
        return posyaw(p_est, p_gt)
    if method == "se3":
        return umeyama(p_est, p_gt, with_scale=False)
    if method == "sim3":
        return umeyama(p_est, p_gt, with_scale=True)
    raise InputError(f"alignment: unknown method '{method}'; use one of {', '.join(METHODS)}")
