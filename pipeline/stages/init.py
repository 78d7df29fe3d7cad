"""Stage `init` (paper stage 1): every initialiser on the VIO poses of the initialisation window -> init.pkl,
init.json, the `init` rows of anchors.csv."""

from __future__ import annotations

import numpy as np

from pipeline.core.errors import InputError
from pipeline.core.names import INIT_METHODS

from .. import rundir as rd
from .. import runlog as rl
from .context import StageContext, StageResult


def run(ctx: StageContext) -> StageResult:
    from ..uwb_filter import initialize_anchors, windows_from_trajectory

    win = ctx.windows()
    vio = ctx.dir.load_npz("vio.npz", "init")
    cal = ctx.reader.calibration
    rng = ctx.reader.read_ranges(start_ns=win.start_ns, end_ns=win.init_end_ns)
    if len(rng) == 0:
        raise InputError(
            f"{ctx.recording}: no UWB ranges in the initialisation window "
            f"({win.start_ns * 1e-9:.1f}-{win.init_end_ns * 1e-9:.1f} s)"
        )
    windows = windows_from_trajectory(vio, vars(rng), cal, win.start_ns, win.init_end_ns)
    results = {m: initialize_anchors(windows, ctx.config.uwb, cal, method=m) for m in INIT_METHODS}
    ctx.dir.save_pickle("init.pkl", results)
    chosen = ctx.config.uwb.init_method
    summary = {m: {str(a): rd.init_summary(r) for a, r in res.items()} for m, res in results.items()}
    ctx.dir.save_json("init.json", {"chosen": chosen, "window": win.as_dict(), "methods": summary})
    rows = [rd.anchor_row(a, m, "init", r.x) for m, res in results.items() for a, r in res.items() if r.ok]
    rd.write_anchors(ctx.dir, rows, replace_stage="init")
    warns = [f"init {chosen} anchor {a}: {w}" for a, r in results[chosen].items() for w in r.warnings]
    warns += [f"init {chosen} anchor {a}: {r.status}" for a, r in results[chosen].items() if not r.ok]
    with ctx.runlog("init") as log:
        log.stage("init", win.start_ns)
        ctx.log_truth_anchors(log)
        log.legend(list(results))
        for m, res in results.items():
            for a, r in res.items():
                if not r.ok:
                    continue
                log.initialiser(a, m, r.x[:3])
                if m == chosen and np.all(np.isfinite(r.cov[:3, :3])):  # 3σ, then updated over refinement
                    log.ellipsoids(
                        rl.anchor_world(a, "cov"), r.x[:3], r.cov[None, :3, :3], t_ns=win.init_end_ns
                    )
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
    errs = ctx.anchor_errors({a: r.x for a, r in results[chosen].items() if r.ok})
    return StageResult("init", f"{chosen}: {ok}/{len(results[chosen])} anchors initialised{errs}", warns)
