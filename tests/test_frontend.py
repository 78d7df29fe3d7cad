import numpy as np
import pytest

from uwbcal.convert.euroc import EUROC_CAMERAS
from uwbcal.convert.recording import META_CALIBRATION, RecordingReader, RecordingWriter
from uwbcal.pipeline.core.errors import InputError
from uwbcal.pipeline.core.geometry import exp_so3
from uwbcal.pipeline.vio.camera import Camera
from uwbcal.pipeline.vio.config import FrontendConfig
from uwbcal.pipeline.vio.frontend import (
    DescriptorFrontend,
    GyroRotation,
    KltFrontend,
    bucket_select,
    decode_image,
    make_frontend,
    run_frontend,
    track_frames,
)

from support import T0

W, H = 320, 240
PINHOLE = {
    "intrinsics": [250.0, 250.0, 160.0, 120.0],
    "distortion_model": "radtan",
    "distortion": [0, 0, 0, 0],
    "resolution": [W, H],
    "T_imu_cam": [[1.0, 0.0, 0.0, 0.0], [0.0, 1.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0], [0.0, 0.0, 0.0, 1.0]],
}


def _texture(seed=0, w=W + 80, h=H + 80):
    import cv2

    rng = np.random.default_rng(seed)
    img = rng.uniform(0, 255, size=(h // 4, w // 4)).astype(np.float32)
    img = cv2.resize(img, (w, h), interpolation=cv2.INTER_CUBIC)
    img = cv2.GaussianBlur(img, (0, 0), 1.2)
    return np.clip(img, 0, 255).astype(np.uint8)


def _shifted_frames(n=12, step=(1.5, -0.75)):
    """Frames cut from one texture with a sub-pixel shift per frame: scene point x appears at x - k*step."""
    import cv2

    tex = _texture()
    frames = []
    for k in range(n):
        dx, dy = k * step[0], k * step[1]
        # output pixel u shows texture at u + 40 + k*step
        M = np.array([[1.0, 0.0, 40.0 + dx], [0.0, 1.0, 40.0 + dy]])
        img = cv2.warpAffine(tex, M, (W, H), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP)
        frames.append((T0 + k * 50_000_000, img))
    return frames


def test_bucket_select_caps_each_cell_in_quality_order():
    pts = np.array([[10, 10], [20, 20], [30, 30], [110, 10], [15, 110], [120, 120]], float)
    need = np.array([2, 0, 1, 1])  # 2x2 grid on a 200x200 image
    sel = bucket_select(pts, need, 2, 2, 200, 200)
    assert sel.tolist() == [0, 1, 4, 5]


def test_tracks_follow_a_known_image_motion_with_persistent_ids():
    step = np.array([1.5, -0.75])
    frames = _shifted_frames(step=tuple(step))
    fe = KltFrontend(PINHOLE, FrontendConfig(max_features=120, equalize=False))
    out = list(track_frames(fe, frames))
    assert len(out) == len(frames)
    first_ids, first_uv = out[0][1], out[0][2]
    assert len(first_ids) >= 100
    for k, (_, ids, uv) in enumerate(out):
        common, i0, i1 = np.intersect1d(first_ids, ids, return_indices=True)
        assert len(common) > 0.8 * len(first_ids)  # ids persist
        err = uv[i1] - (first_uv[i0] - k * step)
        assert np.median(np.linalg.norm(err, axis=1)) < 0.05
        assert np.abs(err).max() < 0.5
    assert len(np.unique(out[-1][1])) == len(out[-1][1])
    st = fe.stats
    assert st.frames == len(frames) and st.features_mean >= 100
    assert st.inlier_ratio_mean > 0.95


def test_ransac_rejects_points_inconsistent_with_the_epipolar_geometry():
    rng = np.random.default_rng(1)
    cam = Camera.from_calibration({"cameras": {"cam0": PINHOLE}})
    # 3-D points in front of camera 0, camera 1 rotated and translated
    X = np.column_stack([rng.uniform(-3, 3, 200), rng.uniform(-2, 2, 200), rng.uniform(4, 12, 200)])
    R = exp_so3(np.array([0.02, -0.05, 0.01]))
    t = np.array([0.4, 0.05, 0.1])
    uv0 = cam.project(X)
    uv1 = cam.project(X @ R.T + t)
    uv0 += 0.1 * rng.normal(size=uv0.shape)
    uv1 += 0.1 * rng.normal(size=uv1.shape)
    bad = rng.choice(200, 30, replace=False)
    uv1[bad] += rng.uniform(6, 20, size=(30, 2)) * rng.choice([-1, 1], size=(30, 2))
    fe = KltFrontend(PINHOLE)
    inl = fe.ransac_inliers(uv0, uv1)
    truth = np.ones(200, bool)
    truth[bad] = False
    assert (inl & ~truth).sum() <= 2  # outliers caught
    assert (inl & truth).sum() >= 0.95 * truth.sum()  # inliers kept


def _write_images(path, frames, calib=PINHOLE, extra=None):
    with RecordingWriter(path) as w:
        for t, img in frames:
            w.write_image("/cam0/image_raw", t, img)
        if extra:
            extra(w)
        w.set_metadata(META_CALIBRATION, {"cameras": {"cam0": calib}})
    return RecordingReader(path)


def test_run_frontend_writes_tracks_and_counts_corrupt_images(tmp_path):
    from uwbcal.convert import msgs
    from uwbcal.convert.recording import _types

    frames = _shifted_frames(11)
    drop = frames.pop(4)  # written as a corrupt image (header stamp damaged too)
    frames.pop(6)  # missing: a gap in the stamps

    def corrupt(w):
        _, T = _types()
        bad = T[msgs.IMAGE](
            header=T["std_msgs/msg/Header"](
                stamp=T["builtin_interfaces/msg/Time"](sec=0, nanosec=0), frame_id=""
            ),
            height=H,
            width=W,
            encoding="mono8",
            is_bigendian=0,
            step=W,
            data=np.zeros(100, np.uint8),
        )
        w.write("/cam0/image_raw", drop[0], bad)

    rd = _write_images(tmp_path / "rec.mcap", frames, extra=corrupt)
    calls = []

    def on_frame(t, img, uv, ids):  # records what the front-end shows its observer
        calls.append((t, img.shape, len(ids), uv.shape))

    stats = run_frontend(
        rd, tmp_path / "features.mcap", FrontendConfig(max_features=80, log_every=4), on_frame
    )
    assert len(calls) == 3 and all(n > 0 and uv == (n, 2) for _, _, n, uv in calls)
    assert stats.frames == 9 and stats.frames_corrupt == 1 and stats.frames_missing == 1
    assert "corrupt" in str(stats)
    out = RecordingReader(tmp_path / "features.mcap")
    got = list(out.iter_features())
    assert [t for t, _, _ in got] == [t for t, _ in frames]
    assert all(len(ids) >= 60 and uv.shape == (len(ids), 2) for _, ids, uv in got)
    assert out.metadata("uwbcal.frontend")["stats"]["frames"] == 9


def test_run_frontend_empty_topic_is_an_input_error(tmp_path):
    with RecordingWriter(tmp_path / "none.mcap") as w:
        w.write_imu_batch([T0, T0 + 5_000_000], np.zeros((2, 3)), np.ones((2, 3)))
    with pytest.raises(InputError, match="/cam0/image_raw"):
        run_frontend(RecordingReader(tmp_path / "none.mcap"), tmp_path / "f.mcap")
    assert not (tmp_path / "f.mcap").exists()


def test_decode_image_rejects_short_buffers_and_converts_colour():
    class M:
        height, width, step, encoding = 2, 3, 9, "rgb8"
        data = np.arange(18, dtype=np.uint8)

    img, _ = decode_image(M)
    assert img.shape == (2, 3) and img.dtype == np.uint8
    M.data = np.zeros(5, np.uint8)
    img, why = decode_image(M)
    assert img is None and "bytes" in why


# -- real data ------------------------------------------------------------------------------------------------------
def _euroc_png_frames(folder):
    import cv2

    files = sorted(folder.glob("*.png"))
    for f in files:
        yield int(f.stem), cv2.imread(str(f), cv2.IMREAD_GRAYSCALE)


EUROC_CAM0 = EUROC_CAMERAS["cam0"]


def test_real_euroc_excerpt_tracks_enough_features(data_dir):
    folder = data_dir / "euroc/V1_01_micro/mav0/cam0/data"
    fe = KltFrontend(EUROC_CAM0, FrontendConfig())
    out = list(track_frames(fe, _euroc_png_frames(folder)))
    st = fe.stats
    print(f"\nEuRoC V1_01_micro: {st}")
    assert len(out) == 95 and st.frames == 95
    assert st.features_mean >= 100
    assert np.isfinite(st.inlier_ratio_mean) and st.inlier_ratio_mean > 0.8
    assert st.track_length_mean > 5


@pytest.fixture(scope="module")
def euroc_recording(euroc_micro):
    return euroc_micro[0]  # the session's one conversion (conftest)


def test_real_euroc_recording_to_features_with_stereo(euroc_recording, tmp_path):
    rd = RecordingReader(euroc_recording)
    stats = run_frontend(rd, tmp_path / "f.mcap", FrontendConfig(stereo=True))
    assert stats.frames == 95 and stats.features_mean >= 100
    # cam1 has matching stamps for all 95 cam0 frames: most features are found in the right image
    assert len(stats.stereo_ratio) == 95 and np.mean(stats.stereo_ratio) > 0.5
    got = list(RecordingReader(tmp_path / "f.mcap").iter_features())
    assert len(got) == 95


def test_descriptor_tracker_follows_a_fast_motion_with_the_rotation_prediction():
    """30 px per frame (a fast turn at a low frame rate): the tracker started at the gyro-predicted pixels keeps
    the ids and the positions; the rotation that moves the image by the step is what a gyro would report."""
    step = np.array([30.0, 0.0])
    frames = _shifted_frames(n=6, step=tuple(step))
    theta = np.arctan(step[0] / 250.0)

    def rotation(t0, t1):
        return exp_so3(np.array([0.0, theta * (t1 - t0) / 50_000_000, 0.0]))

    cfg = FrontendConfig(tracker="descriptor", max_features=120, equalize=False)
    fe = make_frontend(cfg, Camera.from_calibration({"cameras": {"cam0": PINHOLE}}), rotation=rotation)
    assert isinstance(fe, DescriptorFrontend)
    out = list(track_frames(fe, frames))
    for k in range(1, len(out)):
        (_, ida, uva), (_, idb, uvb) = out[k - 1], out[k]
        common, ia, ib = np.intersect1d(ida, idb, return_indices=True)
        assert len(common) > 0.6 * len(ida)
        err = uvb[ib] - (uva[ia] - step)
        assert np.median(np.linalg.norm(err, axis=1)) < 0.2


def test_gyro_rotation_is_the_camera_frame_rotation_between_stamps():
    t = T0 + np.arange(101) * 10_000_000
    w = np.tile([0.0, 0.0, 0.5], (len(t), 1))
    R_ic = exp_so3(np.array([0.3, -0.2, 0.1]))
    rot = GyroRotation(t, w, R_ic)
    got = rot(int(t[10]) + 5_000_000, int(t[60]))
    want = R_ic.T @ exp_so3(np.array([0.0, 0.0, 0.5 * 0.495])) @ R_ic
    np.testing.assert_allclose(got, want, atol=1e-9)
