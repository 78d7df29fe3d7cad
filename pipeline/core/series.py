"""Sample-series helpers shared by the converters and the run log."""

from __future__ import annotations

import numpy as np


def sliding_mean(x: np.ndarray, k: int) -> np.ndarray:
    """Mean of every ``k`` consecutive samples along axis 0 (``len(x) - k + 1`` of them; none when ``len(x) < k``),
    from one cumulative sum."""
    x = np.asarray(x, dtype=np.float64)
    if len(x) < k:
        return x[:0]
    c = np.concatenate([np.zeros((1, *x.shape[1:])), np.cumsum(x, axis=0)])
    return (c[k:] - c[:-k]) / k
