import numpy as np
import pytest

from uwbcal.convert.recording import RecordingReader, RecordingWriter
from uwbcal.pipeline.core.errors import InputError
from uwbcal.pipeline.core.geometry import exp_so3
from uwbcal.pipeline.vio.static_init import (
    StaticInitConfig,
    gravity_aligned_rotation,
    image_still,
    roll_pitch,
    static_init_from_recording,
    static_initialize,
    still_prefix,
)

from support import T0

G = 9.81


def _synthetic(still_s=3.0, moving_s=2.0, rate=200.0, roll=0.3, pitch=-0.2, yaw=1.1, seed=0):
    """IMU at rest with a known attitude and biases, then shaking; returns t, gyro, acc, R_true, bg, ba."""
    rng = np.random.default_rng(seed)
    n = int((still_s + moving_s) * rate)
    t = T0 + (np.arange(n) * 1e9 / rate).astype(np.int64)
    R = exp_so3(np.array([0, 0, yaw])) @ exp_so3(np.array([0, pitch, 0])) @ exp_so3(np.array([roll, 0, 0]))
    bg = np.array([0.01, -0.02, 0.005])
    ba = np.array([0.05, -0.03, 0.02])
    f = R.T @ np.array([0, 0, G])
    gyro = bg + 2e-3 * rng.normal(size=(n, 3))
    acc = f + ba + 0.02 * rng.normal(size=(n, 3))
    moving = np.arange(n) >= int(still_s * rate)
    s = np.arange(moving.sum()) / rate
    gyro[moving] += np.column_stack([np.sin(7 * s), np.cos(5 * s), 0.5 * np.sin(3 * s)])
    acc[moving] += 3.0 * np.column_stack([np.sin(9 * s), np.cos(4 * s), np.sin(6 * s)])
    return t, gyro, acc, R, bg, ba


def test_gravity_aligned_rotation_and_roll_pitch():
    R = exp_so3(np.array([0, 0.4, 0])) @ exp_so3(np.array([-0.7, 0, 0]))
    f = R.T @ np.array([0, 0, G])
    Re = gravity_aligned_rotation(f)
    assert np.allclose(Re, R, atol=1e-12)
    assert np.allclose(roll_pitch(Re), [-0.7, 0.4], atol=1e-12)
    assert np.allclose(Re @ (f / G), [0, 0, 1], atol=1e-12)


def test_recovers_tilt_and_gyro_bias_and_finds_the_still_period():
    t, gyro, acc, R, bg, ba = _synthetic()
    res = static_initialize(t, gyro, acc)
    # still prefix ends within a window of the true end (3 s)
    assert 2.0 <= (res.t_end_ns - res.t_start_ns) * 1e-9 <= 3.0
    # roll/pitch: exact up to the accelerometer bias tilt (|ba_perp| / g) and noise
    assert np.allclose(roll_pitch(res.state.R), roll_pitch(R), atol=np.linalg.norm(ba) / G + 1e-3)
    # yaw is set to 0: the gravity direction in the body frame is what must agree
    up_true, up_est = R.T @ [0, 0, 1], res.state.R.T @ [0, 0, 1]
    assert np.degrees(np.arccos(np.clip(up_true @ up_est, -1, 1))) < 0.5
    assert abs(np.arctan2(res.state.R[1, 0], res.state.R[0, 0])) < 1e-12
    assert np.allclose(res.state.bg, bg, atol=5e-4)
    assert np.allclose(res.state.ba, 0) and np.allclose(res.state.p, 0) and np.allclose(res.state.v, 0)
    P = res.P
    assert P.shape == (15, 15) and np.allclose(P, P.T) and np.linalg.eigvalsh(P).min() > 0
    R_, p, v, bg_, ba_ = res.astuple()
    assert R_.shape == (3, 3) and bg_.shape == (3,)


def test_yaw_sigma_is_about_world_z():
    t, gyro, acc, R, _, _ = _synthetic(roll=0.6, pitch=0.4)
    cfg = StaticInitConfig(sigma_roll_pitch_deg=2.0, sigma_yaw_deg=0.01)
    res = static_initialize(t, gyro, acc, cfg)
    Rh = res.state.R
    # world-frame covariance of dtheta_world = R dtheta_body: tight about z, loose about x, y
    Pw = Rh @ res.P[0:3, 0:3] @ Rh.T
    assert np.sqrt(Pw[2, 2]) == pytest.approx(np.radians(0.01), rel=1e-6)
    assert np.sqrt(Pw[0, 0]) == pytest.approx(np.radians(2.0), rel=1e-6)


def test_gravity_residual_accel_bias():
    t, gyro, acc, R, bg, ba = _synthetic(moving_s=0.0, still_s=2.0)
    res = static_initialize(t, gyro, acc, StaticInitConfig(accel_bias="gravity_residual"))
    f = acc[: res.samples].mean(axis=0)
    up = f / np.linalg.norm(f)
    assert np.allclose(res.state.ba, (np.linalg.norm(f) - G) * up, atol=1e-12)
    assert abs(res.state.ba @ up - ba @ (R.T @ [0, 0, 1])) < 5e-3


def test_moving_start_is_refused_with_a_clear_message():
    t, gyro, acc, *_ = _synthetic(still_s=0.0, moving_s=3.0)
    with pytest.raises(InputError, match="not still at the start.*ground-truth initialisation"):
        static_initialize(t, gyro, acc, source="x.mcap: /imu")
    t, gyro, acc, *_ = _synthetic(still_s=0.5, moving_s=3.0)
    assert 0 < still_prefix(t, gyro, acc, StaticInitConfig(window_s=0.25)) < 0.5 * 200 + 1
    with pytest.raises(InputError, match="still for"):
        static_initialize(t, gyro, acc)


def test_wrong_units_and_nan_are_input_errors():
    t, gyro, acc, *_ = _synthetic(moving_s=0.0)
    with pytest.raises(InputError, match="not g"):
        static_initialize(t, gyro, acc / G)  # accelerometer in g, not m/s^2
    acc = acc.copy()
    acc[10, 0] = np.nan
    with pytest.raises(InputError, match=str(int(t[10]))):
        static_initialize(t, gyro, acc)


def test_from_recording(tmp_path):
    t, gyro, acc, R, bg, _ = _synthetic()
    with RecordingWriter(tmp_path / "imu.mcap") as w:
        w.write_imu_batch(t, gyro, acc)
    res = static_init_from_recording(RecordingReader(tmp_path / "imu.mcap"))
    assert np.allclose(res.state.bg, bg, atol=5e-4)
    with RecordingWriter(tmp_path / "none.mcap") as w:
        w.write_range_batch([T0], [0], [0], [1], [2.0])
    with pytest.raises(InputError, match="/imu"):
        static_init_from_recording(RecordingReader(tmp_path / "none.mcap"))


def _euroc_imu(data_dir):
    d = np.loadtxt(data_dir / "euroc/V1_01_micro/mav0/imu0/data.csv", delimiter=",", comments="#")
    return d[:, 0].astype(np.int64), d[:, 1:4], d[:, 4:7]


def test_real_euroc_excerpt_starts_still(data_dir):
    """V1_01 starts with the MAV on the ground, rotors running (|acc| std ~0.3 m/s^2); take-off after ~4.5 s."""
    t, gyro, acc = _euroc_imu(data_dir)
    res = static_initialize(t, gyro, acc)
    still = (res.t_end_ns - res.t_start_ns) * 1e-9
    assert 3.0 < still < 5.5
    # ground truth (V1_01_easy.csv, first row): gyro bias and body attitude
    gt = np.loadtxt(
        data_dir / "euroc/groundtruth/V1_01_easy.csv", delimiter=",", comments="#", skiprows=1, max_rows=1
    )
    assert np.allclose(res.state.bg, gt[11:14], atol=2e-3)
    from uwbcal.pipeline.core.geometry import quat_to_rot

    R_gt = quat_to_rot(gt[[5, 6, 7, 4]])
    ang = np.degrees(np.arccos(np.clip((R_gt.T @ [0, 0, 1]) @ (res.state.R.T @ [0, 0, 1]), -1, 1)))
    assert ang < 1.0
    # the attitude explains the raw data: the still period's bias-corrected specific force, rotated to the world,
    # is gravity (vertical, 9.81 m/s^2 within the accelerometer noise)
    still_rows = (t >= res.t_start_ns) & (t <= res.t_end_ns)
    f_w = res.state.R @ (acc[still_rows].mean(0) - res.state.ba)
    assert (
        np.degrees(np.arccos(f_w[2] / np.linalg.norm(f_w))) < 0.1 and abs(np.linalg.norm(f_w) - 9.81) < 0.05
    )


def test_real_euroc_flight_part_is_refused(data_dir):
    t, gyro, acc = _euroc_imu(data_dir)
    start = np.searchsorted(t, t[0] + int(8e9))  # in flight
    with pytest.raises(InputError, match="not still at the start"):
        static_initialize(t[start:], gyro[start:], acc[start:])


def _frames(t_move_s, n=30, rate=3.0, speed_px=20.0):
    """Tracks at rest (0.3 px noise) until t_move_s, then sliding at speed_px per frame."""
    rng = np.random.default_rng(1)
    ids = np.arange(50)
    uv0 = rng.uniform(50, 400, size=(50, 2))
    for k in range(n):
        t = k / rate
        shift = max(0.0, t - t_move_s) * rate * speed_px
        yield T0 + int(t * 1e9), ids, uv0 + [shift, 0.0] + 0.3 * rng.normal(size=(50, 2))


def test_images_end_the_still_period_when_the_camera_moves_first():
    """A hand-held start: the IMU passes as still for 3 s, the images move after 2 s."""
    t, gyro, acc, *_ = _synthetic(still_s=3.0)
    cfg = StaticInitConfig()
    imgs = image_still(_frames(2.0), cfg)
    assert imgs.moved and imgs.t_end_ns == T0 + 2 * 1_000_000_000
    res = static_initialize(t, gyro, acc, cfg, images=imgs)
    assert res.t_end_ns <= imgs.t_end_ns and "images move" in res.image_check
    assert not image_still(_frames(99.0), cfg).moved
    with pytest.raises(InputError, match="images move"):
        static_initialize(t, gyro, acc, cfg, images=image_still(_frames(0.4), cfg))
