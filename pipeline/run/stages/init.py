"""Stage `init` (paper stage 1): every initialiser on the VIO poses of the initialisation window -> init.pkl,
init.json, the `init` rows of anchors.csv."""

from __future__ import annotations

import numpy as np

from uwbcal.pipeline.core.errors import InputError
from uwbcal.pipeline.core.names import INIT_METHODS
from uwbcal.pipeline.run import rundir as rd
from uwbcal.pipeline.run.context import StageContext, StageResult
from uwbcal.pipeline.run.windows import Windows
from uwbcal.pipeline.uwb.clock import NO_OFFSET, ClockOffset, estimate_clock
from uwbcal.pipeline.uwb.planar_levers import planar_windows, refit_searches
from uwbcal.pipeline.uwb.schedule import join_time
from uwbcal.pipeline.uwb.updater import (
    evidence_spec,
    initialize_anchors,
    search_window,
    windows_from_trajectory,
)
from uwbcal.pipeline.uwb.window import InitWindow, subsample
from uwbcal.pipeline.viz import runlog as rl
from uwbcal.pipeline.viz.runlog import RunLog

CLOCK_RANGES = 500  # ranges per anchor the clock scan refits at each offset


def run(ctx: StageContext) -> StageResult:

    win = ctx.windows()
    vio = ctx.dir.load_npz("vio.npz", "init")
    cal = ctx.reader.calibration
    cfg = ctx.config.uwb
    per_anchor = ctx.config.run.schedule == "per-anchor"
    end = win.end_ns + 1 if per_anchor else win.init_end_ns  # the late anchors' windows run up to their join
    rng = vars(ctx.reader.read_ranges(start_ns=win.start_ns, end_ns=end))
    if not np.any(np.asarray(rng["t_ns"]) < win.init_end_ns):
        raise InputError(
            f"{ctx.recording}: no UWB ranges in the initialisation window "
            f"({win.start_ns * 1e-9:.1f}-{win.init_end_ns * 1e-9:.1f} s)"
        )
    windows, levers = _lever_arms(ctx, windows_from_trajectory(vio, rng, cal, win.start_ns, end))
    clock = _range_clock(ctx, vio, rng, win.start_ns, end, levers)
    if clock.used:  # the ranges re-stamped, the arms as estimated
        rng = {**rng, "t_ns": np.asarray(rng["t_ns"]) + round(clock.offset_s * 1e9)}
        windows = windows_from_trajectory(vio, rng, cal, win.start_ns, end)
        windows = levers.apply(windows) if levers is not None else windows
    whole = levers is not None or (cfg.search and ctx.bounded_poses())
    windows, searches, joins = _schedule(ctx, windows, win.init_end_ns, per_anchor, whole, levers is not None)
    if levers is not None and searches:  # the lever model's link offsets correct the ranges; then the rule
        searches = refit_searches(levers, windows, searches, cfg.sigma(cal) * cfg.sigma_scale)
        windows, searches = _link_corrected(windows, searches), None
    results = {  # every initialiser for comparison; the chosen one's covariance in full
        m: initialize_anchors(
            windows,
            cfg,
            cal,
            method=m,
            searches=searches if m == cfg.init_method else None,
            cheap=m != cfg.init_method,
            pose_tau_s=ctx.pose_correlation_s(),
        )
        for m in INIT_METHODS
    }
    for res in results.values():
        for a, r in res.items():
            _add_clock_cov(r, clock.position_cov(a))
            j = joins.get(a)
            r.join_ns = j if (j is not None and j > win.init_end_ns) else None
    ctx.dir.save_pickle("init.pkl", results)
    chosen = cfg.init_method
    summary = {m: {str(a): rd.init_summary(r) for a, r in res.items()} for m, res in results.items()}
    info = {"chosen": chosen, "window": win.as_dict(), "methods": summary}
    if levers is not None:
        info["lever_arms"] = levers.summary()
    if clock.anchors:
        info["range_clock"] = clock.summary()
    ctx.dir.save_json("init.json", info)
    return _report(ctx, results, chosen, win, levers, clock)


def _add_clock_cov(r, C: np.ndarray) -> None:
    """The clock offset's error in the anchor's covariance."""
    if not r.ok or not np.any(C):
        return
    r.cov = r.cov.copy()
    r.cov[:3, :3] += C


def _link_corrected(windows: dict, searches: dict) -> dict:
    """Each anchor's ranges less its links' offsets as the joint lever-arm fit estimated them."""
    out = {}
    for a, w in windows.items():
        sr = searches.get(a)
        corr = sr.gamma_of(w.links()) if sr is not None and sr.ok else np.zeros(len(w))
        out[a] = InitWindow(w.d - corr, w.p_T, w.R, w.p, w.P_pose, w.t_ns, w.link)
    return out


def _range_clock(ctx: StageContext, vio, rng: dict, start_ns: int, end_ns: int, levers) -> ClockOffset:
    """The range-to-pose clock offset (`clock.estimate_clock`) on the evidence path, else none, on the ranges
    with the estimated lever arms (an arm error turning with the carrier would pass for a clock); the reader of
    the later stages re-stamps the ranges by it when it is used."""
    cfg = ctx.config.uwb
    ctx.reader.range_shift_ns = 0
    if not cfg.search or cfg.clock_scan_s <= 0:
        return NO_OFFSET
    cal = ctx.reader.calibration
    margin = round(cfg.clock_scan_s * 1e9)
    t = np.asarray(rng["t_ns"])
    t0, t1 = int(vio["t_ns"][0]) + margin, int(vio["t_ns"][-1]) - margin
    inside = np.flatnonzero(
        (t >= t0) & (t <= t1)
    )  # the same ranges at every offset, at most CLOCK_RANGES each
    anchor = np.asarray(rng["anchor"])[inside]
    keep = np.concatenate(
        [inside[anchor == a][subsample(int(np.sum(anchor == a)), CLOCK_RANGES)] for a in np.unique(anchor)]
        or [np.zeros(0, np.int64)]
    )
    sub = {k: np.asarray(v)[np.sort(keep)] for k, v in rng.items()}

    def windows_at(tau: float) -> dict:
        shifted = {**sub, "t_ns": sub["t_ns"] + round(tau * 1e9)}
        ws = windows_from_trajectory(vio, shifted, cal, None, None)
        return levers.apply(ws) if levers is not None else ws

    sigma = cfg.sigma(cal) * cfg.sigma_scale
    spec = evidence_spec(cfg, sigma, cal, cfg.init_method)
    clock = estimate_clock(
        windows_at, spec, max_s=cfg.clock_scan_s, max_ranges=CLOCK_RANGES, pose_tau_s=ctx.pose_correlation_s()
    )
    ctx.reader.range_shift_ns = round(clock.applied_s * 1e9)
    return clock


def _report(ctx: StageContext, results: dict, chosen: str, win: Windows, levers, clock) -> StageResult:
    """anchors.csv's init rows, the warnings, the run log and the stage's one-line summary."""
    rows = [rd.anchor_row(a, m, "init", r.x) for m, res in results.items() for a, r in res.items() if r.ok]
    rows += [rd.undetermined_row(a, chosen, "init") for a, r in results[chosen].items() if not r.ok]
    rd.write_anchors(ctx.dir, rows, replace_stage="init")
    warns = [f"init {chosen} anchor {a}: {w}" for a, r in results[chosen].items() for w in r.warnings]
    if levers is not None:
        warns.insert(0, f"init: {levers.message()}")
    if clock.used:
        warns.insert(0, f"init: {clock.message()}")
    warns += [
        f"init {chosen} anchor {a}: {r.status}"
        for a, r in results[chosen].items()
        if not r.ok and r.status != "not determined"  # its warning states the reason
    ]
    with ctx.runlog("init") as log:
        log.stage("init", win.start_ns)
        ctx.log_truth_anchors(log)
        log.legend(list(results))
        _log_initialisers(log, results, chosen, win)
        for w in warns:
            log.text(w, "WARN", win.init_end_ns)
    res = results[chosen]
    ok = sum(r.ok for r in res.values())
    errs = ctx.anchor_errors({a: r.x for a, r in res.items() if r.ok})
    late = sum(r.join_ns is not None for r in res.values() if r.ok)
    weak = sum(not r.verdict.get("height_observable", True) for r in res.values() if r.ok)
    nd = [str(a) for a, r in res.items() if not r.ok]
    extra = f" ({late} joining later)" if late else ""
    extra += f"; height unobservable for {weak}" if weak else ""
    extra += f"; not determined: {', '.join(nd)}" if nd else ""
    extra += f"; range clock {clock.offset_s:+.3f} s" if clock.used else ""
    sched = ctx.config.run.schedule
    return StageResult("init", f"{chosen} [{sched}]: {ok}/{len(res)} anchors initialised{extra}{errs}", warns)


def _log_initialisers(log: RunLog, results: dict, chosen: str, win: Windows) -> None:
    """Each method's anchors, the chosen one's covariance (3σ, then updated over refinement), the cost and FIM
    series."""
    for m, res in results.items():
        for a, r in res.items():
            if not r.ok:
                continue
            log.initialiser(a, m, r.x[:3])
            if m == chosen and np.all(np.isfinite(r.cov[:3, :3])):  # 3σ, then updated over refinement
                log.ellipsoids(rl.anchor_world(a, "cov"), r.x[:3], r.cov[None, :3, :3], t_ns=win.init_end_ns)
            if r.costs:
                t = np.linspace(win.start_ns, win.init_end_ns, len(r.costs)).astype(np.int64)
                log.scalars(rl.init(m, "cost") + f"/{a}", t, np.asarray(r.costs))
            if r.fim is not None:
                log.scalars(
                    rl.init(m, "fim_logdet") + f"/{a}",
                    [win.init_end_ns],
                    [r.fim.summary().get("logdet", np.nan)],
                )


def _lever_arms(ctx: StageContext, windows: dict):
    """``uwb.lever_arms = "planar"``: the windows with the planar carrier's estimated lever arms and the model
    (saved as lever_arms.pkl for refine and localize); else the windows as given and None."""

    cfg = ctx.config.uwb
    if ctx.dir.exists("lever_arms.pkl"):
        ctx.dir.file("lever_arms.pkl").unlink()
    if cfg.lever_arms != "planar":
        return windows, None
    sigma = cfg.sigma(ctx.reader.calibration) * cfg.sigma_scale
    windows, levers = planar_windows(
        windows, lambda w: search_window(w, cfg, sigma, ctx.reader.calibration, cfg.init_method, True), sigma
    )
    if levers is not None:
        ctx.dir.save_pickle("lever_arms.pkl", levers)
    return windows, levers


def _schedule(
    ctx: StageContext,
    windows: dict,
    init_end_ns: int,
    per_anchor: bool,
    whole: bool = False,
    starts: bool = False,
):
    """Per anchor: the window its initialisation uses, its search result and its join time
    (`schedule.join_time`); without the search (the paper's multi-start) the first window for every anchor.
    ``whole`` (per-anchor schedule with estimated planar lever arms, or poses of bounded error on the evidence
    path): every anchor from all its ranges, at the end. The arms come from every anchor's ranges over the whole
    recording, so an anchor initialised from a prefix would already lean on the later ranges and its refinement
    would count them twice; poses that do not drift leave the filter nothing to add to one robust fit over all
    the ranges, which relinearises where the filter's first-estimate Jacobians cannot. ``starts``: the fits only
    start the joint lever-arm fit (the evidence path fits again on the corrected ranges)."""

    cfg = ctx.config.uwb
    if not cfg.search:
        return {a: w.subset(w.t_ns < init_end_ns) for a, w in windows.items()}, None, {}
    sigma = cfg.sigma(ctx.reader.calibration) * cfg.sigma_scale
    out_w, searches, joins = {}, {}, {}
    for a, w in windows.items():
        end = init_end_ns
        if whole and per_anchor and len(w):
            end = int(w.t_ns.max()) + 1
        j = join_time(
            w,
            end,
            lambda sub: search_window(
                sub, cfg, sigma, ctx.reader.calibration, cfg.init_method, starts, ctx.pose_correlation_s()
            ),
            per_anchor=per_anchor and not whole,
            min_ranges=max(cfg.min_ranges, 30),
            join_sigma=cfg.join_sigma_m if per_anchor else None,
            join_ratio=cfg.join_ratio,
        )
        out_w[a], searches[a], joins[a] = j.window, j.search, j.join_ns
    return out_w, searches, joins
