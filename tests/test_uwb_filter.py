"""UWB filter side: covariance initialisation, EKF/SKF/frozen updates, anchor NEES over Monte Carlo runs."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from scipy.stats import chi2

from uwbcal.evaluate.experiments.ri_vs_lsi import smooth_trajectory
from uwbcal.pipeline.core.geometry import exp_so3, log_so3, rot_to_quat
from uwbcal.pipeline.core.state import Kind, Pose, State, Vec
from uwbcal.pipeline.uwb.config import UwbConfig
from uwbcal.pipeline.uwb.updater import (
    METHODS,
    UwbUpdater,
    add_anchor_to_state,
    add_initialised_anchors,
    anchor_var,
    initialize_anchors,
    windows_from_trajectory,
)
from uwbcal.pipeline.vio.estimator import RangeMeasurement

ARMS = {(1, 0): np.array([0.2, 0.3, 0.0]), (1, 1): np.array([0.2, -0.3, 0.0])}
CALIB = {
    "uwb": {
        "tags": {"1": {"antennas": [[0.2, 0.3, 0.0], [0.2, -0.3, 0.0]]}},
        "sigma_range": 0.1,
        "gamma_prior": {"mean": 0.5, "sigma": 0.3},
    }
}
ANCHORS = {7: np.array([8.0, -6.0, 4.0]), 9: np.array([-7.0, 9.0, 5.0])}


class _Est:
    def __init__(self, state: State) -> None:
        self.state = state
        self.t_ns = 0


def _propagate(state: State, dR: np.ndarray, q_pos: float) -> None:
    """Pose-only 'odometry' propagation: dtheta <- dR^T dtheta, dp <- dp + w (world random walk)."""
    sl = state.slice("imu")
    Phi = np.eye(6)
    Phi[0:3, 0:3] = dR.T
    P = state.P
    P[sl, :] = Phi @ P[sl, :]
    P[:, sl] = P[:, sl] @ Phi.T
    P[sl.start + 3 : sl.stop, sl.start + 3 : sl.stop] += np.eye(3) * q_pos
    v = state.value("imu")
    return v


def _simulate_run(
    seed: int,
    mode: str,
    *,
    init_s=30.0,
    refine_s=30.0,
    beta_sigma=1e-3,
    sig_th0=0.01,
    sig_p0=0.1,
    rw=0.02,
    refuse=(),
    withhold=(),
):
    """One init + refine run. ``refuse``: anchors whose initialisation is marked refused (the pipeline's
    `add_initialised_anchors` then leaves them out; their ranges still reach the updater). ``withhold``: anchors
    whose refinement ranges are never passed to the updater (the same random draws are made)."""
    rng = np.random.default_rng(seed)
    dt = 0.1
    t = np.arange(0.0, init_s + refine_s, dt)
    R_nom, p_nom = smooth_trajectory(rng, t, extent=(5.0, 5.0, 3.0), z0=2.0, freq=(0.03, 0.12))
    q_pos = rw**2 * dt
    P0 = np.diag([sig_th0**2] * 3 + [sig_p0**2] * 3)
    e0 = rng.normal(size=6) * np.sqrt(np.diag(P0))
    R_true, p_true = R_nom[0] @ exp_so3(e0[:3]), p_nom[0].copy()
    state = State(use_fej=True)
    state.add("imu", Pose(R_nom[0], p_nom[0] - e0[3:]), P0, kind=Kind.NAV)
    truth = {a: np.r_[pa, rng.normal(1.0, beta_sigma), rng.normal(0.5, 0.3)] for a, pa in ANCHORS.items()}
    cfg = UwbConfig(  # the paper's initialisation (multi-start), whose consistency this checks
        init_method="ri", refine_method=mode, beta_sigma=beta_sigma, n_perturbed_starts=0, search=False
    )
    traj = {"t_ns": [], "p": [], "q_xyzw": [], "cov": []}
    ranges = {k: [] for k in ("t_ns", "tag", "antenna", "anchor", "distance")}
    updater = None
    nees_init = {}
    n_init = int(round(init_s / dt))
    for k in range(len(t)):
        t_ns = int(round(t[k] * 1e9))
        if k > 0:
            dR = R_nom[k - 1].T @ R_nom[k]
            R_true = R_true @ dR
            p_true = p_true + (p_nom[k] - p_nom[k - 1]) + rng.normal(0, np.sqrt(q_pos), 3)
            v = state.value("imu")
            state.set_value("imu", Pose(v.R @ dR, v.p + (p_nom[k] - p_nom[k - 1])))
            _propagate(state, dR, q_pos)
        if k == n_init:
            tr = {kk: np.asarray(vv) for kk, vv in traj.items()}
            rg = {kk: np.asarray(vv) for kk, vv in ranges.items()}
            wins = windows_from_trajectory(tr, rg, CALIB)
            res = initialize_anchors(wins, cfg, CALIB)
            if refuse:
                res = {a: replace(r, status="refused") if a in refuse else r for a, r in res.items()}
                warns = add_initialised_anchors(state, res, cfg, CALIB)
                assert warns == [f"refine: anchor {a} not initialised (refused); left out" for a in refuse]
            for a, r in res.items():
                if refuse:
                    break
                assert r.ok, r.warnings
                add_anchor_to_state(
                    state, a, r, sigma_range=0.1, gamma_prior=(0.5, 0.3), beta_prior=(1.0, beta_sigma)
                )
            for a in res:
                if anchor_var(a) in state:
                    e = truth[a] - state.value(anchor_var(a)).x
                    nees_init[a] = float(e @ np.linalg.solve(state.cov(anchor_var(a)), e))
            updater = UwbUpdater.from_config(cfg, CALIB)
        v = state.value("imu")
        for j, (a, xa) in enumerate(truth.items()):
            ant = (k + j) % 2
            pT = ARMS[(1, ant)]
            d = xa[3] * (np.linalg.norm(p_true + R_true @ pT - xa[:3]) + rng.normal(0, 0.1)) + xa[4]
            m = RangeMeasurement(t_ns + j, 1, ant, a, float(d))
            if updater is None:
                for kk, vv in zip(ranges, (m.t_ns, 1, ant, a, d), strict=True):
                    ranges[kk].append(vv)
            elif a not in withhold:
                updater(_Est(state), m)
        if updater is None:
            v = state.value("imu")
            for j in range(2):
                traj["t_ns"].append(t_ns + j)
                traj["p"].append(v.p)
                traj["q_xyzw"].append(rot_to_quat(v.R))
                traj["cov"].append(state.cov("imu")[:6, :6].copy())
    nees_end = {}
    for a in truth:
        if anchor_var(a) not in state:
            continue
        e = truth[a] - state.value(anchor_var(a)).x
        nees_end[a] = float(e @ np.linalg.solve(state.cov(anchor_var(a)), e))
    v = state.value("imu")
    ep = np.r_[log_so3(v.R.T @ R_true), p_true - v.p]
    nees_pose = float(ep @ np.linalg.solve(state.cov("imu")[:6, :6], ep))
    return nees_init, nees_end, nees_pose, updater, state


@pytest.mark.parametrize("mode", ["ekf", "skf"])
def test_anchor_nees_consistent_monte_carlo(mode):
    runs = 25
    init, end, pose = [], [], []
    for s in range(runs):
        ni, ne, npo, upd, _ = _simulate_run(100 + s, mode)
        init += list(ni.values())
        end += list(ne.values())
        pose.append(npo)
    K = len(init)
    lo, hi = chi2.ppf([0.025, 0.975], 5 * K) / K
    print(mode, "ANEES init", np.mean(init), "end", np.mean(end), "bounds", lo, hi, "pose", np.mean(pose))
    assert lo < np.mean(init) < hi
    assert lo < np.mean(end) < hi
    lo6, hi6 = chi2.ppf([0.025, 0.975], 6 * runs) / runs
    assert lo6 < np.mean(pose) < hi6


@pytest.mark.parametrize("mode", ["ekf", "skf"])
def test_anchor_left_out_of_refinement(mode):
    """An anchor whose initialisation is refused stays out of the state: its ranges are skipped (counted), it
    gets no record, and the filter ends exactly where it ends when those ranges never arrive."""
    _, ne, _, upd, st = _simulate_run(200, mode, init_s=20.0, refine_s=10.0, refuse=(9,))
    _, ne_ref, _, upd_ref, st_ref = _simulate_run(
        200, mode, init_s=20.0, refine_s=10.0, refuse=(9,), withhold=(9,)
    )
    assert anchor_var(9) not in st.names and anchor_var(7) in st.names and set(ne) == {7}
    assert (
        9 not in upd.records and len(upd.records[7].t_ns) == upd.counts["accepted"] + upd.counts["rejected"]
    )
    assert upd.counts["skipped"] == 100 and upd_ref.counts["skipped"] == 0  # 10 s of ranges at 10 Hz
    assert st.names == st_ref.names
    # the same filter along two paths (ranges skipped vs never delivered: other epoch batches): equal to rounding
    np.testing.assert_allclose(st.P, st_ref.P, rtol=0, atol=1e-12 * np.abs(st_ref.P).max())
    np.testing.assert_allclose(
        st.value(anchor_var(7)).x, st_ref.value(anchor_var(7)).x, rtol=1e-12, atol=1e-12
    )
    np.testing.assert_allclose(st.value("imu").p, st_ref.value("imu").p, rtol=1e-12, atol=1e-12)


def test_methods_mapping():
    assert METHODS["viro"] == ("lsi", "ekf")
    assert METHODS["ri+skf"] == ("ri", "skf")


def _state_with_anchor():
    rng = np.random.default_rng(0)
    state = State()
    A = rng.normal(size=(6, 6)) * 0.05
    state.add(
        "imu",
        Pose(exp_so3(np.array([0.1, -0.2, 0.3])), np.array([1.0, 2.0, 0.5])),
        A @ A.T + 1e-4 * np.eye(6),
        kind=Kind.NAV,
    )
    state.add("clone/1", Pose(np.eye(3), np.zeros(3)), np.eye(6) * 0.01, kind=Kind.CLONE, key=1)
    state.P[0:6, 6:12] = state.P[6:12, 0:6] = 0.005 * np.eye(6)
    # anchor correlated with imu through the initialisation map
    J = np.zeros((5, 6))
    J[0:3, 3:6] = -np.eye(3)
    state.augment(
        "anchor/3",
        Vec(np.array([5.0, 4.0, 3.0, 1.0, 0.2])),
        {"imu": J},
        Q=np.diag([0.04, 0.04, 0.04, 0.0025, 0.04]),
        kind=Kind.ANCHOR,
        key=3,
    )
    return state


def test_skf_keeps_navigation_state_and_covariance_updates_anchor_and_cross():
    state = _state_with_anchor()
    imu0, clone0 = state.value("imu"), state.value("clone/1")
    sl_nav = np.r_[0:12]
    P0 = state.P.copy()
    upd = UwbUpdater("skf", ARMS, sigma_range=0.1, chi2_quantile=None)
    x0 = state.value("anchor/3").x.copy()
    res = upd.update(state, RangeMeasurement(1, 1, 0, 3, 6.0))
    assert res.accepted
    assert np.array_equal(state.value("imu").R, imu0.R) and np.array_equal(state.value("imu").p, imu0.p)
    assert np.array_equal(state.value("clone/1").p, clone0.p)
    assert np.allclose(state.P[np.ix_(sl_nav, sl_nav)], P0[np.ix_(sl_nav, sl_nav)], atol=1e-15)
    assert not np.allclose(state.value("anchor/3").x, x0)
    sa = state.slice("anchor/3")
    assert not np.allclose(state.P[sa, sa], P0[sa, sa])
    assert not np.allclose(state.P[0:6, sa], P0[0:6, sa])
    # EKF moves the navigation state
    st2 = _state_with_anchor()
    UwbUpdater("ekf", ARMS, sigma_range=0.1, chi2_quantile=None).update(
        st2, RangeMeasurement(1, 1, 0, 3, 6.0)
    )
    assert not np.allclose(st2.value("imu").p, imu0.p)


def test_frozen_updates_only_navigation_and_gate_counts():
    state = _state_with_anchor()
    x0 = state.value("anchor/3").x.copy()
    upd = UwbUpdater("frozen", ARMS, sigma_range=0.1, chi2_quantile=0.95)
    p0 = state.value("imu").p.copy()
    h = np.linalg.norm(p0 + state.value("imu").R @ ARMS[(1, 0)] - x0[:3]) + x0[4]
    upd.update(state, RangeMeasurement(1, 1, 0, 3, h + 0.05))
    assert np.array_equal(state.value("anchor/3").x, x0)
    assert not np.allclose(state.value("imu").p, p0)
    upd.update(state, RangeMeasurement(2, 1, 0, 3, h + 50.0))  # gross outlier: gated
    assert upd.counts["rejected"] == 1 and upd.counts["accepted"] == 1
    arr = upd.arrays()[3]
    assert arr["rejected"].tolist() == [False, True] and arr["cov"].shape == (2, 5, 5)
    # frozen anchors not in the state: given as constants
    st = State()
    st.add("imu", Pose(np.eye(3), np.zeros(3)), np.eye(6) * 0.01, kind=Kind.NAV)
    UwbUpdater("frozen", ARMS, anchors={3: x0}, chi2_quantile=None).update(
        st, RangeMeasurement(3, 1, 1, 3, 7.0)
    )
    assert st.size == 6
    # none: nothing changes
    st3 = _state_with_anchor()
    P3 = st3.P.copy()
    u3 = UwbUpdater("none", ARMS)
    u3.update(st3, RangeMeasurement(4, 1, 0, 3, 6.0))
    assert np.array_equal(st3.P, P3) and u3.counts["recorded"] == 1
    # unknown anchor: skipped
    u3.update(st3, RangeMeasurement(5, 1, 0, 42, 6.0))
    assert u3.counts["skipped"] == 1


def test_frozen_considers_the_anchor_covariance():
    """Frozen (localisation): the anchor of the state is considered: the innovation variance holds its Jacobian
    and covariance, S = H P H^T + R over [imu, anchor] (closed form), the gain on the anchor is zero (estimate and
    own covariance unchanged) and the rest is the Joseph update with that gain."""
    from uwbcal.pipeline.uwb.model import jacobians

    state = _state_with_anchor()
    P0 = state.P.copy()
    x0 = state.value("anchor/3").x.copy()
    pose = state.value("imu")
    J = jacobians(pose.R, pose.p, ARMS[(1, 0)], x0)
    d = float(J.h[0]) + 0.07
    H = np.zeros((1, state.size))
    H[0, 0:6] = J.H_I[0]
    sa = state.slice("anchor/3")
    H[0, sa] = J.H_U[0]
    R = (0.1 * x0[3]) ** 2
    S = (H @ P0 @ H.T).item() + R
    res = UwbUpdater("frozen", ARMS, sigma_range=0.1, chi2_quantile=None).update(
        state, RangeMeasurement(1, 1, 0, 3, d)
    )
    assert res.nis == pytest.approx(0.07**2 / S, rel=1e-9)
    K = (P0 @ H.T / S).ravel()
    K[sa] = 0.0
    IKH = np.eye(state.size) - np.outer(K, H)
    np.testing.assert_allclose(state.P, IKH @ P0 @ IKH.T + R * np.outer(K, K), atol=1e-14)
    assert np.array_equal(state.value("anchor/3").x, x0)
    np.testing.assert_array_equal(state.P[sa, sa], P0[sa, sa])
    np.testing.assert_allclose(state.value("imu").p - pose.p, (K[3:6] * 0.07), atol=1e-12)


def test_frozen_localisation_is_consistent_over_monte_carlo():
    """Localisation on anchors with a calibration error drawn from their covariance (3 anchors, sigma 5 cm,
    gamma 5 cm, beta 1 %): 20 epochs of ranges at one pose, 150 runs. The pose ANEES (6 dof) after the frozen
    updates is inside its two-sided 95 % chi-squared bounds; taking the anchors as exact (the same updater with
    the anchors given only as constants, as localisation did before) is far above them."""
    rng = np.random.default_rng(5)
    anchors = np.array([[5.0, 4.0, 3.0], [-6.0, 3.0, 1.0], [1.0, -7.0, 2.5]])
    Pa = np.diag([0.05**2] * 3 + [0.01**2, 0.05**2])
    P_pose = np.diag([0.02**2] * 3 + [0.3**2] * 3)
    runs = 150
    out = {"considered": [], "exact": []}
    for _ in range(runs):
        R_hat, p_hat = exp_so3(np.array([0.1, -0.2, 0.3])), np.array([1.0, 0.5, 0.8])
        e_pose = rng.multivariate_normal(np.zeros(6), P_pose)
        R_true, p_true = R_hat @ exp_so3(e_pose[:3]), p_hat + e_pose[3:]
        x_hat = [np.r_[a, 1.0, 0.3] for a in anchors]
        x_true = [x + rng.multivariate_normal(np.zeros(5), Pa) for x in x_hat]
        d = []
        for _ in range(20):
            for i, xt in enumerate(x_true):
                for ant in (0, 1):
                    rho = np.linalg.norm(p_true + R_true @ ARMS[(1, ant)] - xt[:3])
                    d.append(RangeMeasurement(1, 1, ant, i, xt[3] * (rho + rng.normal(0, 0.1)) + xt[4]))
        for mode in out:
            st = State()
            st.add("imu", Pose(R_hat, p_hat), P_pose.copy(), kind=Kind.NAV)
            if mode == "considered":
                for i, x in enumerate(x_hat):
                    st.add(anchor_var(i), Vec(x.copy()), Pa.copy(), kind=Kind.ANCHOR, key=i)
            upd = UwbUpdater(
                "frozen", ARMS, sigma_range=0.1, chi2_quantile=None, anchors=dict(enumerate(x_hat))
            )
            for k in range(0, len(d), 6):  # one epoch: the 6 ranges of one stamp
                upd.update_epoch(st, d[k : k + 6])
            x = st.value("imu")
            e = np.r_[log_so3(x.R.T @ R_true), p_true - x.p]
            out[mode].append(e @ np.linalg.solve(st.cov("imu"), e))
    lo, hi = chi2.ppf([0.025, 0.975], 6 * runs) / runs
    considered, exact = np.mean(out["considered"]), np.mean(out["exact"])
    print(f"pose ANEES {considered:.2f} in [{lo:.2f}, {hi:.2f}]; anchors taken as exact {exact:.1f}")
    assert lo < considered < hi
    assert exact > 2 * hi


def test_windows_from_trajectory_interpolates():
    t = np.array([0, 10, 20], np.int64) * 10**8
    traj = {
        "t_ns": t,
        "p": np.array([[0.0, 0, 0], [1, 0, 0], [2, 0, 0]]),
        "q_xyzw": np.array([[0, 0, 0, 1.0]] * 3),
        "cov": np.stack([np.eye(6) * v for v in (1.0, 2.0, 3.0)]),
    }
    ranges = {
        "t_ns": np.array([5, 15, 25]) * 10**8,
        "tag": np.array([1, 1, 1]),
        "antenna": np.array([0, 1, 0]),
        "anchor": np.array([3, 3, 4]),
        "distance": np.array([1.0, 2.0, 3.0]),
    }
    w = windows_from_trajectory(traj, ranges, CALIB)
    assert set(w) == {3}  # the range at 2.5 s is outside the trajectory
    assert np.allclose(w[3].p[:, 0], [0.5, 1.5]) and np.allclose(w[3].P_pose[:, 0, 0], [1.5, 2.5])
    assert np.allclose(w[3].p_T, [ARMS[(1, 0)], ARMS[(1, 1)]])


def test_log_and_summaries_write_an_rrd(tmp_path):
    from uwbcal.evaluate.experiments.ri_vs_lsi import simulate_window
    from uwbcal.pipeline.run.rundir import anchor_row, init_summary
    from uwbcal.pipeline.viz.observers import log_uwb_updates
    from uwbcal.pipeline.viz.runlog import RunLog, read_rrd_summary

    w = simulate_window(np.random.default_rng(0), 0.05)
    res = initialize_anchors(
        {5: w}, UwbConfig(init_method="lsi", n_perturbed_starts=0, estimate_beta=False), CALIB
    )
    row = anchor_row(5, "lsi", "init", res[5].x)
    assert row["anchor"] == "5" and row["method"] == "lsi" and float(row["beta"]) == 1.0
    summ = init_summary(res[5])
    assert summ["fim"]["logdet"] > 0 and summ["n_used"] == len(w)
    state = _state_with_anchor()
    upd = UwbUpdater("skf", ARMS, chi2_quantile=0.95)
    for k in range(5):
        upd.update(state, RangeMeasurement(10 + k, 1, k % 2, 3, 6.0))
    path = tmp_path / "init.rrd"
    with RunLog(path, anchors=[3, 5]) as log:
        log_uwb_updates(log, upd)
    assert path.is_file() and path.stat().st_size > 0
    s = read_rrd_summary(path)  # one residual row per range the updater processed, for the anchor it was for
    assert s.rows["uwb/3/residual"] == len(upd.records[3].t_ns) == 5 and "uwb/5/residual" not in s.rows


def _two_link_result(seed: int = 5, spread: float = 0.2):
    """Anchor 7 ranged over two links whose offsets differ by +-``spread`` about 0.5 m, 40 s at 20 Hz: the
    evidence fit's result (it takes per-link offsets where they differ) and the last pose."""
    rng = np.random.default_rng(seed)
    t = np.arange(0.0, 40.0, 0.05)
    R, p = smooth_trajectory(rng, t, extent=(5.0, 5.0, 3.0), z0=2.0, freq=(0.03, 0.12))
    a = ANCHORS[7]
    ant = np.arange(len(t)) % 2
    pT = np.stack([ARMS[(1, int(k))] for k in ant])
    offsets = np.where(ant == 0, spread, -spread)
    d = np.linalg.norm(p + np.einsum("nij,nj->ni", R, pT) - a, axis=1) + 0.5 + offsets
    d += rng.normal(0, 0.1, len(t))
    t_ns = (t * 1e9).astype(np.int64)
    traj = {
        "t_ns": t_ns,
        "p": p,
        "q_xyzw": rot_to_quat(R),
        "cov": np.broadcast_to(np.eye(6) * 1e-4, (len(t), 6, 6)),
    }
    rg = {
        "t_ns": t_ns,
        "tag": np.ones(len(t), int),
        "antenna": ant,
        "anchor": np.full(len(t), 7),
        "distance": d,
    }
    cfg = UwbConfig(init_method="ri", estimate_beta=False)
    return initialize_anchors(windows_from_trajectory(traj, rg, CALIB), cfg, CALIB)[7], R[-1], p[-1]


def test_link_offset_map_matches_refit():
    """Per-link bias: the anchor's initial covariance carries the offsets' error through J[links/<id>], the
    first-order map of a change of one link's offset into the fitted anchor. Independent reference: refit the
    window with that link's ranges shifted by eps (the solver, not the formula) and difference."""
    from uwbcal.pipeline.uwb.initializer import solve_from
    from uwbcal.pipeline.uwb.updater import anchor_init_covariance, link_var
    from uwbcal.pipeline.uwb.window import InitWindow

    res, R_end, p_end = _two_link_result()
    assert res.ok and len(res.link_offsets) == 2 and res.link_cov is not None
    state = State()
    state.add("imu", Pose(R_end, p_end), np.eye(6) * 1e-4, kind=Kind.NAV)
    state.add(
        link_var(7),
        Vec(np.array(list(res.link_offsets.values()))),
        np.asarray(res.link_cov) + 1e-9 * np.eye(2),
    )
    J, _ = anchor_init_covariance(
        res, state, sigma_range=0.1, gamma_prior=(0.5, 0.3), beta_prior=(1.0, 0.05), links=link_var(7)
    )
    w = (
        res.window
    )  # its ranges as measured: the estimator given the offsets fits them corrected by the offsets
    kw = dict(weighted=True, sigma_range=0.1, gamma_prior=(0.5, 0.3))
    th0 = res.x[list(res.params)]
    d = w.d - np.array([res.link_offsets[int(lk)] for lk in w.links()])
    base = solve_from(InitWindow(d, w.p_T, w.R, w.p, w.P_pose, w.t_ns, w.link), th0, **kw).theta
    eps = 0.01
    for col, lk in enumerate(res.link_offsets):
        shifted = InitWindow(d - eps * (w.links() == lk), w.p_T, w.R, w.p, w.P_pose, w.t_ns, w.link)
        dx = (solve_from(shifted, th0, **kw).theta - base) / eps
        np.testing.assert_allclose(dx, J[link_var(7)][list(res.params), col], rtol=0.03, atol=1e-3)


def test_evidence_anchor_joins_at_least_as_uncertain_as_both_covariances():
    """An evidence anchor joins the filter with, along each axis, the larger of its init covariance and the error
    map's (`covariance_upper_bound`): both bound the joined covariance from below, and the joined one is no wider
    than the two together (their sum)."""
    from uwbcal.pipeline.uwb.updater import anchor_init_covariance

    res, R_end, p_end = _two_link_result(seed=6, spread=0.0)
    assert res.ok and res.model_priors is not None and not res.link_offsets
    gamma, beta = res.model_priors
    for pose_var in (1e-4, 4e-2):  # an error map below and above the init covariance
        state = State()
        state.add("imu", Pose(R_end, p_end), np.eye(6) * pose_var, kind=Kind.NAV)
        mapped_state = State()
        mapped_state.add("imu", Pose(R_end, p_end), np.eye(6) * pose_var, kind=Kind.NAV)
        add_anchor_to_state(state, 7, res, sigma_range=0.1, gamma_prior=None)
        P = state.cov(anchor_var(7))
        J, Q = anchor_init_covariance(
            res, mapped_state, sigma_range=0.1, gamma_prior=gamma, beta_prior=beta, links=None
        )
        mapped = sum(M @ mapped_state.cov(v) @ M.T for v, M in J.items()) + Q
        scale = np.sqrt(np.outer(np.diag(P), np.diag(P)))
        for lower in (res.cov, mapped):
            assert np.linalg.eigvalsh((P - lower) / scale).min() > -1e-9
        assert np.linalg.eigvalsh((res.cov + mapped - P) / scale).min() > -1e-9


def test_gate_rates_and_warning_name_the_faulty_anchor():
    """The windowed gate rate per anchor (a 4 s window at 10 ranges/s: 40 ranges) against a direct count over
    each run of 40 ranges; a burst of rejections on anchor 7 is named with its span (s after t0) and the
    one-anchor cause, anchor 3's consistent 5 % is not; with a robust loss (no gate, nothing rejected) the rate
    counts the NIS beyond the quantile instead; every anchor bursting: the pose is named."""
    from uwbcal.pipeline.uwb.updater import AnchorRecord

    rng = np.random.default_rng(1)
    gate = chi2.ppf(0.95, 1)
    upd = UwbUpdater("skf", ARMS, chi2_quantile=0.95)
    t0 = 1_000_000_000
    for a, n in ((3, 400), (7, 300)):
        t = t0 + 500_000_000 + np.arange(n) * 100_000_000
        nis = rng.chisquare(1, n)
        if a == 7:
            nis[150:200] = 50.0  # the anchor's ranges 1 m off for 5 s
        upd.records[a] = AnchorRecord(t_ns=list(t), nis=list(nis), rejected=list(nis > gate))
    k = 40
    rates = upd.gate_rates(4.0, 20, 0.95)
    for a, (t, failed, rate) in rates.items():
        rec = upd.records[a]
        direct = [np.mean(rec.rejected[i : i + k]) for i in range(len(rec.t_ns) - k + 1)]
        np.testing.assert_allclose(rate, direct, atol=1e-12)
        assert np.array_equal(t, rec.t_ns) and np.array_equal(failed, rec.rejected)
    assert rates[3][2].max() < 0.25 and rates[7][2].max() == 1.0
    warns = upd.gate_warnings("localize", 4.0, 20, 0.5, 0.95, t0)
    assert len(warns) == 1 and warns[0].startswith("localize: more than 50% of the ranges of a 4 s window"), (
        warns
    )
    assert "anchor 7 from" in warns[0] and "anchor 3" not in warns[0] and "(up to 100%)" in warns[0]
    assert "only these anchors" in warns[0] and "pose" not in warns[0]
    t7, rej7 = np.asarray(upd.records[7].t_ns), np.asarray(upd.records[7].rejected)
    covered = np.zeros(len(t7), bool)  # the span: the first to the last failed range of the windows above 0.5
    for i in np.flatnonzero(rates[7][2] > 0.5):
        covered[i : i + k] = True
    hit = np.flatnonzero(covered & rej7)
    assert 150 - k < hit[0] <= 150 and 199 <= hit[-1] < 200 + k
    assert f"anchor 7 from {(t7[hit[0]] - t0) * 1e-9:.1f} s to {(t7[hit[-1]] - t0) * 1e-9:.1f} s" in warns[0]
    for rec in upd.records.values():  # a robust loss: nothing rejected, the NIS beyond the quantile counted
        rec.rejected = [False] * len(rec.t_ns)
    assert upd.gate_warnings("localize", 4.0, 20, 0.5, 0.95, t0) == warns
    assert upd.gate_warnings("refine", 4.0, 20, 0.5, None, t0) == []  # no gate at all: nothing to judge
    assert upd.gate_rates(31.0, 20, 0.95).keys() == {3}  # fewer ranges than a window: not judged
    upd.records[3].nis[300:360] = [50.0] * 60
    both = upd.gate_warnings("refine", 4.0, 20, 0.5, 0.95, t0)
    assert "anchor 3 from" in both[0] and "anchor 7 from" in both[0] and "every anchor: the pose" in both[0]


def test_gate_excess_warning_against_the_binomial_tail():
    """A consistent filter rejects ~5 % at a 95 % gate (counted from the records): 50 of 1000 (the expected
    count) and 65 (tail 0.02) stay
    silent; 90 of 1000 (tail 1e-7) warns with the counts and the tail of scipy.stats' binomial; per anchor the
    bound is alpha / anchors: an anchor with 60 of 400 rejected (tail 5e-14) is named beside one with a
    consistent 20 of 400 (the total, 80 of 800, tail 6e-9, warns too); no gate (robust
    loss): silent."""

    from scipy.stats import binom

    from uwbcal.pipeline.uwb.updater import AnchorRecord

    upd = UwbUpdater("skf", ARMS, chi2_quantile=0.95)
    for k, warns in ((0, False), (50, False), (65, False), (90, True)):
        # four anchors sharing the rejections (per anchor <= 23 of 250: tail >= 2e-3 > 1e-3 / 4, none named)
        ks = [k // 4 + (i < k % 4) for i in range(4)]
        upd.records = {
            a: AnchorRecord(rejected=[True] * ka + [False] * (250 - ka)) for a, ka in enumerate(ks)
        }
        got = upd.gate_excess_warning("refine")
        assert bool(got) is warns, (k, got)
        if warns:
            tail = binom.sf(k - 1, 1000, 0.05)
            assert got[0].startswith(f"refine: {k} of 1000 ranges (9.0%; tail {tail:.1e}) rejected"), got
            assert "; anchor" not in got[0], got
    assert binom.sf(64, 1000, 0.05) > 1e-3 > binom.sf(89, 1000, 0.05)
    assert binom.sf(22, 250, 0.05) > 1e-3 / 4

    per = UwbUpdater("skf", ARMS, chi2_quantile=0.95)
    for a, k in ((3, 20), (7, 60)):
        per.records[a] = AnchorRecord(rejected=[True] * k + [False] * (400 - k))
    got = per.gate_excess_warning("localize")
    assert len(got) == 1 and "anchor 7: 60 of 400 (15%" in got[0] and "anchor 3" not in got[0], got
    assert f"tail {binom.sf(59, 400, 0.05):.1e}" in got[0]
    per.records[7] = AnchorRecord(rejected=[True] * 20 + [False] * 380)
    assert per.gate_excess_warning("localize") == []

    # every range of a long stretch rejected: the tail underflows and prints as such, not as 0
    per.records = {5: AnchorRecord(rejected=[True] * 2000)}
    got = per.gate_excess_warning("localize")
    assert "tail < 1e-308" in got[0] and "e+00" not in got[0], got

    robust = UwbUpdater("skf", ARMS, chi2_quantile=None)
    robust.records = {1: AnchorRecord(rejected=[True] * 500)}
    assert robust.gate_excess_warning("refine") == []


def test_filter_warnings_go_to_the_stage_log():
    """`filter_warnings` returns the pose source's and the range gate's warnings and logs each to the stage's
    rerun log as a WARN text at the stage's end (what the viewer shows)."""
    from types import SimpleNamespace

    from uwbcal.pipeline.run.context import filter_warnings
    from uwbcal.pipeline.uwb.config import UwbConfig

    logged = []
    log = SimpleNamespace(text=lambda msg, level="INFO", t_ns=None: logged.append((msg, level, t_ns)))
    ctx = SimpleNamespace(
        config=SimpleNamespace(uwb=UwbConfig()),
        windows=lambda: SimpleNamespace(start_ns=0),
        check_health=lambda stage, est, a, b, ranges=None: [f"{stage}: inconsistent visual updates"],
    )
    est = SimpleNamespace()
    from uwbcal.pipeline.uwb.updater import AnchorRecord

    upd = UwbUpdater("skf", ARMS, chi2_quantile=0.95)
    upd.records = {1: AnchorRecord(rejected=[True] * 100 + [False] * 900)}
    warns = filter_warnings(ctx, "refine", est, upd, 5, 9_000, log)
    assert len(warns) == 2 and warns[0] == "refine: inconsistent visual updates"
    assert warns[1].startswith("refine: 100 of 1000 ranges"), warns
    assert logged == [(w, "WARN", 9_000) for w in warns]
    assert filter_warnings(ctx, "refine", est, upd, 5, 9_000) == warns  # no log: the same warnings
