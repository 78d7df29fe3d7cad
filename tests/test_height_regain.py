"""The height verdict against what corrupts the motion along the plane normal, and heights flagged at init
regained in refinement when the vehicle later moves vertically (pipeline/anchor_search, pipeline/height_regain)."""

from __future__ import annotations

import numpy as np

from uwbcal.pipeline.core.state import Kind, Pose, State
from uwbcal.pipeline.uwb.config import UwbConfig
from uwbcal.pipeline.uwb.height_regain import HeightRegain
from uwbcal.pipeline.uwb.initializer import InitWindow
from uwbcal.pipeline.uwb.search import NORMAL_SNR, normal_corruption, plane_frame, search_anchor
from uwbcal.pipeline.uwb.updater import (
    UwbUpdater,
    add_initialised_anchors,
    anchor_var,
    initialize_anchors,
    search_window,
)
from uwbcal.pipeline.vio.estimator import RangeMeasurement

CALIB = {
    "uwb": {
        "tags": {"1": {"antennas": [[0.0, 0.0, 0.0]]}},
        "sigma_range": 0.1,
        "gamma_prior": {"mean": 0.0, "sigma": 0.5},
    }
}


def _flight(t):
    """A drone's first third (V1_01-like): 1.5 x 0.45 m in the plane, 0.14 m along the normal (ratio 0.095)."""
    return np.c_[2.2 * np.sin(t / 5), 0.7 * np.sin(t / 7.3 + 0.4), 1.25 + 0.21 * np.sin(t / 3.1)]


def test_normal_corruption_closed_form():
    n = np.array([0.0, 0.0, 1.0])
    P = np.broadcast_to(np.diag([0.04, 0.04, 0.0009]), (4, 3, 3))
    arms = np.array([[0.1, 0, 0.02], [0.1, 0, -0.02], [0.1, 0, 0.02], [0.1, 0, -0.02]])
    assert normal_corruption(n, P) == np.sqrt(0.0009)
    assert normal_corruption(n, None, arms) == 0.0  # the arms' swing is not corruption, nor signal
    att = np.full(4, 0.01)
    want = np.sqrt(0.0009 + np.mean((0.01 * np.linalg.norm(arms, axis=1)) ** 2))
    assert np.isclose(normal_corruption(n, P, arms, att), want)


def test_height_observable_when_the_normal_spread_beats_its_corruption():
    """The same near-planar flight (smallest extent < 0.1 x the largest): with a 1 cm pose sigma the height is
    estimated (and right within 2 sigma) in both basins' cases; with 5 cm (spread < 3 x sigma) it is flagged
    with a sigma covering the error."""
    t = np.linspace(0, 48, 480)
    xyz = _flight(t)
    ext = plane_frame(xyz)[2]
    assert ext[2] < 0.1 * ext[0]
    n_obs = 0
    for seed in range(4):
        rng = np.random.default_rng(seed)
        for anchor in (np.array([-2.6, 3.5, 2.5]), np.array([2.6, -2.7, 0.6])):
            d = np.linalg.norm(xyz - anchor, axis=1) + 0.1 + rng.normal(0, 0.1, len(t))
            for s in (0.01, 0.05):
                P = np.broadcast_to(np.eye(3) * s**2, (len(t), 3, 3))
                r = search_anchor(xyz, d, t_ns=t * 1e9, sigma_range=0.1, pos_cov=P)
                assert r.ok and r.planar
                assert np.isclose(r.normal_sigma, s) and np.isclose(r.normal_spread, ext[2])
                assert abs(r.p[2] - anchor[2]) <= 2 * r.sigma_h, (seed, s, r.p, r.sigma_h)
                if s == 0.05:  # the spread is under NORMAL_SNR x its corruption
                    assert ext[2] < NORMAL_SNR * s and not r.height_observable
                else:
                    n_obs += r.height_observable
                    assert r.sigma_h < 0.3
    assert n_obs == 8


def test_arms_swinging_out_of_the_plane_do_not_make_a_height():
    """A planar carrier whose given arms, rotated by a wrong attitude, swing the tags +-0.1 m out of its plane
    (the trolley's quaternion-order case): the swing is not signal (the carrier itself stays in its plane), the
    height stays flagged."""
    rng = np.random.default_rng(5)
    t = np.linspace(0, 100, 2000)
    body = np.c_[3 * np.cos(t / 8), 2 * np.sin(t / 8), np.full(len(t), 0.3)]
    arm = np.c_[0.15 * np.cos(t / 1.3), np.zeros(len(t)), 0.1 * np.sin(t / 1.3)]
    xyz = body + arm
    anchor = np.array([5.0, 4.0, 1.5])
    d = np.linalg.norm(xyz - anchor, axis=1) + rng.normal(0, 0.05, len(t))
    P = np.broadcast_to(np.eye(3) * 0.003**2, (len(t), 3, 3))
    r = search_anchor(xyz, d, t_ns=t * 1e9, sigma_range=0.05, pos_cov=P, arm_xyz=arm)
    assert r.ok and not r.height_observable and r.normal_spread < 3 * r.normal_sigma
    assert abs(r.p[2] - anchor[2]) <= 2 * r.sigma_h


def _window(xyz, d, t, sigma_pose):
    n = len(d)
    P = np.zeros((n, 6, 6))
    P[:, 3:, 3:] = np.eye(3) * sigma_pose**2
    P[:, :3, :3] = np.eye(3) * 1e-6
    return InitWindow(d, np.zeros(3), np.broadcast_to(np.eye(3), (n, 3, 3)), xyz, P, t * 1e9, np.full(n, 256))


def _refine(regain_on: bool, seed: int = 0):
    """Init on a ground loop (height flagged), then 60 s of refinement while the vehicle climbs and descends
    +-0.6 m: returns (init result, anchor state x, its z sigma, the regain watcher)."""
    rng = np.random.default_rng(seed)
    anchor = np.array([4.0, 3.0, 0.2])  # below the ground loop: init reports the basin above it
    sp = 0.02
    t1 = np.linspace(0, 40, 400)
    xyz1 = np.c_[3 * np.cos(t1 / 6), 2 * np.sin(t1 / 6), 1.0 + 0.003 * rng.normal(size=len(t1))]
    d1 = np.linalg.norm(xyz1 - anchor, axis=1) + rng.normal(0, 0.1, len(t1))
    cfg = UwbConfig(init_method="ri")
    res = initialize_anchors({7: _window(xyz1, d1, t1, sp)}, cfg, CALIB)
    assert res[7].ok and res[7].verdict["height_observable"] is False
    state = State()
    P6 = np.diag([1e-6] * 3 + [sp**2] * 3)
    state.add("imu", Pose(np.eye(3), xyz1[-1]), P6.copy(), kind=Kind.NAV)
    add_initialised_anchors(state, res, cfg, CALIB)
    upd = UwbUpdater("skf", {(1, 0): np.zeros(3)}, sigma_range=0.1, chi2_quantile=None)
    upd.schedule(
        res,
        {
            "sigma_range": 0.1,
            "gamma_prior": (0.0, 0.5),
            "beta_prior": (1.0, 0.05),
            "pose_correlation_s": None,
        },
    )
    if regain_on:
        upd.regain = HeightRegain(
            res,
            lambda w: search_window(w, cfg, 0.1, CALIB),
            lambda a, w, sr: initialize_anchors({a: w}, cfg, CALIB, searches={a: sr})[a],
        )
    t2 = np.linspace(40, 100, 600)
    xyz2 = np.c_[3 * np.cos(t2 / 6), 2 * np.sin(t2 / 6), 1.0 + 0.6 * np.sin((t2 - 40) / 4)]
    d2 = np.linalg.norm(xyz2 - anchor, axis=1) + rng.normal(0, 0.1, len(t2))
    for k in range(len(t2)):
        state.set_value("imu", Pose(np.eye(3), xyz2[k]))
        upd.update(state, RangeMeasurement(int(t2[k] * 1e9), 1, 0, 7, float(d2[k])))
    x = state.value(anchor_var(7)).x
    return res[7], x, float(np.sqrt(state.cov(anchor_var(7))[2, 2])), upd.regain, anchor


def test_flagged_height_regained_when_the_vehicle_moves_vertically():
    init, x, sz, regain, anchor = _refine(True)
    assert abs(init.x[2] - anchor[2]) > 1.0  # init: the basin above the loop, the mirror of the truth
    assert 7 in regain.regained and 7 not in regain.watch
    g = regain.summary()["7"]
    assert 40.0 < g["t_s"] < 100.0 and g["n_ranges"] > len(init.window)
    assert abs(x[2] - anchor[2]) < 0.15 and abs(x[2] - anchor[2]) <= 3 * sz and sz < 0.2
    assert np.hypot(*(x[:2] - anchor[:2])) < 0.15
    # without it the height stays where init left it, with init's sigma
    init0, x0, sz0, _, _ = _refine(False)
    assert x0[2] == init0.x[2] and sz0 >= 0.9 * np.sqrt(init0.cov[2, 2])
