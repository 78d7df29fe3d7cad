"""The zero-velocity update (OpenVINS' UpdaterZeroVelocity): the test whether the interval since the last frame
was static (`ZuptUpdater.detect`) and the update of the IMU state with the at-rest model and v = 0
(`ZuptUpdater.update`). It keeps its own references: the state at the last frame, the last MSCKF frame and the
recent frames (the disparity test's reference)."""

from __future__ import annotations

from collections import deque

import numpy as np

from uwbcal.pipeline.core.geometry import exp_so3, skew
from uwbcal.pipeline.core.state import ImuState, State, chi2_ppf, ekf_update
from uwbcal.pipeline.vio.camera import Camera
from uwbcal.pipeline.vio.config import VioConfig
from uwbcal.pipeline.vio.imu import GRAVITY, ImuNoise
from uwbcal.pipeline.vio.stats import VioStats


class ZuptUpdater:
    """Zero-velocity detection and update; counts into the shared `VioStats` (``zupt_updates``, ``zupt_time_s``)."""

    def __init__(self, config: VioConfig, camera: Camera, noise: ImuNoise, stats: VioStats) -> None:
        self.config = config
        self.camera = camera
        self.noise = noise
        self.stats = stats
        # disparity reference: ids, pixels and the IMU orientation estimate of the last MSCKF frame
        self.last_frame: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None
        self.last_frame_t = -1
        # the recent frames (t, ids, pixels, orientation), every frame, static or not: the disparity reference when
        # the last MSCKF frame is younger than vio.zupt_disparity_baseline_s
        self._recent: deque[tuple[int, np.ndarray, np.ndarray, np.ndarray]] = deque()
        self._ref_xy: tuple[np.ndarray, np.ndarray] | None = None  # `_undistorted`: ids of the frame, its xy
        self.ref: tuple[int, ImuState, np.ndarray, np.ndarray] | None = None  # `set_reference`

    def model(
        self, gyro: np.ndarray, acc: np.ndarray, x: ImuState, fej_R: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Per-sample residuals (n, 6) of the IMU at rest, their Jacobian (6, 15) and noise variances (6,).

        At rest ``w_m = b_g + n_g`` and ``a_m = b_a - R^T g + n_a``; with ``R = R_hat Exp(dtheta)`` the
        residual ``[w_m - b_g_hat, a_m - b_a_hat + R_hat^T g]`` is ``[dbg, dba - [R^T g]x dtheta] + n``. The
        orientation column is taken at the first estimate (FEJ): it has no component along the global yaw.
        """
        r = np.concatenate([gyro - x.bg, acc - x.ba + x.R.T @ GRAVITY], axis=1)
        H = np.zeros((6, 15))
        H[0:3, 9:12] = np.eye(3)
        H[3:6, 0:3] = -skew(fej_R.T @ GRAVITY)
        H[3:6, 12:15] = np.eye(3)
        k = self.config.zupt_noise_inflation**2 * self.noise.rate_hz  # sigma^2 / dt per sample, inflated
        var = np.repeat([k * self.noise.sigma_g**2, k * self.noise.sigma_a**2], 3)
        return r, H, var

    @staticmethod
    def _imu_samples(t0: int, t1: int, imu_t: np.ndarray) -> slice:
        return slice(int(np.searchsorted(imu_t, t0, "right")), int(np.searchsorted(imu_t, t1, "right")))

    def detect(
        self, t_ns: int, ids: np.ndarray, uv: np.ndarray, imu_t: np.ndarray, gyro: np.ndarray, acc: np.ndarray
    ) -> bool:
        """Zero velocity over (t_ref, t_ns]? (t_ref: the last frame, `set_reference`; the tests use the state
        there.) All of:

        - the estimated speed is small and v = 0 passes a chi-squared test with the state covariance (a slow
          constant velocity looks like rest to the IMU);
        - the IMU samples pass a chi-squared test of the at-rest model (with the state covariance);
        - with at least ``zupt_min_features`` tracks in common with the reference frame, their disparity is
          pixel noise (chi-squared). The reference is the last frame that went through the MSCKF (static frames
          do not replace it), so that a slow drift accumulates disparity instead of hiding below the noise, and
          at least ``zupt_disparity_baseline_s`` before this frame (`disparity_reference`): the first frame of a
          slow motion must not be compared with the frame just before it only. The reference pixels are turned by
          the rotation between the frames (`derotate`): zero velocity, not zero rotation, is tested.

        The disparity test alone is not enough: with 1 px noise and tracks ~10 m away, slow flight (a few cm/s)
        passes it (false ZUPTs; docs/results/measurements.md). The IMU test rejects rotor vibration of a MAV
        standing on the ground (far above the white-noise model), so there the ZUPT only fires in the quieter
        intervals.
        """
        cfg = self.config
        t_ref, x, fej_R, P_imu = self.ref
        if float(np.linalg.norm(x.v)) > cfg.zupt_max_velocity:
            return False
        v_cov = P_imu[6:9, 6:9] + cfg.zupt_sigma_v**2 * np.eye(3)
        if float(x.v @ np.linalg.solve(v_cov, x.v)) > chi2_ppf(cfg.zupt_chi2_quantile, 3):
            return False
        sl = self._imu_samples(t_ref, t_ns, imu_t)
        n = sl.stop - sl.start
        if n < 2:
            return False
        r, H, var = self.model(gyro[sl], acc[sl], x, fej_R)
        # The stacked residual splits into two independent parts (no 6n x 6n matrix): the deviations from the
        # sample mean are white, sum |r_i - r_mean|^2_R ~ chi2(6 (n - 1)), and the mean carries the state
        # uncertainty, r_mean^T (H P H^T + R / n)^-1 r_mean ~ chi2(6). Their sum is the test of the at-rest model
        # (vibration shows in the deviations); the mean is also tested on its own: a mean angular rate or
        # acceleration is motion, and in the 6n-dof sum its 6 dof drown: the slow start of a motion
        # (acceleration growing from zero) passed as rest for several frames, the ZUPT pinning v = 0 while the
        # platform already moved at centimetres per second.
        rm = r.mean(axis=0)
        S = H @ P_imu @ H.T + np.diag(var / n)
        mean = float(rm @ np.linalg.solve(S, rm))
        q = cfg.zupt_chi2_quantile
        if mean > chi2_ppf(q, 6) or mean + float((((r - rm) ** 2) / var).sum()) > chi2_ppf(q, 6 * n):
            return False
        ref = self.disparity_reference(t_ns)
        if ref is not None and len(ids):
            ids0, uv0, R0 = ref
            common, i0, i1 = np.intersect1d(ids0, ids, assume_unique=False, return_indices=True)
            if len(common) >= cfg.zupt_min_features:
                # the orientation now: the state's at the last frame and the mean gyro since (a few samples)
                R1 = x.R @ exp_so3((gyro[sl].mean(axis=0) - x.bg) * ((t_ns - t_ref) * 1e-9))
                uv_ref = self.derotate(self._undistorted(ids0, uv0)[i0], R0, R1)
                d2 = float(((uv[i1] - uv_ref) ** 2).sum()) / (2.0 * cfg.pixel_sigma**2)
                return d2 < chi2_ppf(cfg.zupt_chi2_quantile, 2 * len(common))
        return True

    def _undistorted(self, ids: np.ndarray, uv: np.ndarray) -> np.ndarray:
        """``camera.undistort(uv)`` of a reference frame, once per frame (in a static stretch the reference
        stays the same frame for many frames)."""
        if self._ref_xy is None or self._ref_xy[0] is not ids:
            self._ref_xy = (ids, self.camera.undistort(uv))
        return self._ref_xy[1]

    def derotate(self, xy: np.ndarray, R_ref: np.ndarray, R_now: np.ndarray) -> np.ndarray:
        """Undistorted points ``xy`` of the reference frame in pixels as the camera would see them now after a
        rotation only (IMU orientations ``R_ref`` -> ``R_now``): the disparity test is of zero *velocity*, and a
        platform at rest still turns a little (V1_01 on the ground: 0.05-0.08 deg in 0.3 s, 0.4-0.6 px, enough
        to fail the test over that baseline); the camera's displacement from the rotation about the IMU (lever
        arm x angle) is left out."""
        Ric = self.camera.R_imu_cam
        R = Ric.T @ R_now.T @ R_ref @ Ric  # camera_now <- camera_ref
        b = np.column_stack([xy, np.ones(len(xy))]) @ R.T
        return self.camera.project(b)

    def disparity_reference(self, t_ns: int) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
        """The frame the disparity test compares with: the last MSCKF frame, or, when that one is younger than
        ``zupt_disparity_baseline_s``, the newest recent frame at least that old (the oldest kept at the start).

        Over one frame (50 ms at 20 Hz) a platform that has just started to move at 0.1 m/s shifts features a
        few metres away by ~0.5 px, inside the 1 px noise of the two frames: the test passed and the ZUPT pinned
        v = 0 while the MAV was climbing at 0.1 m/s (hybrid V1_01 take-off, the MSCKF then diverged). Over
        0.3 s the same motion shows as ~4 px."""
        if self.last_frame is None:
            return None
        if t_ns - self.last_frame_t >= self.config.zupt_disparity_baseline_s * 1e9 or not self._recent:
            return self.last_frame
        t_old = t_ns - self.config.zupt_disparity_baseline_s * 1e9
        ref = self._recent[0]
        for fr in self._recent:  # a handful of frames, oldest first
            if fr[0] > t_old:
                break
            ref = fr
        return ref[1:]

    def keep_recent(self, t_ns: int, ids: np.ndarray, uv: np.ndarray, R: np.ndarray) -> None:
        """Append the frame to the recent ones; drop those no longer needed as a disparity reference."""
        self._recent.append((t_ns, ids, uv, R))
        t_old = t_ns - self.config.zupt_disparity_baseline_s * 1e9
        while len(self._recent) > 1 and self._recent[1][0] <= t_old:
            self._recent.popleft()

    def after_frame(self, t_ns: int, ids: np.ndarray, uv: np.ndarray, R: np.ndarray, static: bool) -> None:
        """A frame processed (``R``: the IMU orientation after it): the last MSCKF frame (a static frame does not
        replace it) and the recent frames."""
        ok = np.isfinite(uv).all(axis=1) if len(uv) else np.zeros(0, bool)
        frame_ok = (ids[ok], uv[ok], R)
        if not static or self.last_frame is None:
            self.last_frame = frame_ok
            self.last_frame_t = t_ns
        if self.config.zupt_disparity_baseline_s > 0:
            self.keep_recent(t_ns, *frame_ok)

    def set_reference(self, state: State, t_ns: int) -> None:
        """The state the next frame's zero-velocity test is about: time, velocity and IMU covariance at the last
        frame (or the span start); ranges between two frames do not enter the test."""
        im = state.slice("imu")
        x = state.value("imu")  # values are replaced, never changed in place: a reference is a snapshot
        self.ref = (t_ns, x, state.fej("imu").R, state.P[im, im].copy())

    def update(
        self, state: State, t0: int, t1: int, imu_t: np.ndarray, gyro: np.ndarray, acc: np.ndarray
    ) -> None:
        """The zero-velocity update of (t0, t1] through `ekf_update`: the mean of the at-rest residuals (same
        Jacobian for every sample, so the mean carries all their information) and v = 0."""
        Hz = np.zeros((3, 15))
        Hz[:, 6:9] = np.eye(3)
        rz = -state.value("imu").v
        Rz = np.full(3, self.config.zupt_sigma_v**2)
        if self.config.zupt_imu:
            sl = self._imu_samples(t0, t1, imu_t)
            r, H, var = self.model(gyro[sl], acc[sl], state.value("imu"), state.fej("imu").R)
            Hz = np.vstack([H, Hz])
            rz = np.concatenate([r.mean(axis=0), rz])
            Rz = np.concatenate([var / len(r), Rz])
        ekf_update(state, {"imu": Hz}, rz, np.diag(Rz))
        self.stats.zupt_updates += 1
        self.stats.zupt_time_s += (t1 - t0) * 1e-9
