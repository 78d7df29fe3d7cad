"""`uwbcal experiment`: the paper's experiments as seeded Monte Carlo sweeps.

Each experiment is a list of job parameters and one picklable job function; `montecarlo.run_jobs` runs them
in-process, on local processes (``--jobs``) or on a Dask cluster (``--scheduler``) with identical results.
An output folder holds the config, per-run metrics (parquet), tables (md/csv/tex), plots and ``summary.json``
(the flat metrics that `uwbcal diff` compares against ``recordings/reference/``).
"""

from __future__ import annotations

import inspect
import json
import time
from pathlib import Path

from uwbcal.evaluate.experiments import anchor_nees, ntu_viral, ri_vs_lsi, ri_vs_lsi_drift, table1
from uwbcal.evaluate.tables import render, write_tables
from uwbcal.pipeline.core.atomic import atomic_path, write_text_atomic
from uwbcal.pipeline.core.errors import InputError

DEFAULT_RUNS = {"ri-vs-lsi": 100, "ri-vs-lsi-drift": 30, "table1": 50, "ntu-viral": 1, "anchor-nees": 25}

EXPERIMENTS = {
    "ri-vs-lsi": ri_vs_lsi.experiment,
    "ri-vs-lsi-drift": ri_vs_lsi_drift.ri_vs_lsi_drift,
    "table1": table1.experiment,
    "ntu-viral": ntu_viral.experiment,
    "anchor-nees": anchor_nees.experiment,
}


def _experiment_params(name: str, raw: dict[str, str]) -> dict:
    """``--param KEY=VALUE`` pairs, checked against the experiment's keyword arguments and converted to their
    default's type; returns every keyword argument (defaults resolved, so config.json states them all)."""
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
