"""`uwbcal experiment`: the paper's experiments as seeded Monte Carlo sweeps (DESIGN §7).

Each experiment is a list of job parameters and one picklable job function; `montecarlo.run_jobs` runs them
in-process, on local processes (``--jobs``) or on a Dask cluster (``--scheduler``) with identical results.
An output folder holds the config, per-run metrics (parquet), tables (md/csv/tex), plots and ``summary.json``
(the flat metrics that `uwbcal diff` compares against ``recordings/reference/``).
"""

from __future__ import annotations

import json
import tempfile
import time
from pathlib import Path

import numpy as np
import polars as pl

from convert.datasets import data_root
from pipeline.core.atomic import atomic_path, write_text_atomic
from pipeline.core.errors import InputError

from .evaluation import evaluate_stage
from .montecarlo import run_jobs, run_seeds
from .ri_vs_lsi_drift import ri_vs_lsi_drift, vio_drift
from .tables import PAPER_TABLE1, PAPER_TABLE2, render, side_by_side, write_tables

RI_VS_LSI_SIGMAS = (0.05, 0.1, 0.2, 0.3, 0.5, 0.8)
TABLE1_CELLS = ((0.1, 1.0), (0.3, 1.0), (0.3, 0.9), (0.5, 0.9))
TABLE1_PRIORS = ("fixed", "tuned")
# prmse_m: over the refinement window; prmse_calib_m: over the whole calibration (initialisation + refinement
# windows, the reading of the paper's Table 2 caption "on calibration trajectory segments only")
TABLE1_METRICS = ("prmse_m", "prmse_calib_m", "anchor_error_m")
DEFAULT_RUNS = {"ri-vs-lsi": 100, "ri-vs-lsi-drift": 30, "table1": 50, "ntu-viral": 1, "anchor-nees": 25}


# -- ri-vs-lsi ----------------------------------------------------------------------------------------------------
def ri_vs_lsi_job(p: dict) -> dict:
    """One localisation-error level: `runs` seeded windows, every initialiser on each (common random numbers)."""
    from .ri_vs_lsi import ri_vs_lsi_sweep

    res = ri_vs_lsi_sweep([p["sigma_r"]], runs=p["runs"], seed=p["seed"])
    return {
        "sigma_r": p["sigma_r"],
        "errors": {m: e[0].tolist() for m, e in res["errors"].items()},
        "gamma_errors": {m: e[0].tolist() for m, e in res["gamma_errors"].items()},
    }


def _ri_vs_lsi(
    out: Path, runs: int, jobs: int, scheduler: str | None, seed: int
) -> tuple[pl.DataFrame, dict]:
    from .plots import plot_ri_vs_lsi

    params = [{"sigma_r": s, "runs": runs, "seed": seed} for s in RI_VS_LSI_SIGMAS]
    results = run_jobs(ri_vs_lsi_job, params, jobs=jobs, scheduler=scheduler, description="ri-vs-lsi")
    rows = [
        {
            "sigma_r": r["sigma_r"],
            "run": i,
            "method": m,
            "anchor_error_m": e,
            "gamma_error_m": r["gamma_errors"][m][i],
        }
        for r in results
        for m, errs in r["errors"].items()
        for i, e in enumerate(errs)
    ]
    per_run = pl.DataFrame(rows)
    table = (
        per_run.group_by("sigma_r", "method", maintain_order=True)
        .agg(
            pl.col("anchor_error_m").mean().alias("mean_m"),
            pl.col("anchor_error_m").median().alias("median_m"),
            pl.col("anchor_error_m").quantile(0.9).alias("p90_m"),
        )
        .sort("sigma_r", "method")
    )
    wide = per_run.pivot(on="method", index=["sigma_r", "run"], values="anchor_error_m")
    wins = wide.group_by("sigma_r", maintain_order=True).agg(
        (pl.col("ri") < pl.col("lsi")).mean().alias("ri_beats_lsi")
    )
    table = table.join(wins, on="sigma_r", how="left")
    errors = {m: np.array([r["errors"][m] for r in results]) for m in results[0]["errors"]}
    plot_ri_vs_lsi(out / "ri_vs_lsi.png", np.array(RI_VS_LSI_SIGMAS), errors)
    summary = {
        f"sigma_{r['sigma']:.2f}.{r['method']}.anchor_error_m": r["mean_m"]
        for r in table.rename({"sigma_r": "sigma"}).iter_rows(named=True)
    }
    return table, {"per_run": per_run, "summary": summary}


# -- table1 -------------------------------------------------------------------------------------------------------
def table1_job(p: dict) -> dict:
    """One seed of the EuRoC-trajectory simulation: VIO once, then every (σ_I, σ_U, method) cell from the same
    checkpoint. σ_I perturbs the initial anchor positions (per axis), σ_U scales the filter's range noise.

    ``prior`` is what the filter believes about that perturbation: ``fixed`` (default, the paper's setting as we
    read it: the extra error is injected after initialisation, so the filter keeps a prior of
    ``prior_sigma`` per axis whatever σ_I is), ``tuned`` (the prior σ equals σ_I, a consistent filter) or
    ``both`` (rows for each, labelled in ``prior``; a cell where the two priors agree is refined once)."""
    import pickle

    from convert.simulator import SimConfig, simulate_to_file
    from pipeline.config import load_config
    from pipeline.driver import run_estimator
    from pipeline.run import Pipeline
    from pipeline.state import Kind, Vec, remove_probes
    from pipeline.uwb_filter import UwbUpdater, anchor_var

    from .export import compare, load_ground_truth
    from .metrics import position_errors, prmse, rms
    from .vio_degrade import VioDegrade

    rng = np.random.default_rng(p["seed"])
    degrade = VioDegrade.of(p.get("vio_noise_scale", 1.0), p.get("vio_noise_told"))
    out = []
    with tempfile.TemporaryDirectory(prefix="uwbcal-table1-") as tmp:
        rec = Path(tmp) / "sim.mcap"
        sim = SimConfig(trajectory=p["trajectory"], seed=p["seed"], duration=p.get("duration"), n_anchors=4)
        simulate_to_file(degrade.sim(sim), rec)
        run = {"recording": str(rec), "log": False, "stages": ["vio"], "vio_extent": "init"}
        cfg = load_config(None, {**degrade.config(), "run": run})
        pipe = Pipeline(cfg, Path(tmp) / "run", evaluate_stage)
        pipe.run(progress=lambda *_: None)
        win = pipe.ctx.windows()
        truth = pipe.ctx.reader.truth["anchors"]
        cal = pipe.ctx.reader.calibration
        gt = load_ground_truth(rec)
        vio = pipe.dir.load_npz("vio.npz", "table1")
        drift = vio_drift(vio, gt, win.start_ns, win.init_end_ns)
        # both methods share the initialisation window's VIO: its errors open every cell's calibration PRMSE
        seg = (vio["t_ns"] >= win.start_ns) & (vio["t_ns"] < win.init_end_ns)
        c = compare(vio["t_ns"][seg], vio["p"][seg], vio["q_xyzw"][seg], gt)
        err_init = position_errors(c.p_est, c.p_gt)
        blob = pipe.dir.file("checkpoint_init.pkl").read_bytes()
        offsets = {a: rng.normal(size=3) for a in truth}  # one draw per seed, scaled by σ_I per cell
        priors = TABLE1_PRIORS if p["prior"] == "both" else (p["prior"],)
        for sigma_i, sigma_u in p["cells"]:
            # the prior conventions that give this cell the same filter prior share one refinement
            by_s0: dict[float, list[str]] = {}
            for prior in priors:
                by_s0.setdefault(sigma_i if prior == "tuned" else p["prior_sigma"], []).append(prior)
            for s0, same in by_s0.items():
                P0 = np.diag([s0**2] * 3 + [0.1**2, 0.5**2])
                for method in ("ekf", "skf"):
                    est = pickle.loads(blob)
                    # the anchors are placed by hand here, not initialised from the window's poses
                    remove_probes(est.state)
                    for a, t in truth.items():
                        x0 = np.r_[np.asarray(t["position"]) + sigma_i * offsets[a], 1.0, 0.0]
                        est.state.add(anchor_var(int(a)), Vec(x0), P0, kind=Kind.ANCHOR, key=int(a))
                    ucfg = cfg.uwb.model_copy(update={"sigma_scale": sigma_u, "refine_method": method})
                    upd = UwbUpdater.from_config(ucfg, cal)
                    run_estimator(est, pipe.ctx.reader, win.init_end_ns, win.refine_end_ns, on_range=upd)
                    h = est.history().arrays()
                    seg = (h["t_ns"] >= win.init_end_ns) & (h["t_ns"] < win.refine_end_ns)
                    c = compare(h["t_ns"][seg], h["p"][seg], h["q_xyzw"][seg], gt)
                    errs = [
                        np.linalg.norm(est.state.value(anchor_var(int(a))).x[:3] - np.asarray(t["position"]))
                        for a, t in truth.items()
                    ]
                    row = {
                        "seed": p["seed"],
                        "sigma_i": sigma_i,
                        "sigma_u": sigma_u,
                        "method": method,
                        "prmse_m": prmse(c.p_est, c.p_gt),
                        "prmse_calib_m": rms(np.r_[err_init, position_errors(c.p_est, c.p_gt)]),
                        "anchor_error_m": float(np.mean(errs)),
                        "rejected": upd.counts["rejected"],
                        **drift,
                    }
                    out += [{**row, "prior": prior} for prior in same]
    return {"rows": out}


def table1_beside_paper(per_run: pl.DataFrame) -> tuple[pl.DataFrame, pl.DataFrame]:
    """Per-run table1 rows -> (our cell means with the run count, the same beside the paper's Table 1); with
    several prior conventions in ``per_run`` one block per convention, led by a ``prior`` column."""
    if "prior" in per_run.columns and per_run["prior"].n_unique() > 1:
        parts = [
            table1_beside_paper(per_run.filter(pl.col("prior") == v).drop("prior"))
            for v in per_run["prior"].unique(maintain_order=True)
        ]
        names = per_run["prior"].unique(maintain_order=True).to_list()
        return tuple(  # type: ignore[return-value]
            pl.concat([t.select(pl.lit(n).alias("prior"), pl.all()) for n, t in zip(names, ts, strict=True)])
            for ts in zip(*parts, strict=True)
        )
    metrics = [m for m in TABLE1_METRICS if m in per_run.columns]
    ours = (
        per_run.group_by("sigma_i", "sigma_u", "method", maintain_order=True)
        .agg(*[pl.col(m).mean() for m in metrics], pl.len().alias("runs"))
        .sort("sigma_i", "sigma_u", "method", descending=[False, True, False])
    )
    paper = PAPER_TABLE1.with_columns(pl.col("method").str.to_lowercase())
    table = side_by_side(ours, paper, on=["sigma_i", "sigma_u", "method"], metrics=metrics)
    return ours, table


def _table1(
    out: Path,
    runs: int,
    jobs: int,
    scheduler: str | None,
    seed: int,
    trajectory: str = "MH_01_easy",
    duration: float | None = None,
    prior: str = "fixed",
    prior_sigma: float = 0.1,
    vio_noise_scale: float = 1.0,
    vio_noise_told: float | None = None,
) -> tuple[pl.DataFrame, dict]:
    """``vio_noise_scale``: the VIO-degrade knob (`vio_degrade`; 1 = the simulator's EuRoC-like sensors);
    ``vio_noise_told``: the factor the MSCKF is told instead (unset: the same, a consistently tuned VIO)."""
    from .vio_degrade import VioDegrade

    if prior not in (*TABLE1_PRIORS, "both"):
        raise InputError(
            f"table1: prior={prior!r}; use 'fixed', 'tuned' or 'both' (one VIO pass for the two)"
        )
    VioDegrade.of(vio_noise_scale, vio_noise_told)  # a bad value fails here, not in every worker
    params = [
        {
            "seed": s,
            "trajectory": trajectory,
            "duration": duration,
            "cells": TABLE1_CELLS,
            "prior": prior,
            "prior_sigma": float(prior_sigma),
            "vio_noise_scale": float(vio_noise_scale),
            "vio_noise_told": vio_noise_told,
        }
        for s in run_seeds(seed, runs)
    ]
    results = run_jobs(table1_job, params, jobs=jobs, scheduler=scheduler, description="table1")
    per_run = pl.DataFrame([r for res in results for r in res["rows"]])
    ours, table = table1_beside_paper(per_run)
    summary = {
        ("" if prior != "both" else f"{r['prior']}.")
        + f"si{r['sigma_i']}_su{r['sigma_u']}.{r['method']}.{k}": r[k]
        for r in ours.iter_rows(named=True)
        for k in TABLE1_METRICS
    }
    return table, {"per_run": per_run, "summary": summary}


# -- anchor-nees --------------------------------------------------------------------------------------------------
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

    from convert.simulator import SimConfig, simulate_to_file
    from pipeline.config import load_config, merge_dicts
    from pipeline.run import Pipeline
    from pipeline.uwb_filter import add_initialised_anchors, anchor_var

    from .consistency import anchor_nees

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
            states = json.loads((d / "anchor_states.json").read_text())
            for a, s in states.items():
                x, P = np.asarray(s["x"]), np.asarray(s["P"])
                rows.append(_nees_row(p, method, a, anchor_nees(x, P, truth[int(a)]), x, truth[int(a)]))
    return {"rows": rows}


def parse_overrides(text: str) -> dict:
    """``"vio.max_clones=30;uwb.chi2_quantile=0.99"`` -> nested config overrides (values parsed as JSON when
    they are JSON: numbers, true/false, null; else kept as strings)."""
    out: dict = {}
    for item in (t.strip() for t in text.split(";")):
        if not item:
            continue
        key, sep, value = item.partition("=")
        parts = [k.strip() for k in key.split(".")]
        if not sep or len(parts) < 2 or not all(parts):
            raise InputError(f"overrides: {item!r}: expected SECTION.KEY=VALUE (e.g. vio.max_clones=30)")
        try:
            v = json.loads(value)
        except json.JSONDecodeError:
            v = value.strip()
        node = out
        for k in parts[:-1]:
            node = node.setdefault(k, {})
        node[parts[-1]] = v
    return out


def _nees_row(p: dict, method: str, anchor, nees: float, x: np.ndarray, truth: np.ndarray) -> dict:
    return {
        "seed": p["seed"],
        "pose_source": p["pose_source"],
        "method": method,
        "anchor": str(anchor),
        "nees": float(nees),
        "error_m": float(np.linalg.norm(x[:3] - truth[:3])),
    }


def _anchor_nees(
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
    from .consistency import chi2_bounds

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


# -- ntu-viral ----------------------------------------------------------------------------------------------------
NTU_METHODS = {"viro": ("lsi", "ekf"), "ri+ekf": ("ri", "ekf"), "ri+skf": ("ri", "skf")}


# The paper's initialisation (its multi-start, global windows): the experiments reproduce the paper
PAPER_INIT: dict = {"uwb": {"search": False}}


def ntu_job(p: dict) -> dict:
    from convert.ntu_viral import convert_ntu_viral
    from pipeline.config import load_config
    from pipeline.run import Pipeline

    folder = Path(p["folder"])
    with tempfile.TemporaryDirectory(prefix="uwbcal-ntu-") as tmp:
        rec = Path(tmp) / f"{folder.name}.mcap"
        convert_ntu_viral(folder, rec)
        cfg = load_config(
            None,
            {
                "run": {"recording": str(rec), "log": False, "schedule": "windows"},
                "uwb": {**PAPER_INIT["uwb"], "init_method": p["init"], "refine_method": p["refine"]},
            },
        )
        Pipeline(cfg, Path(tmp) / "run", evaluate_stage).run(progress=lambda *_: None)
        m = json.loads((Path(tmp) / "run" / "metrics.json").read_text())
    return {
        "sequence": folder.name,
        "method": p["method"],
        "prmse_m": m.get("prmse_m", {}).get("refine"),
        "anchor_error_m": m.get("anchor_error_m"),
        "anchors": {a: v.get("error_m") for a, v in m.get("anchors", {}).items()},
    }


def _ntu(out: Path, runs: int, jobs: int, scheduler: str | None, seed: int) -> tuple[pl.DataFrame, dict]:
    root = data_root() / "ntu_viral"
    seqs = sorted(d for d in root.glob("*_0*") if (d / "uwb_ranges.csv").is_file()) if root.is_dir() else []
    if not seqs:
        raise InputError(f"{root}: no NTU-VIRAL sequence folders (set UWBCAL_DATA)")
    params = [
        {"folder": str(s), "method": m, "init": i, "refine": r}
        for s in seqs
        for m, (i, r) in NTU_METHODS.items()
    ]
    results = run_jobs(ntu_job, params, jobs=jobs, scheduler=scheduler, description="ntu-viral")
    ours = pl.DataFrame(
        [{k: v for k, v in r.items() if k != "anchors"} for r in results],
        schema={"sequence": pl.Utf8, "method": pl.Utf8, "prmse_m": pl.Float64, "anchor_error_m": pl.Float64},
    )
    table = side_by_side(ours, PAPER_TABLE2, on=["sequence", "method"], metrics=["prmse_m", "anchor_error_m"])
    summary = {
        f"{r['sequence']}.{r['method']}.{k}": r[k]
        for r in ours.iter_rows(named=True)
        for k in ("prmse_m", "anchor_error_m")
        if r[k] is not None
    }
    per_anchor = pl.DataFrame(
        [
            {"sequence": r["sequence"], "method": r["method"], "anchor": a, "error_m": e}
            for r in results
            for a, e in r["anchors"].items()
        ]
    )
    return table, {"per_run": per_anchor, "summary": summary}


EXPERIMENTS = {
    "ri-vs-lsi": _ri_vs_lsi,
    "ri-vs-lsi-drift": ri_vs_lsi_drift,
    "table1": _table1,
    "ntu-viral": _ntu,
    "anchor-nees": _anchor_nees,
}


def _experiment_params(name: str, raw: dict[str, str]) -> dict:
    """``--param KEY=VALUE`` pairs, checked against the experiment's keyword arguments and converted to their
    default's type; returns every keyword argument (defaults resolved, so config.json states them all)."""
    import inspect

    sig = inspect.signature(EXPERIMENTS[name])
    known = {k: v.default for k, v in sig.parameters.items() if v.default is not inspect.Parameter.empty}
    out = dict(known)
    for k, v in raw.items():
        if k not in known:
            raise InputError(
                f"experiment {name}: unknown parameter {k!r}; known: {', '.join(known) or 'none'}"
            )
        conv = float if known[k] is None else type(known[k])  # the optional ones are numbers (duration)
        try:
            out[k] = conv(v)
        except ValueError:
            raise InputError(f"experiment {name}: {k}={v!r} is not a {conv.__name__}") from None
    return out


def run_experiment(
    name: str,
    output: Path,
    *,
    runs: int | None = None,
    jobs: int = 1,
    scheduler: str | None = None,
    seed: int = 0,
    params: dict[str, str] | None = None,
) -> str:
    if name not in EXPERIMENTS:
        raise InputError(f"unknown experiment {name!r}; known: {', '.join(EXPERIMENTS)}")
    kwargs = _experiment_params(name, params or {})
    out = Path(output)
    out.mkdir(parents=True, exist_ok=True)
    runs = runs or DEFAULT_RUNS[name]
    config = {"experiment": name, "runs": runs, "jobs": jobs, "scheduler": scheduler, "seed": seed, **kwargs}
    write_text_atomic(out / "config.json", json.dumps(config, indent=2) + "\n")
    t0 = time.perf_counter()
    table, extra = EXPERIMENTS[name](out, runs, jobs, scheduler, seed, **kwargs)
    wall = time.perf_counter() - t0
    with atomic_path(out / "runs.parquet") as tmp:
        extra["per_run"].write_parquet(tmp)
    write_tables(table, out / name)
    summary = {name: extra["summary"], "runs": runs, "seed": seed, "wall_s": wall}
    write_text_atomic(out / "summary.json", json.dumps(summary, indent=2) + "\n")
    return f"{render(table, 'md')}\n\n{name}: {runs} run(s) per cell, {wall:.1f} s -> {out}"
