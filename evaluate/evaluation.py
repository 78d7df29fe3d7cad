"""`uwbcal evaluate`: a run directory -> metrics.json and readable tables.

Only what can be computed is written: a metric without ground truth is absent, never faked.
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import polars as pl

from uwbcal.convert.recording import RecordingReader
from uwbcal.evaluate.align import Alignment, initial_pose
from uwbcal.evaluate.align import align as fit_alignment
from uwbcal.evaluate.anchor_report import (
    AnchorReference,
    RunAnchors,
    aligned_anchors,
    anchor_metrics,
    read_run_anchors,
    reference_anchors,
)
from uwbcal.evaluate.consistency import chi2_bounds, pose_nees, summarize_nees
from uwbcal.evaluate.export import (
    Compared,
    GroundTruth,
    RunTrajectory,
    compare,
    load_ground_truth,
    load_run_trajectory,
    run_recording_path,
)
from uwbcal.evaluate.gravity import level_truth
from uwbcal.evaluate.metrics import ormse_deg_by_segment, prmse_by_segment, segment_masks_from_ids
from uwbcal.evaluate.quality import range_quality
from uwbcal.evaluate.report import write_report
from uwbcal.evaluate.tables import render
from uwbcal.pipeline.core.atomic import write_text_atomic
from uwbcal.pipeline.core.errors import InputError
from uwbcal.pipeline.core.geometry import quat_to_rot
from uwbcal.pipeline.run import artefacts
from uwbcal.pipeline.run.config import run_config
from uwbcal.pipeline.run.resolve import imu_is_real
from uwbcal.pipeline.viz import runlog as rl

if TYPE_CHECKING:
    from uwbcal.pipeline.viz.runlog import RunLog

SEGMENT_NAMES = ("init", "refine", "localize")


@dataclass(frozen=True)
class _Run:
    """What the parts of an evaluation read: the run directory, its recording and trajectory, and the frame."""

    run_dir: Path
    reader: RecordingReader
    traj: RunTrajectory
    static_frame: bool  # a VIO started by the static initialiser: estimates in its own frame
    align: str  # the trajectory's alignment method


@dataclass
class _TrajectoryFit:
    alignment: Alignment | None = None  # fitted to the ground truth (None: no trajectory comparison)
    gauge: Alignment | None = (
        None  # a static-initialised run: its filter's gauge (yaw and position of the first pose)
    )


def evaluate_run(run_dir: Path, align: str | None = None, series: dict | None = None) -> dict:
    """metrics.json content; ``series`` (if given) receives the per-time NEES arrays for logging."""
    run_dir = Path(run_dir)
    t0 = time.perf_counter()
    rec_path = run_recording_path(run_dir)
    reader = RecordingReader(rec_path)
    traj = load_run_trajectory(run_dir)
    metrics = _run_notes(run_dir, reader, traj)
    ref = reference_anchors(reader)
    # a VIO started by the static initialiser estimates in its own frame (gravity-aligned, yaw 0, origin at
    # the start): position and yaw are a gauge, the anchors live in that frame too
    static_frame = artefacts.present(run_dir / "static_init.json")
    if align in (None, "auto"):
        simulated = ref is not None and ref.kind == "simulated"
        align = "posyaw" if static_frame else "none" if simulated else "se3"
    metrics["alignment"] = align
    run = _Run(run_dir, reader, traj, static_frame, align)
    try:
        gt = load_ground_truth(rec_path)
    except InputError as exc:
        gt = None
        metrics["warnings"].append(f"no trajectory metrics: {exc}")
    if gt is not None and static_frame and imu_is_real(reader.source):
        # compared in position and yaw only: a ground truth whose frame is not level (motion capture) is first
        # turned into the gravity-aligned frame the filter estimates in (the simulator's world is level)
        gt, ref, metrics["truth_levelled"] = level_truth(reader, gt, ref)
    fit = _TrajectoryFit()
    if gt is not None and len(traj):
        part, fit = _trajectory_metrics(run, gt, series)
        metrics.update(part)
    part, warnings = _anchor_section(run, ref, fit)
    metrics.update(part)
    metrics["warnings"].extend(warnings)
    if metrics.get("groundtruth_glitches"):
        metrics["warnings"].append(_glitch_note(metrics["groundtruth_glitches"]))
    metrics["evaluate_s"] = time.perf_counter() - t0
    return metrics


def _glitch_note(n: int) -> str:
    return (
        f"ground truth: {n} sample(s) dropped as glitches (a jump away and back no carrier can make in one sample "
        "interval, e.g. a motion-capture marker swap; evaluate.association.glitch_mask)"
    )


def _run_notes(run_dir: Path, reader: RecordingReader, traj: RunTrajectory) -> dict:
    """The warnings of the recording (truncation, damage) and of the stages, the stages' wall time, the span."""
    summary_path = run_dir / "stages.json"
    stages = artefacts.read_json(summary_path, artefacts.STAGES) if artefacts.present(summary_path) else {}
    warnings: list[str] = []
    warnings.extend(w for w in reader.verify() if w not in warnings)  # truncation, damage
    for st in stages.values():
        warnings.extend(str(w) for w in st.get("warnings", []) if w not in warnings)
    notes: dict = {"warnings": warnings}
    if stages:
        notes["wall_s"] = float(sum(float(st.get("wall_s", 0.0)) for st in stages.values()))
    if len(traj):
        notes["duration_s"] = float((traj.t_ns[-1] - traj.t_ns[0]) * 1e-9)
    if artefacts.present(run_dir / "health.json"):  # the pose source's health checks per stage (check_health)
        notes["vio_health"] = artefacts.read_json(run_dir / "health.json", artefacts.HEALTH)
    return notes


def _trajectory_metrics(run: _Run, gt: GroundTruth, series: dict | None) -> tuple[dict, _TrajectoryFit]:
    """PRMSE and ORMSE per segment after the alignment, the pose NEES where the covariance is in the ground
    truth's frame (no fitted alignment, or the static initialiser's gauge)."""
    traj = run.traj
    out: dict = {}
    cmp = compare(traj.t_ns, traj.p, traj.q_xyzw, gt)
    fit = _TrajectoryFit(fit_alignment(cmp.p_est, cmp.p_gt, run.align))
    R_est = quat_to_rot(cmp.q_est)
    p_al, R_al = fit.alignment.apply_positions(cmp.p_est), fit.alignment.apply_rotations(R_est)
    seg = traj.segment[cmp.assoc.idx] if traj.segment is not None else np.zeros(len(cmp.t_ns), np.int64)
    masks = segment_masks_from_ids(seg)
    out["prmse_m"] = prmse_by_segment(p_al, cmp.p_gt, masks)
    if cmp.q_gt is not None:
        R_gt = quat_to_rot(cmp.q_gt)
        out["ormse_deg"] = ormse_deg_by_segment(R_al, R_gt, masks)
        if run.static_frame:
            fit.gauge = initial_pose(R_est[0], cmp.p_est[0], R_gt[0], cmp.p_gt[0])
        if (run.align == "none" or run.static_frame) and traj.cov is not None:
            out.update(_pose_nees(traj, cmp, R_est, R_gt, fit.gauge, series))
    out["matched_poses"] = int(len(cmp.t_ns))
    out["groundtruth_glitches"] = cmp.assoc.n_gt_glitches  # dropped (association.glitch_mask)
    return out, fit


def _pose_nees(
    traj: RunTrajectory,
    cmp: Compared,
    R_est: np.ndarray,
    R_gt: np.ndarray,
    gauge: Alignment | None,
    series: dict | None,
) -> dict:
    """NEES of the body pose (the lever arm is zero for full-pose ground truth). In the static initialiser's
    frame: after the alignment that is its gauge (yaw and position of the first pose set to the ground truth's;
    the filter's covariance starts ~0 in them), not a fitted one (that would take out error the covariance
    accounts for)."""
    out: dict = {}
    ga = Alignment()
    if gauge is not None:
        ga = gauge
        out["nees_alignment"] = "initial pose (yaw, position): the static initialiser's gauge"
    A = np.eye(6)
    A[3:, 3:] = ga.R
    cov = A @ traj.cov[cmp.assoc.idx] @ A.T
    p_body = ga.apply_positions(traj.p[cmp.assoc.idx])
    ne = pose_nees(ga.apply_rotations(R_est), p_body, cov, R_gt, cmp.p_gt)
    out["nees_pose"] = summarize_nees(ne.pose, 6)
    out["nees_orientation"] = summarize_nees(ne.orientation, 3)
    out["nees_position"] = summarize_nees(ne.position, 3)
    if series is not None:
        series.update(
            t_ns=cmp.t_ns, nees_pose=ne.pose, nees_orientation=ne.orientation, nees_position=ne.position
        )
    return out


def _anchor_section(run: _Run, ref: AnchorReference | None, fit: _TrajectoryFit) -> tuple[dict, list[str]]:
    """The anchors' part of metrics.json and its warnings: errors and NEES against the reference, the
    initialiser's verdicts, the heights refinement regained, the range check."""
    run_anchors = read_run_anchors(run.run_dir, run_config(run.run_dir).uwb.init_method)
    own_frame = run_anchors.estimates  # the frame of the run's trajectory, which the range check uses
    run_anchors, ref, nees_states, out = _anchors_in_truth_frame(run, run_anchors, ref, fit)
    fitted_nees = None
    if nees_states is not None:
        fitted_nees = anchor_metrics(run_anchors, ref)[1].get("nees_anchor_position")
    if not (run_anchors.estimates or run_anchors.undetermined):
        return out, []
    anchors, top, warnings = anchor_metrics(run_anchors, ref, nees_states)
    if fitted_nees is not None:
        top["nees_anchor_position_fitted"] = fitted_nees
    out.update(top)
    warnings.extend(range_quality(run.reader, run.traj, own_frame))
    warnings.extend(_init_verdicts(run.run_dir, anchors))
    out["anchors"] = anchors
    vals = [a["nees"] for a in anchors.values() if "nees" in a]
    if vals:
        out["nees_anchor"] = summarize_nees(np.asarray(vals), 5)
    return out, warnings


def _anchors_in_truth_frame(
    run: _Run, anchors: RunAnchors, ref: AnchorReference | None, fit: _TrajectoryFit
) -> tuple[RunAnchors, AnchorReference | None, dict | None, dict]:
    """(anchors, reference, the states their NEES are taken of, the notes for metrics.json). A run started from
    the ground truth estimates in its frame: unchanged. A static-initialised run estimates in its own frame: its
    anchors get the trajectory's alignment (the same `Alignment`, so trajectory and anchors are compared in one
    frame) and their NEES the filter's gauge, as the pose NEES (the fitted alignment's own error, the trajectory's
    drift averaged over the run, is not in the anchors' covariance). Without a trajectory fit there is no common
    frame: only the frame-free inter-anchor distances are compared."""
    if not run.static_frame or ref is None or not ref.same_frame:
        return anchors, ref, None, {}
    if fit.alignment is None:
        return anchors, replace(ref, same_frame=False), None, {}
    notes = {"anchor_alignment": f"{run.align} alignment of the trajectory (static initialiser's frame)"}
    nees_states = None
    if fit.gauge is not None:
        nees_states = aligned_anchors(anchors, fit.gauge).states
        notes["anchor_nees_alignment"] = "initial pose (yaw, position): the static initialiser's gauge"
    return aligned_anchors(anchors, fit.alignment), ref, nees_states, notes


def _init_verdicts(run_dir: Path, anchors: dict) -> list[str]:
    """The chosen initialiser's FIM summary and verdict into each anchor's entry; a warning per anchor it could
    not determine."""
    init_path = run_dir / "init.json"
    if not artefacts.present(init_path):
        return []
    warnings = []
    init = artefacts.read_json(init_path, artefacts.INIT)
    for aid, r in (init.get("methods") or {}).get(init.get("chosen"), {}).items():
        if aid in anchors and isinstance(r, dict) and r.get("fim") is not None:
            anchors[aid]["fim"] = r["fim"]  # log det, condition number, weakest direction
        if aid in anchors and r.get("verdict"):
            anchors[aid]["verdict"] = r["verdict"]
            anchors[aid]["join_s"] = r.get("join_s")
        if aid in anchors and not anchors[aid].get("determined", True):
            warnings.append(f"anchor {aid} not determined: {anchors[aid].get('reason', '')}")
    return warnings


def metrics_tables(metrics: dict) -> tuple[pl.DataFrame, pl.DataFrame | None]:
    segs = [s for s in (*SEGMENT_NAMES, "all") if s in metrics.get("prmse_m", {})]
    traj = pl.DataFrame(
        {
            "segment": segs,
            "prmse_m": [metrics["prmse_m"][s] for s in segs],
            "ormse_deg": [metrics.get("ormse_deg", {}).get(s) for s in segs],
        },
        schema={"segment": pl.Utf8, "prmse_m": pl.Float64, "ormse_deg": pl.Float64},
    )
    anchors = metrics.get("anchors")
    if not anchors:
        return traj, None
    ids = sorted(anchors, key=lambda s: (len(s), s))

    def col(key: str, i: int | None = None) -> list:
        vals = [anchors[a].get(key) for a in ids]
        return [None if v is None else v[i] for v in vals] if i is not None else vals

    anc = pl.DataFrame(
        {
            "anchor": ids,
            "method": [anchors[a].get("method", "") for a in ids],
            "x": col("estimate", 0),
            "y": col("estimate", 1),
            "z": col("estimate", 2),
            "beta": col("beta"),
            "gamma": col("gamma"),
            "error_m": col("error_m"),
            "horizontal_m": col("error_horizontal_m"),
            "sigma_z_m": col("sigma_xyz", 2),
            "nees_pos": col("nees_position"),
            "status": [
                "estimated"
                if anchors[a].get("determined", True)
                else f"not determined: {anchors[a]['reason']}"
                for a in ids
            ],
        },
        schema_overrides={
            k: pl.Float64
            for k in ("x", "y", "z", "beta", "gamma", "error_m", "horizontal_m", "sigma_z_m", "nees_pos")
        },
    )
    return traj, anc


def render_metrics(metrics: dict, fmt: str = "md") -> str:
    traj, anc = metrics_tables(metrics)
    parts = [render(traj, fmt)] if len(traj) else []
    if anc is not None:
        parts.append(render(anc, fmt))
    lines = []
    if "anchor_error_m" in metrics:
        lines.append(
            f"anchor error (mean): {metrics['anchor_error_m']:.3f} m vs {metrics.get('anchor_reference')}"
        )
    at = metrics.get("anchor_truth", {})
    if "error_3d_m" in at:
        e3, eh = at["error_3d_m"], at["error_horizontal_m"]
        lines.append(
            f"anchor error vs {at['reference']}: 3-D mean {e3['mean']:.3f} m, max {e3['max']:.3f} m; "
            f"horizontal mean {eh['mean']:.3f} m, max {eh['max']:.3f} m ({at['n_estimated']} of {at['n_truth']})"
        )
    if "inter_anchor_distance_error_m" in at:
        d = at["inter_anchor_distance_error_m"]
        lines.append(
            f"inter-anchor distance error (frame-free, {d['pairs']} pairs): mean |e| {d['mean_abs']:.3f} m, "
            f"max |e| {d['max_abs']:.3f} m"
        )
    for aid in at.get("not_determined", []):
        reason = metrics.get("anchors", {}).get(aid, {}).get("reason", "")
        lines.append(f"anchor {aid} not determined: {reason}")
    for key in ("nees_pose", "nees_anchor", "nees_anchor_position", "nees_anchor_position_fitted"):
        if key in metrics and "mean" in metrics[key]:
            n = metrics[key]
            lo, hi = n["bounds"]
            lines.append(
                f"{key}: mean {n['mean']:.2f} (dof {n['dof']}, n {n.get('n_runs', 1)}, "
                f"95% bounds [{lo:.2f}, {hi:.2f}])"
            )
    lines += [f"warning: {w}" for w in metrics.get("warnings", [])]
    return "\n\n".join(parts + (["\n".join(lines)] if lines else []))


RESULTS = {"md": "results.md", "csv": "results.csv", "latex": "results.tex"}


def evaluate_run_cli(
    run_dir: Path, align: str | None = None, fmt: str = "md", series: dict | None = None
) -> str:
    """metrics.json, the results table (results.md, and results.csv / .tex for those formats; a table of
    another format from an earlier evaluation removed) and report.html: every view of the run from one
    evaluation, so the page and the tables never disagree with metrics.json."""
    run_dir = Path(run_dir)
    metrics = evaluate_run(run_dir, align, series)
    write_text_atomic(run_dir / "metrics.json", json.dumps(metrics, indent=2) + "\n")
    for f, name in RESULTS.items():
        if f in ("md", fmt):
            write_text_atomic(run_dir / name, render_metrics(metrics, f) + "\n")
        elif artefacts.present(run_dir / name):
            (run_dir / name).unlink()
    write_report(run_dir)
    return render_metrics(metrics, fmt)


def evaluate_stage(run_dir: Path, align: str | None, open_log: Callable[[], RunLog]) -> str:
    """The pipeline's `evaluate` stage (handed to `Pipeline(..., evaluator=)`): metrics.json, results.md and
    report.html, and the pose NEES over time with its chi-square bounds in the stage's rerun log."""

    series: dict = {}
    text = evaluate_run_cli(run_dir, align=align, series=series)
    if series:
        with open_log() as log:
            log.stage("evaluate", int(series["t_ns"][0]))
            for key, dof, entity in (
                ("nees_pose", 6, rl.NEES_POSE),
                ("nees_position", 3, f"{rl.FILTER}/nees_position"),
                ("nees_orientation", 3, f"{rl.FILTER}/nees_orientation"),
            ):
                log.scalars(entity, series["t_ns"], series[key])
                bounds = np.array(chi2_bounds(1, dof))
                log.constant(f"{entity}_bounds", series["t_ns"], bounds, ["χ² 2.5 %", "χ² 97.5 %"])
    return text
