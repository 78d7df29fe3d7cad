"""Sample-series helpers shared by the converters, the run log, the evaluator and the calibration: interpolation,
and the statistics of errors correlated in time."""

from __future__ import annotations

import numpy as np

from uwbcal.pipeline.core.geometry import quat_slerp
from uwbcal.pipeline.core.state import chi2_ppf, nearest_psd


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


def noise_inflation(
    t_ns: np.ndarray | None,
    e: np.ndarray,
    weights: np.ndarray | None = None,
    *,
    block_s: float = 10.0,
    min_blocks: int = 4,
    quantile: float = 0.99,
) -> float:
    """Variance inflation kappa >= 1 for time-correlated range errors, from the post-fit whitened residuals.

    The estimator treats the ranges as independent. Real UWB errors are not: multipath and the antenna pattern
    make them vary slowly with the geometry (NTU-VIRAL: per-anchor residuals keep correlating over tens of
    seconds), so N ranges carry far less than N independent ranges' information and the inverse information
    is over-confident by a factor kappa (docs/results/measurements.md). Batch means:
    with blocks of ``block_s`` seconds holding n_b inlier residuals, kappa = mean(n_b mean_b^2) / mean(e^2),
    which is chi2(B)/B-distributed around 1 for white errors; it is used only when it exceeds that
    distribution's ``quantile`` (white noise, as in the simulator, keeps kappa = 1).
    """
    e = np.asarray(e, float)
    if t_ns is None or len(e) < 2 * min_blocks:
        return 1.0
    ok = np.isfinite(e)
    if weights is not None:
        ok &= np.asarray(weights, float) > 0.5
    e = e[ok]
    t = (np.asarray(t_ns, np.int64)[ok] - int(np.min(t_ns))) * 1e-9
    if len(e) < 2 * min_blocks:
        return 1.0
    e = e - e.mean()
    b = np.floor(t / block_s).astype(np.int64)
    cnt = np.bincount(b)
    tot = np.bincount(b, e)
    m = cnt >= 3
    nb = int(m.sum())
    if nb < min_blocks:
        return 1.0
    kappa = float(np.sum(tot[m] ** 2 / cnt[m]) / nb / np.mean(e**2))
    return kappa if kappa > chi2_ppf(quantile, nb) / nb else 1.0


def autocorrelation_time(e: np.ndarray) -> float:
    """The integrated autocorrelation time of a series (Geyer's initial positive sequence: 1 + 2 sum of the
    autocorrelations, summed in pairs while a pair is positive), >= 1: how many of its samples carry the
    information of one independent sample. Sharper than batch means where few blocks fit in the series."""
    e = np.asarray(e, float) - np.mean(e)
    n = len(e)
    if n < 8 or not np.any(e):
        return 1.0
    f = np.fft.rfft(e, 2 * n)
    acf = np.fft.irfft(f * np.conj(f))[:n] / (np.dot(e, e))
    pairs = acf[: n - n % 2].reshape(-1, 2).sum(axis=1)
    stop = np.flatnonzero(pairs <= 0)
    m = int(stop[0]) if len(stop) else len(pairs)
    return max(2.0 * float(np.sum(pairs[:m])) - 1.0, 1.0)


def correlated_errors_covariance(
    v: np.ndarray, var: np.ndarray, t: np.ndarray, tau_s: float | None
) -> np.ndarray:
    """sum_kl V_k Cov(e_k, e_l) V_l^T for d-vector errors e_k at the sorted stamps ``t`` [s], seen through the
    gains ``v`` (N, m, d) (a pose's error mapped to m estimated quantities); ``var``: the errors' covariances
    (N, d, d), or (N,) the variances of isotropic ones. Bounded errors e_k = S_k z_k (S_k the covariance's square
    root, z stationary with correlation exp(-|dt| / ``tau_s``): a recursion over the stamps); ``tau_s`` None: a
    random walk, the covariance of two errors that of the earlier one (its increments clipped to PSD). Returns
    (m, m)."""
    v, var = np.asarray(v, float), np.asarray(var, float)
    m, d = v.shape[1:]
    if not np.any(var):
        return np.zeros((m, m))
    P = var[:, None, None] * np.eye(d) if var.ndim == 1 else var
    if tau_s is None:
        dP = nearest_psd(np.diff(P, axis=0, prepend=np.zeros((1, d, d))))
        S = np.cumsum(v[::-1], axis=0)[::-1]  # S_j = sum_{k>=j} V_k
        return np.einsum("nik,nkl,njl->ij", S, dP, S)
    if var.ndim == 1:
        a = np.sqrt(np.maximum(var, 0.0))[:, None, None] * v
    else:
        w, U = np.linalg.eigh(0.5 * (P + np.swapaxes(P, 1, 2)))
        a = v @ ((U * np.sqrt(np.maximum(w, 0.0))[:, None, :]) @ np.swapaxes(U, 1, 2))
    decay = np.exp(-np.diff(t, prepend=t[0]) / tau_s)
    acc, cross = np.zeros((m, d)), np.zeros((m, m))
    for k in range(len(a)):  # acc_k = sum_{l<k} rho_kl a_l
        acc = decay[k] * acc
        cross += a[k] @ acc.T
        acc = acc + a[k]
    return np.einsum("nik,njk->ij", a, a) + cross + cross.T
