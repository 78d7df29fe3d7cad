"""`vio.health`: the checks that tell a diverged VIO, each on a history built to fail it at a known time."""

import numpy as np

from uwbcal.pipeline.vio.config import VioConfig
from uwbcal.pipeline.vio.health import assess, speed, windowed_median_nis

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


def test_range_nis_is_the_windowed_median_and_fires_when_the_ranges_stop_fitting():
    cfg = VioConfig()
    t = np.arange(0, 30 * S, S // 20)  # 20 Hz
    rng = np.random.default_rng(0)
    nis = rng.chisquare(1, len(t))
    nis[::10] = 1e4  # one range in ten NLOS: not a divergence
    nis[t >= 20 * S] *= 1e4  # every range off from 20 s
    tm, med = windowed_median_nis(t, nis, cfg.range_nis_window_s, cfg.range_nis_min_ranges)
    assert np.isnan(med[: cfg.range_nis_min_ranges - 1]).all()
    assert np.nanmax(med[tm < 20 * S]) < 2.0
    f = assess(_history(400, 20.0, 0.5), cfg, None, ranges=(t, nis))
    assert f.check == "range_nis" and 20 * S < f.t_ns < 23 * S and "vio.max_range_nis" in f.message("x", 0)


def test_a_localisation_whose_pose_is_metres_off_is_caught_by_its_ranges(tmp_path):
    """The odometry pose source (no visual chi2 test at all) is shifted 3 m with its covariance claiming cm
    after refinement: the localisation's ranges tell it, the run stops (exit 3) naming the check. The recording
    is long enough for the calibration to determine every anchor: an anchor left open (or not determined) cannot
    tell a shift along its open direction from its own uncertainty."""
    import json
    import pickle

    from typer.testing import CliRunner

    from uwbcal.cli import app
    from uwbcal.convert.simulator import SimConfig, simulate_to_file
    from uwbcal.pipeline.core.state import Pose

    rec = tmp_path / "sim.mcap"
    simulate_to_file(SimConfig(duration=60.0, n_anchors=3, odometry_rate=20.0, camera=False, seed=1), rec)
    run = tmp_path / "run"
    stages = ["run", str(rec), "-o", str(run), "--no-log", "--stages"]
    res = CliRunner().invoke(app, [*stages, "vio,init,refine,localize"])
    assert res.exit_code == 0, res.output
    assert json.loads((run / "health.json").read_text())["localize"] == {"failed": False}
    ck = run / "checkpoint_refine.pkl"
    est = pickle.loads(ck.read_bytes())
    nav = est.state.nav
    x = est.state.value(nav)
    est.state.set_value(nav, Pose(x.R, x.p + np.array([3.0, 0.0, 0.0])))
    ck.write_bytes(pickle.dumps(est))
    res = CliRunner().invoke(app, [*stages, "localize"])
    assert res.exit_code == 3, res.output
    health = json.loads((run / "health.json").read_text())["localize"]
    assert health["check"] == "range_nis" and health["value"] > VioConfig().max_range_nis
