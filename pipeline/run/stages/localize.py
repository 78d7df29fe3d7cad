"""Stage `localize` (paper stage 3): UWB-aided localisation with the refined anchors frozen."""

from __future__ import annotations

import numpy as np

from uwbcal.pipeline.run import artefacts
from uwbcal.pipeline.run import rundir as rd
from uwbcal.pipeline.run.context import StageContext, StageResult, filter_warnings
from uwbcal.pipeline.run.driver import run_estimator
from uwbcal.pipeline.uwb.updater import UwbUpdater, link_columns
from uwbcal.pipeline.viz import observers


def run(ctx: StageContext) -> StageResult:
    ctx.apply_range_clock()

    win = ctx.windows()
    if win.refine_end_ns >= win.end_ns:
        return StageResult("localize", "no data left after refinement; skipped")
    est = ctx.dir.load_pickle("checkpoint_refine.pkl", "localize")
    states = ctx.dir.load_json("anchor_states.json", "localize", artefacts.ANCHOR_STATES)
    anchors = {rd.anchor_key(a): np.asarray(s["x"]) for a, s in states.items()}
    inflation = {rd.anchor_key(a): float(s.get("noise_inflation", 1.0)) for a, s in states.items()}
    updater = UwbUpdater.from_config(
        ctx.config.uwb, ctx.reader.calibration, mode="frozen", anchors=anchors, inflation=inflation
    )
    if ctx.dir.exists("lever_arms.pkl"):  # a planar carrier's estimated lever arms (init)
        updater.planar_arms = ctx.dir.load_pickle("lever_arms.pkl", "localize")
    updater.link_offsets = {
        rd.anchor_key(a): {int(k): float(v) for k, v in s.get("link_offsets", {}).items()}
        for a, s in states.items()
    }
    # offsets that are still state variables (links/<id>, in refinement's column order) are considered
    updater.link_cols = {a: link_columns(list(off)) for a, off in updater.link_offsets.items() if off}
    with ctx.runlog("localize") as log:
        log.stage("localize", win.refine_end_ns)
        run_estimator(est, ctx.features_reader(), win.refine_end_ns, win.end_ns, on_range=updater, log=log)
        observers.log_uwb_updates(log, updater)
        warns = filter_warnings(ctx, "localize", est, updater, win.refine_end_ns, win.end_ns, log)
        hist = est.history().arrays()
        seg = hist["t_ns"] >= win.refine_end_ns
        part = {k: v[seg] for k, v in hist.items()}
        ctx.dir.save_npz("localize.npz", **part)
        rd.write_odometry(ctx.dir, "localize.mcap", part)
        traj = ctx.assemble_trajectory()
        ctx.log_trajectory(log, "estimate", traj)
    c = updater.counts
    return StageResult(
        "localize",
        f"frozen anchors: {c['accepted']} range updates, {c['rejected']} rejected",
        warns,
    )
