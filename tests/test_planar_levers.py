"""Planar-carrier lever arms (issue #14, pipeline/planar_levers.py): closed-form Jacobians against finite
differences, the heading about the spin axis whatever the body frame, the `auto` choice, and recovery of known
arms on the simulated `planar` scenario when the given arms are those of another body frame (upside down) and
off by centimetres."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from uwbcal.convert.scenarios import simulate_scenario
from uwbcal.pipeline.core.geometry import quat_to_rot
from uwbcal.pipeline.uwb.evidence import FitSpec, fit_anchor
from uwbcal.pipeline.uwb.planar_levers import (
    LeverData,
    carrier_heading,
    choose_lever_arms,
    estimate_planar_levers,
    fit_planar_levers,
    lever_residuals,
    refit_searches,
    shared_offsets,
)
from uwbcal.pipeline.uwb.window import InitWindow


def test_lever_residual_jacobians_match_finite_differences():
    rng = np.random.default_rng(0)
    N, A, K = 40, 3, 2
    n = np.array([0.0, 0.0, 1.0])
    e1, e2 = np.array([1.0, 0, 0]), np.array([0, 1.0, 0])
    data = LeverData(
        rng.integers(0, A, N),
        rng.integers(0, K, N),
        rng.uniform(2, 6, N),
        rng.normal(0, 2, (N, 3)),
        rng.uniform(-3, 3, N),
    )
    B = rng.normal(0, 4, (A, 3))
    G = rng.normal(0, 0.2, (A, K))
    lam = rng.normal(0, 0.2, (K, 2))
    h = rng.normal(0, 0.1, K)
    for sense in (1, -1):
        r, u, dlam = lever_residuals(data, B, G, lam, h, sense, e1, e2, n)
        eps = 1e-6
        for j in range(3):
            dB = np.zeros_like(B)
            dB[:, j] = eps
            num = (lever_residuals(data, B + dB, G, lam, h, sense, e1, e2, n)[0] - r) / eps
            np.testing.assert_allclose(u[:, j], num, atol=1e-5)  # dr/db_a (each range depends on its anchor)
        for i in range(K):
            for j in range(2):
                dl = np.zeros_like(lam)
                dl[i, j] = eps
                num = (lever_residuals(data, B, G, lam + dl, h, sense, e1, e2, n)[0] - r) / eps
                np.testing.assert_allclose(np.where(data.k == i, dlam[:, j], 0.0), num, atol=1e-5)


def _spin(psi: np.ndarray, axis) -> np.ndarray:
    return Rotation.from_rotvec(np.outer(psi, axis)).as_matrix()


def test_heading_about_the_spin_axis_any_body_frame():
    psi = np.linspace(0, 6 * np.pi, 500) % (2 * np.pi) - np.pi
    body = Rotation.from_euler(
        "xyz", [180, 0, 37], degrees=True
    ).as_matrix()  # upside-down, rotated body frame
    R = _spin(psi, [0, 0, 1]) @ body
    h = carrier_heading(R, [0, 0, 1])
    assert h.sense is not None and h.turn > 0.9
    d = np.angle(np.exp(1j * (h.sense * h.psi(R) - (psi - psi[0]))))
    assert np.max(np.abs(d)) < 1e-6
    # an attitude spinning about an in-plane axis (e.g. the quaternion read in another order): inconsistent
    Rx = _spin(psi, [1, 0, 0])
    hx = carrier_heading(Rx, [0, 0, 1])
    assert hx.sense is None
    dx = np.angle(np.exp(1j * (np.abs(hx.psi(Rx)) - np.abs(np.angle(np.exp(1j * (psi - psi[0])))))))
    assert np.max(np.abs(dx)) < 1e-6


def test_auto_choice():
    t = np.linspace(0, 60, 600)
    p = np.c_[2 * np.cos(0.3 * t), 1.5 * np.sin(0.3 * t), np.full_like(t, 0.3)]
    R = _spin(0.3 * t, [0, 0, 1])
    assert choose_lever_arms(R, p)[0] == "planar"
    assert choose_lever_arms(np.broadcast_to(np.eye(3), R.shape), p)[0] == "given"  # never turns
    p3 = p + np.c_[np.zeros((len(t), 2)), np.sin(0.7 * t)]
    assert choose_lever_arms(R, p3)[0] == "given"  # not planar
    assert choose_lever_arms(R, p, n_antennas=1)[0] == "given"  # one antenna


@pytest.fixture(scope="module")
def planar_sim():
    data = simulate_scenario("planar", seed=2, duration=60.0)
    r, gt = data.ranges, data.groundtruth
    i = np.clip(np.searchsorted(gt.t_ns, r.t_ns), 0, len(gt.t_ns) - 1)
    R = quat_to_rot(gt.q_xyzw[i])
    p = gt.p[i]
    arms = data.config.lever_arms()
    tag_i = r.tag - data.config.tag_id
    return data, R, p, arms, tag_i


def test_planar_scenario_recovers_arms_of_another_body_frame(planar_sim):
    """The planar trolley (IMU x up) with its arms given in a frame turned upside down about IMU z and off by
    3 cm: the estimated in-plane arms put every antenna within 1 cm of the truth, the range residuals fall to
    the noise, and the anchors' horizontal errors drop (by a third; the scenario's common offset of 0.2 m, which a
    fit from inside the anchors' ring trades against their distance, is the rest)."""
    data, R, p, arms, tag_i = planar_sim
    r = data.ranges
    true_off = np.einsum("nij,nj->ni", R, arms[tag_i])
    flip = np.diag([-1.0, -1.0, 1.0])  # 180 deg about IMU z: in-plane components mirrored
    given = arms @ flip.T + np.array([0.0, 0.03, -0.03])
    link = r.tag.astype(np.int64) * 256
    d = r.distance
    xyz_given = p + np.einsum("nij,nj->ni", R, given[tag_i])
    starts, before = {}, []
    for a in range(len(data.anchors)):
        m = r.anchor == a
        sr = fit_anchor(
            xyz_given[m], d[m], link[m], t_ns=r.t_ns[m], spec=FitSpec(sigma_range=0.1, refine_cov=False)
        )
        assert sr.ok
        starts[a] = (sr.p, {int(lk): float(g) for lk, g in zip(sr.links, sr.gamma, strict=True)})
        before.append(np.hypot(*(sr.p - data.anchors[a])[:2]))
    pl = estimate_planar_levers(R, p, d, r.anchor, link, given[tag_i], starts, t_ns=r.t_ns, sigma_range=0.1)
    assert pl is not None and pl.heading.sense is not None
    err = pl.world_offsets(R, link) - true_off
    err_plane = err - np.outer(err @ pl.heading.normal, pl.heading.normal)  # the height is not estimated
    assert np.sqrt(np.mean(np.sum(err_plane**2, 1))) < 0.01, np.sqrt(np.mean(np.sum(err_plane**2, 1)))
    assert pl.info["residual_sigma_m"] < 0.12 < pl.info["residual_sigma_given_m"], pl.info
    # the body-frame arms reproduce the world offsets
    np.testing.assert_allclose(
        np.einsum("nij,nj->ni", R, pl.body_arms(R, link)), pl.world_offsets(R, link), atol=1e-9
    )
    # second pass as the init stage runs it: fits on the corrected windows, re-fitted jointly with the arms held
    wins, searches = {}, {}
    for a in starts:
        m = r.anchor == a
        wins[a] = InitWindow(
            d[m], pl.body_arms(R[m], link[m]), R[m], p[m], np.zeros((6, 6)), r.t_ns[m], link[m]
        )
        searches[a] = fit_anchor(
            wins[a].tag_xyz, d[m], link[m], t_ns=r.t_ns[m], spec=FitSpec(sigma_range=0.1, refine_cov=False)
        )
    refit = refit_searches(pl, wins, searches, 0.1)
    after = []  # as the init stage goes on: the joint fit's link offsets off the ranges, then each anchor's fit
    for a in starts:
        w = wins[a]
        corr = w.d - refit[a].gamma_of(w.links())
        fit = fit_anchor(w.tag_xyz, corr, w.link, t_ns=w.t_ns, spec=FitSpec(sigma_range=0.1))
        after.append(np.hypot(*(fit.p - data.anchors[a])[:2]))
    print("horizontal before", np.round(before, 3), "after", np.round(after, 3))
    assert np.mean(after) < 0.75 * np.mean(before), (before, after)


def test_shared_offsets_are_each_links_median_and_robust_spread():
    G = np.array(
        [[0.20, 0.10], [0.22, 0.12], [0.18, 0.14], [0.60, 0.11]]
    )  # anchor 3's first link: an outlier
    seen = np.ones_like(G, bool)
    mu, sd = shared_offsets(G, seen)
    np.testing.assert_allclose(mu, [0.21, 0.115])
    dev = (G - mu).ravel()
    assert sd == pytest.approx(1.4826 * np.median(np.abs(dev - np.median(dev))))
    assert shared_offsets(np.full((4, 2), 0.2), seen)[1] == pytest.approx(0.01)  # identical: the floor
    seen[1:, 1] = [True, False, False]
    assert shared_offsets(G, seen) is None  # two anchors on link 1: no scatter to measure


def _ring(offsets: np.ndarray, radius: float, seed: int = 0):
    """Four anchors on a ring of 4 m, each with its own offset, ranged by one tag (zero arm) circling at
    ``radius`` (inside the ring: each anchor seen from one side, its offset trading against its distance)."""
    rng = np.random.default_rng(seed)
    B = np.array([[4.0, 0, 1], [0, 4.0, 1], [-4.0, 0, 1], [0, -4.0, 1]])
    t = np.linspace(0, 6 * np.pi, 1200)
    p = np.c_[radius * np.cos(t), 0.8 * radius * np.sin(t), np.zeros_like(t)]
    a = np.arange(len(t)) % 4
    d = np.linalg.norm(p - B[a], axis=1) + offsets[a] + rng.normal(0, 0.05, len(t))
    data = LeverData(a, np.zeros(len(t), np.int64), d, p, np.zeros(len(t)))
    return data, B


def _fit(data, B, prior=None, G0=None):
    e = np.eye(3)
    args = (np.zeros((1, 2)), np.zeros(1), 1, e[0], e[1], e[2], 0.15)
    G0 = np.zeros((len(B), 1)) if G0 is None else G0
    return fit_planar_levers(data, B, G0, *args, estimate_lever=False, offset_prior=prior)


def test_the_offset_prior_pulls_only_what_the_ranges_leave_open():
    """From a free fit's optimum (as `refit_searches` starts): around the anchors the ranges fix every offset, and
    a prior of the ranges' own weight (5 cm against 5 cm ranges) changes them by less than 2 cm, keeping one far
    from its mean (the Cauchy tail); a negligible one changes nothing. From inside the ring the offsets trade
    against the distances; the installation's offset as a prior brings the anchors back."""
    true = np.array([0.2, 0.2, 0.2, 0.6])
    data, B = _ring(true, radius=6.0)
    free = _fit(data, B)
    np.testing.assert_allclose(free["G"][:, 0], true, atol=0.02)
    far = _fit(data, B, G0=np.full((4, 1), 0.5))  # the same optimum from offsets 0.1-0.3 m off
    np.testing.assert_allclose(far["G"], free["G"], atol=1e-3)
    own = _fit(data, free["B"], (np.array([0.2]), 1.0), free["G"])
    np.testing.assert_allclose(own["G"][:, 0], true, atol=0.02)
    np.testing.assert_allclose(
        _fit(data, free["B"], (np.array([0.3]), 1e-6), free["G"])["G"], free["G"], atol=1e-4
    )

    data, B = _ring(np.full(4, 0.2), radius=1.5)
    free = _fit(data, B)
    held = _fit(data, free["B"], (np.array([0.2]), 1.0), free["G"])
    err = [np.linalg.norm(f["B"][:, :2] - B[:, :2], axis=1) for f in (free, held)]
    print("inside the ring: free", np.round(err[0], 3), "under the prior", np.round(err[1], 3))
    assert err[1].mean() < 0.5 * err[0].mean(), err
