"""The evidence fit of one anchor as the initialiser sees it (`evidence.fit_anchor` through
`updater.search_window` / `initialize_anchors`) on the classes of motion the calibration meets, and the per-anchor
schedule (`schedule`): 3-D motion with NLOS junk, a planar carrier (open height, two basins), far intermittent
ranges, per-link offsets, a range scale on a one-sided arc, anchors ranged too briefly, late anchors."""

from __future__ import annotations

import numpy as np
import pytest

from uwbcal.pipeline.core.state import State
from uwbcal.pipeline.uwb.config import UwbConfig
from uwbcal.pipeline.uwb.evidence import FitSpec, Model, basin_evidence, fit_anchor, mixture_cov
from uwbcal.pipeline.uwb.initializer import _fuse_z_prior
from uwbcal.pipeline.uwb.schedule import candidate_ends, choose_schedule, join_time
from uwbcal.pipeline.uwb.updater import add_initialised_anchors, initialize_anchors, search_window
from uwbcal.pipeline.uwb.window import InitWindow, plane_frame

CHI2_3_999 = 16.27


def _ground_track(n: int, rng, extent=8.0, z=0.3, z_wobble=0.01):
    """A planar ground robot: a smooth closed loop in x-y at height z."""
    s = np.linspace(0, 2 * np.pi, n)
    xy = np.c_[extent * np.cos(s) + 0.3 * extent * np.sin(3 * s), 0.6 * extent * np.sin(s)]
    return np.c_[xy, z + z_wobble * rng.normal(size=n)]


def _ranges(xyz, anchor, gamma, sigma, rng, junk=0.0):
    d = np.linalg.norm(xyz - anchor, axis=1) + gamma + rng.normal(0, sigma, len(xyz))
    bad = rng.random(len(d)) < junk
    d[bad] += rng.uniform(0.5, 8.0, bad.sum())  # NLOS: always long
    return d


def _window(xyz, d, t_s, link=None):
    n = len(d)
    return InitWindow(
        d, np.zeros(3), np.broadcast_to(np.eye(3), (n, 3, 3)), xyz, np.zeros((6, 6)), t_s * 1e9, link
    )


def _nees(r, p):
    e = r.p - p
    return float(e @ np.linalg.solve(r.cov[:3, :3], e))


def test_3d_motion_with_nlos_junk():
    """30 % one-sided NLOS junk: the redescending loss leaves it out; the offset enters, the anchor is right."""
    rng = np.random.default_rng(1)
    n = 3000
    t = np.linspace(0, 300, n)
    xyz = np.c_[6 * np.cos(t / 20), 5 * np.sin(t / 13), 1.5 + 1.2 * np.sin(t / 7)]
    anchor = np.array([4.0, -7.0, 3.0])
    d = _ranges(xyz, anchor, 0.25, 0.05, rng, junk=0.3)
    res = fit_anchor(xyz, d, t_ns=t * 1e9, spec=FitSpec(sigma_range=0.05))
    assert res.ok, res.reason
    assert np.linalg.norm(res.p - anchor) < 0.05 and _nees(res, anchor) < CHI2_3_999
    assert res.height_observable and not res.mirror
    assert abs(res.gamma[0] - 0.25) < 0.03


def test_planar_motion_height_honest_and_two_basins():
    """A planar carrier: the horizontal position is right and the height's sigma covers its error; an anchor
    well off the plane has its two mirror basins reported and its height open."""
    rng = np.random.default_rng(2)
    xyz = _ground_track(4000, rng, z_wobble=0.0)  # exactly planar: the mirror fits exactly as well
    t = np.linspace(0, 200, len(xyz))
    for h in (0.1, 2.0):
        anchor = np.array([2.0, 9.0, 0.3 + h])
        d = _ranges(xyz, anchor, 0.0, 0.03, rng)
        res = fit_anchor(xyz, d, t_ns=t * 1e9, spec=FitSpec(sigma_range=0.03))
        assert res.ok and res.planar
        assert np.hypot(*(res.p - anchor)[:2]) < 0.1
        assert abs(res.p[2] - anchor[2]) <= 2 * res.sigma_h
        if h == 2.0:
            assert res.mirror and res.mirror_p is not None and not res.height_observable


def test_the_basins_evidence_sums_over_the_range_models():
    """The side of the plane is one question whatever offsets the ranges carry: a basin the chosen family (the
    position alone) rules out but a richer family fits as well keeps its weight in the covariance."""
    p0, p1 = np.array([5.0, 2.0, 1.0]), np.array([5.0, 2.0, -1.0])

    def model(name, basin, z):
        k = 3 + (name != "position")
        return Model(
            name,
            basin,
            p1 if basin else p0,
            1.0,
            np.zeros(1),
            0.0,
            1e4 * np.eye(k),
            np.zeros(1),
            np.ones(1),
            log_evidence=z,
        )

    models = [
        model("position", 0, 0.0),
        model("position", 1, -6.0),
        model("gamma", 0, -1.0),
        model("gamma", 1, 0.5),
    ]
    z = np.array([basin_evidence(models, 0), basin_evidence(models, 1)])
    np.testing.assert_allclose(z, [np.logaddexp(0.0, -1.0), np.logaddexp(-6.0, 0.5)])
    w1 = 1.0 / (1.0 + np.exp(z[0] - z[1]))
    cov = mixture_cov(models, models[0], reach=50.0)
    assert cov[2, 2] == pytest.approx(1e-4 + w1 * 4.0, rel=1e-3)  # the mixture's spread: w1 |p1 - p0|^2
    assert abs(cov[0, 0] - 1e-4) < 1e-6
    # an offset the chosen model holds at its mean moves the position by 0.5 m: it widens the covariance by its
    # model's weight (the evidence's), not in full
    models[2].p = p0 + np.array([0.5, 0.0, 0.0])
    w_g0 = np.exp(-1.0) / np.sum(np.exp([0.0, -6.0, -1.0, 0.5]))
    cov = mixture_cov(models, models[0], reach=50.0)
    assert cov[0, 0] == pytest.approx(1e-4 + w_g0 * 0.25, rel=1e-3)


def test_large_area_far_ranges_intermittent():
    rng = np.random.default_rng(3)
    n = 4000
    t = np.linspace(0, 400, n)
    xyz = np.c_[150 * np.cos(t / 60), 80 * np.sin(t / 45), 0.5 * np.sin(t / 30)]
    anchor = np.array([250.0, 120.0, 8.0])
    vis = (np.sin(t / 9) > -0.2) & (np.linalg.norm(xyz - anchor, axis=1) < 320)
    d = _ranges(xyz[vis], anchor, 0.3, 0.1, rng, junk=0.1)
    res = fit_anchor(xyz[vis], d, t_ns=t[vis] * 1e9, spec=FitSpec(sigma_range=0.1))
    assert res.ok, res.reason
    assert np.hypot(*(res.p - anchor)[:2]) < 0.5
    assert abs(res.p[2] - anchor[2]) <= 2 * max(res.sigma_h, 1e-3)


def _three_link_track(n: int = 6000):
    """200 s of 3-D motion with three antennas (links 0, 1, 2 in turn) and one anchor: (n, t, link, xyz, anchor)."""
    t = np.linspace(0, 200, n)
    body = np.c_[5 * np.cos(t / 15), 4 * np.sin(t / 11), 1.0 + 0.8 * np.sin(t / 5)]
    link = np.arange(n) % 3
    lever = np.array([[0.2, 0.0, 0.0], [-0.2, 0.1, 0.0], [0.0, -0.2, 0.05]])
    return n, t, link, body + lever[link], np.array([-6.0, 3.0, 2.5])


def test_per_link_offsets_enter_only_when_the_links_differ():
    rng = np.random.default_rng(4)
    n, t, link, xyz, anchor = _three_link_track()
    offs = np.array([0.1, 0.3, 0.47])
    d = np.linalg.norm(xyz - anchor, axis=1) + offs[link] + rng.normal(0, 0.02, n)
    res = fit_anchor(xyz, d, link, t_ns=t * 1e9, spec=FitSpec(sigma_range=0.02))
    assert res.ok and res.costs["evidence"]["model"] == "link"
    np.testing.assert_allclose(res.gamma, offs, atol=0.02)
    one = fit_anchor(xyz, d - offs[link] + 0.2, link, t_ns=t * 1e9, spec=FitSpec(sigma_range=0.02))
    assert one.costs["evidence"]["model"] == "gamma"


def test_range_scale_on_a_one_sided_arc():
    """A one-sided near-level arc with the anchor 2.6 m beyond its side and a range scale of 0.9 (d = 0.9 |.| -
    0.3): the recording states a scale prior (1, 0.2), so the scale is in the model; the anchor is either right
    (the scale estimated, the anchor inside its covariance) or honestly not determined along the arc's weak radial
    direction; ranges without a scale error give a scale near 1."""
    t = np.linspace(0, 48, 800)
    xyz = np.c_[0.9 + 1.0 * np.sin(t / 5.0), 0.5 + 2.2 * np.sin(t / 7.3 + 0.4), 1.25 + 0.3 * np.sin(t / 3.1)]
    cal = {"uwb": {"gamma_prior": {"mean": 0.0, "sigma": 1.0}, "beta_prior": {"mean": 1.0, "sigma": 0.2}}}
    far = np.array([-2.65, -2.67, 1.57])
    kept = 0
    for seed in range(3):
        rng = np.random.default_rng(seed)
        d = 0.9 * np.linalg.norm(xyz - far, axis=1) - 0.3 + rng.normal(0, 0.1, len(t))
        res = search_window(_window(xyz, d, t), UwbConfig(), 0.1, cal)
        if res.ok:
            assert res.beta == pytest.approx(0.9, abs=0.03) and _nees(res, far) < CHI2_3_999
        else:
            assert "weak horizontal direction" in res.reason
        d1 = np.linalg.norm(xyz - far, axis=1) - 0.3 + rng.normal(0, 0.1, len(t))
        one = search_window(_window(xyz, d1, t), UwbConfig(), 0.1, cal)
        kept += not one.ok or abs(one.beta - 1.0) < 0.05
    assert kept == 3


def test_the_pose_sigma_floor_is_added_once():
    """The evidence fit an initialisation makes itself is the one the stage makes and hands it."""
    rng = np.random.default_rng(6)
    t = np.linspace(0, 120, 1200)
    xyz = np.c_[5 * np.cos(t / 9), 4 * np.sin(t / 7), 1.0 + 0.8 * np.sin(t / 5)]
    w = _window(xyz, _ranges(xyz, np.array([3.0, -2.0, 2.0]), 0.0, 0.1, rng), t)
    cfg = UwbConfig(pose_sigma_floor_m=0.3)
    own = initialize_anchors({0: w}, cfg, None, method="ri")[0]
    handed = initialize_anchors(
        {0: w}, cfg, None, method="ri", searches={0: search_window(w, cfg, 0.1, None, "ri")}
    )[0]
    np.testing.assert_allclose(own.x, handed.x, atol=1e-9)
    np.testing.assert_allclose(own.cov, handed.cov, rtol=1e-9, atol=1e-12)


def test_too_few_or_too_short_never_enters_the_filter():
    rng = np.random.default_rng(5)
    t = np.linspace(0, 2.0, 20)  # 20 ranges over 2 s
    xyz = np.c_[0.23 * t, np.zeros(20), np.zeros(20)]
    d = _ranges(xyz, np.array([3.0, 2.0, 1.0]), 0.0, 0.05, rng)
    w = _window(xyz, d, t)
    cfg = UwbConfig(min_ranges=5)
    sr = search_window(w, cfg, 0.1)
    assert not sr.ok and "2.0 s" in sr.reason
    res = initialize_anchors({7: w}, cfg, None, method="ri-robust")
    assert res[7].status == "not determined" and not res[7].ok and np.all(np.isnan(res[7].x))
    warns = add_initialised_anchors(State(), res, cfg, None)
    assert any("anchor 7 not initialised" in m for m in warns)


@pytest.mark.parametrize("method", ["lsi", "ri", "ri-robust"])
def test_open_height_on_every_init_method(method):
    rng = np.random.default_rng(6)
    xyz = _ground_track(3000, rng)
    t = np.linspace(0, 150, len(xyz))
    anchor = np.array([-3.0, 7.0, 1.1])
    w = _window(xyz, _ranges(xyz, anchor, 0.1, 0.05, rng), t)
    r = initialize_anchors({0: w}, UwbConfig(), None, method=method)[0]
    assert r.ok
    assert r.verdict["height_observable"] is False
    assert any("height not determined" in m for m in r.warnings)
    assert abs(r.x[2] - anchor[2]) <= 2 * np.sqrt(r.cov[2, 2])
    assert np.hypot(*(r.x[:2] - anchor[:2])) < 0.15


def test_z_prior_fusion_closed_form():
    x = np.array([1.0, 2.0, 0.0, 1.0, 0.1])
    cov = np.diag([0.01, 0.01, 4.0, 1e-4, 0.01])
    x2, c2 = _fuse_z_prior(x, cov, (1.0, 0.2))
    # scalar fusion: z = (0/4 + 1/0.04) / (1/4 + 1/0.04), var = 1 / (1/4 + 1/0.04)
    assert x2[2] == pytest.approx((1 / 0.04) / (1 / 4 + 1 / 0.04))
    assert c2[2, 2] == pytest.approx(1 / (1 / 4 + 1 / 0.04))
    np.testing.assert_allclose(x2[[0, 1, 3, 4]], x[[0, 1, 3, 4]])


def test_choose_schedule_from_stamps():
    t = np.arange(0, 300, 0.1)
    early = np.zeros(len(t), int)
    assert choose_schedule(t * 1e9, early, 100e9)[0] == "windows"
    late = np.where(t > 230, 1, 0)  # anchor 1 only in the last quarter
    sched, why = choose_schedule(t * 1e9, late, 100e9)
    assert sched == "per-anchor" and "1 (0/" in why


def test_late_anchor_joins_and_is_initialised():
    rng = np.random.default_rng(7)
    n = 6000
    t = np.linspace(0, 300, n)
    xyz = np.c_[20 * np.cos(t / 25), 15 * np.sin(t / 19), 1.0 + 0.6 * np.sin(t / 6)]
    anchor = np.array([10.0, -5.0, 3.0])
    seen = t > 235  # first ranged in the last quarter
    d = _ranges(xyz[seen], anchor, 0.2, 0.05, rng)
    w = _window(xyz[seen], d, t[seen])
    ends = candidate_ends(w.t_ns, int(100e9))
    assert ends[0] == int(100e9) and ends[-1] == int(w.t_ns.max()) + 1
    cfg = UwbConfig()
    j = join_time(w, int(100e9), lambda sub: search_window(sub, cfg, 0.05), join_sigma=cfg.join_sigma_m)
    assert j.join_ns is not None and j.join_ns > 235e9 and j.search.ok
    assert np.hypot(*(j.search.p - anchor)[:2]) < 0.3
    assert _nees(j.search, anchor) < CHI2_3_999
    never = join_time(w, int(100e9), lambda sub: search_window(sub, cfg, 0.05), per_anchor=False)
    assert never.join_ns is None and not never.search.ok


def test_plane_frame_is_a_rotation_with_upward_normal():
    rng = np.random.default_rng(8)
    xyz = _ground_track(500, rng)
    c, Vt, ext = plane_frame(xyz)
    assert np.linalg.det(Vt) == pytest.approx(1.0)
    assert Vt[2, 2] > 0.99 and ext[2] < 0.05 * ext[0]
