"""MSCKF: feature Jacobians (finite differences), nullspace projection, triangulation, and end-to-end
runs on a small synthetic visual-inertial recording written through the real recording writer."""

from __future__ import annotations

import pickle

import numpy as np
import pytest

from uwbcal.convert.euroc import EUROC_CAMERAS, EUROC_IMU
from uwbcal.convert.recording import META_CALIBRATION, META_TRUTH, RecordingReader, RecordingWriter
from uwbcal.pipeline.core.errors import InputError
from uwbcal.pipeline.core.geometry import exp_so3, rot_to_quat
from uwbcal.pipeline.core.state import Kind
from uwbcal.pipeline.run.driver import msckf_from_recording, run_estimator
from uwbcal.pipeline.vio.config import VioConfig
from uwbcal.pipeline.vio.features import (
    FeatureDatabase,
    compress,
    compress_normal,
    feature_jacobians,
    landmark_sigma,
    nullspace_project,
    triangulate,
)
from uwbcal.pipeline.vio.imu import GRAVITY
from uwbcal.pipeline.vio.stats import VioStats
from uwbcal.pipeline.vio.update_zupt import ZuptUpdater

from support import CAM, body_rotation, errors_vs_truth, simulate_vi


# ---------------------------------------------------------------------------------------------------------------
# unit tests
# ---------------------------------------------------------------------------------------------------------------
def test_feature_jacobians_finite_differences():
    rng = np.random.default_rng(0)
    k = 20
    R = exp_so3(rng.normal(size=(k, 3)) * 0.3)
    pw = rng.normal(size=(k, 3))
    # features in front of the camera
    pc = np.column_stack([rng.uniform(-1, 1, (k, 2)), rng.uniform(2, 6, k)])
    pf = pw + np.einsum("kij,kj->ki", R, pc @ CAM.R_imu_cam.T + CAM.p_imu_cam)
    uv, H_pose, H_f, _ = feature_jacobians(CAM, R, pw, pf)
    eps = 1e-6
    for i in range(6):
        d = np.zeros(6)
        d[i] = eps
        up = feature_jacobians(CAM, R @ exp_so3(d[:3]), pw + d[3:], pf)[0]
        um = feature_jacobians(CAM, R @ exp_so3(-d[:3]), pw - d[3:], pf)[0]
        np.testing.assert_allclose(H_pose[:, :, i], (up - um) / (2 * eps), rtol=1e-5, atol=1e-4)
    for i in range(3):
        d = np.zeros(3)
        d[i] = eps
        up = feature_jacobians(CAM, R, pw, pf + d)[0]
        um = feature_jacobians(CAM, R, pw, pf - d)[0]
        np.testing.assert_allclose(H_f[:, :, i], (up - um) / (2 * eps), rtol=1e-5, atol=1e-4)


def _window(seed=1, m=6):
    rng = np.random.default_rng(seed)
    R = exp_so3(rng.normal(size=(m, 3)) * 0.05 + np.array([0, 0, 0.0])) @ CAM.R_imu_cam.T
    p = np.column_stack([np.linspace(0, 1, m), rng.normal(0, 0.1, (m, 2))])
    return R, p


def test_triangulation_and_nullspace_noise_free():
    R, p = _window()
    m = len(p)
    rng = np.random.default_rng(3)
    nf = 30
    # points ~4 m in front of the cameras (camera z ~ world z here)
    pts = np.column_stack([rng.uniform(-2, 2, nf), rng.uniform(-2, 2, nf), rng.uniform(3, 6, nf)])
    pts = p.mean(0) + np.einsum("ij,kj->ki", R[0] @ CAM.R_imu_cam, pts)
    fidx = np.repeat(np.arange(nf), m)
    cidx = np.tile(np.arange(m), nf)
    R_wc = R @ CAM.R_imu_cam
    p_wc = p + R @ CAM.p_imu_cam
    uv, H_pose, H_f, p_c = feature_jacobians(CAM, R[cidx], p[cidx], pts[fidx])
    xy = CAM.undistort(uv)
    # perturbed linear start is recovered by Gauss-Newton
    C = cidx.reshape(nf, m)
    est, ok = triangulate(R_wc, p_wc, C, xy.reshape(nf, m, 2), np.ones((nf, m), bool), iterations=5)
    assert ok.all() and np.abs(est - pts).max() < 1e-8
    # padded slots are ignored
    Cp = np.concatenate([C, np.zeros((nf, 2), int)], axis=1)
    xyp = np.concatenate([xy.reshape(nf, m, 2), np.full((nf, 2, 2), 7.0)], axis=1)
    est, ok = triangulate(R_wc, p_wc, Cp, xyp, np.arange(m + 2)[None, :] < m, iterations=5)
    assert ok.all() and np.abs(est - pts).max() < 1e-8
    # nullspace projection, against an independent SVD of H_f: its basis N^T (read back from unit residuals) has
    # orthonormal rows that annihilate H_f and span the same space as the SVD's left-nullspace basis
    Hf = H_f.reshape(nf, 2 * m, 3)
    Hx = np.zeros((nf, m, 2, m, 6))
    for j in range(m):
        Hx[:, j, :, j, :] = H_pose.reshape(nf, m, 2, 6)[:, j]
    Hx = Hx.reshape(nf, 2 * m, 6 * m)
    Hp = H_pose.reshape(nf, m, 2, 6)
    r0 = np.zeros((nf, 2 * m))
    # nullspace_project is linear in r: its basis N^T, column by column, from unit residuals
    Nt = np.stack(
        [
            nullspace_project(Hf, Hp, C, m, np.broadcast_to(np.eye(2 * m)[i], (nf, 2 * m)))[1]
            for i in range(2 * m)
        ],
        axis=2,
    )
    assert Nt.shape == (nf, 2 * m - 3, 2 * m)
    np.testing.assert_allclose(
        Nt @ np.swapaxes(Nt, 1, 2),
        np.broadcast_to(np.eye(2 * m - 3), Nt.shape[:1] + (2 * m - 3,) * 2),
        atol=1e-12,
    )
    assert np.abs(Nt @ Hf).max() < 1e-10 * np.abs(Hf).max()
    U = np.linalg.svd(Hf)[0][:, :, 3:]  # left singular vectors beyond rank 3 = the left nullspace
    np.testing.assert_allclose(np.swapaxes(Nt, 1, 2) @ Nt, U @ np.swapaxes(U, 1, 2), atol=1e-10)
    # Ho, assembled per clone block, is the dense product N^T H_x
    Ho, _ = nullspace_project(Hf, Hp, C, m, r0)
    assert Ho.shape == (nf, 2 * m - 3, 6 * m)
    np.testing.assert_allclose(Ho, Nt @ Hx, atol=1e-12)
    # padded slots (here: the last slot, pointing at clone 0) do not leak into clone 0's columns
    valid = np.ones((nf, m), bool)
    valid[:, -1] = False
    Cp = C.copy()
    Cp[:, -1] = 0
    Hp0 = Hp.copy()
    Hp0[:, -1] = 0.0
    Ho_p, _ = nullspace_project(Hf, Hp0, Cp, m, r0, valid)
    Hx0 = Hx.reshape(nf, m, 2, m, 6).copy()
    Hx0[:, -1] = 0.0
    np.testing.assert_allclose(Ho_p, Nt @ Hx0.reshape(nf, 2 * m, 6 * m), atol=1e-12)
    # a residual made of feature error only vanishes; one made of pose error only maps through Ho
    df = rng.normal(0, 0.1, (nf, 3))
    dx = rng.normal(0, 0.01, 6 * m)
    _, ro_f = nullspace_project(Hf, Hp, C, m, np.einsum("kij,kj->ki", Hf, df))
    assert np.abs(ro_f).max() < 1e-12 * np.abs(Hf @ df[..., None]).max()
    _, ro_x = nullspace_project(Hf, Hp, C, m, Hx @ dx + np.einsum("kij,kj->ki", Hf, df))
    np.testing.assert_allclose(ro_x, Ho @ dx, atol=1e-12)
    # the projected pose Jacobian keeps all but the 7 gauge directions of a visual-only problem
    # (global position, orientation and scale): rank 6m - 7
    sv = np.linalg.svd(np.concatenate(Ho), compute_uv=False)
    assert (sv > 1e-6 * sv[0]).sum() == 6 * m - 7 and sv[6 * m - 8] > 1e-3 * sv[0]
    # with a wrong feature guess (non-linear), the projected residual only depends on the pose error
    dpf = rng.normal(0, 1e-4, (nf, 3))
    uv2 = feature_jacobians(CAM, R[cidx], p[cidx], (pts + dpf)[fidx])[0]
    _, ro2 = nullspace_project(Hf, Hp, C, m, (uv - uv2).reshape(nf, 2 * m))
    assert np.abs(ro2).max() < 1e-3 * np.abs(uv - uv2).max()
    # QR compression keeps the information: H^T H and H^T r
    H, r = np.concatenate(Ho), np.concatenate(ro_x) + rng.normal(0, 1.0, (nf * (2 * m - 3)))
    Hc, rc = compress(H, r)
    assert Hc.shape == (6 * m, 6 * m)
    np.testing.assert_allclose(Hc.T @ Hc, H.T @ H, atol=1e-9 * np.abs(H.T @ H).max())
    np.testing.assert_allclose(Hc.T @ rc, H.T @ r, atol=1e-9 * np.abs(H.T @ r).max())


def test_feature_database_selection():
    db = FeatureDatabase()
    for t in range(5):
        ids = np.array([1, 2, 3]) if t < 4 else np.array([2, 3])
        db.add(t, ids, np.zeros((len(ids), 2)), np.zeros((len(ids), 2)))
    rows, drop = db.select(4, None, 3, 10)
    assert set(db.ids[rows]) == {1} and drop.sum() == 4
    rows, drop = db.select(4, 0, 3, 10)
    assert set(db.ids[rows]) == {1, 2, 3}
    rows, _ = db.select(4, 0, 3, 1)
    assert len(set(db.ids[rows])) == 1


@pytest.fixture(scope="module")
def vi_recording(tmp_path_factory):
    path = tmp_path_factory.mktemp("vio") / "vi.mcap"
    truth = simulate_vi(path, duration=20.0, seed=0)
    return path, truth


@pytest.mark.parametrize("fej", [True, False])
def test_msckf_tracks_synthetic_motion(vi_recording, fej):
    path, (t_ns, p, R) = vi_recording
    reader = RecordingReader(path)
    est = msckf_from_recording(reader, VioConfig(fej=fej))
    run_estimator(est, reader, None, None)
    h, dth, dp = errors_vs_truth(est, t_ns, p, R)
    assert len(h["t_ns"]) > 350
    prmse = np.sqrt((dp**2).sum(1).mean())
    ormse = np.degrees(np.sqrt((dth**2).sum(1).mean()))
    assert prmse < 0.2 and ormse < 1.0, (prmse, ormse)
    assert est.stats.updates > 300 and est.stats.features_used > 1000
    assert est.stats.features_rejected_chi2 < 0.1 * est.stats.features_used
    # consistency (two-sided, over 20 seeds) is tests/test_consistency.py


@pytest.mark.parametrize("slam", [0, 20])
def test_msckf_resumes_after_pickle(vi_recording, slam):
    path, (t_ns, p, R) = vi_recording
    reader = RecordingReader(path)
    mid, end = int(t_ns[0] + 4e9), int(t_ns[0] + 8e9)
    a = msckf_from_recording(reader, VioConfig(max_slam_features=slam))
    run_estimator(a, reader, None, mid)
    assert bool(a.state.of_kind(Kind.LANDMARK)) == bool(slam)  # the pickle carries the landmarks
    b = pickle.loads(pickle.dumps(a))
    run_estimator(b, reader, mid, end)
    full = msckf_from_recording(reader, VioConfig(max_slam_features=slam))
    run_estimator(full, reader, None, end)
    hb, hf = b.history().arrays(), full.history().arrays()
    assert len(hb["t_ns"]) == len(hf["t_ns"])
    assert np.abs(hb["p"] - hf["p"]).max() < 1e-6


def test_landmark_sigma_two_views_closed_form():
    """A point at depth d straight ahead of two cameras b apart (across the optical axis), pixels of unit
    noise: its depth sigma is sqrt(2) d^2 / (f b) (the x Jacobians' depth parts are +-f b / 2d^2), the weakest
    direction of the point."""
    f = EUROC_CAMERAS["cam0"]["intrinsics"][0]
    for d, b in ((4.0, 0.2), (10.0, 0.5), (2.0, 0.02)):
        R_wc = np.eye(3)
        R_wi = R_wc @ CAM.R_imu_cam.T
        centres = np.array([[-b / 2, 0.0, 0.0], [b / 2, 0.0, 0.0]])
        p_wi = centres - (R_wi @ CAM.p_imu_cam)
        pf = np.tile([0.0, 0.0, d], (2, 1))
        _, _, H_f, _ = feature_jacobians(CAM, np.stack([R_wi, R_wi]), p_wi, pf)
        sigma = landmark_sigma(H_f.reshape(1, 4, 3))[0]
        assert sigma == pytest.approx(np.sqrt(2) * d**2 / (f * b), rel=0.02), (d, b)
    # one view: the depth is not fixed at all
    assert landmark_sigma(H_f[:1].reshape(1, 2, 3))[0] > 1e6


def test_slam_features_on_synthetic_motion(vi_recording):
    """SLAM features (OpenVINS): tracks that outlive the window become landmarks, updated in every frame and
    marginalised when their track ends. Their chi-squared gate rejects what a consistent filter's 95% gate does
    (~5%: measured 4.8-5.6% on three seeds); only landmarks whose track is in the last frame are left."""
    path, (t_ns, p, R) = vi_recording
    reader = RecordingReader(path)
    est = msckf_from_recording(reader, VioConfig(max_slam_features=20))
    run_estimator(est, reader, None, None)
    st = est.stats
    assert st.slam_initialized > 50 and st.slam_used > 10 * st.slam_initialized
    assert 0.02 < st.slam_rejected / (st.slam_used + st.slam_rejected) < 0.09
    landmarks = {k for k, _ in est.state.of_kind(Kind.LANDMARK)}
    *_, last = reader.iter_features("/cam0/features")
    assert 0 < len(landmarks) <= 20 and landmarks <= set(last[1].tolist())
    h, dth, dp = errors_vs_truth(est, t_ns, p, R)
    assert np.sqrt((dp**2).sum(1).mean()) < 0.2 and np.degrees(np.sqrt((dth**2).sum(1).mean())) < 1.0


def test_msckf_bad_input(tmp_path):
    path = tmp_path / "nan.mcap"
    t = np.arange(100, dtype=np.int64) * 5_000_000 + 1_000_000_000
    g = np.zeros((100, 3))
    a = np.tile([0, 0, 9.81], (100, 1))
    g[50, 1] = np.nan
    with RecordingWriter(path) as w:
        w.set_metadata(META_CALIBRATION, {"imu": dict(EUROC_IMU), "cameras": {"cam0": EUROC_CAMERAS["cam0"]}})
        w.write_imu_batch(t, g, a)
        w.write_pose_batch(t, np.zeros((100, 3)), np.tile([0, 0, 0, 1.0], (100, 1)))
    reader = RecordingReader(path)
    est = msckf_from_recording(reader, VioConfig())
    with pytest.raises(InputError, match=r"/imu @ 1250000000"):
        run_estimator(est, reader, None, None)
    with pytest.raises(InputError, match="initial IMU state"):
        msckf_from_recording(reader, VioConfig(init_from_groundtruth=False))


def test_msckf_imu_gap_and_no_features(tmp_path):
    path = tmp_path / "gap.mcap"
    t = np.arange(400, dtype=np.int64) * 5_000_000 + 1_000_000_000
    t[200:] += 200_000_000  # 0.2 s gap
    g = np.zeros((400, 3))
    a = np.tile([0, 0, 9.81], (400, 1))
    with RecordingWriter(path) as w:
        w.set_metadata(META_CALIBRATION, {"imu": dict(EUROC_IMU), "cameras": {"cam0": EUROC_CAMERAS["cam0"]}})
        w.write_imu_batch(t, g, a)
        w.write_pose_batch(t, np.zeros((400, 3)), np.tile([0, 0, 0, 1.0], (400, 1)))
        w.write_features(900_000_000, [1], [[10.0, 10.0]])  # before the IMU starts
        for k in range(1, 20):
            w.write_features(int(t[0]) + k * 50_000_000, np.zeros(0), np.zeros((0, 2)))
        tr = int(t[0]) + np.arange(1, 8) * 100_000_000 + 7
        w.write_range_batch(tr, 1, 0, np.arange(7) % 2, np.full(7, 3.0))
    reader = RecordingReader(path)
    est = msckf_from_recording(reader, VioConfig())
    seen = []
    run_estimator(
        est, reader, None, None, on_range=lambda e, m: seen.append((e.t_ns, m.t_ns, m.anchor, m.distance))
    )
    assert [s[0] for s in seen] == tr.tolist() and [s[1] for s in seen] == tr.tolist()
    assert [s[2] for s in seen] == [0, 1, 0, 1, 0, 1, 0] and seen[0][3] == 3.0
    assert set(tr.tolist()) <= set(est.history().arrays()["t_ns"].tolist())
    assert est.stats.imu_gaps == 1 and est.stats.frames_before_imu == 1
    assert est.stats.frames_without_features == 19
    x = est.state.value("imu")
    assert np.abs(x.p).max() < 1e-9 and np.abs(x.v).max() < 1e-9  # static IMU, exact gravity
    assert any("IMU gap" in s for s in est.warnings)


def test_msckf_logs_to_rerun(vi_recording, tmp_path):
    from uwbcal.pipeline.viz.runlog import RunLog, read_rrd_summary

    path, (t_ns, _, _) = vi_recording
    reader = RecordingReader(path)
    est = msckf_from_recording(reader, VioConfig(max_slam_features=10))
    with RunLog(tmp_path / "vio.rrd") as log:
        run_estimator(est, reader, None, int(t_ns[0] + 3e9), log=log)
    summary = read_rrd_summary(tmp_path / "vio.rrd")
    n = len(est.history())
    assert summary.rows.get("world/vio/pose", 0) == n
    assert summary.rows.get("filter/vio/features", 0) > 0
    assert "world/features" in summary.rows
    assert summary.rows.get("world/vio/slam_features", 0) > 0


def test_compress_normal_keeps_information():
    rng = np.random.default_rng(4)
    H = rng.normal(size=(200, 30)) @ np.diag(np.r_[np.ones(26), np.zeros(4)])  # 4 gauge directions
    r = rng.normal(size=200)
    Hq, rq = compress(H, r)
    Hn, rn = compress_normal(H, r)
    assert Hn.shape[0] == 26
    np.testing.assert_allclose(Hn.T @ Hn, H.T @ H, atol=1e-9)
    np.testing.assert_allclose(Hn.T @ rn, H.T @ r, atol=1e-9)
    np.testing.assert_allclose(Hq.T @ Hq, H.T @ H, atol=1e-9)
    # gauge directions that are not coordinate axes (the rank-revealing pivoting must still find them)
    Q = np.linalg.qr(rng.normal(size=(30, 30)))[0]
    Hn, rn = compress_normal(H @ Q, r)
    assert Hn.shape[0] == 26
    np.testing.assert_allclose(Hn.T @ Hn, Q.T @ H.T @ H @ Q, atol=1e-9)
    np.testing.assert_allclose(Hn.T @ rn, Q.T @ H.T @ r, atol=1e-9)


# ---------------------------------------------------------------------------------------------------------------
# zero-velocity update
# ---------------------------------------------------------------------------------------------------------------
def _static_recording(path, duration=6.0, seed=3, v_const=0.0, depth=(3.0, 5.0), jerk=0.0, t_onset=None):
    """The IMU at rest (noisy, with biases) or moving at constant velocity ``v_const`` sideways (along the
    camera x axis; the IMU reads the same), landmarks ``depth`` m in front of the camera, 1 px noise. With
    ``t_onset``: at rest until then, afterwards the same direction with constant ``jerk`` (acceleration growing
    from zero: the start of a smooth motion)."""
    rng = np.random.default_rng(seed)
    rate = 200.0
    t = np.arange(0, duration + 1e-9, 1 / rate)
    t_ns = (t * 1e9).round().astype(np.int64) + 1_000_000_000
    R0 = body_rotation(np.array([[0.05, -0.03, 0.4]]))[0]
    cal = dict(EUROC_IMU)
    dt = 1 / rate
    bg, ba = rng.normal(0, 1e-3, 3), rng.normal(0, 1e-2, 3)
    gyro = bg + rng.normal(0, cal["gyroscope_noise_density"] / np.sqrt(dt), (len(t), 3))
    Rc = R0 @ CAM.R_imu_cam
    tm = np.maximum(t - t_onset, 0.0) if t_onset is not None else np.zeros_like(t)
    a_world = np.outer(jerk * tm, Rc[:, 0])
    acc = (a_world - GRAVITY) @ R0 + ba
    acc += rng.normal(0, cal["accelerometer_noise_density"] / np.sqrt(dt), (len(t), 3))
    v = Rc[:, 0] * v_const
    p = np.outer(t, v) + np.outer(jerk * tm**3 / 6, Rc[:, 0])
    L = (
        Rc
        @ np.column_stack([rng.uniform(-2, 2, 150), rng.uniform(-1.5, 1.5, 150), rng.uniform(*depth, 150)]).T
    )
    L = L.T + R0 @ CAM.p_imu_cam
    with RecordingWriter(path) as w:
        w.set_metadata(META_CALIBRATION, {"imu": cal, "cameras": {"cam0": EUROC_CAMERAS["cam0"]}})
        w.set_metadata(META_TRUTH, {"imu": {"gyro_bias": bg.tolist(), "accel_bias": ba.tolist()}})
        w.write_imu_batch(t_ns, gyro, acc)
        w.write_pose_batch(t_ns, p, np.tile(rot_to_quat(R0[None])[0], (len(t), 1)))
        for i in range(0, len(t), 10):
            P = (L - p[i] - R0 @ CAM.p_imu_cam) @ Rc
            uv = CAM.project(P) + rng.normal(0, 1.0, (len(P), 2))
            w.write_features(int(t_ns[i]) + 1, np.arange(len(P)), uv)
    return p


def test_zupt_holds_a_static_platform(tmp_path):
    path = tmp_path / "static.mcap"
    _static_recording(path)
    reader = RecordingReader(path)
    est = msckf_from_recording(reader, VioConfig())
    run_estimator(est, reader, None, None)
    st = est.stats
    assert st.zupt_updates > 0.9 * st.frames and st.zupt_time_s > 5.0
    assert len(est.clones) < 3  # static frames add no clones (no zero-parallax feature updates)
    x = est.state.value("imu")
    assert np.abs(x.p).max() < 5e-3 and np.abs(x.v).max() < 5e-3
    # without the ZUPT the same data goes through the MSCKF (zero-parallax tracks are gated away)
    est2 = msckf_from_recording(reader, VioConfig(zupt=False))
    run_estimator(est2, reader, None, None)
    assert est2.stats.zupt_updates == 0 and len(est2.clones) > 3


def test_zupt_not_on_slow_constant_velocity(tmp_path):
    """The IMU reads 'at rest' at constant velocity (8 cm/s, ~1 px per frame): the velocity the MSCKF estimates
    and the disparity w.r.t. the last cloned frame must refuse the ZUPT."""
    path = tmp_path / "cv.mcap"
    p = _static_recording(path, v_const=0.08, depth=(1.5, 2.5))
    reader = RecordingReader(path)
    est = msckf_from_recording(reader, VioConfig())
    run_estimator(est, reader, None, None)
    assert est.stats.zupt_updates == 0
    # 0.48 m travelled without rotation (weak scale observability): the MSCKF alone keeps it within 0.1 m
    assert np.linalg.norm(est.state.value("imu").p - p[-1]) < 0.1


def test_zupt_disparity_over_a_baseline(tmp_path):
    """6 cm/s sideways, features 3-5 m away: 0.3 px of motion per frame, inside the 1 px noise of two frames;
    the velocity test made weak on purpose (zupt_sigma_v 5 cm/s: the state of a filter that has been without
    visual updates for a while, the hybrid V1_01 take-off). Compared over one frame (baseline 0, the old test)
    the disparity passes and the ZUPT pins v = 0 on a moving platform; over 0.3 s (1.9 px) it refuses (measured:
    82 vs 2 ZUPTs in 120 frames, the 2 in the first 0.3 s)."""
    path = tmp_path / "slow.mcap"
    p = _static_recording(path, v_const=0.06, depth=(3.0, 5.0))
    reader = RecordingReader(path)
    weak = {"zupt_sigma_v": 0.05}
    old = msckf_from_recording(reader, VioConfig(**weak, zupt_disparity_baseline_s=0.0))
    run_estimator(old, reader, None, None)
    assert old.stats.zupt_updates > 20, old.stats.zupt_updates
    est = msckf_from_recording(reader, VioConfig(**weak))
    run_estimator(est, reader, None, None)
    # only in the first 0.3 s (no frame that old yet: the oldest one is the reference)
    assert est.stats.zupt_updates <= 3, est.stats.zupt_updates
    assert np.linalg.norm(est.state.value("imu").p - p[-1]) < 0.1


def test_disparity_reference_is_derotated():
    """`ZuptUpdater.derotate` against the direct projection: far points (no lever-arm parallax) seen at IMU orientation R0,
    turned to R1 (0.5 deg), land where the camera at R1 sees them; `disparity_reference` picks the newest recent
    frame at least the baseline old when the last MSCKF frame is younger."""
    from uwbcal.pipeline.vio.imu import ImuNoise

    est = ZuptUpdater(VioConfig(), CAM, ImuNoise(1e-4, 1e-3, 1e-5, 1e-4), VioStats())
    rng = np.random.default_rng(1)
    R0 = body_rotation(np.array([[0.05, -0.03, 0.4]]))[0]
    R1 = R0 @ exp_so3(np.radians([0.3, -0.2, 0.35]))
    Ric = CAM.R_imu_cam
    bear = np.column_stack([rng.uniform(-0.4, 0.4, (50, 2)), np.ones(50)])  # reference camera frame
    pw = (R0 @ Ric @ bear.T).T * 1e6  # world directions (far points), camera at the origin
    uv0 = CAM.project(bear)
    uv1 = CAM.project(pw @ (R1 @ Ric))  # camera_now = Ric^T R1^T world
    np.testing.assert_allclose(est.derotate(CAM.undistort(uv0), R0, R1), uv1, atol=1e-6)
    assert np.abs(uv1 - uv0).max() > 2.0  # the rotation moved them by pixels
    ids = np.arange(50)
    for k in range(10):  # frames every 50 ms, the last MSCKF frame at 0.4 s
        est.keep_recent(k * 50_000_000, ids, uv0 + k, R0)
    est.last_frame, est.last_frame_t = (ids, uv0 + 8, R0), 400_000_000
    ref = est.disparity_reference(500_000_000)
    assert (ref[1] == uv0 + 4).all()  # at 0.5 s: the newest frame at least 0.3 s old, the one at 0.2 s
    assert est.disparity_reference(700_000_000) is est.last_frame  # the last MSCKF frame is 0.3 s old


def test_zupt_stops_at_the_onset_of_motion(tmp_path):
    """At rest for 2 s, then acceleration growing from zero (jerk 1 m/s^3 sideways): the mean of the IMU residuals
    (tested on its own 6 dof, not drowned in the 6n of the samples) refuses the ZUPT within 0.15 s of the onset
    (measured: 0.10 s, a = 0.1 m/s^2, v = 5 mm/s), and the velocity the MSCKF carries 0.4 s after it is within
    5 mm/s of the truth (measured 1-3 mm/s). With the mean inside one 6n-dof sum the ZUPT held v = 0 until
    0.25 s (v = 3 cm/s) and left 9-12 mm/s of velocity error (seeds 3-5)."""
    path = tmp_path / "onset.mcap"
    t_onset, jerk = 2.0, 1.0
    _static_recording(path, duration=3.0, jerk=jerk, t_onset=t_onset)
    reader = RecordingReader(path)
    est = msckf_from_recording(reader, VioConfig())
    zupts = []
    process = est.process_frame

    def frame(f):
        n = est.stats.zupt_updates
        process(f)
        if est.stats.zupt_updates > n:
            zupts.append(f[0])

    est.process_frame = frame
    t0 = reader.topics()["/imu"].start_ns
    end = t0 + int((t_onset + 0.4) * 1e9)
    run_estimator(est, reader, None, end)
    last = (max(zupts) - t0) * 1e-9
    assert t_onset - 0.1 < last < t_onset + 0.15, last
    tm = (est.t_ns - t0) * 1e-9 - t_onset
    v_true = jerk * tm**2 / 2
    v = est.state.value("imu").v
    sig_v = np.sqrt(np.diag(est.state.cov("imu"))[6:9])
    assert abs(np.linalg.norm(v) - v_true) < 0.005, (v, v_true, sig_v)


def test_zupt_not_on_motion(vi_recording):
    path, _ = vi_recording
    reader = RecordingReader(path)
    est = msckf_from_recording(reader, VioConfig())
    run_estimator(est, reader, None, None)
    assert est.stats.zupt_updates == 0 and est.stats.updates > 300


def test_static_propagation_keeps_the_unobservable_subspace():
    from uwbcal.pipeline.core.state import ImuState
    from uwbcal.pipeline.vio.imu import ImuNoise, propagate_static

    rng = np.random.default_rng(1)
    noise = ImuNoise(1e-4, 1e-3, 1e-5, 1e-4)

    def nullspace(x):
        ez = np.array([0.0, 0.0, 1.0])
        N = np.zeros((15, 4))
        N[0:3, 0] = x.R.T @ ez
        N[3:6, 0] = -np.cross(x.p, ez)
        N[6:9, 0] = -np.cross(x.v, ez)
        N[3:6, 1:4] = np.eye(3)
        return N

    x_fej = ImuState(exp_so3(rng.normal(size=3)), rng.normal(size=3), rng.normal(size=3) * 0.1)
    x = ImuState(x_fej.R @ exp_so3(rng.normal(size=3) * 0.01), x_fej.p + 0.01, x_fej.v - 0.02)
    prop = propagate_static(x, 0.05, noise, x_fej)
    assert np.allclose(prop.Phi @ nullspace(x_fej), nullspace(prop.state), atol=1e-12)
    assert np.allclose(prop.state.p, x.p + 0.05 * x.v) and np.allclose(prop.state.R, x.R)
    assert np.all(np.linalg.eigvalsh(prop.Q) >= -1e-18)


# ---------------------------------------------------------------------------------------------------------------
# consistency warning (the filter's own chi2 rejections, no ground truth)
# ---------------------------------------------------------------------------------------------------------------
def test_consistency_warning_windows():
    """Sliding-window rejection rate from the per-update counts, against a direct count per window."""
    st = VioStats()
    rng = np.random.default_rng(0)
    t = np.cumsum(rng.integers(1, 3, 200)) * 50_000_000  # 50-100 ms apart
    used = rng.integers(0, 8, 200)
    rej = rng.integers(0, 3, 200)
    rej[120:140] = 30  # a burst of rejections
    st.update_t, st.update_used, st.update_rejected = list(t), list(used), list(rej)
    tt, frac, n = st.rejection_rate(1.0, 20)
    direct = np.full(len(t), np.nan)
    for i in range(len(t)):
        w = (t > t[i] - 1e9) & (t <= t[i])
        nn = used[w].sum() + rej[w].sum()
        assert n[i] == nn
        if nn >= 20:
            direct[i] = rej[w].sum() / nn
    np.testing.assert_allclose(frac, direct, rtol=1e-12)
    first, last = t[direct > 0.5][[0, -1]] * 1e-9
    assert 120 <= np.argmax(direct > 0.5) < 140
    warns = st.consistency_warnings(1.0, 20, 0.5, "vio", None, None, 0)
    assert len(warns) == 1 and f"from {first:.1f} s to {last:.1f} s" in warns[0]
    rej[120:140] = 1
    st.update_rejected = list(rej)
    assert st.consistency_warnings(1.0, 20, 0.5, "vio", None, None, 0) == []


def test_consistency_warning_on_an_overconfident_filter(tmp_path):
    """The synthetic fault: the filter told 0.2 px of pixel noise, the tracks carry 1 px (its NIS is 25x what
    it expects): most tracks fail the chi2 gate and the warning names it; with the true noise, none."""
    path = tmp_path / "cv.mcap"
    _static_recording(path, duration=4.0, v_const=0.3, depth=(1.5, 2.5))
    reader = RecordingReader(path)
    good = msckf_from_recording(reader, VioConfig(zupt=False))
    run_estimator(good, reader, None, None)
    assert good.stats.update_t and not good.span_warnings("vio", None, None, 0)
    bad = msckf_from_recording(reader, VioConfig(zupt=False, pixel_sigma=0.2))
    run_estimator(bad, reader, None, None)
    warns = [w for w in bad.span_warnings("vio", None, None, 0) if "inconsistent visual updates" in w]
    assert len(warns) == 1 and "consistency_max_rejected" in warns[0], bad.warnings


def test_consistency_warning_per_stage_stretch(tmp_path):
    """The stats carry over through a checkpoint (pickle): each stage judges only the updates of its own stretch.
    A filter consistent over the first half (the `vio` stage) turns overconfident in the second (0.2 px told,
    1 px in the tracks: a stand-in for a divergence during refinement): the second stretch's warning names its
    stage and starts inside it, the first stretch stays silent, and the trailing window does not reach back."""
    path = tmp_path / "cv.mcap"
    _static_recording(path, duration=4.0, v_const=0.3, depth=(1.5, 2.5))
    reader = RecordingReader(path)
    mid = 3_000_000_000  # the recording's 4 s start at 1 s
    est = msckf_from_recording(reader, VioConfig(zupt=False))
    run_estimator(est, reader, None, mid)
    est = pickle.loads(pickle.dumps(est))  # checkpoint_init.pkl
    est.config = est.config.model_copy(update={"pixel_sigma": 0.2})
    run_estimator(est, reader, mid, None)
    t0, t = 1_000_000_000, np.asarray(est.stats.update_t)  # the recording's start (its first frame)
    assert est.span_warnings("vio", None, mid, t0) == []
    warns = est.span_warnings("refine", mid, None, t0)
    assert len(warns) == 1 and warns[0].startswith("refine: inconsistent visual updates from "), warns
    first = float(warns[0].split(" from ")[1].split(" s")[0])
    assert first >= (mid - t0) * 1e-9 - 0.05
    _, frac, _ = est.stats.rejection_rate(2.0, 20, mid, None)
    _, frac_all, _ = est.stats.rejection_rate(2.0, 20)
    assert len(frac) == int((t >= mid).sum()) and np.nanmax(frac) > 0.5
    assert np.nanmax(frac_all[: len(t) - len(frac)]) <= 0.5  # the first stretch alone: below the threshold
