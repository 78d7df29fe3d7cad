"""The staged pipeline (DESIGN §4): frontend -> vio -> init -> refine -> localize -> evaluate.

`Pipeline` owns one run directory. Every stage reads the recording and the artefacts of the stage before
(never in-memory state), writes its own artefacts atomically and its own rerun log; a failing stage leaves the
earlier artefacts untouched, and each stage can be re-run alone.
"""

from __future__ import annotations

import csv
import io
import logging
import time
import uuid
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from convert.errors import InputError
from convert.recording import (
    TOPIC_CAM0,
    TOPIC_FEATURES,
    TOPIC_IMU,
    TOPIC_ODOM,
    TOPIC_RANGE,
    TOPIC_VIO,
    MergedReader,
    RecordingReader,
    RecordingWriter,
)

from . import rundir as rd
from . import runlog as rl
from .config import STAGES, PipelineConfig, load_config
from .windows import Windows, split_windows

_log = logging.getLogger(__name__)

STAGE_ORDER = {name: i + 1 for i, name in enumerate(STAGES)}


@dataclass
class StageResult:
    stage: str
    wall_s: float
    summary: str
    warnings: list[str] = field(default_factory=list)


class Pipeline:
    def __init__(self, config: PipelineConfig, run_dir: Path) -> None:
        self.config = config
        self.dir = rd.RunDir(run_dir)
        self.recording = Path(config.run.recording)
        self._reader: RecordingReader | None = None
        self._stages = list(config.run.stages)  # this invocation's stages (run() narrows it)
        self._log_server = None  # rerun logging helper process during run() (runlog_async)

    # -- shared helpers ----------------------------------------------------------------------------------------
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

    def runlog(self, stage: str):
        from .runlog import RunLog

        path = self.dir.stage_rrd(STAGE_ORDER[stage], stage) if self.config.run.log else None
        if path is not None and self._log_server is not None:
            return self._log_server.open(
                path, recording_id=self.recording_id(), run_kind=self.run_kind(), blueprint=False
            )
        return RunLog(
            path,
            recording_id=self.recording_id(),
            run_kind=self.run_kind(),
            enabled=self.config.run.log,
            blueprint=False,
        )

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
        - windows, when not given and the poses come from an odometry with a *bounded* error (a SLAM output in
          the world frame, calibration ``odometry.error_model = "bounded"``, e.g. NTU-VIRAL SLICT): the thirds
          of the paper exist so that a drifting VIO is calibrated before it drifts; a bounded pose source does
          not drift, and the anchors need most of the flight to be observed (NTU-VIRAL: the first third leaves
          them 0.2-0.8 m off, the first two thirds within ~0.2 m). Default: init over the first 2/3, refine over
          the rest, no localisation segment.
        """
        from .odometry_filter import apply_calibration_noise, resolve_error_model
        from .uwb_filter import auto_init_method

        uwb = self.config.uwb
        if uwb.init_method == "auto":
            uwb.init_method = auto_init_method(self.reader.source.get("dataset"))  # type: ignore[assignment]
        run = self.config.run
        odometry = self.pose_source() == "odometry"
        if odometry:
            apply_calibration_noise(self.config.odometry, self.reader.calibration)
        if run.init_window_s is None and run.refine_window_s is None and odometry:
            model, _ = resolve_error_model(self.config.odometry, self.reader.calibration)
            if model == "bounded":
                win = self.windows()
                span = (win.end_ns - win.start_ns) * 1e-9
                run.init_window_s = round(span * 2.0 / 3.0, 3)
                # refine to the end: the 1 s margin absorbs the rounding (split_windows clamps at the end)
                run.refine_window_s = round(span - run.init_window_s + 1.0, 3)

    def pose_source(self) -> str:
        choice = self.config.run.pose_source
        if choice != "auto":
            return choice
        topics = self.reader.topics()
        has_vi = TOPIC_IMU in topics and (TOPIC_FEATURES in topics or TOPIC_CAM0 in topics)
        return "msckf" if has_vi else "odometry"

    # -- driver ------------------------------------------------------------------------------------------------
    def run(self, stages: list[str] | None = None, progress=print) -> list[StageResult]:
        stages = stages or list(self.config.run.stages)
        self._stages = list(stages)
        self.resolve_auto()
        self.dir.path.mkdir(parents=True, exist_ok=True)
        rd.write_text(self.dir.file(rd.CONFIG), self.config.to_toml())
        results = []
        if self.config.run.log and self.config.run.log_process:
            from .runlog_async import start_log_server

            self._log_server = start_log_server()
        try:
            for stage in STAGES:
                if stage not in stages:
                    continue
                t0 = time.perf_counter()
                summary, warns = getattr(self, f"stage_{stage}")()
                res = StageResult(stage, time.perf_counter() - t0, summary, warns)
                results.append(res)
                self._record_stage(res)
                progress(f"[{stage}] {summary} ({res.wall_s:.1f} s)")
        finally:
            server, self._log_server = self._log_server, None
            try:
                if self.config.run.log:
                    if server is not None:
                        server.merge(self.dir.path, self.run_kind())
                    else:
                        self.dir.merge_rrd(self.run_kind())
            finally:
                if server is not None:
                    server.stop()
        return results

    def _record_stage(self, res: StageResult) -> None:
        path = "stages.json"
        stages = self.dir.load_json(path) if self.dir.exists(path) else {}
        stages[res.stage] = {"wall_s": res.wall_s, "summary": res.summary, "warnings": res.warnings}
        self.dir.save_json(path, {k: stages[k] for k in STAGES if k in stages})

    # -- stages --------------------------------------------------------------------------------------------------
    def stage_frontend(self) -> tuple[str, list[str]]:
        topics = self.reader.topics()
        if TOPIC_FEATURES in topics:
            return f"recording has {topics[TOPIC_FEATURES].count} feature frames; skipped", []
        if TOPIC_CAM0 not in topics:
            return "no camera images; skipped", []
        from .frontend import run_frontend

        log = self.runlog("frontend")
        try:
            stats = run_frontend(self.reader, self.dir.file("frontend.mcap"), self.config.frontend, log=log)
        finally:
            log.close()
        return str(stats), []

    def loose(self) -> bool:
        """UWB stages on the VIO output instead of inside the MSCKF (``run.coupling = "loose"``)."""
        return self.config.run.coupling == "loose" and self.pose_source() == "msckf"

    def stage_vio(self) -> tuple[str, list[str]]:
        if self.loose():
            return self._stage_vio_loose()
        win = self.windows()
        est = self._make_estimator()
        self.dir.save_json("windows.json", win.as_dict())
        # the window's poses, kept for the anchors' covariance initialisation (uwb_filter.anchor_init_covariance)
        period = self.config.uwb.init_probe_period_s
        probing = period is not None and hasattr(est, "start_probes")
        if probing:
            est.start_probes(period)
        with self.runlog("vio") as log:
            log.stage("vio", win.start_ns)
            self._log_groundtruth(log)
            est.run(self._features_reader(), win.start_ns, win.init_end_ns, log=log)
            if probing:  # the checkpoint keeps the window's probes; the anchors' initialisation removes them
                est.add_probe()
                est.stop_probes(remove=False)
            self.dir.save_pickle("checkpoint_init.pkl", est)
            if probing:
                est.stop_probes()
            extent = self.config.run.vio_extent
            vio_only_to_end = extent == "full" or (extent == "auto" and "refine" not in self._stages)
            if vio_only_to_end:
                est.run(self._features_reader(), win.init_end_ns, win.end_ns, log=log)
            hist = est.history().arrays()  # the estimators log world/vio themselves
        self.dir.save_npz("vio.npz", **hist)
        self._write_odometry("vio.mcap", hist)
        self._assemble_trajectory()
        warns = list(getattr(est, "warnings", []))
        t_end = win.end_ns if vio_only_to_end else win.init_end_ns
        return (
            f"{self.pose_source()}: {len(hist['t_ns'])} poses over {(t_end - win.start_ns) * 1e-9:.1f} s",
            warns,
        )

    def _stage_vio_loose(self) -> tuple[str, list[str]]:
        """The MSCKF over all data -> vio.mcap (its trajectory on /vio/odometry) -> the odometry filter with a drift
        model fitted to the MSCKF's covariance growth (vio_drift.json) up to the end of the init window."""
        from .odometry_filter import OdometryEstimator, fit_drift_noise

        win = self.windows()
        self.dir.save_json("windows.json", win.as_dict())
        msckf = self._make_estimator()
        with self.runlog("vio") as log:
            log.stage("vio", win.start_ns)
            self._log_groundtruth(log)
            msckf.run(self._features_reader(), win.start_ns, win.end_ns, log=log)
        full = msckf.history().arrays()
        self._write_odometry("vio.mcap", full)
        noise = fit_drift_noise(full)
        self.dir.save_json("vio_drift.json", noise)
        cfg = self.config.odometry.model_copy(update={"topic": TOPIC_VIO, "error_model": "drift", **noise})
        reader = self._features_reader()
        est = OdometryEstimator.from_recording(reader, cfg)
        est.run(reader, win.start_ns, win.init_end_ns)
        self.dir.save_pickle("checkpoint_init.pkl", est)
        hist = est.history().arrays()
        self.dir.save_npz("vio.npz", **hist)
        self._assemble_trajectory()
        drift = ", ".join(f"{k} {v:.3g}" for k, v in noise.items() if v)
        return (
            f"msckf (loose): {len(full['t_ns'])} poses over {(win.end_ns - win.start_ns) * 1e-9:.1f} s; "
            f"UWB stages on its output, drift model {drift}",
            list(msckf.warnings),
        )

    # -- paper stage 1: initialisation ----------------------------------------------------------------------------
    def stage_init(self) -> tuple[str, list[str]]:
        from .uwb_filter import initialize_anchors, windows_from_trajectory

        win = self.windows()
        vio = self.dir.load_npz("vio.npz", "init")
        cal = self.reader.calibration
        rng = self.reader.read_ranges(start_ns=win.start_ns, end_ns=win.init_end_ns)
        if len(rng) == 0:
            raise InputError(
                f"{self.recording}: no UWB ranges in the initialisation window "
                f"({win.start_ns * 1e-9:.1f}-{win.init_end_ns * 1e-9:.1f} s)"
            )
        windows = windows_from_trajectory(vio, vars(rng), cal, win.start_ns, win.init_end_ns)
        results = {m: initialize_anchors(windows, self.config.uwb, cal, method=m) for m in INIT_METHODS}
        self.dir.save_pickle("init.pkl", results)
        chosen = self.config.uwb.init_method
        summary = {m: {str(a): _init_summary(r) for a, r in res.items()} for m, res in results.items()}
        self.dir.save_json("init.json", {"chosen": chosen, "window": win.as_dict(), "methods": summary})
        rows = [_anchor_row(a, m, "init", r.x) for m, res in results.items() for a, r in res.items() if r.ok]
        self._write_anchors(rows, replace_stage="init")
        warns = [f"init {chosen} anchor {a}: {w}" for a, r in results[chosen].items() for w in r.warnings]
        warns += [f"init {chosen} anchor {a}: {r.status}" for a, r in results[chosen].items() if not r.ok]
        with self.runlog("init") as log:
            log.stage("init", win.start_ns)
            self._log_truth_anchors(log)
            for m, res in results.items():
                for a, r in res.items():
                    if not r.ok:
                        continue
                    log.points3d(rl.anchor_world(a, m), r.x[None, :3], labels=[f"{a} {m}"], static=True)
                    if r.costs:
                        t = np.linspace(win.start_ns, win.init_end_ns, len(r.costs)).astype(np.int64)
                        log.scalars(rl.init(m, "cost") + f"/{a}", t, np.asarray(r.costs))
                    if r.fim is not None:
                        log.scalars(
                            rl.init(m, "fim_logdet") + f"/{a}",
                            [win.init_end_ns],
                            [r.fim.summary().get("logdet", np.nan)],
                        )
            for w in warns:
                log.text(w, "WARN", win.init_end_ns)
        ok = sum(r.ok for r in results[chosen].values())
        errs = self._anchor_errors({a: r.x for a, r in results[chosen].items() if r.ok})
        return f"{chosen}: {ok}/{len(results[chosen])} anchors initialised{errs}", warns

    # -- paper stage 2: refinement ----------------------------------------------------------------------------------
    def stage_refine(self) -> tuple[str, list[str]]:
        from .uwb_filter import UwbUpdater, add_initialised_anchors

        win = self.windows()
        est = self.dir.load_pickle("checkpoint_init.pkl", "refine")
        results = self.dir.load_pickle("init.pkl", "refine")[self.config.uwb.init_method]
        cal = self.reader.calibration
        cfg = self.config.uwb
        warns = add_initialised_anchors(est.state, results, cfg, cal)
        inflation = {a: float(r.noise_inflation) for a, r in results.items() if r.ok}
        updater = UwbUpdater.from_config(cfg, cal, inflation=inflation)
        with self.runlog("refine") as log:
            log.stage("refine", win.init_end_ns)
            est.run(self._features_reader(), win.init_end_ns, win.refine_end_ns, on_range=updater, log=log)
            updater.log(log)
            for a, arr in updater.arrays().items():
                if len(arr["t_ns"]) and arr["cov"].any():
                    log.ellipsoid_series(
                        rl.anchor_world(a, "cov"), arr["t_ns"], arr["x"][:, :3], arr["cov"][:, :3, :3]
                    )
                    log.scalars(rl.anchor_world(a, "estimate"), arr["t_ns"], arr["x"][:, :3])
        self.dir.save_pickle("checkpoint_refine.pkl", est)
        hist = est.history().arrays()
        seg = (hist["t_ns"] >= win.init_end_ns) & (hist["t_ns"] < win.refine_end_ns)
        self.dir.save_npz("refine.npz", **{k: v[seg] for k, v in hist.items()})
        self._write_odometry("refine.mcap", {k: v[seg] for k, v in hist.items()})
        names = [n for n in est.state.names if n.startswith("anchor/")]
        states = {
            n.split("/", 1)[1]: {
                "x": est.state.value(n).x,
                "P": est.state.cov(n),
                "noise_inflation": inflation.get(_anchor_key(n.split("/", 1)[1]), 1.0),
            }
            for n in names
        }
        self.dir.save_json("anchor_states.json", states)
        label = f"{cfg.init_method}+{cfg.refine_method}"
        self._write_anchors(
            [_anchor_row(a, label, "refine", s["x"]) for a, s in states.items()], replace_stage="refine"
        )
        self._assemble_trajectory()
        c = updater.counts
        if c["rejected"]:
            warns.append(f"refine: {c['rejected']} ranges rejected by the chi2 gate")
        errs = self._anchor_errors({a: s["x"] for a, s in states.items()})
        return (f"{cfg.refine_method}: {c['accepted']} range updates, {c['rejected']} rejected{errs}", warns)

    # -- paper stage 3: UWB-aided localisation -----------------------------------------------------------------------
    def stage_localize(self) -> tuple[str, list[str]]:
        from .uwb_filter import UwbUpdater

        win = self.windows()
        if win.refine_end_ns >= win.end_ns:
            return "no data left after refinement; skipped", []
        est = self.dir.load_pickle("checkpoint_refine.pkl", "localize")
        states = self.dir.load_json("anchor_states.json")
        anchors = {_anchor_key(a): np.asarray(s["x"]) for a, s in states.items()}
        inflation = {_anchor_key(a): float(s.get("noise_inflation", 1.0)) for a, s in states.items()}
        updater = UwbUpdater.from_config(
            self.config.uwb, self.reader.calibration, mode="frozen", anchors=anchors, inflation=inflation
        )
        with self.runlog("localize") as log:
            log.stage("localize", win.refine_end_ns)
            est.run(self._features_reader(), win.refine_end_ns, win.end_ns, on_range=updater, log=log)
            updater.log(log)
            hist = est.history().arrays()
            seg = hist["t_ns"] >= win.refine_end_ns
            part = {k: v[seg] for k, v in hist.items()}
            self.dir.save_npz("localize.npz", **part)
            self._write_odometry("localize.mcap", part)
            traj = self._assemble_trajectory()
            self._log_trajectory(log, "estimate", traj)
        c = updater.counts
        return f"frozen anchors: {c['accepted']} range updates, {c['rejected']} rejected", []

    # -- evaluation -------------------------------------------------------------------------------------------------
    def stage_evaluate(self) -> tuple[str, list[str]]:
        from evaluate.evaluation import evaluate_run_cli

        series: dict = {}
        text = evaluate_run_cli(
            self.dir.path,
            align=None if self.config.run.align == "auto" else self.config.run.align,
            series=series,
        )
        m = self.dir.load_json(rd.METRICS)
        if series:
            from evaluate.consistency import chi2_bounds

            with self.runlog("evaluate") as log:
                log.stage("evaluate", int(series["t_ns"][0]))
                for key, dof, entity in (
                    ("nees_pose", 6, rl.NEES_POSE),
                    ("nees_position", 3, f"{rl.FILTER}/nees_position"),
                    ("nees_orientation", 3, f"{rl.FILTER}/nees_orientation"),
                ):
                    log.scalars(entity, series["t_ns"], series[key])
                    log.constant(
                        f"{entity}_bounds", series["t_ns"], np.array(chi2_bounds(1, dof)), ["lo", "hi"]
                    )
        parts = []
        if "prmse_m" in m:
            parts.append(f"PRMSE {m['prmse_m'].get('all', float('nan')):.3f} m")
        if "anchor_error_m" in m:
            parts.append(f"anchor error {m['anchor_error_m']:.3f} m")
        self.results_text = text
        return ", ".join(parts) or "metrics written", []

    # -- artefact helpers -------------------------------------------------------------------------------------------
    def _assemble_trajectory(self) -> dict[str, np.ndarray]:
        """trajectory.npz: the estimate of each segment from the stage that owns it (VIO for what is missing)."""
        win = self.windows()
        parts = []
        vio = self.dir.load_npz("vio.npz", "trajectory") if self.dir.exists("vio.npz") else None
        bounds = [
            (win.start_ns, win.init_end_ns),
            (win.init_end_ns, win.refine_end_ns),
            (win.refine_end_ns, win.end_ns + 1),
        ]
        for seg, (name, (lo, hi)) in enumerate(zip(("vio", "refine", "localize"), bounds, strict=True)):
            src = self.dir.load_npz(f"{name}.npz", "trajectory") if self.dir.exists(f"{name}.npz") else vio
            if src is None:
                continue
            m = (src["t_ns"] >= lo) & (src["t_ns"] < hi)
            part = {k: v[m] for k, v in src.items()}
            part["segment"] = np.full(int(m.sum()), seg, np.int8)
            parts.append(part)
        traj = {k: np.concatenate([p[k] for p in parts]) for k in parts[0]} if parts else {}
        if traj:
            self.dir.save_npz(rd.TRAJECTORY, **traj)
        return traj

    def _write_anchors(self, rows: list[dict], replace_stage: str) -> None:
        path = self.dir.file(rd.ANCHORS)
        old = []
        if path.exists():
            with open(path, newline="") as f:
                old = [r for r in csv.DictReader(f) if r["stage"] != replace_stage]
        cols = ["anchor", "method", "stage", "x", "y", "z", "beta", "gamma"]
        buf = io.StringIO()
        w = csv.DictWriter(buf, fieldnames=cols, lineterminator="\n")
        w.writeheader()
        for r in old + rows:
            w.writerow(r)
        rd.write_text(path, buf.getvalue())

    def _anchor_errors(self, est: dict) -> str:
        truth = (self.reader.truth or {}).get("anchors")
        if not truth:
            return ""
        errs = [
            np.linalg.norm(np.asarray(x)[:3] - np.asarray(truth[str(a)]["position"]))
            for a, x in est.items()
            if str(a) in truth
        ]
        return f"; mean anchor error {np.mean(errs):.3f} m" if errs else ""

    def _log_groundtruth(self, log) -> None:
        if not log.enabled:
            return
        topics = self.reader.topics()
        if "/groundtruth/pose" in topics:
            gt = self.reader.read_poses("/groundtruth/pose")
            step = max(1, len(gt.t_ns) // 4000)
            log.trajectory(rl.GT, gt.t_ns[::step], gt.p[::step], gt.q_xyzw[::step])
        elif "/groundtruth/position" in topics:
            gt = self.reader.read_positions("/groundtruth/position")
            log.trajectory(rl.GT, gt.t_ns, gt.p)
        self._log_truth_anchors(log)

    def _log_truth_anchors(self, log) -> None:
        truth = (self.reader.truth or {}).get("anchors") or {}
        for a, t in truth.items():
            log.points3d(
                rl.anchor_world(a, "truth"),
                np.asarray(t["position"])[None],
                labels=[f"{a} truth"],
                static=True,
            )

    def _log_trajectory(self, log, what: str, hist: dict[str, np.ndarray]) -> None:
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

    def _features_reader(self) -> RecordingReader:
        """The reader the estimator consumes: the recording, with the frontend's tracks and (loose coupling) the
        VIO output merged into it."""
        extra = [
            n for n in ("frontend.mcap",) + (("vio.mcap",) if self.loose() else ()) if self.dir.exists(n)
        ]
        if extra:
            return MergedReader(self.reader, *(RecordingReader(self.dir.file(n)) for n in extra))
        return self.reader

    def _make_estimator(self):
        if self.pose_source() == "msckf":
            from .msckf import MsckfEstimator

            initial = cov = None
            if not self.config.vio.init_from_groundtruth:  # real data without usable ground truth
                from .static_init import static_init_from_recording

                res = static_init_from_recording(self.reader, start_ns=self.windows().start_ns)
                _log.info("vio: static initialisation: %s", res)
                initial, cov = res.state, res.P
            return MsckfEstimator.from_recording(self._features_reader(), self.config.vio, initial, cov)
        from .odometry_filter import OdometryEstimator

        return OdometryEstimator.from_recording(self.reader, self.config.odometry)

    def _write_odometry(self, name: str, hist: dict[str, np.ndarray]) -> None:
        cov = hist["cov"]
        # ours: [dtheta, dp]; nav_msgs/Odometry: [x, y, z, rx, ry, rz]
        perm = np.r_[3:6, 0:3]
        ros_cov = cov[:, perm][:, :, perm]
        with RecordingWriter(self.dir.file(name)) as w:
            w.write_odometry_batch(hist["t_ns"], hist["p"], hist["q_xyzw"], ros_cov, topic=TOPIC_VIO)


INIT_METHODS = ("lsi", "ri", "ri-robust")


def _anchor_key(a):
    """Anchor ids are ints in the recording and strings in JSON."""
    return int(a) if str(a).lstrip("-").isdigit() else a


def _init_summary(r) -> dict:
    out = {
        "status": r.status,
        "x": r.x,
        "cov": r.cov,
        "iterations": r.iterations,
        "n_used": r.n_used,
        "n_rejected": r.n_rejected,
        "noise_inflation": r.noise_inflation,
        "residual_rms": r.residual_rms,
        "warnings": r.warnings,
        "costs": r.costs,
    }
    if r.fim is not None:
        out["fim"] = r.fim.summary()
    return out


def _anchor_row(anchor, method: str, stage: str, x) -> dict:
    x = np.asarray(x, float)
    return {
        "anchor": str(anchor),
        "method": method,
        "stage": stage,
        "x": f"{x[0]:.6f}",
        "y": f"{x[1]:.6f}",
        "z": f"{x[2]:.6f}",
        "beta": f"{x[3]:.6f}",
        "gamma": f"{x[4]:.6f}",
    }


def run_cli(
    recording: Path,
    output: Path,
    *,
    config: Path | None,
    init: str | None,
    refine: str | None,
    stages: str | None,
    log: bool,
) -> str:
    overrides: dict = {"run": {"recording": str(Path(recording).resolve()), "log": log}}
    if stages:
        overrides["run"]["stages"] = [s.strip() for s in stages.split(",") if s.strip()]
    uwb: dict = {}
    if init:
        uwb["init_method"] = init
    if refine:
        uwb["refine_method"] = refine
    if uwb:
        overrides["uwb"] = uwb
    cfg = load_config(config, overrides)
    RecordingReader(cfg.run.recording)  # fail early, before the run directory is touched
    pipe = Pipeline(cfg, output)
    pipe.run()
    return getattr(pipe, "results_text", "")
