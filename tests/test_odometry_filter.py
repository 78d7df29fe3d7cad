import pickle

import numpy as np
import pytest

from uwbcal.convert.recording import RecordingReader, RecordingWriter
from uwbcal.pipeline.core.errors import InputError
from uwbcal.pipeline.core.geometry import (
    compose,
    exp_so3,
    log_so3,
    quat_to_rot,
    relative,
    rot_to_quat,
    se3_interpolate,
    skew,
)
from uwbcal.pipeline.core.state import Pose, ekf_update
from uwbcal.pipeline.run.driver import odometry_from_recording, run_estimator
from uwbcal.pipeline.vio.odometry_filter import (
    OdometryFilterConfig,
    OdometryStats,
    clean_odometry,
    increment_noise,
)

from support import T0


def _trajectory(n=200, dt_s=0.1, seed=0):
    """Smooth 3-D trajectory: stamps, rotations [N,3,3], positions [N,3]."""
    rng = np.random.default_rng(seed)
    s = np.arange(n) * dt_s
    p = np.column_stack([3 * np.cos(0.3 * s), 2 * np.sin(0.5 * s), 0.2 * s])
    w = np.column_stack([0.1 * np.sin(0.7 * s), 0.05 * np.cos(0.4 * s), 0.3 * s]) + 0.01 * rng.normal(
        size=(n, 3)
    )
    R = exp_so3(w)
    t = T0 + (s * 1e9).astype(np.int64)
    return t, R, p


def _write(path, t, R, p, ranges=None, cov=None):
    with RecordingWriter(path) as w:
        w.write_odometry_batch(t, p, rot_to_quat(R), np.eye(6) * 0.01 if cov is None else cov)
        if ranges is not None:
            tr = np.asarray(ranges, np.int64)
            n = len(tr)
            w.write_range_batch(tr, np.zeros(n), np.zeros(n), np.full(n, 7), np.full(n, 5.0))
    return RecordingReader(path)


def _rot_err(Ra, Rb):
    return np.linalg.norm(log_so3(np.swapaxes(Ra, -1, -2) @ Rb), axis=-1)


def test_no_updates_reproduces_odometry_and_covariance_grows(tmp_path):
    t, R, p = _trajectory()
    rd = _write(tmp_path / "o.mcap", t, R, p)
    est = odometry_from_recording(rd)
    run_estimator(est, rd, None, None)
    h = est.history().arrays()
    assert np.array_equal(h["t_ns"], t)
    assert np.abs(h["p"] - p).max() < 1e-9
    assert _rot_err(quat_to_rot(h["q_xyzw"]), R).max() < 1e-9
    # In the world-frame (left-invariant) error xi, T = Exp(xi) T_hat, the odometry only ever adds noise:
    # P_w,k - P_w,k-1 = Ad Q Ad^T >= 0. Our error [dtheta_body, dp] maps to it with J = [[R, 0], [p^ R, I]].
    Rh = quat_to_rot(h["q_xyzw"])
    J = np.zeros((len(t), 6, 6))
    J[:, 0:3, 0:3] = Rh
    J[:, 3:6, 0:3] = skew(h["p"]) @ Rh
    J[:, 3:6, 3:6] = np.eye(3)
    Pw = J @ h["cov"] @ np.swapaxes(J, 1, 2)
    growth = np.linalg.eigvalsh(np.diff(Pw, axis=0))
    assert growth.min() > -1e-12
    assert np.all(np.trace(np.diff(Pw, axis=0), axis1=1, axis2=2) > 0)


def test_position_sigma_follows_random_walk_per_metre(tmp_path):
    # straight line, no rotation noise: var_p = sigma0^2 + s^2 * L + floor^2 * T on every axis
    n = 101
    t = T0 + np.arange(n, dtype=np.int64) * 100_000_000
    p = np.column_stack([np.arange(n) * 0.5, np.zeros(n), np.zeros(n)])
    R = np.repeat(np.eye(3)[None], n, axis=0)
    cfg = OdometryFilterConfig(
        sigma_p_per_sqrt_m=0.03,
        sigma_p_per_sqrt_s=0.001,
        initial_sigma_p=0.01,
        sigma_theta_per_sqrt_rad=0.0,
        sigma_theta_per_sqrt_m=0.0,
        sigma_theta_per_sqrt_s=0.0,
        initial_sigma_theta_deg=1e-12,
    )
    rd = _write(tmp_path / "line.mcap", t, R, p)
    est = odometry_from_recording(rd, cfg)
    run_estimator(est, rd, None, None)
    cov = est.history().arrays()["cov"][-1]
    L, T = 50.0, 10.0
    expected = 0.01**2 + 0.03**2 * L + 0.001**2 * T
    assert cov[3, 3] == pytest.approx(expected, rel=1e-9)
    assert cov[4, 4] == pytest.approx(expected, rel=1e-9)
    assert cov[5, 5] == pytest.approx(expected, rel=1e-9)
    # with heading noise the lateral variance grows faster than the along-track one (lever arm)
    est = odometry_from_recording(rd, OdometryFilterConfig(sigma_p_per_sqrt_m=0.03))
    run_estimator(est, rd, None, None)
    cov = est.history().arrays()["cov"][-1]
    assert cov[4, 4] > 2 * cov[3, 3]


def test_range_stamps_are_interpolated(tmp_path):
    t, R, p = _trajectory(50)
    tr = [int(t[3] + 30_000_000), int(t[10]), int(t[20] + 77_000_000), int(t[30] + 1)]
    rd = _write(tmp_path / "r.mcap", t, R, p, ranges=tr)
    seen = []

    def handler(est, m):
        x = est.state.value(est.state.nav)
        seen.append((m.t_ns, est.t_ns, x.R.copy(), x.p.copy(), m.anchor, m.distance))

    est = odometry_from_recording(rd)
    run_estimator(est, rd, None, None, on_range=handler)
    assert [s[0] for s in seen] == tr
    for t_r, t_state, Rx, px, anchor, dist in seen:
        assert t_state == t_r and anchor == 7 and dist == 5.0
        k = int(np.searchsorted(t, t_r, side="left"))
        if t[k] == t_r:
            Re, pe = R[k], p[k]
        else:
            s = (t_r - t[k - 1]) / (t[k] - t[k - 1])
            Re, pe = se3_interpolate(R[k - 1], p[k - 1], R[k], p[k], s)
        assert _rot_err(Rx, Re) < 1e-9
        assert np.abs(px - pe).max() < 1e-9
    # the history holds the range stamps and still every odometry stamp, with the odometry poses
    h = est.history().arrays()
    assert set(tr) <= set(h["t_ns"].tolist()) and set(t.tolist()) <= set(h["t_ns"].tolist())
    at = np.searchsorted(h["t_ns"], t)
    assert np.abs(h["p"][at] - p).max() < 1e-9


def test_position_update_pulls_pose_and_later_increments_apply_to_it(tmp_path):
    t, R, p = _trajectory(60)
    t_fix = int(t[20] + 40_000_000)
    rd = _write(tmp_path / "u.mcap", t, R, p, ranges=[t_fix])
    offset = np.array([0.5, -0.3, 0.2])
    truth = {}

    def handler(est, m):
        x = est.state.value(est.state.nav)
        target = x.p + offset
        truth["target"] = target
        H = np.zeros((3, 6))
        H[:, 3:6] = np.eye(3)
        res = ekf_update(est.state, {est.state.nav: H}, target - x.p, 1e-12)
        assert res.accepted
        truth["R"] = est.state.value(est.state.nav).R.copy()
        truth["p"] = est.state.value(est.state.nav).p.copy()
        truth["sigma_p"] = np.sqrt(np.diag(est.state.cov(est.state.nav))[3:6])

    est = odometry_from_recording(rd)
    run_estimator(est, rd, None, None, on_range=handler)
    assert np.allclose(truth["p"], truth["target"], atol=1e-6)
    assert truth["sigma_p"].max() < 1e-5
    # after the fix: T_hat_k = T_fix (T_odom(t_fix)^-1 T_k)
    k = int(np.searchsorted(t, t_fix))
    s = (t_fix - t[k - 1]) / (t[k] - t[k - 1])
    Ro, po = se3_interpolate(R[k - 1], p[k - 1], R[k], p[k], s)
    Rl, pl = compose(truth["R"], truth["p"], *relative(Ro, po, R[-1], p[-1]))
    x = est.state.value(est.state.nav)
    assert _rot_err(x.R, Rl) < 1e-9
    assert np.allclose(x.p, pl, atol=1e-9)
    assert not np.allclose(x.p, p[-1], atol=1e-3)


def test_split_run_and_pickle_equal_one_run(tmp_path):
    t, R, p = _trajectory(80)
    tr = (t[:-1] + 33_000_000).tolist()
    rd = _write(tmp_path / "s.mcap", t, R, p, ranges=tr)
    one = odometry_from_recording(rd)
    run_estimator(one, rd, None, None)
    mid = int(t[37] + 50_000_000)
    two = odometry_from_recording(rd)
    run_estimator(two, rd, None, mid)
    assert two.t_ns < mid
    two = pickle.loads(pickle.dumps(two))
    run_estimator(two, rd, mid, None)
    a, b = one.history().arrays(), two.history().arrays()
    assert np.array_equal(a["t_ns"], b["t_ns"])
    assert np.allclose(a["p"], b["p"], atol=1e-12)
    assert np.allclose(a["cov"], b["cov"], rtol=1e-9, atol=1e-15)
    assert one.stats.ranges == len(tr)


def test_duplicates_skipped_and_counted_out_of_order_sorted(tmp_path):
    t, R, p = _trajectory(30)
    td = np.insert(t, 10, t[10])
    Rd = np.insert(R, 10, R[10], axis=0)  # a re-sent message
    pd = np.insert(p, 10, p[10], axis=0)
    rd = _write(tmp_path / "d.mcap", td, Rd, pd)
    est = odometry_from_recording(rd)
    run_estimator(est, rd, None, None)
    assert est.stats.duplicates == 1
    assert any("duplicate" in w for w in est.warnings)
    h = est.history().arrays()
    assert len(h["t_ns"]) == len(t)
    assert np.abs(h["p"] - p).max() < 1e-9
    # header stamps out of order (as a reader of a broken source may return): sorted, counted
    st = OdometryStats()
    perm = np.r_[0:5, 6, 5, 7:30]
    ts, Rs, ps, _ = clean_odometry(
        t[perm], p[perm], rot_to_quat(R[perm]), np.zeros((30, 6, 6)), "x", "/odometry", st
    )
    assert st.out_of_order == 1 and np.array_equal(ts, t) and np.allclose(ps, p)


def test_nan_odometry_names_the_stamp(tmp_path):
    t, R, p = _trajectory(20)
    p = p.copy()
    p[7, 1] = np.nan
    rd = _write(tmp_path / "n.mcap", t, R, p)
    est = odometry_from_recording(rd)
    with pytest.raises(InputError, match=str(int(t[7]))):
        run_estimator(est, rd, None, None)


def test_missing_topic_and_ranges_outside_odometry(tmp_path):
    with RecordingWriter(tmp_path / "empty.mcap") as w:
        w.write_range_batch([T0], [0], [0], [1], [3.0])
    with pytest.raises(InputError, match="/odometry"):
        odometry_from_recording(RecordingReader(tmp_path / "empty.mcap"))
    t, R, p = _trajectory(10)
    rd = _write(tmp_path / "o.mcap", t, R, p, ranges=[int(t[0] - 5), int(t[4]), int(t[-1] + 5)])
    calls = []
    est = odometry_from_recording(rd)
    run_estimator(est, rd, int(t[0] - 10), None, on_range=lambda e, m: calls.append(m.t_ns))
    assert calls == [int(t[4])]
    assert est.stats.ranges_before_odometry == 1


def test_increment_noise_is_rate_independent():
    cfg = OdometryFilterConfig()
    dR = exp_so3(np.array([0.0, 0.0, 0.4]))
    dp = np.array([1.0, 0.0, 0.0])
    whole = increment_noise(cfg, dR, dp, 1.0)
    half = increment_noise(cfg, exp_so3(np.array([0.0, 0.0, 0.2])), dp / 2, 0.5)
    assert np.allclose(whole, 2 * half)


# -- simulated odometry: drifts as the filter's drift model says -------------------------------------------------
def _simulated_odometry(tmp_path, seed, scale=1.0, duration=30.0):
    from uwbcal.convert.simulator import SimConfig, simulate_to_file

    path = tmp_path / f"odo{seed}.mcap"
    simulate_to_file(
        SimConfig(seed=seed, duration=duration, camera=False, odometry_rate=20.0, odometry_noise_scale=scale),
        path,
    )
    return RecordingReader(path)


def test_simulated_odometry_is_consistent_with_the_drift_model(tmp_path):
    """The simulator draws the odometry's increments from `increment_noise` (sigmas declared in the recording's
    calibration); the filter that reads those sigmas is consistent: 6-DoF pose ANEES over 8 runs x 30 s inside
    the chi-square bounds of the run average (time-correlated samples: the bounds of 8 runs, not of all samples)."""
    from uwbcal.evaluate.consistency import chi2_bounds
    from uwbcal.pipeline.vio.odometry_filter import declared_noise

    per_run = []
    for seed in range(8):
        rd = _simulated_odometry(tmp_path, seed)
        noise = declared_noise(rd.calibration)
        assert list(noise) == list(rd.calibration["odometry"]["noise"])
        cfg = OdometryFilterConfig(**noise)
        est = odometry_from_recording(rd, cfg)
        run_estimator(est, rd, None, None)
        h = est.history().arrays()
        gt = rd.read_poses()
        i = np.searchsorted(gt.t_ns, h["t_ns"])
        assert np.array_equal(gt.t_ns[i], h["t_ns"])  # odometry stamps are IMU stamps of the simulation
        R_est, R_gt = quat_to_rot(h["q_xyzw"]), quat_to_rot(gt.q_xyzw[i])
        e = np.concatenate([log_so3(np.swapaxes(R_est, 1, 2) @ R_gt), gt.p[i] - h["p"]], axis=1)
        nees = np.einsum("ni,nij,nj->n", e, np.linalg.inv(h["cov"]), e)
        per_run.append(nees[1:].mean())
    lo, hi = chi2_bounds(8, 6)
    assert lo < np.mean(per_run) < hi, per_run


def test_simulated_odometry_without_noise_is_the_truth(tmp_path):
    rd = _simulated_odometry(tmp_path, 0, scale=0.0, duration=5.0)
    od, gt = rd.read_odometry(), rd.read_poses()
    i = np.searchsorted(gt.t_ns, od.t_ns)
    assert np.abs(od.p - gt.p[i]).max() < 1e-9
    assert rd.calibration["odometry"]["error_model"] == "drift"


def test_declared_noise_refuses_unknown_keys():
    from uwbcal.pipeline.vio.odometry_filter import declared_noise

    assert declared_noise({}) == {} and declared_noise(
        {"odometry": {"noise": {"initial_sigma_p": 2e-3}}}
    ) == {"initial_sigma_p": 2e-3}
    with pytest.raises(InputError, match="odometry.noise: unknown key"):
        declared_noise({"odometry": {"noise": {"sigma_x": 1.0}}})


def test_fit_drift_noise_recovers_a_random_walk_per_metre():
    """A trajectory whose position variance grows by s^2 per metre and yaw variance by k^2 per metre gives back
    s and k (the loose coupling's drift model of the MSCKF output)."""
    from uwbcal.pipeline.vio.odometry_filter import fit_drift_noise

    n = 101
    p = np.column_stack([np.linspace(0, 50, n), np.zeros(n), np.zeros(n)])  # 50 m straight
    q = np.tile([0.0, 0.0, 0.0, 1.0], (n, 1))
    L = np.linspace(0, 50, n)
    cov = np.zeros((n, 6, 6))
    cov[:, 3:6, 3:6] = (1e-4 + 0.01**2 * L)[:, None, None] * np.eye(3)
    cov[:, 0:3, 0:3] = (1e-6 + 0.002**2 * L)[:, None, None] * np.eye(3)
    got = fit_drift_noise({"t_ns": np.arange(n), "p": p, "q_xyzw": q, "cov": cov})
    assert got["sigma_p_per_sqrt_m"] == pytest.approx(0.01, rel=1e-6)
    assert got["sigma_theta_per_sqrt_m"] == pytest.approx(0.002, rel=1e-6)
    assert got["initial_sigma_p"] == pytest.approx(0.01, rel=1e-6)
    with pytest.raises(InputError, match="two poses"):
        fit_drift_noise({"t_ns": np.arange(1), "p": p[:1], "q_xyzw": q[:1], "cov": cov[:1]})


# -- the bounded (Gauss-Markov) error model of a SLAM output --------------------------------------------------------
def test_resolve_error_model_precedence():
    from uwbcal.pipeline.vio.odometry_filter import resolve_error_model

    cal = {"odometry": {"error_model": "bounded", "correlation_time_s": 4.0}}
    assert resolve_error_model(OdometryFilterConfig(), cal) == ("bounded", 4.0)
    assert resolve_error_model(OdometryFilterConfig(), None) == ("drift", 10.0)
    assert resolve_error_model(OdometryFilterConfig(), {"odometry": {}}) == ("drift", 10.0)
    assert resolve_error_model(OdometryFilterConfig(error_model="drift"), cal) == ("drift", 4.0)
    assert resolve_error_model(OdometryFilterConfig(correlation_time_s=2.5), cal) == ("bounded", 2.5)
    with pytest.raises(InputError, match="odometry.error_model 'slam'"):
        resolve_error_model(OdometryFilterConfig(), {"odometry": {"error_model": "slam"}})


def test_bounded_step_decays_the_offset_and_its_jacobian_is_exact():
    """The estimate's offset from the odometry (body-frame attitude, world position) decays by phi and is carried
    onto the new odometry pose; F matches finite differences of the step."""
    from uwbcal.pipeline.vio.odometry_filter import bounded_step

    rng = np.random.default_rng(11)
    R_ref, p_ref = exp_so3(rng.normal(size=3)), rng.normal(size=3)
    R_od, p_od = R_ref @ exp_so3(0.3 * rng.normal(size=3)), p_ref + rng.normal(size=3)
    phi = 0.8
    # no offset: the estimate is the odometry
    R_new, p_new, F = bounded_step(R_ref, p_ref, R_ref, p_ref, R_od, p_od, phi)
    np.testing.assert_allclose(R_new, R_od, atol=1e-12)
    np.testing.assert_allclose(p_new, p_od, atol=1e-12)
    # an offset (theta, dp) at the reference becomes (phi dR^T theta, phi dp) at the new stamp
    theta, dp = np.array([0.02, -0.01, 0.03]), np.array([0.3, -0.2, 0.1])
    R_new, p_new, _ = bounded_step(R_ref, p_ref, R_ref @ exp_so3(theta), p_ref + dp, R_od, p_od, phi)
    dR = R_ref.T @ R_od
    np.testing.assert_allclose(log_so3(R_od.T @ R_new), phi * dR.T @ theta, atol=1e-12)
    np.testing.assert_allclose(p_new - p_od, phi * dp, atol=1e-12)
    # F: finite differences of the step w.r.t. the estimate's error [dtheta_body, dp]
    eps = 1e-6
    for k in range(6):
        d = np.zeros(6)
        d[k] = eps
        x = Pose(R_ref, p_ref).boxplus(d)
        Ra, pa, _ = bounded_step(R_ref, p_ref, x.R, x.p, R_od, p_od, phi)
        num = np.concatenate([log_so3(R_od.T @ Ra), pa - p_od]) / eps
        np.testing.assert_allclose(num, F[:, k], atol=1e-6)
    np.testing.assert_allclose(
        F, np.block([[phi * dR.T, np.zeros((3, 3))], [np.zeros((3, 3)), phi * np.eye(3)]])
    )


def test_bounded_model_covariance_relaxes_to_the_stationary_one(tmp_path):
    """Gauss-Markov with P_ss = the initial sigmas (messages without covariance) and phi = exp(-dt/tau) per step:
    from any P0 the covariance is P_k = P_ss + exp(-2 t_k / tau) (P0 - P_ss) (closed form; P_ss is stationary),
    and without updates the estimate is the odometry itself."""
    t, R, p = _trajectory(n=61, dt_s=0.1)
    rd = _write(tmp_path / "b.mcap", t, R, p, cov=np.zeros((len(t), 6, 6)))
    cfg = OdometryFilterConfig(
        error_model="bounded", correlation_time_s=2.0, initial_sigma_p=0.05, initial_sigma_theta_deg=2.0
    )
    est = odometry_from_recording(rd, cfg)
    assert est.error_model == "bounded" and est.correlation_time_s == 2.0
    P_ss = np.diag([np.radians(2.0) ** 2] * 3 + [0.05**2] * 3)
    od = rd.read_odometry()
    est.initialize(int(od.t_ns[0]), quat_to_rot(od.q_xyzw[0]), od.p[0])
    np.testing.assert_allclose(est.state.P, P_ss, rtol=1e-12)  # starts stationary
    P0 = np.diag([np.radians(10.0) ** 2] * 3 + [0.5**2] * 3)  # then pretend a large initial error
    est.state.P = P0.copy()
    for k in range(1, len(t)):
        est.advance(int(od.t_ns[k]), quat_to_rot(od.q_xyzw[k]), od.p[k])
        tk = (od.t_ns[k] - od.t_ns[0]) * 1e-9
        np.testing.assert_allclose(
            est.state.P, P_ss + np.exp(-2 * tk / 2.0) * (P0 - P_ss), rtol=1e-9, atol=1e-15
        )
    np.testing.assert_allclose(est.pose.p, od.p[-1], atol=1e-12)
    assert _rot_err(est.pose.R, quat_to_rot(od.q_xyzw[-1])) < 1e-12
