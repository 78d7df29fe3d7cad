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
from uwbcal.pipeline.core.errors import EstimateFailed
from uwbcal.pipeline.core.names import STAGE_NUMBER
from uwbcal.pipeline.core.topics import (
    TOPIC_GT_POSE,
    TOPIC_GT_POSITION,
)
from uwbcal.pipeline.run import artefacts
from uwbcal.pipeline.run import rundir as rd
from uwbcal.pipeline.run.config import PipelineConfig
from uwbcal.pipeline.run.driver import msckf_from_recording, odometry_from_recording
from uwbcal.pipeline.run.windows import Windows, recording_windows
from uwbcal.pipeline.vio.estimator import Estimator
from uwbcal.pipeline.vio.health import Failure, assess
from uwbcal.pipeline.vio.odometry_filter import resolve_error_model
from uwbcal.pipeline.vio.static_init import StaticInitConfig, static_init_from_recording
from uwbcal.pipeline.vio.stats import VioStats
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
    stage ran, ``[start_ns, end_ns)``: the pose source's health (with anchors frozen, localisation, also judged
    by the NIS of its range updates), the range
    updates' overall gate rate against a consistent filter's (`uwb_filter.UwbUpdater.gate_excess_warning`) and their
    windowed gate rate (`uwb_filter.UwbUpdater.gate_warnings`); times in s after the run's start. Each is also
    logged to the stage's rerun log (``log``) at ``end_ns``."""
    cfg, t0 = ctx.config.uwb, ctx.windows().start_ns
    warns = (
        ctx.check_health(
            stage, est, start_ns, end_ns, updater.range_nis() if updater.mode == "frozen" else None
        )
        + updater.gate_excess_warning(stage)
        + updater.gate_warnings(
            stage, cfg.gate_window_s, cfg.gate_min_ranges, cfg.gate_max_rejected, cfg.chi2_quantile, t0
        )
    )
    if log is not None:
        for w in warns:
            log.text(w, "WARN", end_ns)
    return warns


def _reinit_note(stage: str, f: Failure, t0_ns: int) -> str:
    return (
        f"{stage}: the VIO window was re-initialised at {(f.t_ns - t0_ns) * 1e-9:.1f} s after the start "
        f"({f.check} check: {f.value:.3g} > {f.key} = {f.threshold:g}; at most vio.max_reinits)"
    )


class StageContext:
    def __init__(self, config: PipelineConfig, run_dir: Path, evaluator: Evaluator | None = None) -> None:
        self.config = config
        self.dir = rd.RunDir(run_dir)
        self.recording = Path(config.run.recording)
        self.evaluator = evaluator
        self.stages = list(config.run.stages)  # this invocation's stages (Pipeline.run narrows it)
        self.results_text = ""
        self.choices: list[dict] = []  # the recording-aware defaults resolved for this run (run.resolve)
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
        if not artefacts.present(p):
            rd.write_text(p, uuid.uuid4().hex)
        return artefacts.read_log_id(p)

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

    def check_health(
        self,
        stage: str,
        est: Estimator,
        start_ns: int | None,
        end_ns: int | None,
        ranges: tuple[np.ndarray, np.ndarray] | None = None,
    ) -> list[str]:
        """The pose source's health over the stretch ``stage`` filtered (`health.assess`; ``ranges``: the
        stamps and NIS of its range updates against frozen anchors), kept in health.json.
        A failure stops the run (`EstimateFailed`; metrics.json records it) or, with ``vio.on_failure = "warn"``,
        is a warning."""
        cfg = self.config.vio
        stats = getattr(est, "stats", None)
        reinits = [
            f
            for f in getattr(est, "reinits", [])
            if (start_ns is None or f.t_ns >= start_ns) and (end_ns is None or f.t_ns < end_ns)
        ]
        # after the last re-initialisation: its stamp's pose and update were judged online (they fired)
        online_from = reinits[-1].t_ns + 1 if reinits else None
        rejection = None
        if isinstance(stats, VioStats):
            rejection = stats.rejection_rate(
                cfg.consistency_window_s,
                cfg.consistency_min_tracks,
                start_ns if online_from is None else online_from,
                end_ns,
            )
        fail = assess(est.history().arrays(), cfg, rejection, start_ns, end_ns, ranges, online_from)
        t0 = self.windows().start_ns
        record = (
            dict(self.dir.load_json("health.json", stage, artefacts.HEALTH))
            if self.dir.exists("health.json")
            else {}
        )
        record[stage] = {"failed": False} if fail is None else fail.summary(stage, t0)
        if reinits:
            record[stage]["reinits"] = [f.record(t0) for f in reinits]
        self.dir.save_json("health.json", record)
        notes = [_reinit_note(stage, f, t0) for f in reinits]
        if fail is None:
            return notes
        if cfg.on_failure == "warn":
            return notes + [fail.message(stage, t0)]
        self.dir.save_json("metrics.json", {"vio_failure": record[stage]})
        raise EstimateFailed(fail.message(stage, t0))

    def windows(self) -> Windows:
        run = self.config.run
        return recording_windows(self.reader, run.init_window_s, run.refine_window_s)

    def bounded_poses(self) -> bool:
        """The pose source is an external one of bounded error (motion capture, RTK-GNSS, a SLAM with a map)."""
        return self.pose_source() == "odometry" and self.config.odometry.error_model == "bounded"

    def pose_correlation_s(self) -> float | None:
        """The correlation time of the pose source's errors when they are bounded (None: they drift)."""
        return (
            resolve_error_model(self.config.odometry, self.reader.calibration)[1]
            if self.bounded_poses()
            else None
        )

    def apply_range_clock(self) -> None:
        """Re-stamp the ranges read from now on by the clock offset the init stage used (init.json)."""
        if self.dir.exists("init.json"):
            clock = artefacts.read_json(self.dir.file("init.json"), artefacts.INIT).get("range_clock") or {}
            self.reader.range_shift_ns = (
                round(float(clock.get("offset_s", 0.0)) * 1e9) if clock.get("used") else 0
            )

    def pose_source(self) -> str:
        """The resolved ``run.pose_source`` (`resolve`)."""
        choice = self.config.run.pose_source
        assert choice != "auto", "resolve the config before the stages run"
        return choice

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
                sc = StaticInitConfig(max_disparity_px=self.config.vio.init_max_disparity_px)
                res = static_init_from_recording(self.features_reader(), sc, self.windows().start_ns)
                _log.info("vio: static initialisation: %s", res)
                # the world frame is the initialiser's (gravity-aligned, yaw 0, origin at the start): the
                # evaluator aligns position and yaw when it finds this
                self.dir.save_json("static_init.json", res.summary())
                initial, cov = res.state, res.P
            return msckf_from_recording(self.features_reader(), self.config.vio, initial, cov)

        return odometry_from_recording(self.reader, self.config.odometry)

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
