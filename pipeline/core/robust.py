"""Robust statistics every layer shares: the M-estimators' losses with their IRLS weights, and the MAD sigma."""

from __future__ import annotations

import numpy as np

MAD_SIGMA = 1.4826  # the median absolute deviation times this is a normal distribution's sigma


def robust_loss(e: np.ndarray, kind: str | None, c: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """rho(e) of whitened residuals (scaled so that rho = e^2 near 0) and the IRLS weight rho'(e) / (2 e), scale
    ``c``: None least squares; ``soft_l1`` 2 c^2 (sqrt(1 + (e/c)^2) - 1), convex; ``huber``, convex: a large
    residual keeps a constant influence; ``cauchy`` c^2 log(1 + (e/c)^2), redescending: one-sided NLOS junk pulls
    a convex loss's fit away by a constant influence per range, not this one's."""
    if kind is None:
        return e**2, np.ones_like(e)
    if kind == "huber":
        a = np.abs(e)
        return np.where(a <= c, e**2, 2 * c * a - c**2), np.where(a <= c, 1.0, c / np.maximum(a, 1e-12))
    u = (e / c) ** 2
    if kind == "soft_l1":
        q = np.sqrt(1.0 + u)
        return 2.0 * c**2 * (q - 1.0), 1.0 / q
    if kind == "cauchy":
        return c**2 * np.log1p(u), 1.0 / (1.0 + u)
    raise ValueError(f"unknown robust loss {kind!r} (huber, cauchy or soft_l1)")


def psi_slope(e: np.ndarray, kind: str, c: float) -> np.ndarray:
    """psi'(e) of the robust loss (psi = w e, `robust_loss` weight w): the curvature the estimate really has."""
    if kind == "huber":
        return (np.abs(e) <= c).astype(float)
    if kind == "cauchy":
        return (1.0 - (e / c) ** 2) / (1.0 + (e / c) ** 2) ** 2
    raise ValueError(f"unknown robust loss {kind!r} (huber or cauchy)")


def mad_sigma(x: np.ndarray) -> float:
    """The robust sigma of a sample, `MAD_SIGMA` x its median absolute deviation (NaN when empty)."""
    return float(MAD_SIGMA * np.median(np.abs(x - np.median(x)))) if len(x) else float("nan")
