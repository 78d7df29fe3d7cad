"""Filter consistency: NEES, ANEES over Monte Carlo runs with chi^2 bounds, NIS.

Pose error convention (as the filter's): ``R = R_hat Exp(dtheta)`` (right perturbation, body frame), so
``dtheta = Log(R_hat^T R)``; ``dp = p - p_hat`` (world). The pose covariance is ordered ``[dtheta, dp]``.
Anchor error: ``[p_a - p_hat_a (3), beta - beta_hat, gamma - gamma_hat]`` (3 or 5 dof).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from uwbcal.pipeline.core.geometry import log_so3
from uwbcal.pipeline.core.state import chi2_quantile


def nees(err: np.ndarray, cov: np.ndarray) -> np.ndarray:
    """``e^T P^-1 e`` for (N, d) errors and (N, d, d) covariances (or one (d,) / (d, d)); NaN where P is not
    positive definite."""
    err = np.asarray(err, float)
    cov = np.asarray(cov, float)
    single = err.ndim == 1
    e = err.reshape(-1, err.shape[-1])
    P = cov.reshape(-1, e.shape[1], e.shape[1])
    P = 0.5 * (P + np.swapaxes(P, -1, -2))
    out = np.full(len(e), np.nan)
    try:
        L = np.linalg.cholesky(P)
        z = np.linalg.solve(L, e[..., None])[..., 0]
        out = np.sum(z * z, axis=-1)
    except np.linalg.LinAlgError:
        # some P not positive definite: fall back per sample so that the good ones still count
        for i in range(len(e)):
            try:
                z = np.linalg.solve(np.linalg.cholesky(P[i % len(P)]), e[i])
                out[i] = z @ z
            except np.linalg.LinAlgError:
                pass
    return out[0] if single else out


def nis(residual: np.ndarray, S: np.ndarray) -> np.ndarray | float:
    """Normalised innovation squared ``r^T S^-1 r``: scalar updates (r (N,), S (N,)) or vector updates
    (r (N, m), S (N, m, m)); a single update gives a float."""
    r = np.asarray(residual, float)
    S = np.asarray(S, float)
    if S.ndim == r.ndim:  # scalar innovations with variances
        return r * r / S
    return nees(r, S)


def pose_error(R_est: np.ndarray, p_est: np.ndarray, R_true: np.ndarray, p_true: np.ndarray) -> np.ndarray:
    """(N, 6) pose error ``[dtheta, dp]`` with ``dtheta = Log(R_hat^T R)``, ``dp = p - p_hat``."""
    R_est = np.asarray(R_est, float).reshape(-1, 3, 3)
    R_true = np.asarray(R_true, float).reshape(-1, 3, 3)
    dtheta = log_so3(np.swapaxes(R_est, -1, -2) @ R_true)
    dp = np.asarray(p_true, float).reshape(-1, 3) - np.asarray(p_est, float).reshape(-1, 3)
    return np.concatenate([dtheta, dp], axis=1)


@dataclass
class PoseNees:
    orientation: np.ndarray  # (N,), 3 dof
    position: np.ndarray  # (N,), 3 dof
    pose: np.ndarray  # (N,), 6 dof


def pose_nees(
    R_est: np.ndarray, p_est: np.ndarray, cov: np.ndarray, R_true: np.ndarray, p_true: np.ndarray
) -> PoseNees:
    """NEES of orientation, position and the full pose from (N, 6, 6) ``[dtheta, dp]`` covariances."""
    e = pose_error(R_est, p_est, R_true, p_true)
    cov = np.asarray(cov, float).reshape(-1, 6, 6)
    return PoseNees(
        orientation=nees(e[:, :3], cov[:, :3, :3]),
        position=nees(e[:, 3:], cov[:, 3:, 3:]),
        pose=nees(e, cov),
    )


def position_nees(p_est: np.ndarray, cov: np.ndarray, p_true: np.ndarray) -> np.ndarray:
    """NEES of positions only (e.g. position-only ground truth) from (N, 3, 3) covariances."""
    return nees(np.asarray(p_true, float) - np.asarray(p_est, float), cov)


def anchor_nees(estimate: np.ndarray, cov: np.ndarray, truth: np.ndarray) -> np.ndarray | float:
    """NEES of an anchor state ``[p_a(3)]`` or ``[p_a(3), beta, gamma]`` (dof = its length; the covariance
    block must match). Works on one anchor or a stack (N, d)."""
    e = np.asarray(truth, float) - np.asarray(estimate, float)
    return nees(e, cov)


def anees(nees_runs: np.ndarray) -> np.ndarray:
    """ANEES: mean over Monte Carlo runs (axis 0) at each time, ignoring NaN; (M, T) -> (T,)."""
    x = np.asarray(nees_runs, float)
    with np.errstate(invalid="ignore"):
        n = np.sum(np.isfinite(x), axis=0)
        s = np.nansum(x, axis=0)
    return np.where(n > 0, s / np.maximum(n, 1), np.nan)


def chi2_bounds(n_runs: int, dof: int, confidence: float = 0.95) -> tuple[float, float]:
    """Two-sided bounds on the ANEES of ``n_runs`` runs with ``dof`` degrees of freedom:
    ``(chi2.ppf(a/2, N d) / N, chi2.ppf(1 - a/2, N d) / N)`` with ``a = 1 - confidence``."""
    if n_runs < 1 or dof < 1:
        raise ValueError(f"chi2_bounds: need n_runs >= 1 and dof >= 1, got {n_runs}, {dof}")
    a = 1.0 - confidence
    k = n_runs * dof
    return float(chi2_quantile(a / 2, k) / n_runs), float(chi2_quantile(1 - a / 2, k) / n_runs)


def fraction_inside(values: np.ndarray, bounds: tuple[float, float]) -> float:
    """Share of finite values inside ``[lo, hi]`` (about ``confidence`` for a consistent filter)."""
    v = np.asarray(values, float)
    v = v[np.isfinite(v)]
    return float(np.mean((v >= bounds[0]) & (v <= bounds[1]))) if v.size else float("nan")


def summarize_nees(values: np.ndarray, dof: int, n_runs: int = 1, confidence: float = 0.95) -> dict:
    """A metrics.json-ready summary ``{"mean", "dof", "n_runs", "bounds": [lo, hi], "inside"}`` of a NEES (or
    ANEES over ``n_runs`` runs) time series. ``bounds`` are the per-time two-sided bounds for ``n_runs`` runs
    (not those of the time average: successive NEES values are strongly correlated); ``inside`` is the share
    of samples within them. ``uwbcal diff`` flags a ``mean`` that leaves ``bounds``."""
    v = np.asarray(values, float)
    finite = v[np.isfinite(v)]
    if finite.size == 0:
        return {"dof": dof, "n_runs": n_runs}
    bounds = chi2_bounds(n_runs, dof, confidence)
    return {
        "mean": float(finite.mean()),
        "dof": dof,
        "n_runs": n_runs,
        "bounds": list(bounds),
        "inside": fraction_inside(finite, bounds),
    }
