"""`uwbcal experiment anchor-nees`: the anchors' NEES after initialisation and refinement, per pose source."""

from __future__ import annotations

import tempfile
from pathlib import Path

import numpy as np
import polars as pl

from uwbcal.convert.simulator import SimConfig, simulate_to_file
from uwbcal.evaluate.consistency import anchor_nees, chi2_bounds
from uwbcal.evaluate.evaluation import evaluate_stage
from uwbcal.evaluate.experiments.common import PAPER_INIT, parse_overrides
from uwbcal.evaluate.experiments.montecarlo import run_jobs, run_seeds
from uwbcal.pipeline.core.errors import InputError
from uwbcal.pipeline.run import artefacts
from uwbcal.pipeline.run.config import load_config, merge_dicts
from uwbcal.pipeline.run.stages.pipeline import Pipeline
from uwbcal.pipeline.uwb.updater import add_initialised_anchors, anchor_var

# groundtruth: the odometry source with (almost) no noise; the pose covariance must stay invertible
POSE_SOURCES = {"groundtruth": 1e-3, "odometry": None, "msckf": None, "msckf-loose": None}


def anchor_nees_job(p: dict) -> dict:
    """One seed: simulate, run vio + init once, then refine with each method from the same checkpoint.

    Rows per anchor: the NEES of (p_a, beta, gamma) right after the anchor joins the filter (``init``: the
    covariance and cross-covariances of `add_anchor_to_state`) and after each refinement. Pose sources:
    ``msckf`` (our VIO on simulated camera + IMU, anchors in its state: the paper's tightly coupled filter),
    ``msckf-loose`` (``run.coupling = "loose"``: the UWB stages on the same VIO's output),
    ``odometry`` (simulated odometry that drifts exactly as the odometry filter's drift model says, sigmas x
    ``odometry_noise_scale``: the pose noise is modelled correctly) and ``groundtruth`` (the same with a 1e-3
    scale)."""
    import shutil

    src = p["pose_source"]
    scale = POSE_SOURCES[src] or p["odometry_noise_scale"]
    vio = src.startswith("msckf")
    rows = []
    with tempfile.TemporaryDirectory(prefix="uwbcal-nees-") as tmp:
        rec = Path(tmp) / "sim.mcap"
        sim = SimConfig(
            trajectory=p["trajectory"] or None,
            seed=p["seed"],
            duration=p["duration"],
            camera=vio,
            odometry_rate=None if vio else 20.0,
            odometry_noise_scale=scale,
        )
        simulate_to_file(sim, rec)
        run = {
            "recording": str(rec),
            "log": False,
            "pose_source": "msckf" if vio else "odometry",
            "coupling": "loose" if src == "msckf-loose" else "tight",
            "schedule": "windows",
        }
        over = merge_dicts(PAPER_INIT, p.get("overrides") or {})
        base = Path(tmp) / "base"
        pipe = Pipeline(load_config(None, merge_dicts(over, {"run": run})), base, evaluate_stage)
        pipe.run(["vio", "init"], progress=lambda *_: None)
        cfg, cal = pipe.config, pipe.ctx.reader.calibration
        truth = {
            int(a): np.r_[t["position"], t["beta"], t["gamma"]]
            for a, t in pipe.ctx.reader.truth["anchors"].items()
        }
        results = pipe.dir.load_pickle("init.pkl", "init")[cfg.uwb.init_method]
        est = pipe.dir.load_pickle("checkpoint_init.pkl", "init")
        add_initialised_anchors(est.state, results, cfg.uwb, cal)
        for a, r in results.items():
            if r.ok:
                x, P = r.x, est.state.cov(anchor_var(a))
                rows.append(_nees_row(p, "init", a, anchor_nees(x, P, truth[int(a)]), x, truth[int(a)]))
        for method in p["methods"]:
            d = Path(tmp) / method
            shutil.copytree(base, d)
            mcfg = load_config(None, merge_dicts(over, {"run": run, "uwb": {"refine_method": method}}))
            Pipeline(mcfg, d, evaluate_stage).run(["refine"], progress=lambda *_: None)
            states = artefacts.read_json(d / "anchor_states.json", artefacts.ANCHOR_STATES)
            for a, s in states.items():
                x, P = np.asarray(s["x"]), np.asarray(s["P"])
                rows.append(_nees_row(p, method, a, anchor_nees(x, P, truth[int(a)]), x, truth[int(a)]))
    return {"rows": rows}


def _nees_row(p: dict, method: str, anchor, nees: float, x: np.ndarray, truth: np.ndarray) -> dict:
    return {
        "seed": p["seed"],
        "pose_source": p["pose_source"],
        "method": method,
        "anchor": str(anchor),
        "nees": float(nees),
        "error_m": float(np.linalg.norm(x[:3] - truth[:3])),
    }


def experiment(
    out: Path,
    runs: int,
    jobs: int,
    scheduler: str | None,
    seed: int,
    pose_sources: str = "groundtruth,odometry,msckf-loose,msckf",
    duration: float = 60.0,
    odometry_noise_scale: float = 0.1,
    trajectory: str = "",
    overrides: str = "",
) -> tuple[pl.DataFrame, dict]:
    """Anchor NEES (5 DoF) over ``runs`` seeds x anchors against the two-sided 95 % chi-square bounds of the
    ANEES, per pose source and stage (init = at augmentation, ekf/skf = after refinement)."""

    sources = [s.strip() for s in pose_sources.split(",") if s.strip()]
    bad = [s for s in sources if s not in POSE_SOURCES]
    if bad or not sources:
        raise InputError(
            f"anchor-nees: pose_sources {bad or pose_sources!r}; known: {', '.join(POSE_SOURCES)}"
        )
    params = [
        {
            "seed": s,
            "pose_source": src,
            "duration": float(duration),
            "odometry_noise_scale": float(odometry_noise_scale),
            "trajectory": trajectory,
            "methods": ("ekf", "skf"),
            "overrides": parse_overrides(overrides),
        }
        for src in sources
        for s in run_seeds(seed, runs)
    ]
    results = run_jobs(anchor_nees_job, params, jobs=jobs, scheduler=scheduler, description="anchor-nees")
    per_run = pl.DataFrame([r for res in results for r in res["rows"]])
    rows = []
    for (src, method), g in per_run.group_by("pose_source", "method", maintain_order=True):
        v = g["nees"].to_numpy()
        v = v[np.isfinite(v)]
        lo, hi = chi2_bounds(len(v), 5) if len(v) else (float("nan"), float("nan"))
        one = chi2_bounds(1, 5)
        rows.append(
            {
                "pose_source": src,
                "method": method,
                "values": len(v),
                "anees": float(v.mean()) if len(v) else float("nan"),
                "lo": lo,
                "hi": hi,
                "inside": bool(lo <= v.mean() <= hi) if len(v) else False,
                "median": float(np.median(v)) if len(v) else float("nan"),
                "share_single_inside": float(np.mean((v >= one[0]) & (v <= one[1]))) if len(v) else 0.0,
                "anchor_error_m": float(g["error_m"].mean()),
            }
        )
    table = pl.DataFrame(rows)
    summary: dict = {}
    for r in rows:  # `uwbcal diff` checks an ANEES against its sibling bounds
        key = f"{r['pose_source']}.{r['method']}"
        summary.update({f"{key}.anees": r["anees"], f"{key}.bounds": [r["lo"], r["hi"]]})
        summary[f"{key}.anchor_error_m"] = r["anchor_error_m"]
    return table, {"per_run": per_run, "summary": summary}
