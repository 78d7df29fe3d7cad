"""Stage `refine` (paper stage 2): the chosen initialisation joins the filter state; EKF or Schmidt updates with
every range of the refinement window -> anchor_states.json, refine.npz/.mcap, range_updates.npz (each range's residual,
NIS and gate verdict), the `refine` rows of anchors.csv."""

from __future__ import annotations

import numpy as np

from uwbcal.pipeline.run import rundir as rd
from uwbcal.pipeline.run.context import StageContext, StageResult, filter_warnings
from uwbcal.pipeline.run.driver import run_estimator
from uwbcal.pipeline.uwb.evidence import weak_horizontal
from uwbcal.pipeline.uwb.updater import UwbUpdater, add_initialised_anchors, anchor_var, link_var
from uwbcal.pipeline.vio.estimator import Estimator
from uwbcal.pipeline.viz import observers
from uwbcal.pipeline.viz import runlog as rl
from uwbcal.pipeline.viz.runlog import RunLog

RANGE_UPDATES = "range_updates.npz"  # every range of the refinement: anchor, stamp, residual, NIS, rejected


def _range_updates(per_anchor: dict) -> dict[str, np.ndarray]:
    keys = [k for k in per_anchor if len(per_anchor[k]["t_ns"])]
    cols = {"anchor": np.concatenate([np.full(len(per_anchor[k]["t_ns"]), str(k)) for k in keys] or [[]])}
    for name in ("t_ns", "residual", "nis", "rejected"):
        cols[name] = np.concatenate([per_anchor[k][name] for k in keys] or [np.zeros(0)])
    return cols


def run(ctx: StageContext) -> StageResult:
    ctx.apply_range_clock()

    win = ctx.windows()
    est = ctx.dir.load_pickle("checkpoint_init.pkl", "refine")
    results = ctx.dir.load_pickle("init.pkl", "refine")[ctx.config.uwb.init_method]
    cal = ctx.reader.calibration
    cfg = ctx.config.uwb
    tau = getattr(est, "pose_correlation_s", None)  # bounded pose errors: their correlation time
    warns = add_initialised_anchors(est.state, results, cfg, cal, pose_correlation_s=tau)
    inflation = {a: float(r.noise_inflation) for a, r in results.items() if r.ok}
    updater = _updater(ctx, results, inflation, tau)
    with ctx.runlog("refine") as log:
        log.stage("refine", win.init_end_ns)
        run_estimator(
            est, ctx.features_reader(), win.init_end_ns, win.refine_end_ns, on_range=updater, log=log
        )
        observers.log_uwb_updates(log, updater)
        consistency = filter_warnings(ctx, "refine", est, updater, win.init_end_ns, win.refine_end_ns, log)
        _log_anchors(log, est, updater, win.refine_end_ns)
        states = _anchor_states(est, updater, inflation, warns)
        weak = _weak_after_refine(states, cfg.max_sigma_horizontal_m, warns, log, win.refine_end_ns)
    for a in weak:  # not determined: the localisation does not range to it
        for name in (anchor_var(a), link_var(a)):
            if name in est.state:
                est.state.remove(name)
    ctx.dir.save_pickle("checkpoint_refine.pkl", est)
    hist = est.history().arrays()
    seg = (hist["t_ns"] >= win.init_end_ns) & (hist["t_ns"] < win.refine_end_ns)
    ctx.dir.save_npz("refine.npz", **{k: v[seg] for k, v in hist.items()})
    rd.write_odometry(ctx.dir, "refine.mcap", {k: v[seg] for k, v in hist.items()})
    ctx.dir.save_npz(RANGE_UPDATES, **_range_updates(updater.arrays()))
    ctx.dir.save_json("anchor_states.json", states)
    label = f"{cfg.init_method}+{cfg.refine_method}"
    rd.write_anchors(
        ctx.dir,
        [rd.anchor_row(a, label, "refine", s["x"]) for a, s in states.items()]
        + [rd.undetermined_row(a, label, "refine") for a, r in results.items() if not r.ok]
        + [rd.undetermined_row(a, label, "refine", why) for a, why in weak.items()],
        replace_stage="refine",
    )
    ctx.assemble_trajectory()
    c = updater.counts
    warns += consistency
    errs = ctx.anchor_errors({a: s["x"] for a, s in states.items()})
    return StageResult(
        "refine", f"{cfg.refine_method}: {c['accepted']} range updates, {c['rejected']} rejected{errs}", warns
    )


def _updater(ctx: StageContext, results: dict, inflation: dict, tau: float | None) -> UwbUpdater:
    """The range updater of refinement, its anchors scheduled from the init results."""
    cal = ctx.reader.calibration
    cfg = ctx.config.uwb
    updater = UwbUpdater.from_config(cfg, cal, inflation=inflation)
    if ctx.dir.exists("lever_arms.pkl"):  # a planar carrier's estimated lever arms (init)
        updater.planar_arms = ctx.dir.load_pickle("lever_arms.pkl", "refine")
    updater.schedule(  # late anchors join at their time; per-link offsets; heights left alone where unobservable
        results,
        {
            "sigma_range": cfg.sigma(cal) * cfg.sigma_scale,
            "gamma_prior": cfg.gamma_prior(cal),
            "beta_prior": cfg.beta_prior(cal),
            "pose_correlation_s": tau,
        },
    )
    return updater


def _log_anchors(log: RunLog, est: Estimator, updater: UwbUpdater, t_end_ns: int) -> None:
    """The anchors' estimate and covariance series, and at the end of refinement the covariance
    anchor_states.json holds."""
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
        log.ellipsoids(rl.anchor_world(a, "cov"), x[:3], est.state.cov(n)[None, :3, :3], t_ns=t_end_ns)


def _anchor_states(est: Estimator, updater: UwbUpdater, inflation: dict, warns: list[str]) -> dict[str, dict]:
    """Per anchor (the refined ones and those fitted from all their ranges): state, covariance (an unobservable
    height's variance is the init's: `UwbUpdater.fixed_height`), noise inflation, link offsets; the warnings
    appended to ``warns``."""
    offsets, offset_cov = updater.offsets(est.state), updater.offset_covariances(est.state)
    states = {
        str(a): {
            "x": est.state.value(n).x,
            "P": est.state.cov(n),
            "noise_inflation": inflation.get(a, 1.0),
            "link_offsets": {str(k): v for k, v in offsets.get(a, {}).items()},
            **({"link_offsets_cov": offset_cov[a]} if a in offset_cov else {}),
        }
        for a, n in est.state.anchors.items()
    }
    for a, r in updater.pending.items():  # determined only by all their ranges: nothing left to refine with
        states[str(a)] = {
            "x": r.x,
            "P": r.cov,
            "noise_inflation": float(r.noise_inflation),
            "link_offsets": {str(k): v for k, v in r.link_offsets.items()},
        }
    if updater.pending:
        warns.append(
            f"refine: anchors {sorted(updater.pending)} were determined only by all their ranges; reported at "
            "their initial estimate"
        )
    return states


def _weak_after_refine(
    states: dict, max_sigma: float, warns: list[str], log: RunLog | None = None, t_ns: int | None = None
) -> dict[str, str]:
    """The init's not-determined gate on the covariance the run reports: the anchors whose horizontal sigma after
    refinement (the join keeps what the init window's errors leave open) exceeds ``max_sigma``, taken out of
    ``states``; id -> reason, each also a warning, logged as a WARN text at ``t_ns`` beside the anchor's last
    state."""
    weak = {a: why for a, s in states.items() if (why := weak_horizontal(s["P"], max_sigma))}
    for a, why in weak.items():
        del states[a]
        warns.append(f"refine: anchor {a} not determined: {why}")
        if log is not None:
            log.text(warns[-1], "WARN", t_ns)
    return weak
