"""Paired comparison of two methods run on the same seeds: mean difference with a 95 % t interval."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class PairedDifference:
    mean: float  # mean of a - b (positive: b has the smaller error)
    lo: float  # 95 % t interval of the mean
    hi: float
    n: int  # pairs with both values finite
    share_b: float  # share of pairs where b < a

    @property
    def significant(self) -> bool:
        """The interval excludes zero."""
        return bool(self.lo > 0 or self.hi < 0)


def paired_difference(a: np.ndarray, b: np.ndarray, level: float = 0.95) -> PairedDifference:
    """``a - b`` over the pairs where both are finite (same seed, same anchor, ...)."""
    from scipy.stats import t as student_t

    a, b = np.asarray(a, float).ravel(), np.asarray(b, float).ravel()
    if a.shape != b.shape:
        raise ValueError(f"paired_difference: {a.shape} vs {b.shape}: the pairs must match")
    ok = np.isfinite(a) & np.isfinite(b)
    d = a[ok] - b[ok]
    n = len(d)
    if n == 0:
        return PairedDifference(float("nan"), float("nan"), float("nan"), 0, float("nan"))
    m = float(d.mean())
    if n < 2:
        return PairedDifference(m, float("nan"), float("nan"), n, float(np.mean(d > 0)))
    half = float(student_t.ppf(0.5 + level / 2, n - 1) * d.std(ddof=1) / np.sqrt(n))
    return PairedDifference(m, m - half, m + half, n, float(np.mean(d > 0)))
