"""Typed settings of the visual-inertial layer: front-end and MSCKF (the `[frontend]` and `[vio]` config sections)."""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, ConfigDict, Field


class VioConfig(BaseModel):
    model_config = ConfigDict(extra="forbid")

    fej: bool = Field(True, description="first-estimate Jacobians (keeps the 4-DoF unobservable subspace)")
    max_clones: int = Field(15, ge=2, description="sliding-window length (clones)")
    pixel_sigma: float = Field(1.0, gt=0, description="feature measurement noise [px]")
    chi2_quantile: float = Field(0.95, gt=0, lt=1, description="per-feature chi-squared gate")
    min_track_length: int = Field(3, ge=2, description="frames a track needs before it updates the MSCKF")
    max_features_per_update: int = Field(150, ge=1, description="longest tracks first")
    init_from_groundtruth: bool = Field(True, description="initial R, p, v (and biases) from ground truth")
    init_max_disparity_px: float | None = Field(
        5.0,
        gt=0,
        description="static initialisation: the rest ends before the first frame whose tracks moved more than this "
        "since the first one (median) [px] (OpenVINS' init_max_disparity); unset: the IMU alone decides",
    )
    sigma_theta0: float = Field(1e-3, gt=0, description="initial orientation sigma [rad]")
    sigma_p0: float = Field(1e-3, gt=0, description="initial position sigma [m]")
    sigma_v0: float = Field(1e-2, gt=0, description="initial velocity sigma [m/s]")
    sigma_bg0: float = Field(1e-3, gt=0, description="initial gyro bias sigma [rad/s]")
    sigma_ba0: float = Field(2e-2, gt=0, description="initial accelerometer bias sigma [m/s^2]")
    imu_noise_inflation: float = Field(1.0, gt=0, description="factor on the calibration's noise densities")
    imu_gap_warn_s: float = Field(0.05, gt=0, description="IMU gap counted as a warning")
    imu_gap_max_s: float = Field(1.0, gt=0, description="IMU gap that aborts (InputError)")
    max_propagation_s: float = Field(0.1, gt=0, description="longest single propagation step")
    min_depth: float = Field(0.2, gt=0, description="triangulated features nearer than this [m] are dropped")
    max_depth: float = Field(
        80.0, gt=0, description="triangulated features farther than this [m] are dropped"
    )
    triangulation_iterations: int = Field(
        5, ge=0, description="Gauss-Newton steps of the feature triangulation"
    )
    min_parallax_deg: float = Field(
        0.2, ge=0, description="RMS bearing spread a track needs to be used (below: depth is pixel noise)"
    )
    zupt: bool = Field(
        True, description="zero-velocity update when the IMU and the feature disparity say static"
    )
    zupt_imu: bool = Field(
        False,
        description="ZUPT also uses the IMU-at-rest residuals (w_m - b_g = 0, a_m - b_a + R^T g = 0) and holds "
        "the pose still instead of integrating the IMU (OpenVINS); off: IMU propagation and v = 0 only",
    )
    zupt_chi2_quantile: float = Field(0.99, gt=0, lt=1, description="IMU-at-rest and disparity tests")
    zupt_noise_inflation: float = Field(3.0, ge=1, description="factor on the IMU noise sigmas in the ZUPT")
    zupt_sigma_v: float = Field(0.01, gt=0, description="zero-velocity pseudo-measurement sigma [m/s]")
    zupt_max_velocity: float = Field(0.1, gt=0, description="no ZUPT while the estimated speed exceeds this")
    zupt_min_features: int = Field(10, ge=1, description="tracks needed for the disparity test")
    consistency_window_s: float = Field(
        2.0, gt=0, description="sliding window of the feature updates' chi2 rejection rate (warning)"
    )
    consistency_min_tracks: int = Field(20, ge=1, description="tracks a window needs to be judged")
    consistency_max_rejected: float = Field(
        0.5,
        gt=0,
        le=1,
        description="fraction of a window's tracks failing the chi2 gate above which the vio stage warns that "
        "the filter is inconsistent (consistent: 1 - chi2_quantile)",
    )
    on_failure: Literal["stop", "warn"] = Field(
        "stop",
        description="when a stage's VIO fails a health check (chi2 rejection rate, speed, position sigma, range "
        "NIS): stop the run with an error (exit 3, the failure in health.json and metrics.json), or warn and keep "
        "the estimate",
    )
    max_reinits: int = Field(
        3,
        ge=0,
        description="online recovery: times the MSCKF may re-initialise its window during the run when one of "
        "the health checks (chi2 rejection rate, speed, position sigma) fires over its trailing window: the IMU "
        "estimate is kept, the clones and SLAM features are dropped and the IMU covariance is inflated by the "
        "vio.reinit_sigma_* (0: no recovery; when the re-initialisations are used up, vio.on_failure applies)",
    )
    reinit_sigma_theta: float = Field(
        0.15,
        ge=0,
        description="re-initialisation: orientation sigma added to the IMU covariance [rad] (the orientation "
        "error of a diverged window is some degrees: a smaller one leaves the re-initialised filter overconfident)",
    )
    reinit_sigma_p: float = Field(
        0.3, ge=0, description="re-initialisation: position sigma added to the IMU covariance [m]"
    )
    reinit_sigma_v: float = Field(
        0.5, ge=0, description="re-initialisation: velocity sigma added to the IMU covariance [m/s]"
    )
    max_speed: float = Field(
        50.0, gt=0, description="health check: a faster estimated speed is a divergence [m/s]"
    )
    max_position_sigma: float = Field(
        10.0, gt=0, description="health check: a larger position sigma is a lost filter [m]"
    )
    health_speed_baseline_s: float = Field(
        0.5, gt=0, description="health check: the speed is measured over this much of the trajectory [s]"
    )
    max_range_nis: float = Field(
        100.0,
        gt=0,
        description="health check of the localisation stage: a larger median NIS of the UWB ranges of a window "
        "(against the frozen anchors; a consistent filter's is 0.45, the median of chi2(1)) is a diverged pose; "
        "100: half the ranges 10 sigma off",
    )
    range_nis_window_s: float = Field(
        5.0, gt=0, description="health check: the ranges' NIS is judged over trailing windows this long [s]"
    )
    range_nis_min_ranges: int = Field(
        30, ge=1, description="health check: ranges a window needs for its NIS to be judged"
    )
    max_slam_features: int = Field(
        0,
        ge=0,
        description="SLAM features (OpenVINS): a track still seen when it reaches the oldest clone becomes a "
        "landmark in the state, updated in every frame that sees it until it is lost; they hold the drift down "
        "while the same scene stays in view (0: MSCKF features only)",
    )
    slam_max_depth_sigma: float = Field(
        0.1,
        gt=0,
        description="a track becomes a SLAM feature only when its pixels fix the landmark's depth to this "
        "fraction of its distance (the landmark keeps the Jacobians of its first estimate)",
    )
    zupt_disparity_baseline_s: float = Field(
        0.3,
        ge=0,
        description="shortest time between the two frames of the disparity test: slow motion (a few cm/s) "
        "shows above the pixel noise only over some tenths of a second, not over one frame",
    )


class FrontendConfig(BaseModel):
    model_config = ConfigDict(extra="forbid")

    tracker: Literal["auto", "klt", "descriptor"] = Field(
        "auto",
        description="klt: pyramidal Lucas-Kanade (fast cameras); descriptor: FAST corners + ORB descriptors matched "
        "around the gyro-predicted position (low frame rates, fast turns); auto: descriptor when the camera is "
        "slower than descriptor_below_hz or too few KLT tracks survive between sampled frames (klt_min_survival)",
    )
    descriptor_below_hz: float = Field(
        10.0, gt=0, description="auto: descriptor tracking for cameras slower than this [Hz]"
    )
    klt_min_survival: float = Field(
        0.6,
        gt=0,
        le=1,
        description="auto: descriptor tracking when the lower quartile of the KLT track survival between "
        "consecutive frames (sampled over the recording) is below this fraction",
    )
    match_radius_px: float = Field(
        40.0, gt=0, description="descriptor: search radius around the rotation-predicted position [px]"
    )
    match_max_hamming: int = Field(
        60, gt=0, le=256, description="descriptor: largest Hamming distance of a match (ORB, 256 bits)"
    )
    match_ratio: float = Field(
        0.8,
        gt=0,
        le=1,
        description="descriptor: best match below this fraction of the second best (ratio test)",
    )
    fast_threshold: int = Field(15, gt=0, description="descriptor: FAST corner threshold (intensity levels)")

    max_features: int = Field(200, gt=0, description="target number of live tracks per frame")
    grid_cols: int = Field(
        8, gt=0, description="columns of the detection grid (features spread over the image)"
    )
    grid_rows: int = Field(5, gt=0, description="rows of the detection grid")
    min_distance_px: float = Field(12.0, ge=0, description="minimum distance of a new corner to any track")
    quality_level: float = Field(0.005, gt=0, lt=1, description="Shi-Tomasi quality relative to the best")
    border_px: int = Field(8, ge=0, description="no detections or tracks this close to the image border")
    equalize: bool = Field(True, description="CLAHE histogram equalisation before tracking")
    klt_window: int = Field(21, ge=5, description="KLT search window [px]")
    klt_levels: int = Field(3, ge=0, description="KLT pyramid levels")
    klt_iterations: int = Field(30, gt=0, description="KLT iterations per level")
    fb_threshold_px: float = Field(1.0, gt=0, description="forward-backward KLT consistency")
    ransac: bool = Field(
        True, description="reject tracks against the fundamental matrix of consecutive frames"
    )
    ransac_method: Literal["magsac", "usac", "ransac"] = Field(
        "magsac", description="OpenCV robust estimator"
    )
    ransac_threshold_px: float = Field(1.0, gt=0, description="epipolar distance threshold (undistorted px)")
    ransac_confidence: float = Field(0.999, gt=0, lt=1, description="RANSAC confidence")
    stereo: bool = Field(False, description="match cam0 features into cam1 (KLT + epipolar check)")
    stereo_epipolar_px: float = Field(
        2.0, gt=0, description="stereo matches farther from the epipolar line are dropped [px]"
    )
    log_every: int = Field(10, ge=1, description="log every n-th image and its tracks to rerun")
