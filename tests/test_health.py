"""`vio.health`: the checks that tell a diverged VIO, each on a history built to fail it at a known time."""

import numpy as np

from uwbcal.pipeline.vio.config import VioConfig
from uwbcal.pipeline.vio.health import assess, speed

S = 1_000_000_000


def _history(n=200, rate=10.0, v=1.0):
    t = (np.arange(n) * S / rate).astype(np.int64)
    p = np.column_stack([v * t * 1e-9, np.zeros(n), np.zeros(n)])
    cov = np.tile(np.eye(6) * 1e-4, (n, 1, 1))
    return {"t_ns": t, "p": p, "cov": cov}


def test_a_healthy_history_passes_and_speed_is_the_trailing_mean():
    h = _history()
    assert assess(h, VioConfig(), None) is None
    v = speed(h["t_ns"], h["p"], 0.5)
    assert np.isnan(v[:5]).all() and np.allclose(v[5:], 1.0)


def test_each_check_fires_at_its_time_and_the_earliest_is_reported():
    cfg = VioConfig()
    h = _history()
    h["p"][120:, 0] += np.cumsum(np.full(80, 100.0))  # runs away at 12 s: 1 km/s
    f = assess(h, cfg, None)
    assert f.check == "velocity" and f.t_ns == 12 * S and f.value > cfg.max_speed
    g = _history()
    g["cov"][150:, 3:6, 3:6] = np.eye(3) * 100.0  # sigma 17 m from 15 s
    f = assess(g, cfg, None)
    assert f.check == "covariance" and f.t_ns == 15 * S
    t = np.arange(0, 20 * S, S // 2)
    frac = np.where(t >= 8 * S, 0.7, 0.05)
    f = assess(g, cfg, (t, frac, np.full(len(t), 40)))
    assert f.check == "chi2" and f.t_ns == 8 * S and "vio.consistency_max_rejected" in f.message("vio", 0)
    assert assess(g, cfg, (t, frac, np.full(len(t), 40)), start_ns=16 * S).check == "covariance"
