"""Simulator: exact IMU derivatives, exact projections, the UWB model, determinism, bad input, file output."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from uwbcal.convert.simulator import (
    SimConfig,
    camera_model,
    project_radtan,
    rel_seconds,
    simulate,
    simulate_imu,
    simulate_to_file,
)
from uwbcal.convert.trajectory import default_trajectory, load_groundtruth, load_trajectory
from uwbcal.pipeline.core.errors import InputError
from uwbcal.pipeline.core.geometry import exp_so3, log_so3, quat_to_rot

NOISE_FREE_IMU = dict(
    gyro_noise_density=0.0, gyro_random_walk=0.0, acc_noise_density=0.0, acc_random_walk=0.0
)


@pytest.fixture(scope="module")
def traj():
    return default_trajectory()


@pytest.fixture(scope="module")
def sim_short():
    return simulate(SimConfig(duration=30.0, seed=3))


# ---------------------------------------------------------------------------------------------------------------
# trajectory
# ---------------------------------------------------------------------------------------------------------------
def test_spline_derivatives_match_finite_differences(traj):
    t = np.linspace(5.0, 100.0, 37) + 0.0123
    h = 1e-4
    s, sp, sm = traj.evaluate(t), traj.evaluate(t + h), traj.evaluate(t - h)
    np.testing.assert_allclose(s.v, (sp.p - sm.p) / (2 * h), atol=1e-6)
    np.testing.assert_allclose(s.a, (sp.v - sm.v) / (2 * h), atol=1e-5)
    np.testing.assert_allclose(s.a, (sp.p - 2 * s.p + sm.p) / h**2, atol=1e-3)
    w_fd = log_so3(np.einsum("nji,njk->nik", sm.R, sp.R)) / (2 * h)  # body rate: R^T dR
    np.testing.assert_allclose(s.w, w_fd, atol=1e-6)
    assert np.allclose(np.einsum("nji,njk->nik", s.R, s.R), np.eye(3), atol=1e-12)


def test_spline_is_continuous_across_knots(traj):
    knots = traj.dt * np.arange(10, 20)
    a, b = traj.evaluate(knots - 1e-9), traj.evaluate(knots + 1e-9)
    for x, y in ((a.p, b.p), (a.v, b.v), (a.a, b.a), (a.w, b.w)):
        np.testing.assert_allclose(x, y, atol=1e-6)


def test_default_trajectory_has_vertical_motion_and_starts_still(traj):
    s = traj.evaluate(np.arange(0.0, traj.duration, 0.05))
    assert traj.duration >= 119.9
    assert np.ptp(s.p[:, 2]) >= 1.5
    assert np.linalg.norm(s.v[s.t < 0.5], axis=1).max() < 1e-3
    assert np.linalg.norm(s.v, axis=1).max() > 0.5


def _rk4_integrate(R0, p0, v0, t, gyro, acc, g):
    """Classic RK4 on (R, p, v) with linearly interpolated IMU samples (an independent 'good integrator')."""

    def f(R, v, w, a):
        return R @ np.array([[0, -w[2], w[1]], [w[2], 0, -w[0]], [-w[1], w[0], 0]]), v, R @ a + g

    R, p, v = R0.copy(), p0.copy(), v0.copy()
    for k in range(len(t) - 1):
        dt = t[k + 1] - t[k]
        wm, am = 0.5 * (gyro[k] + gyro[k + 1]), 0.5 * (acc[k] + acc[k + 1])
        k1 = f(R, v, gyro[k], acc[k])
        k2 = f(R + 0.5 * dt * k1[0], v + 0.5 * dt * k1[2], wm, am)
        k3 = f(R + 0.5 * dt * k2[0], v + 0.5 * dt * k2[2], wm, am)
        k4 = f(R + dt * k3[0], v + dt * k3[2], gyro[k + 1], acc[k + 1])
        R = R + dt / 6 * (k1[0] + 2 * k2[0] + 2 * k3[0] + k4[0])
        p = p + dt / 6 * (k1[1] + 2 * k2[1] + 2 * k3[1] + k4[1])
        v = v + dt / 6 * (k1[2] + 2 * k2[2] + 2 * k3[2] + k4[2])
        u, _, vt = np.linalg.svd(R)  # re-orthonormalise
        R = u @ vt
    return R, p, v


def integration_error(traj, t0: float, seconds: float) -> tuple[float, float]:
    cfg = SimConfig(**NOISE_FREE_IMU)
    t_ns = traj.t0_ns + round(t0 * 1e9) + 5_000_000 * np.arange(int(seconds * 200) + 1, dtype=np.int64)
    imu = simulate_imu(traj, t_ns, cfg, np.random.default_rng(0))
    t = rel_seconds(traj, t_ns)
    s = traj.evaluate(t[[0, -1]])
    R, p, _ = _rk4_integrate(s.R[0], s.p[0], s.v[0], t, imu.gyro, imu.acc, np.array([0.0, 0.0, -9.81]))
    return float(np.linalg.norm(p - s.p[1])), float(np.degrees(np.linalg.norm(log_so3(s.R[1].T @ R))))


def test_noise_free_imu_integrates_to_the_true_pose(traj):
    dp, dth = integration_error(traj, 20.0, 10.0)
    print(f"default trajectory, 10 s: position error {dp * 1e3:.3f} mm, rotation error {dth:.5f} deg")
    assert dp < 0.01 and dth < 0.1


def test_noise_free_imu_integrates_on_euroc(data_dir):
    traj = load_trajectory(data_dir / "euroc" / "groundtruth" / "MH_01_easy.txt")
    dp, dth = integration_error(traj, 60.0, 10.0)
    print(f"MH_01_easy, 10 s: position error {dp * 1e3:.3f} mm, rotation error {dth:.5f} deg")
    assert dp < 0.01 and dth < 0.1


def test_imu_noise_and_bias_statistics():
    cfg = SimConfig(gyro_bias_init=(0.01, -0.02, 0.03))
    traj = default_trajectory(duration=20.0)
    t_ns = traj.t0_ns + 5_000_000 * np.arange(4001, dtype=np.int64)
    clean = simulate_imu(traj, t_ns, SimConfig(**NOISE_FREE_IMU), np.random.default_rng(0))
    imu = simulate_imu(traj, t_ns, cfg, np.random.default_rng(1))
    white = imu.gyro - clean.gyro - imu.bg
    np.testing.assert_allclose(white.std(axis=0), cfg.gyro_noise_density * np.sqrt(200.0), rtol=0.06)
    np.testing.assert_allclose(imu.bg[0], [0.01, -0.02, 0.03])
    steps = np.diff(imu.ba, axis=0)
    np.testing.assert_allclose(steps.std(axis=0), cfg.acc_random_walk * np.sqrt(1 / 200.0), rtol=0.06)
    # at rest (first second) the accelerometer reads +g along world up
    R0 = traj.evaluate(np.array([0.0])).R[0]
    np.testing.assert_allclose(R0 @ clean.acc[0], [0.0, 0.0, 9.81], atol=1e-5)


# ---------------------------------------------------------------------------------------------------------------
# camera
# ---------------------------------------------------------------------------------------------------------------
def _cv2_project(P_c, cam):
    fu, fv, cu, cv = cam["intrinsics"]
    K = np.array([[fu, 0, cu], [0, fv, cv], [0, 0, 1.0]])
    uv, _ = cv2.projectPoints(
        P_c.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), K, np.asarray(cam["distortion"])
    )
    return uv.reshape(-1, 2)


def test_project_radtan_matches_opencv():
    cam = camera_model()
    rng = np.random.default_rng(0)
    P = np.column_stack([rng.uniform(-3, 3, 500), rng.uniform(-2, 2, 500), rng.uniform(1, 10, 500)])
    np.testing.assert_allclose(
        project_radtan(P, cam["intrinsics"], cam["distortion"]), _cv2_project(P, cam), atol=1e-8
    )


def test_noise_free_features_reproject_exactly():
    data = simulate(SimConfig(duration=10.0, pixel_sigma=0.0, seed=5))
    cam = data.metadata["uwbcal.calibration"]["cameras"]["cam0"]
    T = np.asarray(cam["T_imu_cam"])
    fs = data.features
    counts = fs.counts
    assert counts.mean() > 80 and counts.max() <= 200
    for f in range(0, len(fs.t_ns), 17):
        t, ids, uv = fs.frame(f)
        s = data.trajectory.evaluate(rel_seconds(data.trajectory, [t]))
        R_wc, p_wc = s.R[0] @ T[:3, :3], s.p[0] + s.R[0] @ T[:3, 3]
        P_c = (data.landmarks[ids] - p_wc) @ R_wc
        assert np.all(P_c[:, 2] > 0)
        np.testing.assert_allclose(uv, _cv2_project(P_c, cam), atol=1e-6)
        w, h = cam["resolution"]
        assert np.all((uv >= 0) & (uv < [w, h]))


def test_pixel_noise_level(sim_short):
    clean = simulate(SimConfig(duration=30.0, seed=3, pixel_sigma=0.0))
    a, b = sim_short.features, clean.features
    # same landmarks and poses; noisy rows are a subset (a few leave the image)
    key_a = a.ids + 10**6 * np.repeat(np.arange(len(a.t_ns)), a.counts)
    key_b = b.ids + 10**6 * np.repeat(np.arange(len(b.t_ns)), b.counts)
    common, ia, ib = np.intersect1d(key_a, key_b, return_indices=True)
    assert len(common) > 0.95 * len(key_a)
    err = a.uv[ia] - b.uv[ib]
    np.testing.assert_allclose(err.std(axis=0), 1.0, rtol=0.03)


# ---------------------------------------------------------------------------------------------------------------
# UWB
# ---------------------------------------------------------------------------------------------------------------
def test_ranges_regress_to_beta_gamma_sigma():
    beta, gamma, sigma = [0.9, 1.05, 0.95, 1.0], [-0.3, 0.2, 0.0, 0.5], 0.1
    data = simulate(SimConfig(camera=False, seed=11, beta=beta, gamma=gamma, sigma_range=sigma))
    r = data.ranges
    assert set(np.unique(r.anchor)) == {0, 1, 2, 3}
    for a in range(4):
        m = r.anchor == a
        x, y = r.true_distance[m], r.distance[m]
        X = np.column_stack([x, np.ones_like(x)])
        coef, res, *_ = np.linalg.lstsq(X, y, rcond=None)
        n = len(x)
        s2 = res[0] / (n - 2)
        se = np.sqrt(np.diag(s2 * np.linalg.inv(X.T @ X)))
        assert abs(coef[0] - beta[a]) < 3 * se[0], (a, coef, se)
        assert abs(coef[1] - gamma[a]) < 3 * se[1], (a, coef, se)
        sig_hat = np.sqrt(s2) / beta[a]
        assert abs(sig_hat - sigma) < 3 * sigma / np.sqrt(2 * n)
    # staggered stamps: per anchor 10 Hz, all anchors at distinct times
    assert len(np.unique(r.t_ns)) == len(r.t_ns)
    assert np.all(np.diff(r.t_ns) > 0)
    np.testing.assert_allclose(np.diff(r.t_ns[r.anchor == 0]), 100_000_000)


def test_ranges_use_the_tag_lever_arm():
    data = simulate(SimConfig(camera=False, duration=5.0, tag_lever_arm=(0.3, -0.2, 0.5)))
    r = data.ranges
    s = data.trajectory.evaluate(rel_seconds(data.trajectory, r.t_ns))
    tag = s.p + np.einsum("nij,j->ni", s.R, [0.3, -0.2, 0.5])
    np.testing.assert_allclose(r.true_distance, np.linalg.norm(tag - data.anchors[r.anchor], axis=1))


def test_default_anchors_are_spread_in_3d(sim_short):
    a = sim_short.anchors
    assert a.shape == (4, 3)
    assert np.ptp(a[:, 2]) > 1.0 and len(np.unique(np.round(a[:, 2], 3))) == 4
    assert abs(np.linalg.det(np.column_stack([a[1:] - a[0]]))) > 1.0  # not coplanar


def test_nlos_dropout_and_max_range_are_honoured():
    cfg = SimConfig(camera=False, seed=2, nlos_rate=0.2, nlos_bias_mean=1.5, dropout_rate=0.1)
    data = simulate(cfg)
    r = data.ranges
    n = r.candidates
    kept = len(r.t_ns)
    assert abs(kept / n - 0.9) < 3 * np.sqrt(0.09 / n)
    frac = r.nlos.mean()
    assert abs(frac - 0.2) < 3 * np.sqrt(0.16 / kept)
    excess = r.distance - (data.beta[r.anchor] * r.true_distance + data.gamma[r.anchor])
    bias = excess[r.nlos].mean()
    se = np.sqrt((1.5**2 + 0.09**2) / r.nlos.sum())
    assert abs(bias - 1.5) < 3 * se
    assert abs(excess[~r.nlos].mean()) < 3 * 0.09 / np.sqrt((~r.nlos).sum())
    assert data.metadata["uwbcal.truth"]["nlos_rate"] == 0.2

    limited = simulate(SimConfig(camera=False, seed=2, duration=30.0, max_range=6.0))
    assert limited.ranges.true_distance.max() <= 6.0
    assert 0 < len(limited.ranges.t_ns) < limited.ranges.candidates


# ---------------------------------------------------------------------------------------------------------------
# determinism
# ---------------------------------------------------------------------------------------------------------------
def _arrays(d):
    return [
        d.imu.gyro,
        d.imu.acc,
        d.features.ids,
        d.features.uv,
        d.ranges.distance,
        d.landmarks,
        d.groundtruth.p,
    ]


def test_same_seed_same_data_different_seed_different(sim_short):
    again = simulate(SimConfig(duration=30.0, seed=3))
    for x, y in zip(_arrays(sim_short), _arrays(again), strict=True):
        np.testing.assert_array_equal(x, y)
    other = simulate(SimConfig(duration=30.0, seed=4))
    assert not np.array_equal(sim_short.imu.gyro, other.imu.gyro)
    assert not np.array_equal(sim_short.ranges.distance, other.ranges.distance)
    assert not np.array_equal(sim_short.landmarks, other.landmarks)
    np.testing.assert_array_equal(sim_short.groundtruth.p, other.groundtruth.p)  # the trajectory is fixed


def test_sensor_streams_are_independent(sim_short):
    changed = simulate(SimConfig(duration=30.0, seed=3, pixel_sigma=2.0, nlos_rate=0.3))
    np.testing.assert_array_equal(sim_short.imu.gyro, changed.imu.gyro)
    np.testing.assert_array_equal(sim_short.imu.acc, changed.imu.acc)
    np.testing.assert_array_equal(sim_short.landmarks, changed.landmarks)
    clean = ~changed.ranges.nlos
    np.testing.assert_array_equal(sim_short.ranges.distance[clean], changed.ranges.distance[clean])


# ---------------------------------------------------------------------------------------------------------------
# bad input and loading
# ---------------------------------------------------------------------------------------------------------------
@pytest.fixture
def fake_data(tmp_path, monkeypatch):
    gt = tmp_path / "euroc" / "groundtruth"
    gt.mkdir(parents=True)
    t = np.arange(0, 3.0, 0.005)
    rows = ["# timestamp(s) tx ty tz qx qy qz qw"]
    rows += [
        f"{100 + x:.6f} {np.sin(x):.6f} {np.cos(x):.6f} {0.1 * x:.6f} 0 0 {np.sin(x / 4):.6f} {np.cos(x / 4):.6f}"
        for x in t
    ]
    (gt / "Fake_01.txt").write_text("\n".join(rows) + "\n")
    monkeypatch.setenv("UWBCAL_DATA", str(tmp_path))
    return gt


def test_trajectory_by_name_and_missing_name(fake_data):
    traj = load_trajectory("Fake_01")
    assert traj.name == "Fake_01" and abs(traj.duration - 2.9) < 1e-9
    assert traj.t0_ns == 100_000_000_000
    s = traj.evaluate(np.array([1.0]))
    np.testing.assert_allclose(s.p[0], [np.sin(1.0), np.cos(1.0), 0.1], atol=2e-4)
    np.testing.assert_allclose(s.R[0], exp_so3(np.array([0, 0, 0.5])), atol=1e-3)
    with pytest.raises(InputError, match=r"Nope_02.*not found.*Fake_01"):
        load_trajectory("Nope_02")
    with pytest.raises(InputError, match="missing.txt"):
        simulate(SimConfig(trajectory=str(fake_data / "missing.txt")))


def test_malformed_csv_names_file_and_line(tmp_path):
    f = tmp_path / "bad.csv"
    lines = ["#timestamp, p_x, p_y, p_z, q_w, q_x, q_y, q_z"]
    lines += [f"{1000000000 + i * 5000000},0,0,{i * 0.01},1,0,0,0" for i in range(10)]
    lines[4] = "1015000000,0,zero,0,1,0,0,0"
    f.write_text("\n".join(lines) + "\n")
    with pytest.raises(InputError, match=r"bad\.csv: line 5"):
        load_trajectory(f)
    lines[4] = "1015000000,0,0,0,1"
    f.write_text("\n".join(lines) + "\n")
    with pytest.raises(InputError, match=r"bad\.csv: line 5"):
        load_trajectory(f)


def test_csv_time_going_backwards(tmp_path):
    f = tmp_path / "back.csv"
    rows = [f"{1000000000 + i * 5000000},0,0,0,1,0,0,0" for i in range(10)]
    rows[6], rows[7] = rows[7], rows[6]
    f.write_text("\n".join(rows) + "\n")
    with pytest.raises(InputError, match="backwards"):
        load_groundtruth(f)


@pytest.mark.parametrize(
    "kwargs",
    [
        dict(duration=-1.0),
        dict(duration=0.0),
        dict(imu_rate=0.0),
        dict(uwb_rate=-10.0),
        dict(n_anchors=0),
        dict(nlos_rate=1.5),
        dict(sigma_range=-0.1),
        dict(anchors=[[0, 0]]),
        dict(beta=[0.9, 1.0]),
        dict(max_range=0.0),
        dict(odometry_rate=0.0),
        dict(odometry_noise_scale=-1.0),
        dict(range_latency_s=float("nan")),
        dict(range_latency_s=10.0),
        dict(antenna_pattern=[[0.1, 0.1, 0.0, 0.1]]),  # 4 anchors
        dict(n_anchors=1, antenna_pattern=[[0.1, 0.1, 0.0]]),
    ],
)
def test_bad_config_raises_input_error(kwargs):
    with pytest.raises(InputError, match="simulate: "):
        SimConfig(**kwargs)


def test_duration_longer_than_trajectory():
    with pytest.raises(InputError, match="lasts 120.0 s"):
        simulate(SimConfig(duration=500.0, camera=False))


def test_euroc_mh01_loads(data_dir):
    path = data_dir / "euroc" / "groundtruth" / "MH_01_easy.txt"
    traj = load_trajectory("MH_01_easy")
    assert traj.source == path and abs(traj.duration - 181.9) < 0.01
    t_ns, p, q = load_groundtruth(path)
    assert len(t_ns) == 36382 and t_ns[0] == traj.t0_ns
    s = traj.evaluate(rel_seconds(traj, t_ns[::10]))
    dp = np.linalg.norm(s.p - p[::10], axis=1)
    dth = np.degrees(np.linalg.norm(log_so3(np.einsum("nji,njk->nik", quat_to_rot(q[::10]), s.R)), axis=1))
    assert dp.max() < 0.01 and np.sqrt(np.mean(dth**2)) < 0.3
    csv = load_trajectory("MH_04_difficult")  # EuRoC CSV (ns, wxyz)
    assert csv.source.suffix == ".csv" and 95 < csv.duration < 100


# ---------------------------------------------------------------------------------------------------------------
# file output
# ---------------------------------------------------------------------------------------------------------------
def test_simulate_to_file_round_trip(tmp_path):
    from uwbcal.convert.recording import RecordingReader

    out = tmp_path / "sim.mcap"
    cfg = SimConfig(duration=8.0, seed=9, nlos_rate=0.1)
    summary = simulate_to_file(cfg, out)
    assert str(out) in summary and "/uwb/range" in summary
    data = simulate(cfg)
    rec = RecordingReader(out)
    imu = rec.read_imu()
    np.testing.assert_array_equal(imu.t_ns, data.imu.t_ns)
    np.testing.assert_allclose(imu.gyro, data.imu.gyro)
    rng = rec.read_ranges()
    np.testing.assert_array_equal(rng.t_ns, data.ranges.t_ns)
    np.testing.assert_array_equal(rng.anchor, data.ranges.anchor)
    np.testing.assert_allclose(rng.distance, data.ranges.distance)
    assert set(rng.tag) == {1} and set(rng.antenna) == {0}
    poses = rec.read_poses()
    np.testing.assert_allclose(poses.p, data.groundtruth.p)
    frames = list(rec.iter_features())
    assert len(frames) == len(data.features.t_ns)
    t, ids, uv = frames[3]
    _, ids0, uv0 = data.features.frame(3)
    np.testing.assert_array_equal(ids, ids0)
    np.testing.assert_allclose(uv, uv0)
    truth, calib, source = rec.truth, rec.calibration, rec.source
    np.testing.assert_allclose(truth["anchors"]["2"]["position"], data.anchors[2])
    assert truth["anchors"]["0"]["beta"] == 0.9 and truth["anchors"]["0"]["gamma"] == -0.3
    assert truth["seed"] == 9 and truth["nlos_rate"] == 0.1
    assert calib["cameras"]["cam0"]["intrinsics"] == [458.654, 457.296, 367.215, 248.375]
    assert calib["uwb"]["tags"]["1"]["antennas"] == [[0.05, 0.0, 0.1]]
    assert calib["imu"]["gyroscope_noise_density"] == 1.6968e-4
    assert source["dataset"] == "simulation" and source["sequence"] == "default"


def test_world_does_not_depend_on_duration(sim_short):
    full = simulate(SimConfig(seed=3, camera=False))
    np.testing.assert_array_equal(full.anchors, sim_short.anchors)
    np.testing.assert_array_equal(full.landmarks, sim_short.landmarks)
    n = len(sim_short.imu.t_ns)
    np.testing.assert_array_equal(full.imu.t_ns[:n], sim_short.imu.t_ns)
