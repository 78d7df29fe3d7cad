"""`uwbcal bench`: every case runs in its own process; we report wall time, CPU time (user + system of the case
and its finished children: less sensitive to other load than wall time), real-time factor (data seconds / wall),
peak memory and the ratio to the case's baseline measured in the same invocation (machines are noisy: ratios,
not seconds).

``--against TREE`` also runs every case on another checkout of uwbcal (e.g. a ``git worktree`` of main) in the
same invocation, alternating the two trees case by case, and reports the speed-up of this tree over it."""

from __future__ import annotations

import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from dataclasses import asdict, dataclass
from pathlib import Path

from uwbcal.benchmarks.cases import CASES
from uwbcal.convert.datasets import data_root
from uwbcal.pipeline.core.atomic import write_text_atomic
from uwbcal.pipeline.core.errors import InputError


@dataclass
class BenchResult:
    case: str
    wall_s: float
    cpu_s: float | None  # the case's timed part (as the case reports it)
    peak_rss_mb: float
    data_s: float | None
    realtime_factor: float | None
    baseline: str | None
    ratio_to_baseline: float | None
    extra: dict
    ok: bool
    error: str | None = None
    process_cpu_s: float | None = None  # the whole case process incl. its children (setup too)


def _child_command(name: str, quick: bool, tree: Path | None, tmp: Path) -> tuple[list[str], dict]:
    """The command (and environment) that runs one case, from this install or from another checkout ``tree``.

    A checkout of the one-package layout (a root ``__init__.py``) is imported as ``uwbcal`` through a symlink
    in ``tmp``; an older flat checkout by its top-level ``benchmarks`` package."""
    flags = ["--quick"] if quick else []
    env = dict(os.environ)
    env.setdefault("OPENBLAS_NUM_THREADS", "1")  # many small matrices: BLAS threads only cost
    if tree is None:
        return [sys.executable, "-m", "uwbcal.benchmarks.cases", name, *flags], env
    env.setdefault("UWBCAL_DATA", str(data_root()))  # the other tree may have no data folder beside it
    if (tree / "__init__.py").is_file():
        (tmp / "uwbcal").symlink_to(tree, target_is_directory=True)
        path, module = tmp, "uwbcal.benchmarks.cases"
    else:
        path, module = tree, "benchmarks.cases"
    env["PYTHONPATH"] = os.pathsep.join([str(path)] + ([env["PYTHONPATH"]] if env.get("PYTHONPATH") else []))
    return [sys.executable, "-m", module, name, *flags], env


def _run_in_child(name: str, quick: bool, tree: Path | None = None) -> BenchResult:
    """Run one case in a child process; ``tree``: import uwbcal from that checkout instead of this one."""
    with tempfile.TemporaryDirectory(prefix="uwbcal-bench-") as tmp:
        cmd, env = _child_command(name, quick, tree, Path(tmp))
        return _measure_child(name, cmd, env, tree)


def _measure_child(name: str, cmd: list[str], env: dict | None, tree: Path | None) -> BenchResult:
    c0 = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=tree, env=env)
    out, err = proc.communicate()
    wall = time.perf_counter() - t0
    c1 = resource.getrusage(resource.RUSAGE_CHILDREN)
    proc_cpu = (c1.ru_utime + c1.ru_stime) - (c0.ru_utime + c0.ru_stime)
    # ru_maxrss of RUSAGE_CHILDREN is the max over all children so far; read this child's own figure from it
    # via the value the child reports about itself (it measures its own peak incl. grandchildren it waited on).
    payload: dict = {}
    for line in out.splitlines()[::-1]:
        if line.startswith("{"):
            payload = json.loads(line)
            break
    if proc.returncode != 0 or not payload:
        tail = (err or out).strip().splitlines()[-3:]
        return BenchResult(name, wall, None, 0.0, None, None, None, None, {}, False, " | ".join(tail))
    data_s = payload.get("data_s")
    return BenchResult(
        case=name,
        wall_s=payload.get("wall_s", wall),
        cpu_s=payload.get("cpu_s"),
        peak_rss_mb=payload.get("peak_rss_mb", 0.0),
        data_s=data_s,
        realtime_factor=(data_s / payload["wall_s"]) if data_s and payload.get("wall_s") else None,
        baseline=CASES[name].baseline,
        ratio_to_baseline=None,
        extra=payload.get("extra", {}),
        ok=True,
        process_cpu_s=proc_cpu,
    )


def _cases_of(tree: Path) -> set[str]:
    """The case names another checkout's ``benchmarks/cases.py`` registers (an older tree may lack new ones)."""
    import re

    text = (tree / "benchmarks" / "cases.py").read_text()
    return set(re.findall(r'^\s+"(\w+)": Case\(', text, flags=re.M))


def _check_tree(tree: Path) -> Path:

    tree = Path(tree).resolve()
    if not (tree / "benchmarks" / "cases.py").is_file():
        raise InputError(f"{tree}: not a uwbcal checkout (no benchmarks/cases.py); give the root of one")
    return tree


def run_benchmarks(
    output: Path | None, cases: str | None = None, quick: bool = False, against: Path | None = None
) -> str:

    names = [c.strip() for c in cases.split(",")] if cases else list(CASES)
    unknown = [n for n in names if n not in CASES]
    if unknown:
        raise InputError(f"unknown benchmark case(s) {unknown}; known: {sorted(CASES)}")
    other_tree = _check_tree(against) if against is not None else None
    load_start = os.getloadavg()
    # baselines run first so that every ratio is measured in this same invocation
    needed = []
    for n in names:
        b = CASES[n].baseline
        if b and b not in needed and b not in names:
            needed.append(b)
    results: dict[str, BenchResult] = {}
    other: dict[str, BenchResult] = {}
    other_cases = _cases_of(other_tree) if other_tree is not None else set()
    for n in needed + names:
        if n in other_cases:  # alternate the trees so that load changes hit both alike
            other[n] = _run_in_child(n, quick, other_tree)
        results[n] = _run_in_child(n, quick)
    for r in results.values():
        if r.baseline and r.ok and results.get(r.baseline) and results[r.baseline].ok:
            r.ratio_to_baseline = r.wall_s / results[r.baseline].wall_s
    load = os.getloadavg()
    lines = [
        f"machine: {os.cpu_count()} CPUs, load average {load[0]:.2f} / {load[1]:.2f} / {load[2]:.2f} (1/5/15 min; "
        f"at the start {load_start[0]:.2f} / {load_start[1]:.2f} / {load_start[2]:.2f})",
        f"{'case':<28} {'wall s':>8} {'cpu s':>8} {'RTF':>8} {'peak MB':>9} {'ratio':>7}  baseline / note",
    ]
    for r in results.values():
        if not r.ok:
            lines.append(f"{r.case:<28} FAILED: {r.error}")
            continue
        rtf = f"{r.realtime_factor:8.1f}" if r.realtime_factor else f"{'-':>8}"
        ratio = f"{r.ratio_to_baseline:7.2f}" if r.ratio_to_baseline else f"{'-':>7}"
        note = r.baseline or ""
        if r.extra:
            note += " " + ", ".join(f"{k}={v}" for k, v in r.extra.items())
        cpu = f"{r.cpu_s:8.2f}" if r.cpu_s is not None else f"{'-':>8}"
        lines.append(f"{r.case:<28} {r.wall_s:8.2f} {cpu} {rtf} {r.peak_rss_mb:9.0f} {ratio}  {note.strip()}")
    if other_tree is not None:
        lines += ["", f"against {other_tree} (same invocation, alternating):"]
        lines.append(
            f"{'case':<28} {'this s':>8} {'other s':>8} {'speed-up':>9} {'cpu speed-up':>13}  other's note"
        )
        for n, r in results.items():
            o = other.get(n)
            if o is None:
                lines.append(f"{n:<28} (not a case of {other_tree.name})")
                continue
            if not (r.ok and o.ok):
                lines.append(f"{n:<28} FAILED: {(r.error if not r.ok else o.error)}")
                continue
            note = ", ".join(f"{k}={v}" for k, v in o.extra.items())
            # whole case processes (setup included): the older tree may not report its timed CPU
            rc, oc = r.process_cpu_s, o.process_cpu_s
            cpu = f"{oc / rc:12.2f}x" if rc and oc else f"{'-':>13}"
            lines.append(f"{n:<28} {r.wall_s:8.2f} {o.wall_s:8.2f} {o.wall_s / r.wall_s:8.2f}x {cpu}  {note}")
    if output:
        doc = {
            "machine": {
                "cpus": os.cpu_count(),
                "python": sys.version.split()[0],
                "load_avg_1_5_15": [round(x, 2) for x in load],
                "load_avg_1_5_15_at_start": [round(x, 2) for x in load_start],
            },
            "quick": quick,
            "results": [asdict(r) for r in results.values()],
        }
        if other_tree is not None:
            doc["against"] = {"tree": str(other_tree), "results": [asdict(r) for r in other.values()]}
        write_text_atomic(output, json.dumps(doc, indent=2))
    return "\n".join(lines)
