"""UWB range model d = beta * (||p_I + R p_T - p_a|| + n) + gamma, vectorised over N ranges.

Conventions: ``R`` world_from_body (N,3,3), ``p`` (N,3) the IMU position, ``p_T`` (N,3) or (3,) the tag antenna
lever arm in the IMU frame, ``x_U = [p_a(3), beta, gamma]`` (5,) or (N,5). Pose errors are right perturbations
``R = R_hat Exp(dtheta)``, ``p = p_hat + dp``, ordered ``[dtheta, dp]`` (columns 0:6 of the variable "imu").
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from uwbcal.pipeline.core.geometry import I3, norms, skew


@dataclass
class RangeJacobians:
    h: np.ndarray  # (N,) predicted ranges
    H_I: np.ndarray  # (N,6) wrt [dtheta, dp]
    H_U: np.ndarray  # (N,5) wrt [p_a, beta, gamma]
    u: np.ndarray  # (N,3) unit vectors anchor -> tag
    rho: np.ndarray  # (N,) geometric distance
    G: np.ndarray  # (N,3,6) d(tag position)/d[dtheta, dp] = [-R [p_T]x, I]


def _broadcast(R: np.ndarray, p: np.ndarray, p_T: np.ndarray, x_U: np.ndarray):
    R = np.asarray(R, float).reshape(-1, 3, 3)
    p = np.asarray(p, float).reshape(-1, 3)
    p_T = np.asarray(p_T, float).reshape(-1, 3)
    x_U = np.asarray(x_U, float).reshape(-1, 5)
    n = max(R.shape[0], p.shape[0], p_T.shape[0], x_U.shape[0])  # one pose, many ranges: broadcast the pose
    # (broadcast_to only where a leading size differs: it costs a few us per call, and this runs per range)
    return (
        R if R.shape[0] == n else np.broadcast_to(R, (n, 3, 3)),
        p if p.shape[0] == n else np.broadcast_to(p, (n, 3)),
        p_T if p_T.shape[0] == n else np.broadcast_to(p_T, (n, 3)),
        x_U if x_U.shape[0] == n else np.broadcast_to(x_U, (n, 5)),
    )


def tag_positions(R: np.ndarray, p: np.ndarray, p_T: np.ndarray) -> np.ndarray:
    """World position of the tag antenna, p + R p_T, (N,3)."""
    R, p, p_T, _ = _broadcast(R, p, p_T, np.zeros(5))
    return _tag(R, p, p_T)


def _tag(R: np.ndarray, p: np.ndarray, p_T: np.ndarray) -> np.ndarray:
    """`tag_positions` of arrays broadcast already."""
    return p + np.einsum("nij,nj->ni", R, p_T)


def lines_of_sight(p: np.ndarray, xyz: np.ndarray) -> np.ndarray:
    """(N, 3) unit vectors from the anchor ``p`` to the tag positions ``xyz``: a range's change per unit tag
    displacement."""
    diff = np.asarray(xyz, float) - p
    return diff / np.maximum(np.linalg.norm(diff, axis=1), 1e-9)[:, None]


def range_model(R: np.ndarray, p: np.ndarray, p_T: np.ndarray, x_U: np.ndarray) -> np.ndarray:
    """The paper's range model, noise-free: h = beta |p + R p_T - p_a| + gamma for x_U = [p_a, beta, gamma];
    (N,) ranges."""
    R, p, p_T, x_U = _broadcast(R, p, p_T, x_U)
    rho = norms(_tag(R, p, p_T) - x_U[:, :3])
    return x_U[:, 3] * rho + x_U[:, 4]


def jacobians(R: np.ndarray, p: np.ndarray, p_T: np.ndarray, x_U: np.ndarray) -> RangeJacobians:
    """h, H_I = beta u^T [-R [p_T]x, I] and H_U = [-beta u^T, rho, 1] (paper eq. uwb_j, right perturbation)."""
    R, p, p_T, x_U = _broadcast(R, p, p_T, x_U)
    diff = _tag(R, p, p_T) - x_U[:, :3]
    rho = norms(diff)
    u = diff / np.maximum(rho, 1e-9)[:, None]
    beta = x_U[:, 3]
    n = rho.shape[0]
    G = np.zeros((n, 3, 6))
    G[:, :, 0:3] = -R @ skew(p_T)
    G[:, :, 3:6] = I3
    H_I = beta[:, None] * np.einsum("ni,nij->nj", u, G)
    H_U = np.empty((n, 5))
    H_U[:, :3] = -beta[:, None] * u
    H_U[:, 3] = rho
    H_U[:, 4] = 1.0
    return RangeJacobians(beta * rho + x_U[:, 4], H_I, H_U, u, rho, G)


def range_variance(
    R: np.ndarray,
    p: np.ndarray,
    p_T: np.ndarray,
    x_U: np.ndarray,
    P_pose: np.ndarray,
    q_d: float | np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """Sigma_k = Q_d + H_Ik P_k H_Ik^T (paper) and its analytic derivative dSigma_k/dx_U (N,5).

    With H_I = beta u^T G and M = G P G^T: Sigma = q_d + beta^2 u^T M u; du/dp_a = -(I - u u^T)/rho.
    ``q_d`` is the variance of the range noise as it enters d (i.e. already multiplied by beta^2 if wanted).
    """
    R, p, p_T, x_U = _broadcast(R, p, p_T, x_U)
    J = jacobians(R, p, p_T, x_U)
    P_pose = np.broadcast_to(np.asarray(P_pose, float).reshape(-1, 6, 6), (len(J.rho), 6, 6))
    M = J.G @ P_pose @ np.swapaxes(J.G, 1, 2)
    Mu = np.einsum("nij,nj->ni", M, J.u)
    uMu = np.einsum("ni,ni->n", J.u, Mu)
    beta = x_U[:, 3]
    sigma = np.asarray(q_d, float) + beta**2 * uMu
    dS = np.zeros((len(J.rho), 5))
    # d(u^T M u)/dp_a = 2 (M u)^T du/dp_a = -2 (Mu - u (u^T M u))^T / rho
    dS[:, :3] = -2.0 * beta[:, None] ** 2 * (Mu - J.u * uMu[:, None]) / np.maximum(J.rho, 1e-9)[:, None]
    dS[:, 3] = 2.0 * beta * uMu
    return sigma, dS
