"""Association, alignment, metrics and consistency against closed forms (and evo where it has the same thing)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.stats import chi2

from uwbcal.evaluate import align as al
from uwbcal.evaluate import consistency as cs
from uwbcal.evaluate import metrics as mt
from uwbcal.evaluate.association import associate, lever_point
from uwbcal.pipeline.core.errors import InputError
from uwbcal.pipeline.core.geometry import exp_so3, quat_to_rot, rot_to_quat
from uwbcal.pipeline.core.series import interpolate_positions


def _rand_rot(rng, n=None):
    w = rng.normal(size=(3,) if n is None else (n, 3))
    return exp_so3(w)


# -- association ---------------------------------------------------------------------------------------------------
def test_linear_motion_interpolated_exactly():
    t_gt = np.arange(0, 10_000_000_001, 100_000_000, dtype=np.int64) + 1_600_000_000_000_000_000
    v = np.array([0.3, -1.2, 0.05])
    p0 = np.array([1.0, 2.0, 3.0])
    p_gt = p0 + ((t_gt - t_gt[0]) * 1e-9)[:, None] * v
    rng = np.random.default_rng(0)
    t_est = np.sort(t_gt[0] - 500_000_000 + rng.integers(0, 11_000_000_000, 400))
    a = associate(t_est, t_gt, p_gt)
    inside = (t_est >= t_gt[0]) & (t_est <= t_gt[-1])
    assert a.n_outside == int((~inside).sum()) > 0
    assert a.n_gap == 0
    np.testing.assert_array_equal(a.idx, np.flatnonzero(inside))
    expect = p0 + ((a.t_ns - t_gt[0]) * 1e-9)[:, None] * v
    np.testing.assert_allclose(a.p, expect, atol=1e-12)
    assert a.q_xyzw is None


def test_constant_rate_rotation_slerped_exactly():
    t_gt = np.arange(0, 2_000_000_001, 50_000_000, dtype=np.int64)
    w = np.array([0.2, -0.4, 0.9])  # rad/s, body rate (constant axis: slerp is exact)
    R0 = exp_so3(np.array([0.1, 0.2, 0.3]))
    q_gt = rot_to_quat(R0 @ exp_so3((t_gt * 1e-9)[:, None] * w))
    t_est = np.array([1, 123_456_789, 1_000_000_000, 1_999_999_999], np.int64)
    a = associate(t_est, t_gt, np.zeros((len(t_gt), 3)), q_gt)
    R_expect = R0 @ exp_so3((t_est * 1e-9)[:, None] * w)
    np.testing.assert_allclose(quat_to_rot(a.q_xyzw), R_expect, atol=1e-12)


def test_gaps_dropped_and_unsorted_duplicates_tolerated():
    t_gt = np.array([0, 10, 20, 30, 1000, 1010, 1020, 20], np.int64)  # a gap 30..1000, one repeated stamp
    p_gt = np.c_[t_gt, t_gt, t_gt].astype(float)
    t_est = np.array([5, 30, 500, 1000, 1005, 2000], np.int64)
    a = associate(t_est, t_gt, p_gt, max_gap_ns=100)
    np.testing.assert_array_equal(a.t_ns, [5, 30, 1000, 1005])
    assert (a.n_outside, a.n_gap, a.n_dropped) == (1, 1, 2)
    np.testing.assert_allclose(a.p[:, 0], [5, 30, 1000, 1005])
    # the automatic limit (10 x median interval = 100 ns) gives the same
    assert associate(t_est, t_gt, p_gt).n_gap == 1
    with pytest.raises(InputError):
        associate(t_est, [1], [[0, 0, 0]])


def _spin(t_s: np.ndarray, rate_deg_s: float, wobble_deg: float = 0.0) -> np.ndarray:
    """Rotation about a tilted axis at a constant rate plus a 5 Hz wobble about x (quaternions)."""
    axis = np.array([0.3, -0.5, 0.8]) / np.linalg.norm([0.3, -0.5, 0.8])
    R = exp_so3(np.radians(rate_deg_s) * t_s[:, None] * axis)
    wob = exp_so3(np.radians(wobble_deg) * np.sin(2 * np.pi * 5.0 * t_s)[:, None] * np.array([1.0, 0, 0]))
    return rot_to_quat(R @ wob)


def test_ground_truth_glitches_dropped_and_counted():
    """Motion capture at 100 Hz, 40 deg/s: a one-sample 20 deg jump and a 3-sample 150 deg marker swap (the samples
    either side agree) are dropped; the ground truth at their stamps is interpolated from the good neighbours."""
    t_gt = np.arange(0, 3_000_000_000, 10_000_000, dtype=np.int64)
    t_s = t_gt * 1e-9
    q_true = _spin(t_s, 40.0)
    p_gt = np.c_[np.sin(t_s), np.cos(t_s), 0.1 * t_s]
    q_gt = q_true.copy()
    q_gt[100] = rot_to_quat(quat_to_rot(q_true[100]) @ exp_so3(np.radians([20.0, 0, 0])))
    swap = exp_so3(np.radians([0, 0, 150.0]))
    q_gt[200:203] = rot_to_quat(quat_to_rot(q_true[200:203]) @ swap)
    p_gt[200:203] += 0.03  # the swap moves the fitted centroid by a few cm too
    a = associate(t_gt[50:250], t_gt, p_gt, q_gt)
    assert a.n_gt_glitches == 4
    np.testing.assert_allclose(quat_to_rot(a.q_xyzw), quat_to_rot(q_true[50:250]), atol=2e-5)
    # a position-only track (20 Hz prism) with a one-sample 3 m jump: 60 m/s for one interval and back
    t20 = np.arange(0, 2_000_000_000, 50_000_000, dtype=np.int64)
    p20 = np.c_[t20 * 1e-9, np.zeros(len(t20)), np.zeros(len(t20))]
    p20[17, 1] += 3.0
    assert associate(t20, t20, p20).n_gt_glitches == 1


def test_fast_real_motion_is_not_a_glitch():
    """Fast but rigid motion is kept: a 900 deg/s spin (9 deg per 100 Hz sample), a 5 Hz +-15 deg wobble, a stop
    from 600 deg/s to rest in one sample, a 40 m/s car, and arrival stamps bunched 0.1 ms apart."""
    rng = np.random.default_rng(3)
    t_gt = np.arange(0, 2_000_000_000, 10_000_000, dtype=np.int64) + rng.integers(-4_900_000, 4_900_000, 200)
    t_gt.sort()
    t_s = t_gt * 1e-9
    p_car = np.c_[40.0 * t_s, np.zeros(len(t_s)), np.zeros(len(t_s))]
    for q in (_spin(t_s, 900.0), _spin(t_s, 0.0, wobble_deg=15.0), _spin(np.minimum(t_s, 1.0), 600.0)):
        assert associate(t_gt, t_gt, p_car, q).n_gt_glitches == 0


def test_interpolation_keeps_nanoseconds_at_epoch_scale():
    t_gt = np.array([1_700_000_000_000_000_000, 1_700_000_000_000_000_010], np.int64)
    p = interpolate_positions(t_gt, np.array([[0.0, 0, 0], [10.0, 0, 0]]), t_gt[:1] + 3)
    assert p[0, 0] == pytest.approx(3.0, abs=1e-12)


def test_lever_point():
    rng = np.random.default_rng(1)
    R = _rand_rot(rng, 5)
    p = rng.normal(size=(5, 3))
    lever = np.array([0.1, -0.2, 0.3])
    out = lever_point(p, rot_to_quat(R), lever)
    np.testing.assert_allclose(out, p + np.einsum("nij,j->ni", R, lever), atol=1e-12)
    np.testing.assert_array_equal(lever_point(p, rot_to_quat(R), None), p)


# -- alignment -----------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("method", ["se3", "sim3", "posyaw", "none"])
def test_alignment_recovers_known_transform(method):
    rng = np.random.default_rng(2)
    x = rng.normal(size=(50, 3)) * [5, 3, 1]
    if method == "posyaw":
        R = exp_so3(np.array([0, 0, 2.5]))
    elif method == "none":
        R = np.eye(3)
    else:
        R = _rand_rot(rng)
    s = 1.7 if method == "sim3" else 1.0
    t = np.zeros(3) if method == "none" else np.array([3.0, -1.0, 0.5])
    y = s * x @ R.T + t
    a = al.align(x, y, method)
    np.testing.assert_allclose(a.R, R, atol=1e-10)
    np.testing.assert_allclose(a.t, t, atol=1e-10)
    assert a.s == pytest.approx(s, abs=1e-12)
    p, Rs = al.apply(a, x, np.repeat(np.eye(3)[None], len(x), 0))
    np.testing.assert_allclose(p, y, atol=1e-9)
    np.testing.assert_allclose(Rs, np.broadcast_to(R, Rs.shape), atol=1e-10)
    np.testing.assert_allclose(a.matrix()[:3, :3], s * R, atol=1e-10)


@pytest.mark.parametrize("with_scale", [False, True])
def test_umeyama_matches_evo_with_noise(with_scale):
    from evo.core.geometry import umeyama_alignment

    rng = np.random.default_rng(3)
    x = rng.normal(size=(80, 3)) * [4, 2, 1]
    y = 1.3 * x @ _rand_rot(rng).T + [1, 2, 3] + rng.normal(scale=0.1, size=x.shape)
    R, t, s = umeyama_alignment(x.T, y.T, with_scale)
    a = al.umeyama(x, y, with_scale)
    np.testing.assert_allclose(a.R, R, atol=1e-10)
    np.testing.assert_allclose(a.t, t, atol=1e-10)
    assert a.s == pytest.approx(s, rel=1e-12)


def test_posyaw_is_least_squares_optimum_with_noise():
    rng = np.random.default_rng(4)
    x = rng.normal(size=(60, 3)) * [4, 2, 1]
    y = x @ exp_so3(np.array([0, 0, -1.0])).T + [1, 2, 3] + rng.normal(scale=0.2, size=x.shape)
    a = al.posyaw(x, y)

    def cost(psi):
        Rz = exp_so3(np.array([0, 0, psi]))
        t = y.mean(0) - Rz @ x.mean(0)
        return np.sum((y - x @ Rz.T - t) ** 2)

    psi = np.arctan2(a.R[1, 0], a.R[0, 0])
    grid = np.linspace(psi - 0.05, psi + 0.05, 101)
    assert cost(psi) <= min(cost(g) for g in grid) + 1e-12
    assert a.R[2, 2] == 1.0 and a.s == 1.0


def test_degenerate_alignment_refused():
    x = np.c_[np.arange(10.0), np.zeros(10), np.zeros(10)]
    with pytest.raises(InputError, match="degenerate"):
        al.align(x, x, "se3")
    with pytest.raises(InputError):
        al.align(x[:2], x[:2], "sim3")
    with pytest.raises(InputError, match="unknown"):
        al.align(x, x, "se4")


# -- metrics -------------------------------------------------------------------------------------------------------
def test_prmse_ormse_of_constructed_errors():
    rng = np.random.default_rng(5)
    n = 40
    p = rng.normal(size=(n, 3))
    d = rng.normal(size=(n, 3))
    d *= (np.where(np.arange(n) % 2 == 0, 0.1, 0.3) / np.linalg.norm(d, axis=1))[:, None]
    assert mt.prmse(p + d, p) == pytest.approx(np.sqrt((0.01 + 0.09) / 2), rel=1e-12)
    R = _rand_rot(rng, n)
    ang = np.where(np.arange(n) < 10, np.radians(2.0), np.radians(4.0))
    axis = rng.normal(size=(n, 3))
    axis /= np.linalg.norm(axis, axis=1, keepdims=True)
    R_est = R @ exp_so3(axis * ang[:, None])  # error of either side: same angle
    expect = np.sqrt((10 * 4.0 + 30 * 16.0) / 40)
    assert mt.ormse_deg(R_est, R) == pytest.approx(expect, rel=1e-9)
    assert mt.ormse_deg(R, R_est) == pytest.approx(expect, rel=1e-9)


def test_rmse_by_segment():
    seg = np.array([0, 0, 1, 1, 1, 2])
    err = np.array([1.0, 1.0, 2.0, 2.0, 2.0, 3.0])
    p_gt = np.zeros((6, 3))
    p_est = np.c_[err, np.zeros(6), np.zeros(6)]
    out = mt.prmse_by_segment(p_est, p_gt, mt.segment_masks_from_ids(seg))
    assert out["init"] == pytest.approx(1.0)
    assert out["refine"] == pytest.approx(2.0)
    assert out["localize"] == pytest.approx(3.0)
    assert out["all"] == pytest.approx(np.sqrt((2 + 12 + 9) / 6))
    masks = mt.segment_masks_from_bounds(
        np.arange(6) * 10, {"init": (0, 20), "refine": (20, 50), "localize": (99, 100)}
    )
    out2 = mt.rmse_by_segment(err, masks)
    assert "localize" not in out2  # no samples: absent, never faked
    assert out2["refine"] == pytest.approx(2.0)
    R = np.repeat(np.eye(3)[None], 6, 0)
    o = mt.ormse_deg_by_segment(R @ exp_so3(np.c_[np.zeros(6), np.zeros(6), np.radians(err)]), R, masks)
    assert o["init"] == pytest.approx(1.0) and o["refine"] == pytest.approx(2.0)


def test_anchor_errors():
    truth = {
        "1": {"position": [0, 0, 0], "beta": 0.9, "gamma": -0.3},
        "2": {"position": [1, 1, 1]},
        "3": [5, 5, 5],
    }
    est = {1: {"position": [3, 4, 0], "beta": 1.0, "gamma": -0.1}, 2: np.array([1, 1, 2.0])}
    r = mt.anchor_errors(est, truth)
    assert r.missing == ["3"]
    assert r.per_anchor["1"]["error_m"] == pytest.approx(5.0)
    assert r.per_anchor["2"]["error_m"] == pytest.approx(1.0)
    assert r.mean_m == pytest.approx(3.0)
    assert r.per_anchor["1"]["beta_error"] == pytest.approx(0.1)
    assert r.per_anchor["1"]["gamma_error"] == pytest.approx(0.2)
    assert "beta_error" not in r.per_anchor["2"]
    assert r.mean_abs_gamma == pytest.approx(0.2)


# -- consistency ---------------------------------------------------------------------------------------------------
def _random_cov(rng, d, n):
    A = rng.normal(size=(n, d, d))
    return A @ np.swapaxes(A, 1, 2) + 0.1 * np.eye(d)


@pytest.mark.parametrize("d", [1, 3, 5, 6])
def test_nees_of_sampled_gaussians_has_mean_dof(d):
    rng = np.random.default_rng(10 + d)
    n = 20000
    P = _random_cov(rng, d, n)
    e = np.einsum("nij,nj->ni", np.linalg.cholesky(P), rng.normal(size=(n, d)))
    v = cs.nees(e, P)
    # mean of n chi2_d samples: sd = sqrt(2 d / n); 5 sigma tolerance
    assert abs(v.mean() - d) < 5 * np.sqrt(2 * d / n)
    assert abs(np.var(v) - 2 * d) < 0.15 * 2 * d
    assert cs.nees(e[0], P[0]) == pytest.approx(v[0])


def test_pose_nees_convention_and_blocks():
    rng = np.random.default_rng(11)
    n = 20000
    P = _random_cov(rng, 6, n) * 1e-3
    dx = np.einsum("nij,nj->ni", np.linalg.cholesky(P), rng.normal(size=(n, 6)))
    R_hat = _rand_rot(rng, n)
    p_hat = rng.normal(size=(n, 3))
    R_true = R_hat @ exp_so3(dx[:, :3])  # R = R_hat Exp(dtheta)
    p_true = p_hat + dx[:, 3:]  # dp = p - p_hat
    np.testing.assert_allclose(cs.pose_error(R_hat, p_hat, R_true, p_true), dx, atol=1e-9)
    r = cs.pose_nees(R_hat, p_hat, P, R_true, p_true)
    for v, d in ((r.orientation, 3), (r.position, 3), (r.pose, 6)):
        assert abs(v.mean() - d) < 5 * np.sqrt(2 * d / n)
    np.testing.assert_allclose(cs.position_nees(p_hat, P[:, 3:, 3:], p_true), r.position)


def test_anchor_nees_and_nis():
    rng = np.random.default_rng(12)
    P = _random_cov(rng, 5, 1)[0]
    truth = np.array([10, 10, 10, 0.9, -0.3])
    e = rng.normal(size=5)
    assert cs.anchor_nees(truth - e, P, truth) == pytest.approx(e @ np.linalg.solve(P, e))
    assert cs.anchor_nees(truth[:3] - e[:3], P[:3, :3], truth[:3]) == pytest.approx(
        e[:3] @ np.linalg.solve(P[:3, :3], e[:3])
    )
    np.testing.assert_allclose(cs.nis(np.array([0.2, -0.1]), np.array([0.04, 0.01])), [1.0, 1.0])
    assert cs.nis(e[:2], P[:2, :2]) == pytest.approx(e[:2] @ np.linalg.solve(P[:2, :2], e[:2]))
    bad = np.zeros((2, 3, 3))
    bad[0] = np.eye(3)
    out = cs.nees(np.ones((2, 3)), bad)
    assert out[0] == pytest.approx(3.0) and np.isnan(out[1])


def test_anees_and_chi2_bounds_closed_form():
    lo, hi = cs.chi2_bounds(50, 3)
    assert lo == pytest.approx(chi2.ppf(0.025, 150) / 50) and hi == pytest.approx(chi2.ppf(0.975, 150) / 50)
    # known values: N=1, d=1 -> (chi2_1 2.5 %, 97.5 %) = (0.000982, 5.0239)
    lo1, hi1 = cs.chi2_bounds(1, 1)
    assert lo1 == pytest.approx(0.00098207, rel=1e-4) and hi1 == pytest.approx(5.02389, rel=1e-5)
    # large N d: bounds -> d (1 -/+ 1.96 sqrt(2 / (N d)))
    lo, hi = cs.chi2_bounds(2000, 6)
    assert lo == pytest.approx(6 * (1 - 1.96 * np.sqrt(2 / 12000)), rel=2e-3)
    assert hi == pytest.approx(6 * (1 + 1.96 * np.sqrt(2 / 12000)), rel=2e-3)
    # ANEES of N consistent runs stays within the bounds about 95 % of the time
    rng = np.random.default_rng(13)
    runs = rng.chisquare(3, size=(25, 4000))
    runs[0, 0] = np.nan
    a = cs.anees(runs)
    assert a[0] == pytest.approx(np.mean(runs[1:, 0]))
    inside = cs.fraction_inside(a, cs.chi2_bounds(25, 3))
    assert abs(inside - 0.95) < 0.02
    s = cs.summarize_nees(a, 3, n_runs=25)
    assert s["bounds"][0] < s["mean"] < s["bounds"][1] and s["dof"] == 3
