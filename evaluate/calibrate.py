"""``uwbcal calibrate INPUT -o OUT``: a dataset in, calibrated anchors out, in one command.

INPUT is a ROS 1 / ROS 2 bag, a EuRoC folder (``mav0/``), an NTU-VIRAL sequence folder (``uwb_ranges.csv``), a
folder holding ``poses.tum`` + ``ranges.csv`` (tabular), or a uwbcal recording; ``--poses TUM --ranges CSV`` names
the tabular files instead. Beside the data, ``antennas.yaml`` / ``uwb_antennas.yaml``, ``anchors_truth.csv`` and a
bag's ``calibration.yaml`` are used when present (the summary says so). OUT gets ``recording.mcap``, ``check.txt``
(`uwbcal check`), ``run/`` (the pipeline with its defaults, evaluated when truth exists), ``anchors.json``,
``uwb_anchors.yaml`` + ``localization.yaml`` (with covariance) and ``report.html``.
"""

from __future__ import annotations

import contextlib
import os
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from uwbcal.convert.bag import convert_bag, is_bag
from uwbcal.convert.euroc import convert_euroc
from uwbcal.convert.ntu_viral import convert_ntu_viral
from uwbcal.convert.recording import written_by_uwbcal
from uwbcal.convert.tabular import convert_tabular
from uwbcal.evaluate.anchors_export import export_anchors
from uwbcal.evaluate.check import check_recording
from uwbcal.evaluate.evaluation import evaluate_stage
from uwbcal.evaluate.report import write_report
from uwbcal.pipeline.core.atomic import write_text_atomic
from uwbcal.pipeline.core.errors import InputError
from uwbcal.pipeline.core.names import STAGES
from uwbcal.pipeline.run import artefacts
from uwbcal.pipeline.run.config import load_config
from uwbcal.pipeline.run.provenance import claim, recording_id, recording_record
from uwbcal.pipeline.run.rundir import RunDir
from uwbcal.pipeline.run.stages.pipeline import Pipeline

ANTENNA_NAMES = ("antennas.yaml", "uwb_antennas.yaml")


@dataclass
class CalibrateInput:
    """What the user gave (paths may be None: found beside the data)."""

    path: Path | None = None
    poses: Path | None = None
    ranges: Path | None = None
    antennas: Path | None = None
    anchors_truth: Path | None = None
    calibration: Path | None = None
    stamp_unit: str | None = None
    time_offset: float = 0.0
    config: Path | None = None
    log: bool = False
    overwrite: bool = False  # replace OUT's calibration of another input


RECORDING = "recording.mcap"
STAGED = ".recording.incoming.mcap"  # a conversion waits here until OUT is known to be free for it
# what `calibrate` writes beside its run directory (``run/``, whose artefacts `provenance.claim` clears)
OUTPUTS = (
    RECORDING,
    "convert.txt",
    "check.txt",
    "anchors.json",
    "uwb_anchors.yaml",
    "localization.yaml",
    "report.html",
)


@dataclass
class Conversion:
    kind: str
    recording: Path
    notes: list[str] = field(default_factory=list)
    text: str = ""  # the converter's summary (convert.txt)


def claim_output(out: Path, conv: Conversion, overwrite: bool) -> Conversion:
    """Make OUT the calibration of this input before anything in it is replaced: a calibration of another
    input there (its recording.mcap, or its run directory's stages) is refused, or with ``overwrite`` removed
    first; then the staged conversion becomes ``out/recording.mcap``."""
    record = recording_record(conv.recording)
    prior = out / RECORDING
    other = conv.kind != "recording" and prior.is_file() and recording_id(prior) != record["id"]
    if other and not overwrite:
        raise InputError(
            f"{out}: holds the calibration of another input ({prior}); choose another output directory, or "
            "pass --overwrite to replace it"
        )
    claim(RunDir(out / "run"), record, list(STAGES), overwrite)  # refuses, or clears, another recording's run
    if other:
        for name in OUTPUTS:
            with contextlib.suppress(FileNotFoundError):
                (out / name).unlink()
    if conv.kind == "recording":
        return conv
    os.replace(conv.recording, prior)
    write_text_atomic(out / "convert.txt", conv.text + "\n")
    return Conversion(conv.kind, prior, conv.notes, conv.text)


def _beside(
    folder: Path, names: tuple[str, ...], given: Path | None, notes: list[str], what: str
) -> Path | None:
    if given is not None:
        return given
    for n in names:
        if (folder / n).is_file():
            notes.append(f"{what}: {folder / n} (found beside the data)")
            return folder / n
    return None


def _kind(inp: CalibrateInput) -> str:
    p = inp.path
    if inp.poses is not None or inp.ranges is not None:
        if inp.poses is None or inp.ranges is None:
            raise InputError("--poses and --ranges go together (a TUM trajectory and a ranges CSV)")
        return "tabular"
    if p is None:
        raise InputError("calibrate: give INPUT (bag, dataset folder, recording) or --poses TUM --ranges CSV")
    if not p.exists():
        raise InputError(f"{p}: no such file or folder")
    if p.is_file() and p.suffix == ".mcap" and written_by_uwbcal(p):
        return "recording"
    if is_bag(p):
        return "bag"
    if p.is_dir() and (p / "mav0").is_dir() or p.name == "mav0":
        return "euroc"
    if p.is_dir() and (p / "uwb_ranges.csv").is_file():
        return "ntu-viral"
    if p.is_dir() and (p / "poses.tum").is_file() and (p / "ranges.csv").is_file():
        return "tabular"
    raise InputError(
        f"{p}: not a bag, EuRoC folder (mav0/), NTU-VIRAL sequence (uwb_ranges.csv), tabular folder "
        "(poses.tum + ranges.csv) or uwbcal recording; or give --poses TUM --ranges CSV"
    )


def convert_input(inp: CalibrateInput, out: Path) -> Conversion:
    """The input converted into ``out/STAGED`` (`claim_output` moves it to ``out/recording.mcap``; a recording is
    used where it is)."""
    kind = _kind(inp)
    rec = out / STAGED
    notes: list[str] = []
    if kind == "recording":
        return Conversion(kind, inp.path, notes)
    data = inp.path or inp.ranges
    folder = data if data.is_dir() and kind != "bag" else data.parent  # a ROS 2 bag folder: beside it
    truth = _beside(folder, ("anchors_truth.csv",), inp.anchors_truth, notes, "anchor truth")
    if kind == "tabular":
        poses, ranges = inp.poses or folder / "poses.tum", inp.ranges or folder / "ranges.csv"
        ant = _beside(folder, ANTENNA_NAMES, inp.antennas, notes, "lever arms")
        text = convert_tabular(
            poses,
            ranges,
            rec,
            ant,
            anchors_truth=truth,
            stamp_unit=inp.stamp_unit,
            time_offset=inp.time_offset,
        )
    elif kind == "bag":
        cal = _beside(folder, ("calibration.yaml",), inp.calibration, notes, "calibration")
        ant = _beside(folder, ANTENNA_NAMES, inp.antennas, notes, "lever arms")
        text = convert_bag(
            inp.path, rec, antennas=ant, calibration=cal, time_offset=inp.time_offset, anchors_truth=truth
        )
    elif kind == "euroc":
        text = convert_euroc(inp.path, rec)
    else:
        text = convert_ntu_viral(inp.path, rec, antennas=inp.antennas, anchors_truth=truth)
    return Conversion(kind, rec, notes, text.replace(str(rec), str(out / RECORDING)))


def _sigma_text(a: dict) -> str:
    s = np.asarray(a.get("sigma_xyz") or [np.nan] * 3, float)
    return f"{np.hypot(s[0], s[1]):.2f}/{s[2]:.2f}"


def summary_lines(out: Path, metrics: dict, check_text: str, files: list[Path]) -> list[str]:
    """The five lines `uwbcal calibrate` prints."""
    anchors = metrics.get("anchors") or {}
    est = [a for a, v in anchors.items() if v.get("determined", True) and v.get("estimate")]
    nd = {a: v.get("reason") or "not determined" for a, v in anchors.items() if a not in est}
    nd_text = "; ".join(f"{a}: {r}" for a, r in nd.items()) or "none"
    problems = [ln for ln in check_text.splitlines() if ln.startswith("PROBLEM ")]
    err = metrics.get("anchor_error_m")
    ref = metrics.get("anchor_reference")
    if err is not None:
        h = ((metrics.get("anchor_truth") or {}).get("error_horizontal_m") or {}).get("mean")
        truth = f"vs {ref}: 3-D mean {err:.3f} m" + (f", horizontal mean {h:.3f} m" if h is not None else "")
    elif ref:
        pairs = ((metrics.get("anchor_truth") or {}).get("inter_anchor_distance_error_m") or {}).get(
            "mean_abs"
        )
        truth = (
            f"vs {ref} (another frame): inter-anchor distances mean |e| {pairs:.3f} m" if pairs else str(ref)
        )
    else:
        truth = "no anchor truth: not evaluated"
    return [
        f"anchors   {len(est)} estimated ({', '.join(est) or 'none'}); not determined: {nd_text}",
        "sigma     "
        + (", ".join(f"{a} {_sigma_text(anchors[a])}" for a in est) or "-")
        + "  (m, horizontal/z)",
        f"truth     {truth}",
        f"check     {len(problems)} problem(s) in {out / 'check.txt'}"
        + (f": {problems[0][8:][:90]}..." if problems else ""),
        "files     " + ", ".join(str(f) for f in files),
    ]


def calibrate(inp: CalibrateInput, out: str | Path, progress: Callable[[str], None] = print) -> str:
    """Convert, check, run with the defaults, evaluate, export and report; returns the five-line summary."""
    out = Path(out)
    created = not out.exists()
    out.mkdir(parents=True, exist_ok=True)
    try:
        conv = claim_output(out, convert_input(inp, out), inp.overwrite)
    except InputError:
        if created:  # a refused input leaves no empty output directory behind
            with contextlib.suppress(OSError):
                out.rmdir()
        raise
    finally:
        with contextlib.suppress(FileNotFoundError):
            (out / STAGED).unlink()
    for n in conv.notes:
        progress(f"note: {n}")
    progress(f"[convert] {conv.kind} -> {conv.recording}")
    check_text = check_recording(conv.recording).render()
    write_text_atomic(out / "check.txt", check_text + "\n")
    progress(f"[check] {sum(ln.startswith('PROBLEM ') for ln in check_text.splitlines())} problem(s)")
    overrides = {"run": {"recording": str(conv.recording.resolve()), "log": inp.log}}
    pipe = Pipeline(load_config(inp.config, overrides), out / "run", evaluator=evaluate_stage)
    pipe.run(progress=progress)
    files = [out / "anchors.json", out / "uwb_anchors.yaml", out / "localization.yaml"]
    try:
        export_anchors(pipe.dir.path, out, "anchors-json")
        export_anchors(pipe.dir.path, out, "anchors-yaml")
    except InputError as exc:  # no anchor determined: the report and the summary say why
        progress(f"note: nothing exported ({exc})")
        files = []
    report = write_report(pipe.dir.path, out / "report.html", check_text=check_text)
    metrics = (
        artefacts.read_json(pipe.dir.file("metrics.json"), artefacts.METRICS)
        if pipe.dir.exists("metrics.json")
        else {}
    )
    return "\n".join(summary_lines(out, metrics, check_text, [*files, report]))
