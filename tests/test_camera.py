"""Pinhole + radtan camera: Jacobians against finite differences, undistortion round trip."""

import numpy as np

from uwbcal.convert.euroc import EUROC_CAMERAS
from uwbcal.pipeline.vio.camera import Camera

CAM = Camera.from_calibration({"cameras": EUROC_CAMERAS})


def test_calibration_loaded():
    assert CAM.fu == 458.654 and CAM.k1 < 0 and CAM.R_imu_cam.shape == (3, 3)


def test_projection_jacobian_finite_differences():
    rng = np.random.default_rng(0)
    p = np.column_stack([rng.uniform(-1, 1, (50, 2)), rng.uniform(1, 5, 50)])
    _, J = CAM.project_jacobian(p)
    eps = 1e-6
    Jfd = np.stack(
        [(CAM.project(p + eps * e) - CAM.project(p - eps * e)) / (2 * eps) for e in np.eye(3)], axis=-1
    )
    assert np.abs(J - Jfd).max() < 1e-5 * np.abs(Jfd).max()


def test_distortion_jacobian_finite_differences():
    rng = np.random.default_rng(1)
    n = rng.uniform(-0.7, 0.7, (50, 2))
    J = CAM.distort_jacobian(n)
    eps = 1e-7
    Jfd = np.stack([(CAM.distort(n + eps * e) - CAM.distort(n - eps * e)) / (2 * eps) for e in np.eye(2)], -1)
    assert np.abs(J - Jfd).max() < 1e-7


def test_undistort_round_trip():
    rng = np.random.default_rng(2)
    n = rng.uniform(-0.6, 0.6, (200, 2))
    uv = CAM.normalised_to_pixel(n)
    assert np.abs(CAM.undistort(uv) - n).max() < 1e-10
