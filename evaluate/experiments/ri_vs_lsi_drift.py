"""`uwbcal experiment ri-vs-lsi-drift`: RI vs LSI on the VIO's own poses as the VIO degrades (paper Fig. "init
comparison", with the simulated EuRoC flight and our MSCKF instead of synthetic pose errors).

Per drift level (``vio.noise_scale`` k, `vio_degrade`) and seed: simulate the trajectory with the degraded sensors,
run the VIO over the initialisation window and every initialiser on its poses (the paper's global windows, no
search), and record each anchor's error per method together with the VIO's own position sigma (RMS over the
window of sqrt(trace(P_p)/3)) and its actual position RMSE over the window. The x axis of the result is the
VIO's own sigma, not k: that is what the robust initialiser is given.
"""

from __future__ import annotations

import tempfile
from pathlib import Path

import numpy as np
import polars as pl

from uwbcal.convert.simulator import SimConfig, simulate_to_file
from uwbcal.evaluate.evaluation import evaluate_stage
from uwbcal.evaluate.experiments.common import PAPER_INIT
from uwbcal.evaluate.experiments.montecarlo import run_jobs, run_seeds
from uwbcal.evaluate.experiments.paired import paired_difference
from uwbcal.evaluate.experiments.vio_degrade import VioDegrade
from uwbcal.evaluate.export import compare, load_ground_truth
from uwbcal.evaluate.plots import plot_ri_vs_lsi_drift
from uwbcal.pipeline.core.errors import InputError
from uwbcal.pipeline.run.config import load_config, merge_dicts
from uwbcal.pipeline.run.stages.pipeline import Pipeline

DEFAULT_LEVELS = "1,2,3,4,6"  # k = 10 diverges on MH_01 (PRMSE ~6 m)


def parse_levels(text: str) -> list[float]:
    """``"1,2,4"`` -> [1.0, 2.0, 4.0]; InputError on anything but distinct numbers in (0, 100]."""
    try:
        levels = [float(t) for t in text.split(",") if t.strip()]
    except ValueError:
        raise InputError(
            f"vio_noise_scales={text!r}: expected comma-separated numbers, e.g. 1,2,4,8"
        ) from None
    if not levels or len(set(levels)) != len(levels) or not all(0 < v <= 100 for v in levels):
        raise InputError(f"vio_noise_scales={text!r}: expected distinct numbers in (0, 100], e.g. 1,2,4,8")
    return sorted(levels)


def vio_drift(hist: dict, gt, t0_ns: int, t1_ns: int) -> dict:
    """The VIO's own position sigma (RMS of sqrt(trace(P_p)/3)) and its position RMSE (per axis, so the two
    compare directly) over [t0, t1)."""

    seg = (hist["t_ns"] >= t0_ns) & (hist["t_ns"] < t1_ns)
    Pp = hist["cov"][seg][:, 3:6, 3:6]
    sigma = float(np.sqrt(np.mean(np.trace(Pp, axis1=1, axis2=2) / 3.0)))
    c = compare(hist["t_ns"][seg], hist["p"][seg], hist["q_xyzw"][seg], gt)
    rmse = float(np.sqrt(np.mean((c.p_est - c.p_gt) ** 2)))
    return {"vio_sigma_m": sigma, "vio_rmse_m": rmse}


def drift_job(p: dict) -> dict:
    """One (level, seed): per-anchor errors of every initialiser on the degraded VIO's poses."""

    degrade = VioDegrade.of(p["vio_noise_scale"])
    rows = []
    with tempfile.TemporaryDirectory(prefix="uwbcal-drift-") as tmp:
        rec = Path(tmp) / "sim.mcap"
        traj = p["trajectory"] or None  # "": the built-in trajectory
        sim = SimConfig(trajectory=traj, seed=p["seed"], duration=p.get("duration"), n_anchors=4)
        simulate_to_file(degrade.sim(sim), rec)
        run = {"recording": str(rec), "log": False, "schedule": "windows", "vio_extent": "init"}
        cfg = load_config(None, merge_dicts(merge_dicts(PAPER_INIT, degrade.config()), {"run": run}))
        pipe = Pipeline(cfg, Path(tmp) / "run", evaluate_stage)
        pipe.run(["vio", "init"], progress=lambda *_: None)
        win = pipe.ctx.windows()
        truth = pipe.ctx.reader.truth["anchors"]
        hist = pipe.dir.load_npz("vio.npz", "ri-vs-lsi-drift")
        drift = vio_drift(hist, load_ground_truth(rec), win.start_ns, win.init_end_ns)
        results = pipe.dir.load_pickle("init.pkl", "ri-vs-lsi-drift")
        for method, res in results.items():
            for a, t in truth.items():
                r = res.get(int(a))
                ok = r is not None and r.ok
                err = float(np.linalg.norm(r.x[:3] - np.asarray(t["position"]))) if ok else float("nan")
                rows.append(
                    {
                        "vio_noise_scale": p["vio_noise_scale"],
                        "seed": p["seed"],
                        "anchor": int(a),
                        "method": method,
                        "anchor_error_m": err,
                        **drift,
                    }
                )
    return {"rows": rows}


def summarise(per_run: pl.DataFrame, a: str = "lsi", b: str = "ri") -> pl.DataFrame:
    """Per level: the VIO's mean own sigma and RMSE, and per method the mean, median and 90th percentile of the
    anchor error (over seeds x anchors; ``{method}_failed``: anchors it left undetermined); ``b_gain_m`` = mean of the paired difference a - b (positive: b better),
    ``b_gain_lo/hi`` its 95 % t interval over the (seed, anchor) pairs, ``b_wins`` the share of pairs b wins."""

    out = []
    for k, g in per_run.group_by("vio_noise_scale", maintain_order=True):
        row: dict = {
            "vio_noise_scale": k[0],
            "vio_sigma_m": float(g["vio_sigma_m"].mean()),
            "vio_rmse_m": float(g["vio_rmse_m"].mean()),
        }
        for m in (a, b):
            all_e = g.filter(pl.col("method") == m)["anchor_error_m"]
            e = all_e.drop_nans().to_numpy()
            row |= {
                f"{m}_failed": len(all_e) - len(e),
                f"{m}_mean_m": float(e.mean()) if len(e) else float("nan"),
                f"{m}_median_m": float(np.median(e)) if len(e) else float("nan"),
                f"{m}_p90_m": float(np.quantile(e, 0.9)) if len(e) else float("nan"),
            }
        wide = g.pivot(on="method", index=["seed", "anchor"], values="anchor_error_m")
        d = paired_difference(wide[a].to_numpy(), wide[b].to_numpy())
        row |= {f"{b}_gain_m": d.mean, f"{b}_gain_lo": d.lo, f"{b}_gain_hi": d.hi, f"{b}_wins": d.share_b}
        out.append(row)
    return pl.DataFrame(out).sort("vio_noise_scale")


def ri_vs_lsi_drift(
    out: Path,
    runs: int,
    jobs: int,
    scheduler: str | None,
    seed: int,
    vio_noise_scales: str = DEFAULT_LEVELS,
    trajectory: str = "MH_01_easy",
    duration: float | None = None,
) -> tuple[pl.DataFrame, dict]:
    """The experiment: ``runs`` seeds per level (the same seeds at every level: common random numbers)."""

    levels = parse_levels(vio_noise_scales)
    params = [
        {"vio_noise_scale": k, "seed": s, "trajectory": trajectory, "duration": duration}
        for k in levels
        for s in run_seeds(seed, runs)
    ]
    results = run_jobs(drift_job, params, jobs=jobs, scheduler=scheduler, description="ri-vs-lsi-drift")
    per_run = pl.DataFrame([r for res in results for r in res["rows"]])
    table = summarise(per_run)
    plot_ri_vs_lsi_drift(out / "ri_vs_lsi_drift.png", table)
    summary = {
        f"k{r['vio_noise_scale']:g}.{m}.anchor_error_m": r[f"{m}_mean_m"]
        for r in table.iter_rows(named=True)
        for m in ("lsi", "ri")
    }
    return table, {"per_run": per_run, "summary": summary}
