"""Stage `refine` (paper stage 2): the chosen initialisation joins the filter state; EKF or Schmidt updates with
every range of the refinement window -> anchor_states.json, refine.npz/.mcap, the `refine` rows of anchors.csv."""

from __future__ import annotations

from .. import rundir as rd
from .. import runlog as rl
from ..driver import run_estimator
from .context import StageContext, StageResult


def run(ctx: StageContext) -> StageResult:
    from ..uwb_filter import UwbUpdater, add_initialised_anchors

    win = ctx.windows()
    est = ctx.dir.load_pickle("checkpoint_init.pkl", "refine")
    results = ctx.dir.load_pickle("init.pkl", "refine")[ctx.config.uwb.init_method]
    cal = ctx.reader.calibration
    cfg = ctx.config.uwb
    warns = add_initialised_anchors(est.state, results, cfg, cal)
    inflation = {a: float(r.noise_inflation) for a, r in results.items() if r.ok}
    updater = UwbUpdater.from_config(cfg, cal, inflation=inflation)
    with ctx.runlog("refine") as log:
        log.stage("refine", win.init_end_ns)
        run_estimator(
            est, ctx.features_reader(), win.init_end_ns, win.refine_end_ns, on_range=updater, log=log
        )
        updater.log(log)
        for a, arr in updater.arrays().items():
            if len(arr["t_ns"]) and arr["cov"].any():
                log.ellipsoid_series(
                    rl.anchor_world(a, "cov"), arr["t_ns"], arr["x"][:, :3], arr["cov"][:, :3, :3]
                )
                log.point_series(rl.anchor_world(a, "estimate"), arr["t_ns"], arr["x"][:, :3])
        for (
            a,
            n,
        ) in est.state.anchors.items():  # at the end of refinement: the covariance anchor_states.json holds
            x = est.state.value(n).x
            log.ellipsoids(
                rl.anchor_world(a, "cov"), x[:3], est.state.cov(n)[None, :3, :3], t_ns=win.refine_end_ns
            )
    ctx.dir.save_pickle("checkpoint_refine.pkl", est)
    hist = est.history().arrays()
    seg = (hist["t_ns"] >= win.init_end_ns) & (hist["t_ns"] < win.refine_end_ns)
    ctx.dir.save_npz("refine.npz", **{k: v[seg] for k, v in hist.items()})
    rd.write_odometry(ctx.dir, "refine.mcap", {k: v[seg] for k, v in hist.items()})
    states = {
        str(a): {"x": est.state.value(n).x, "P": est.state.cov(n), "noise_inflation": inflation.get(a, 1.0)}
        for a, n in est.state.anchors.items()
    }
    ctx.dir.save_json("anchor_states.json", states)
    label = f"{cfg.init_method}+{cfg.refine_method}"
    rd.write_anchors(
        ctx.dir,
        [rd.anchor_row(a, label, "refine", s["x"]) for a, s in states.items()],
        replace_stage="refine",
    )
    ctx.assemble_trajectory()
    c = updater.counts
    if c["rejected"]:
        warns.append(f"refine: {c['rejected']} ranges rejected by the chi2 gate")
    errs = ctx.anchor_errors({a: s["x"] for a, s in states.items()})
    return StageResult(
        "refine", f"{cfg.refine_method}: {c['accepted']} range updates, {c['rejected']} rejected{errs}", warns
    )
