"""`uwbcal experiment ntu-viral`: the paper's Table 2 on the real NTU-VIRAL ranges (VIRO, RI+EKF, RI+SKF)."""

from __future__ import annotations

import tempfile
from pathlib import Path

import polars as pl

from uwbcal.convert.datasets import data_root
from uwbcal.convert.ntu_viral import convert_ntu_viral
from uwbcal.evaluate.evaluation import evaluate_stage
from uwbcal.evaluate.experiments.common import PAPER_INIT
from uwbcal.evaluate.experiments.montecarlo import run_jobs
from uwbcal.evaluate.tables import PAPER_TABLE2, side_by_side
from uwbcal.pipeline.core.errors import InputError
from uwbcal.pipeline.run import artefacts
from uwbcal.pipeline.run.config import load_config
from uwbcal.pipeline.run.stages.pipeline import Pipeline

NTU_METHODS = {"viro": ("lsi", "ekf"), "ri+ekf": ("ri", "ekf"), "ri+skf": ("ri", "skf")}


def ntu_job(p: dict) -> dict:

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
        m = artefacts.read_json(Path(tmp) / "run" / "metrics.json", artefacts.METRICS)
    return {
        "sequence": folder.name,
        "method": p["method"],
        "prmse_m": m.get("prmse_m", {}).get("refine"),
        "anchor_error_m": m.get("anchor_error_m"),
        "anchors": {a: v.get("error_m") for a, v in m.get("anchors", {}).items()},
    }


def experiment(
    out: Path, runs: int, jobs: int, scheduler: str | None, seed: int
) -> tuple[pl.DataFrame, dict]:
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
