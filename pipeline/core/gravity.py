"""Gravity in the frame of a ground truth, fitted to an IMU: how far a motion-capture frame is from level.

A motion-capture frame is set up with a wand or on the floor: its z axis is gravity's only to some tenths of a
degree (EuRoC V1_01: 0.24°). Over windows k of ``window_s``, the IMU's specific force f = R^T (a - g) + b_a + n
integrates to ``sum_k R f dt = dv_k - g T_k + (sum_k R dt) b_a``, with R the ground truth's orientation at the IMU
stamps and dv_k its velocity change over the window (central differences of its positions). Gravity g (and a
constant accelerometer bias b_a when the ground truth's is not given) follow by linear least squares: no double
differentiation of the positions. A horizontal bias is told from a tilt only when the platform turns; without
that the fit is undetermined.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from uwbcal.pipeline.core.geometry import exp_so3, quat_to_rot, rot_to_quat
from uwbcal.pipeline.core.series import interpolate_positions, interpolate_quats

DOWN = np.array([0.0, 0.0, -1.0])
_CHUNK = 65536  # IMU samples per pass


@dataclass(frozen=True)
class GravityFit:
    gravity: np.ndarray  # (3,) gravity in the ground truth's frame [m/s^2]
    # the constant accelerometer bias fitted with it (zero when the bias was given) [m/s^2]
    bias: np.ndarray
    tilt_sigma_deg: float  # standard deviation of the gravity direction (from the residuals)
    windows: int
    residual_rms: float  # per-window residual of the integrated specific force, divided by the window [m/s^2]

    @property
    def tilt_deg(self) -> float:
        """Angle between the fitted gravity and the ground truth's -z."""
        u = self.gravity / np.linalg.norm(self.gravity)
        return float(np.degrees(np.arccos(np.clip(u @ DOWN, -1.0, 1.0))))

    def summary(self) -> dict:
        """What the run directory and the recording's metadata say of the fit."""
        return {
            "tilt_deg": self.tilt_deg,
            "tilt_sigma_deg": self.tilt_sigma_deg,
            "gravity_m_s2": [float(v) for v in self.gravity],
            "windows": self.windows,
            "residual_m_s2": self.residual_rms,
        }

    def level(self) -> Level:
        """The rotation (about a horizontal axis) that takes the fitted gravity to -z."""
        u = self.gravity / np.linalg.norm(self.gravity)
        axis = np.cross(u, DOWN)
        s = np.linalg.norm(axis)
        if s < 1e-12:
            return Level(np.eye(3))
        return Level(exp_so3(axis / s * np.arctan2(s, u @ DOWN)))


@dataclass(frozen=True)
class Level:
    """levelled_from_truth rotation: positions p -> R p, orientations R_wb -> R R_wb (no yaw)."""

    R: np.ndarray

    def positions(self, p: np.ndarray) -> np.ndarray:
        return np.asarray(p, float) @ self.R.T

    def quats(self, q_xyzw: np.ndarray) -> np.ndarray:
        return rot_to_quat(self.R @ quat_to_rot(q_xyzw))


def fit_gravity(
    t_imu: np.ndarray,
    acc: np.ndarray,
    t_gt: np.ndarray,
    p_gt: np.ndarray,
    q_gt: np.ndarray,
    acc_bias: np.ndarray | None = None,
    window_s: float = 2.0,
    velocity_baseline_s: float = 0.1,
) -> GravityFit | None:
    """Gravity (and a constant accelerometer bias) in the frame of the ground-truth poses (``p_gt``: the IMU's
    position, ``q_gt``: its orientation, xyzw) from the accelerometer samples ``acc`` at ``t_imu`` (int64 ns).
    ``acc_bias`` (the ground truth's accelerometer bias at ``t_imu``, e.g. EuRoC's): removed from ``acc`` and
    gravity alone is fitted; without it a constant bias is fitted with gravity. None when the windows inside the
    ground truth's span are too few or the bias and the tilt cannot be told apart (a platform that does not
    turn)."""
    t_imu = np.asarray(t_imu, np.int64)
    t_gt = np.asarray(t_gt, np.int64)
    h = int(velocity_baseline_s * 1e9)
    inside = (t_imu >= t_gt[0] + h) & (t_imu <= t_gt[-1] - h)
    t, f = t_imu[inside], np.asarray(acc, float)[inside]
    if acc_bias is not None:
        f = f - np.asarray(acc_bias, float)[inside]
    finite = np.isfinite(f).all(axis=1)  # a damaged sample is left out (its interval joins the next one's)
    t, f = t[finite], f[finite]
    if len(t) < 3:
        return None
    dt = np.diff(t) * 1e-9
    cT = np.concatenate([[0.0], np.cumsum(dt)])
    n_win = int(cT[-1] // window_s)
    if n_win < 6:
        return None
    edges = np.searchsorted(cT, np.arange(n_win + 1) * window_s)
    T = cT[edges[1:]] - cT[edges[:-1]]
    # per window: S = sum R f dt and A = sum R dt over its samples, streamed in chunks (no (n, 3, 3) array for a
    # long recording)
    win = np.searchsorted(edges, np.arange(len(dt)), "right") - 1
    S, Asum = np.zeros((n_win, 3)), np.zeros((n_win, 9))
    p_gt, q_gt = np.asarray(p_gt, float), np.asarray(q_gt, float)
    n_used = int(np.searchsorted(win, n_win))  # the samples after the last whole window are left out
    for c0 in range(0, n_used, _CHUNK):
        sl = slice(c0, min(c0 + _CHUNK, n_used))
        R = quat_to_rot(interpolate_quats(t_gt, q_gt, t[sl])) * dt[sl, None, None]
        Rf = np.einsum("nij,nj->ni", R, f[sl])
        w = win[sl]
        for k in range(3):
            S[:, k] += np.bincount(w, Rf[:, k], n_win)
        R9 = R.reshape(-1, 9)
        for k in range(9):
            Asum[:, k] += np.bincount(w, R9[:, k], n_win)
    te = t[edges]
    v = (interpolate_positions(t_gt, p_gt, te + h) - interpolate_positions(t_gt, p_gt, te - h)) / (
        2 * h * 1e-9
    )
    # S - dv = -T g + A b
    y = S - (v[1:] - v[:-1])
    A = np.zeros((n_win, 3, 6))
    A[:, :, :3] = -T[:, None, None] * np.eye(3)
    A[:, :, 3:] = Asum.reshape(n_win, 3, 3)
    nx = 3 if acc_bias is not None else 6
    A2, y2 = A[:, :, :nx].reshape(-1, nx), y.reshape(-1)
    sv = np.linalg.svd(A2, compute_uv=False)
    if sv[-1] < 1e-3 * sv[0]:
        return None
    x, *_ = np.linalg.lstsq(A2, y2, rcond=None)
    res = y2 - A2 @ x
    s2 = float(res @ res) / max(len(y2) - nx, 1)
    cov = s2 * np.linalg.inv(A2.T @ A2)
    g = x[:3]
    # the direction's variance: the gravity covariance across the direction, over |g|^2
    P = np.eye(3) - np.outer(g, g) / (g @ g)
    tilt_var = float(np.trace(P @ cov[:3, :3] @ P)) / float(g @ g)
    return GravityFit(
        gravity=g,
        bias=x[3:] if nx == 6 else np.zeros(3),
        tilt_sigma_deg=float(np.degrees(np.sqrt(tilt_var / 2))),
        windows=n_win,
        residual_rms=float(np.sqrt(np.mean((res.reshape(n_win, 3) / T[:, None]) ** 2))),
    )
