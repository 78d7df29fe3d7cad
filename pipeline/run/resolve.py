"""Recording-aware defaults: ``resolve(config, reader) -> ResolvedConfig``, every ``"auto"`` key decided once.

The input config is never changed: the resolved one is a copy, and each decision is a `Choice` (key, value,
reason) that the run directory keeps (``resolved.json``) beside the config that reproduces the run
(``config.toml``). A key the user set is never changed. The rules, in order:

- ``run.pose_source``: the MSCKF when the recording has an IMU and camera (images or tracks), else the
  odometry filter;
- ``frontend.tracker``: descriptor tracking for slow cameras or poor KLT survival (`choose_tracker`), when the
  recording has images and no tracks;
- ``uwb.init_method``: ri-robust on real recordings (NLOS ranges are the rule), the paper's ri on simulated;
- odometry pose source: ``odometry.error_model`` and the drift sigmas the recording's calibration declares;
- MSCKF on a real IMU: `REAL_IMU_DEFAULTS` for the vio keys not set, the IMU noise inflation from the
  calibration's ``imu.noise_origin`` (`imu_noise_inflation`);
- ``uwb.lever_arms``: planar lever arms when an external, bounded pose source carries several antennas in a
  plane (`planar_levers.choose_lever_arms`), else the calibration's;
- ``run.schedule``: per anchor when an anchor is ranged mostly after the first window, or the poses have a
  bounded error (the thirds of the paper guard against a drift that is not there), else the paper's windows;
- windows of a bounded pose source without the search: init over the first 2/3, refine over the rest.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from uwbcal.convert.recording import RecordingReader
from uwbcal.pipeline.core.geometry import quat_to_rot
from uwbcal.pipeline.core.noise import NOISE_KEYS
from uwbcal.pipeline.core.topics import TOPIC_CAM0, TOPIC_FEATURES, TOPIC_IMU, TOPIC_ODOM
from uwbcal.pipeline.run.config import PipelineConfig
from uwbcal.pipeline.run.windows import Windows, recording_windows
from uwbcal.pipeline.uwb.planar_levers import choose_lever_arms
from uwbcal.pipeline.uwb.schedule import choose_schedule
from uwbcal.pipeline.uwb.updater import auto_init_method, lever_arms
from uwbcal.pipeline.vio.frontend import choose_tracker
from uwbcal.pipeline.vio.odometry_filter import declared_noise, resolve_error_model

# VIO defaults for a *real* IMU (its recording's source is not the simulator, or a hybrid lists /imu as real):
# - init_from_groundtruth = false: the static initialiser starts the filter, as for a user without ground truth
#   (world frame gravity-aligned, yaw 0, origin at the start; the evaluator aligns position and yaw);
# - max_clones = 30: a real camera's tracks need the parallax of a long window;
# - max_slam_features = 25 (OpenVINS' EuRoC setting): landmarks in the state hold the drift while in view.
# The IMU noise inflation is `imu_noise_inflation`'s: the calibration's values as given unless they are declared a
# static Allan-variance figure.
REAL_IMU_DEFAULTS: dict[str, object] = {
    "init_from_groundtruth": False,
    "max_clones": 30,
    "max_slam_features": 25,
}
# a static Allan-variance / datasheet figure leaves out vibration, scale-factor and axis-misalignment errors in
# motion (docs/results/measurements.md: EuRoC V1_01's residual densities are 5-10x its sensor.yaml's)
ALLAN_NOISE_INFLATION = 5.0


def imu_noise_inflation(calibration: dict | None) -> tuple[float, str]:
    """The factor on a real IMU's declared noise, and why (``imu.noise_origin`` of the calibration)."""
    origin = ((calibration or {}).get("imu") or {}).get("noise_origin")
    if origin == "allan":
        return (
            ALLAN_NOISE_INFLATION,
            "real IMU, calibration noise is a static Allan-variance figure (imu.noise_origin)",
        )
    return 1.0, f"real IMU, the calibration's noise values as given (imu.noise_origin {origin or 'unset'})"


@dataclass(frozen=True)
class Choice:
    key: str  # "section.key"
    value: Any
    reason: str

    def __str__(self) -> str:
        return f"{self.key} = {self.value!r}: {self.reason}"


@dataclass(frozen=True)
class ResolvedConfig:
    config: PipelineConfig  # no "auto" left among the keys resolved here
    choices: tuple[Choice, ...] = field(default_factory=tuple)

    def summary(self) -> list[dict]:
        return [{"key": c.key, "value": c.value, "reason": c.reason} for c in self.choices]


def imu_is_real(source: dict | None) -> bool:
    """Whether the recording's /imu is a real sensor's (not the simulator's)."""
    source = source or {}
    if "real" in source:
        return "/imu" in (source.get("real") or [])
    return str(source.get("dataset") or "simulation").lower() != "simulation"


class _Builder:
    """The copy being resolved and the choices made on it."""

    def __init__(self, config: PipelineConfig) -> None:
        self.config = config.model_copy(deep=True)
        self.choices: list[Choice] = []

    def set(self, key: str, value: Any, reason: str) -> None:
        section, name = key.split(".")
        setattr(getattr(self.config, section), name, value)
        self.choices.append(Choice(key, value, reason))

    def unset(self, key: str) -> bool:
        section, name = key.split(".")
        return name not in getattr(self.config, section).model_fields_set


def resolve(config: PipelineConfig, reader: RecordingReader) -> ResolvedConfig:
    """Every recording-aware default of ``config`` for ``reader``'s recording (the module docstring's rules)."""
    b = _Builder(config)
    _pose_source(b, reader)
    _tracker(b, reader)
    if b.config.uwb.init_method == "auto":
        m = auto_init_method(reader.source.get("dataset"))
        b.set("uwb.init_method", m, "simulated recording" if m == "ri" else "real recording: NLOS ranges")
    if b.config.run.pose_source == "odometry":
        _odometry(b, reader)
    elif imu_is_real(reader.source):
        for k, v in REAL_IMU_DEFAULTS.items():
            if b.unset(f"vio.{k}"):
                b.set(f"vio.{k}", v, "real-IMU default")
        if b.unset("vio.imu_noise_inflation"):
            b.set("vio.imu_noise_inflation", *imu_noise_inflation(reader.calibration))
    if b.config.uwb.lever_arms == "auto":
        b.set("uwb.lever_arms", *_lever_arms(b.config, reader))
    if b.config.run.schedule == "auto":
        _schedule(b, reader)
    _per_anchor_windows(b, reader)
    _bounded_windows(b, reader)
    return ResolvedConfig(b.config, tuple(b.choices))


def _pose_source(b: _Builder, reader: RecordingReader) -> None:
    if b.config.run.pose_source != "auto":
        return
    topics = reader.topics()
    if TOPIC_IMU in topics and (TOPIC_FEATURES in topics or TOPIC_CAM0 in topics):
        b.set("run.pose_source", "msckf", "IMU and camera in the recording")
    else:
        b.set("run.pose_source", "odometry", "no IMU + camera: the odometry filter on /odometry")


def _tracker(b: _Builder, reader: RecordingReader) -> None:
    topics = reader.topics()
    if b.config.frontend.tracker == "auto" and TOPIC_CAM0 in topics and TOPIC_FEATURES not in topics:
        b.set("frontend.tracker", *choose_tracker(reader, b.config.frontend))


def _odometry(b: _Builder, reader: RecordingReader) -> None:
    if b.config.odometry.error_model == "auto":
        model, _ = resolve_error_model(b.config.odometry, reader.calibration)
        b.set("odometry.error_model", model, "the recording's calibration (odometry.error_model), else drift")
    for k, v in declared_noise(reader.calibration).items():
        if k in NOISE_KEYS and b.unset(f"odometry.{k}"):
            b.set(f"odometry.{k}", v, "declared by the recording's calibration (odometry.noise)")


def _bounded(b: _Builder) -> bool:
    return b.config.run.pose_source == "odometry" and b.config.odometry.error_model == "bounded"


def _lever_arms(config: PipelineConfig, reader: RecordingReader) -> tuple[str, str]:
    """Planar lever arms only from poses of an external system in the anchors' frame (error model bounded:
    motion capture, SLAM with a map), whose body frame need not be the one the arms were measured in."""
    if config.run.pose_source != "odometry":
        return "given", "VIO poses: the calibration's lever arms are in its IMU frame"
    if config.odometry.error_model != "bounded":
        return (
            "given",
            f"{config.odometry.error_model} odometry: the robot's own frame, the calibration's arms",
        )
    odo = reader.read_poses(TOPIC_ODOM)
    step = max(1, len(odo.t_ns) // 20000)
    n_ant = len(lever_arms(reader.calibration))
    return choose_lever_arms(quat_to_rot(odo.q_xyzw[::step]), odo.p[::step], n_ant)


def _windows(b: _Builder, reader: RecordingReader) -> Windows:
    run = b.config.run
    return recording_windows(reader, run.init_window_s, run.refine_window_s)


def _schedule(b: _Builder, reader: RecordingReader) -> None:
    rng = reader.read_ranges()
    init_end = _windows(b, reader).init_end_ns
    schedule, why = choose_schedule(
        rng.t_ns, rng.anchor, init_end, min_ranges=max(b.config.uwb.min_ranges, 30)
    )
    if schedule == "windows" and _bounded(b) and b.config.uwb.search:
        schedule, why = "per-anchor", "bounded pose source: anchors refined to the end of the data"
    b.set("run.schedule", schedule, why)


def _per_anchor_windows(b: _Builder, reader: RecordingReader) -> None:
    if b.config.run.schedule == "per-anchor" and b.config.run.refine_window_s is None:
        win = _windows(b, reader)
        span = round((win.end_ns - win.init_end_ns) * 1e-9 + 1.0, 3)
        b.set("run.refine_window_s", span, "per-anchor schedule: late anchors are refined to the end")
        if b.config.run.vio_extent == "auto":
            b.set("run.vio_extent", "full", "per-anchor schedule: late anchors need the poses to the end")


def _bounded_windows(b: _Builder, reader: RecordingReader) -> None:
    run = b.config.run
    if run.init_window_s is not None or run.refine_window_s is not None or b.config.uwb.search:
        return
    if not _bounded(b):
        return
    win = _windows(b, reader)
    span = (win.end_ns - win.start_ns) * 1e-9
    init = round(span * 2.0 / 3.0, 3)
    b.set("run.init_window_s", init, "bounded pose source: the anchors need most of the data")
    # refine to the end: the 1 s margin absorbs the rounding (split_windows clamps at the end)
    b.set("run.refine_window_s", round(span - init + 1.0, 3), "bounded pose source: refine over the rest")
