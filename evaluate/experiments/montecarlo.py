"""Seeded, reproducible Monte Carlo execution: in-process, on local worker processes, or on a Dask cluster.

A job is a picklable top-level function called with one dict of parameters (which includes its own seed) and
returning a flat dict of results. The same parameters give the same result wherever the job runs, so the
three executors give identical tables for the same seeds.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Sequence
from concurrent.futures import ProcessPoolExecutor, as_completed
from typing import Any

import numpy as np
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn

from uwbcal.pipeline.core.blas import limit_blas_threads

Job = Callable[[dict[str, Any]], dict[str, Any]]


def run_seeds(base_seed: int, n: int) -> list[int]:
    """Independent per-run seeds derived from one base seed (stable across executors and job counts)."""
    children = np.random.SeedSequence(base_seed).spawn(n)
    return [int(c.generate_state(1)[0]) for c in children]


def _progress(description: str) -> Progress:
    return Progress(
        TextColumn("[bold]{task.description}"),
        BarColumn(),
        MofNCompleteColumn(),
        TimeRemainingColumn(),
        transient=False,
        disable=not os.isatty(2),
    )


def _worker_init() -> None:
    """One BLAS thread per worker process: ``jobs`` workers each running a multi-threaded BLAS would put
    ``jobs x cores`` threads on the cores."""

    limit_blas_threads(1)


def run_jobs(
    job: Job,
    params: Sequence[dict[str, Any]],
    *,
    jobs: int = 1,
    scheduler: str | None = None,
    description: str = "runs",
) -> list[dict[str, Any]]:
    """Run ``job`` over ``params``; results come back in the order of ``params``."""
    results: list[dict[str, Any] | None] = [None] * len(params)
    with _progress(description) as progress:
        task = progress.add_task(description, total=len(params))
        if scheduler:
            from distributed import Client
            from distributed import as_completed as dask_completed

            with Client(scheduler) as client:
                futures = client.map(job, list(params), pure=False)
                index = {f.key: i for i, f in enumerate(futures)}
                for fut in dask_completed(futures):
                    results[index[fut.key]] = fut.result()
                    progress.advance(task)
        elif jobs <= 1:
            for i, p in enumerate(params):
                results[i] = job(p)
                progress.advance(task)
        else:
            with ProcessPoolExecutor(max_workers=jobs, initializer=_worker_init) as pool:
                futs = {pool.submit(job, p): i for i, p in enumerate(params)}
                for fut in as_completed(futs):
                    results[futs[fut]] = fut.result()
                    progress.advance(task)
    return [r for r in results if r is not None]
