"""Stage `vio`: the pose source (MSCKF or odometry filter) over the initialisation window (and on to the end
when no refinement follows), checkpointed for the UWB stages; loose coupling: the MSCKF's output as odometry."""

from __future__ import annotations

from uwbcal.pipeline.core.topics import TOPIC_VIO
from uwbcal.pipeline.run import rundir as rd
from uwbcal.pipeline.run.context import StageContext, StageResult
from uwbcal.pipeline.run.driver import odometry_from_recording, run_estimator
from uwbcal.pipeline.vio.odometry_filter import fit_drift_noise


def run(ctx: StageContext) -> StageResult:
    if ctx.loose():
        return _run_loose(ctx)
    win = ctx.windows()
    est = ctx.make_estimator()
    ctx.dir.save_json("windows.json", win.as_dict())
    # the window's poses, kept for the anchors' covariance initialisation (uwb_filter.anchor_init_covariance)
    period = ctx.config.uwb.init_probe_period_s
    probing = period is not None and est.keeps_probes
    if probing:
        est.start_probes(period)
    with ctx.runlog("vio") as log:
        log.stage("vio", win.start_ns)
        ctx.log_groundtruth(log)
        run_estimator(est, ctx.features_reader(), win.start_ns, win.init_end_ns, log=log)
        if probing:  # the checkpoint keeps the window's probes; the anchors' initialisation removes them
            est.add_probe()
            est.stop_probes(remove=False)
        ctx.dir.save_pickle("checkpoint_init.pkl", est)
        if probing:
            est.stop_probes()
        extent = ctx.config.run.vio_extent
        vio_only_to_end = extent == "full" or (extent == "auto" and "refine" not in ctx.stages)
        if vio_only_to_end:
            run_estimator(est, ctx.features_reader(), win.init_end_ns, win.end_ns, log=log)
        hist = est.history().arrays()  # the estimators log world/vio themselves
        t_end = win.end_ns if vio_only_to_end else win.init_end_ns
        warns = list(est.warnings) + ctx.check_health("vio", est, win.start_ns, t_end)
        for w in warns:
            log.text(w, "WARN", t_end)
    ctx.dir.save_npz("vio.npz", **hist)
    rd.write_odometry(ctx.dir, "vio.mcap", hist)
    ctx.assemble_trajectory()
    return StageResult(
        "vio",
        f"{ctx.pose_source()}: {len(hist['t_ns'])} poses over {(t_end - win.start_ns) * 1e-9:.1f} s",
        warns,
    )


def _run_loose(ctx: StageContext) -> StageResult:
    """The MSCKF over all data -> vio.mcap (its trajectory on /vio/odometry) -> the odometry filter with a drift
    model fitted to the MSCKF's covariance growth (vio_drift.json) up to the end of the init window."""

    win = ctx.windows()
    ctx.dir.save_json("windows.json", win.as_dict())
    msckf = ctx.make_estimator()
    with ctx.runlog("vio") as log:
        log.stage("vio", win.start_ns)
        ctx.log_groundtruth(log)
        run_estimator(msckf, ctx.features_reader(), win.start_ns, win.end_ns, log=log)
        warns = list(msckf.warnings) + ctx.check_health("vio", msckf, win.start_ns, win.end_ns)
        for w in warns:
            log.text(w, "WARN", win.end_ns)
    full = msckf.history().arrays()
    rd.write_odometry(ctx.dir, "vio.mcap", full)
    noise = fit_drift_noise(full)
    ctx.dir.save_json("vio_drift.json", noise)
    cfg = ctx.config.odometry.model_copy(update={"topic": TOPIC_VIO, "error_model": "drift", **noise})
    reader = ctx.features_reader()
    est = odometry_from_recording(reader, cfg)
    run_estimator(est, reader, win.start_ns, win.init_end_ns)
    ctx.dir.save_pickle("checkpoint_init.pkl", est)
    hist = est.history().arrays()
    ctx.dir.save_npz("vio.npz", **hist)
    ctx.assemble_trajectory()
    drift = ", ".join(f"{k} {v:.3g}" for k, v in noise.items() if v)
    return StageResult(
        "vio",
        f"msckf (loose): {len(full['t_ns'])} poses over {(win.end_ns - win.start_ns) * 1e-9:.1f} s; "
        f"UWB stages on its output, drift model {drift}",
        warns,
    )
