"""What every stage is given: the config, the run directory, the recording, and the helpers stages share.

A stage reads the recording and the artefacts of the stages before it (never in-memory state), writes its own
artefacts atomically (`rundir`) and its own rerun log; the context only resolves what all stages agree on
(windows, pose source, the estimator, the reader the estimator consumes).
"""

from __future__ import annotations

import logging
import uuid
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from uwbcal.convert.recording import MergedReader, RecordingReader
from uwbcal.pipeline.core.errors import InputError
from uwbcal.pipeline.core.geometry import quat_to_rot
from uwbcal.pipeline.core.names import STAGE_NUMBER
from uwbcal.pipeline.core.topics import (
    TOPIC_CAM0,
    TOPIC_FEATURES,
    TOPIC_GT_POSE,
    TOPIC_GT_POSITION,
    TOPIC_IMU,
    TOPIC_ODOM,
    TOPIC_RANGE,
)
from uwbcal.pipeline.run import rundir as rd
from uwbcal.pipeline.run.config import PipelineConfig
from uwbcal.pipeline.run.real_imu import apply_real_imu_defaults
from uwbcal.pipeline.run.windows import Windows, split_windows
from uwbcal.pipeline.uwb.planar_levers import choose_lever_arms
from uwbcal.pipeline.uwb.schedule import choose_schedule
from uwbcal.pipeline.uwb.updater import auto_init_method, lever_arms
from uwbcal.pipeline.vio.estimator import Estimator
from uwbcal.pipeline.vio.msckf import MsckfEstimator
from uwbcal.pipeline.vio.odometry_filter import (
    OdometryEstimator,
    apply_calibration_noise,
    resolve_error_model,
)
from uwbcal.pipeline.vio.static_init import static_init_from_recording
from uwbcal.pipeline.viz import runlog as rl

_log = logging.getLogger(__name__)

# the evaluation (a layer above the stages) handed to the evaluate stage: (run dir, align, open the stage's
# rerun log) -> the results text
Evaluator = Callable[[Path, str | None, Callable[[], "rl.RunLog"]], str]


@dataclass
class StageResult:
    stage: str
    summary: str
    warnings: list[str] = field(default_factory=list)
    wall_s: float = 0.0


def filter_warnings(
    ctx: StageContext, stage: str, est: Estimator, updater, start_ns: int, end_ns: int, log=None
) -> list[str]:
    """What the filters of a UWB stage (refine, localize) say about their own consistency over the stretch the
    stage ran, ``[start_ns, end_ns)``: the pose source's (the MSCKF's visual chi2 rejections), the range
    updates' overall gate rate against a consistent filter's (`uwb_filter.UwbUpdater.gate_excess_warning`) and their
    windowed gate rate (`uwb_filter.UwbUpdater.gate_warnings`); times in s after the run's start. Each is also
    logged to the stage's rerun log (``log``) at ``end_ns``."""
    cfg, t0 = ctx.config.uwb, ctx.windows().start_ns
    warns = (
        est.span_warnings(stage, start_ns, end_ns, t0)
        + updater.gate_excess_warning(stage)
        + updater.gate_warnings(
            stage, cfg.gate_window_s, cfg.gate_min_ranges, cfg.gate_max_rejected, cfg.chi2_quantile, t0
        )
    )
    if log is not None:
        for w in warns:
            log.text(w, "WARN", end_ns)
    return warns


class StageContext:
    def __init__(self, config: PipelineConfig, run_dir: Path, evaluator: Evaluator | None = None) -> None:
        self.config = config
        self.dir = rd.RunDir(run_dir)
        self.recording = Path(config.run.recording)
        self.evaluator = evaluator
        self.stages = list(config.run.stages)  # this invocation's stages (Pipeline.run narrows it)
        self.results_text = ""
        self._reader: RecordingReader | None = None
        self.log_server = None  # rerun logging helper process while Pipeline.run runs (runlog_async)

    @property
    def reader(self) -> RecordingReader:
        if self._reader is None:
            self._reader = RecordingReader(self.recording)
        return self._reader

    def run_kind(self) -> str:
        ds = str(self.reader.source.get("dataset", "simulation")).lower()
        return "ntu-viral" if "ntu" in ds else ("euroc" if "euroc" in ds else "simulation")

    def recording_id(self) -> str:
        p = self.dir.file("recording_id.txt")
        if not p.exists():
            rd.write_text(p, uuid.uuid4().hex)
        return p.read_text().strip()

    def runlog(self, stage: str) -> rl.RunLog:
        path = self.dir.stage_rrd(STAGE_NUMBER[stage], stage) if self.config.run.log else None
        kw = dict(
            recording_id=self.recording_id(),
            run_kind=self.run_kind(),
            blueprint=False,
            time_origin_ns=self.time_origin(),
        )
        if path is not None and self.log_server is not None:  # the log's calls go to the helper process
            return self.log_server.open(path, **kw)  # type: ignore[return-value]  (same methods as RunLog)
        return rl.RunLog(path, enabled=self.config.run.log, **kw)

    def time_origin(self) -> int | None:
        """Simulated recordings: the replay's time axis in seconds from the recording's start (same origin for every
        stage and every run of the recording); real data (a surveyed anchor truth included): its own stamps."""
        truth = self.reader.truth
        simulated = truth is not None and truth.get("kind", "simulated") == "simulated"
        return self.reader.time_span()[0] if simulated else None

    def windows(self) -> Windows:
        topics = self.reader.topics()
        if TOPIC_RANGE not in topics:
            raise InputError(f"{self.recording}: no '{TOPIC_RANGE}' topic; UWB calibration needs ranges")
        src = [t for t in (TOPIC_IMU, TOPIC_ODOM) if t in topics]
        if not src:
            raise InputError(f"{self.recording}: neither '{TOPIC_IMU}' nor '{TOPIC_ODOM}'; no pose source")
        start = max(topics[TOPIC_RANGE].start_ns, min(topics[t].start_ns for t in src))
        end = min(topics[TOPIC_RANGE].end_ns, max(topics[t].end_ns for t in src))
        return split_windows(
            start, end, self.config.run.init_window_s, self.config.run.refine_window_s, str(self.recording)
        )

    def resolve_auto(self) -> None:
        """Recording-aware defaults, resolved before the config is written (so config.toml states them).

        - ``uwb.init_method = "auto"``: ri-robust on real recordings, ri on simulated ones;
        - odometry pose source: drift sigmas the recording declares (calibration ``odometry.noise``, e.g. the
          simulator's odometry) for those the config does not set;
        - MSCKF on a real IMU: the real-IMU vio defaults (`pipeline.real_imu`) for the settings not given;
        - windows, when not given and the poses come from an odometry with a *bounded* error (a SLAM output in
          the world frame, calibration ``odometry.error_model = "bounded"``, e.g. NTU-VIRAL SLICT): the thirds
          of the paper exist so that a drifting VIO is calibrated before it drifts; a bounded pose source does
          not drift, and the anchors need most of the flight to be observed. Default: init over the first 2/3,
          refine over the rest, no localisation segment.
        """

        uwb = self.config.uwb
        if uwb.init_method == "auto":
            uwb.init_method = auto_init_method(self.reader.source.get("dataset"))  # type: ignore[assignment]
        run = self.config.run
        odometry = self.pose_source() == "odometry"
        if odometry:
            apply_calibration_noise(self.config.odometry, self.reader.calibration)
        else:  # a real IMU: static initialisation and the real-IMU noise model (pipeline/run/real_imu.py)
            for k, v in apply_real_imu_defaults(self.config.vio, self.reader.source).items():
                _log.info("vio.%s = %s (real-IMU default, pipeline/run/real_imu.py)", k, v)
        if uwb.lever_arms == "auto":
            uwb.lever_arms, why = self.choose_lever_arms()  # type: ignore[assignment]
            _log.info("uwb.lever_arms = %s: %s", uwb.lever_arms, why)
        if run.schedule == "auto":
            rng = self.reader.read_ranges()
            init_end = self.windows().init_end_ns
            run.schedule, why = choose_schedule(  # type: ignore[assignment]
                rng.t_ns, rng.anchor, init_end, min_ranges=max(uwb.min_ranges, 30)
            )
            if run.schedule == "windows" and odometry and uwb.search:
                model, _ = resolve_error_model(self.config.odometry, self.reader.calibration)
                if model == "bounded":
                    # poses in the anchors' frame that do not drift (ground truth, SLAM with a map): the thirds
                    # guard against drift that is not there; every anchor joins when its own ranges pin it
                    # down and is refined to the end of the data
                    run.schedule = "per-anchor"  # type: ignore[assignment]
                    why = "bounded pose source: anchors refined to the end of the data"
            _log.info("run.schedule = %s: %s", run.schedule, why)
        if run.schedule == "per-anchor" and run.refine_window_s is None:
            # late anchors are refined from their own join time: refinement runs to the end
            win = self.windows()
            run.refine_window_s = round((win.end_ns - win.init_end_ns) * 1e-9 + 1.0, 3)
            if run.vio_extent == "auto":
                run.vio_extent = "full"  # the late anchors' init windows need the poses up to their join
        # (with the search the per-anchor schedule does this per anchor, from the data)
        if run.init_window_s is None and run.refine_window_s is None and odometry and not uwb.search:
            model, _ = resolve_error_model(self.config.odometry, self.reader.calibration)
            if model == "bounded":
                win = self.windows()
                span = (win.end_ns - win.start_ns) * 1e-9
                run.init_window_s = round(span * 2.0 / 3.0, 3)
                # refine to the end: the 1 s margin absorbs the rounding (split_windows clamps at the end)
                run.refine_window_s = round(span - run.init_window_s + 1.0, 3)

    def choose_lever_arms(self) -> tuple[str, str]:
        """``uwb.lever_arms = "auto"`` (`planar_levers.choose_lever_arms`) from the odometry poses the UWB stages
        use, when they come from an external system in the anchors' frame (error model bounded: motion capture,
        SLAM with a map), whose body frame need not be the one the arms were measured in. A VIO or a drifting
        odometry is the robot's own (the arms are given in its frame) and keeps the calibration's arms."""

        if self.pose_source() != "odometry":
            return "given", "VIO poses: the calibration's lever arms are in its IMU frame"
        model, _ = resolve_error_model(self.config.odometry, self.reader.calibration)
        if model != "bounded":
            return "given", f"{model} odometry: the robot's own frame, the calibration's lever arms"
        odo = self.reader.read_poses(TOPIC_ODOM)
        step = max(1, len(odo.t_ns) // 20000)
        n_ant = len(lever_arms(self.reader.calibration))
        return choose_lever_arms(quat_to_rot(odo.q_xyzw[::step]), odo.p[::step], n_ant)

    def pose_source(self) -> str:
        choice = self.config.run.pose_source
        if choice != "auto":
            return choice
        topics = self.reader.topics()
        has_vi = TOPIC_IMU in topics and (TOPIC_FEATURES in topics or TOPIC_CAM0 in topics)
        return "msckf" if has_vi else "odometry"

    def loose(self) -> bool:
        """UWB stages on the VIO output instead of inside the MSCKF (``run.coupling = "loose"``)."""
        return self.config.run.coupling == "loose" and self.pose_source() == "msckf"

    def features_reader(self) -> RecordingReader:
        """The reader the estimator consumes: the recording, with the frontend's tracks and (loose coupling) the
        VIO output merged into it."""
        extra = [
            n for n in ("frontend.mcap",) + (("vio.mcap",) if self.loose() else ()) if self.dir.exists(n)
        ]
        if extra:
            return MergedReader(self.reader, *(RecordingReader(self.dir.file(n)) for n in extra))
        return self.reader

    def make_estimator(self) -> Estimator:
        if self.pose_source() == "msckf":
            initial = cov = None
            if not self.config.vio.init_from_groundtruth:  # real data without usable ground truth
                res = static_init_from_recording(self.reader, start_ns=self.windows().start_ns)
                _log.info("vio: static initialisation: %s", res)
                # the world frame is the initialiser's (gravity-aligned, yaw 0, origin at the start): the
                # evaluator aligns position and yaw when it finds this
                self.dir.save_json("static_init.json", res.summary())
                initial, cov = res.state, res.P
            return MsckfEstimator.from_recording(self.features_reader(), self.config.vio, initial, cov)

        return OdometryEstimator.from_recording(self.reader, self.config.odometry)

    def assemble_trajectory(self) -> dict[str, np.ndarray]:
        return rd.assemble_trajectory(self.dir, self.windows())

    def anchor_errors(self, est: dict) -> str:
        truth = (self.reader.truth or {}).get("anchors")
        if not truth or self.dir.exists("static_init.json"):  # own frame: the evaluator aligns, not here
            return ""
        errs = [
            np.linalg.norm(np.asarray(x)[:3] - np.asarray(truth[str(a)]["position"]))
            for a, x in est.items()
            if str(a) in truth
        ]
        return f"; mean anchor error {np.mean(errs):.3f} m" if errs else ""

    # -- rerun logging shared by stages ----------------------------------------------------------------------------
    def log_groundtruth(self, log: rl.RunLog) -> None:
        if not log.enabled:
            return
        topics = self.reader.topics()
        if TOPIC_GT_POSE in topics:
            gt = self.reader.read_poses(TOPIC_GT_POSE)
            step = max(1, len(gt.t_ns) // 4000)
            log.trajectory(rl.GT, gt.t_ns[::step], gt.p[::step], gt.q_xyzw[::step])
        elif TOPIC_GT_POSITION in topics:
            gt = self.reader.read_positions(TOPIC_GT_POSITION)
            log.trajectory(rl.GT, gt.t_ns, gt.p)
        self.log_truth_anchors(log)

    def log_truth_anchors(self, log: rl.RunLog) -> None:
        truth = (self.reader.truth or {}).get("anchors") or {}
        for a, t in truth.items():
            log.points3d(
                rl.anchor_world(a, "truth"),
                np.asarray(t["position"])[None],
                labels=[str(a)],
                radii=[0.05],
                static=True,
            )

    def log_trajectory(self, log: rl.RunLog, what: str, hist: dict[str, np.ndarray]) -> None:
        if not log.enabled or not len(hist.get("t_ns", [])):
            return
        entity = rl.VIO if what == "vio" else f"{rl.WORLD}/{what}"
        log.trajectory(entity, hist["t_ns"], hist["p"], hist["q_xyzw"])
        step = max(1, len(hist["t_ns"]) // 200)
        log.ellipsoid_series(
            f"{entity}/cov", hist["t_ns"][::step], hist["p"][::step], hist["cov"][::step, 3:6, 3:6]
        )
        log.scalars(
            f"{rl.SIGMA}/{what}_position",
            hist["t_ns"],
            np.sqrt(np.maximum(np.trace(hist["cov"][:, 3:6, 3:6], axis1=1, axis2=2), 0.0)),
        )
