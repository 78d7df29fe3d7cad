"""`uwbcal evaluate`: a run directory -> metrics.json and readable tables (DESIGN §6, §9).

Only what can be computed is written: a metric without ground truth is absent, never faked.
"""

from __future__ import annotations

import csv
import json
import time
import tomllib
from pathlib import Path

import numpy as np
import polars as pl

from convert.atomic import write_text_atomic
from convert.datasets import data_root
from convert.errors import InputError
from convert.recording import RecordingReader
from pipeline.lie import quat_to_rot

from .align import Alignment
from .align import align as fit_alignment
from .consistency import anchor_nees, pose_nees, summarize_nees
from .export import compare, load_ground_truth, load_run_trajectory, run_recording_path
from .metrics import anchor_errors, ormse_deg_by_segment, prmse_by_segment, segment_masks_from_ids
from .tables import render

SEGMENT_NAMES = ("init", "refine", "localize")


def read_anchors_csv(run_dir: Path) -> list[dict]:
    path = Path(run_dir) / "anchors.csv"
    if not path.is_file():
        return []
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


def final_anchor_estimates(rows: list[dict], init_method: str | None = None) -> dict[str, dict]:
    """The calibrated anchors: the refine-stage rows, else those of the init method that was used."""
    refine = [r for r in rows if r["stage"] == "refine"]
    chosen = refine or [r for r in rows if r["stage"] == "init" and r["method"] == init_method]
    return {
        r["anchor"]: {
            "position": [float(r["x"]), float(r["y"]), float(r["z"])],
            "beta": float(r["beta"]),
            "gamma": float(r["gamma"]),
            "method": r["method"],
        }
        for r in chosen
    }


def reference_anchors(reader: RecordingReader) -> tuple[dict[str, dict], str] | tuple[None, None]:
    """Simulation truth, or the published NTU-VIRAL anchor estimates (SLICT frame) for that site."""
    truth = reader.truth
    if truth and truth.get("anchors"):
        return {str(k): v for k, v in truth["anchors"].items()}, "truth"
    src = reader.source
    seq = str(src.get("sequence", ""))
    if "ntu" in str(src.get("dataset", "")).lower() and seq:
        site = seq.split("_")[0]
        path = data_root() / "ntu_viral" / "published_anchors.csv"
        if path.is_file():
            df = pl.read_csv(path)
            rows = df.filter(pl.col("site") == site)
            if len(rows):
                return {
                    str(r["anchor"]): {"position": [r["x"], r["y"], r["z"]]}
                    for r in rows.iter_rows(named=True)
                }, f"published ({path.name}, site {site})"
    return None, None


def initial_pose_alignment(R_est0: np.ndarray, p_est0: np.ndarray, R_gt0: np.ndarray, p_gt0: np.ndarray):
    """The yaw rotation and offset that put the first estimated pose on the ground truth's (the gauge of a
    filter that starts in its own gravity-aligned frame)."""
    D = R_gt0 @ R_est0.T
    yaw = np.arctan2(D[1, 0], D[0, 0])
    c, s = np.cos(yaw), np.sin(yaw)
    Rz = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    return Alignment(R=Rz, t=p_gt0 - Rz @ p_est0, method="initial-pose")


def evaluate_run(run_dir: Path, align: str | None = None, series: dict | None = None) -> dict:
    """metrics.json content; ``series`` (if given) receives the per-time NEES arrays for logging."""
    run_dir = Path(run_dir)
    t0 = time.perf_counter()
    rec_path = run_recording_path(run_dir)
    reader = RecordingReader(rec_path)
    traj = load_run_trajectory(run_dir)
    metrics: dict = {"warnings": []}
    summary_path = run_dir / "stages.json"
    stages = json.loads(summary_path.read_text()) if summary_path.is_file() else {}
    for st in stages.values():
        metrics["warnings"].extend(st.get("warnings", []))
    if stages:
        metrics["wall_s"] = float(sum(st.get("wall_s", 0.0) for st in stages.values()))
    if len(traj):
        metrics["duration_s"] = float((traj.t_ns[-1] - traj.t_ns[0]) * 1e-9)

    ref, ref_kind = reference_anchors(reader)
    # a VIO started by the static initialiser estimates in its own frame (gravity-aligned, yaw 0, origin at
    # the start): position and yaw are a gauge, the anchors live in that frame too
    static_frame = (run_dir / "static_init.json").is_file()
    if align in (None, "auto"):
        align = "posyaw" if static_frame else "none" if ref_kind == "truth" else "se3"
    metrics["alignment"] = align

    # -- trajectory -----------------------------------------------------------------------------------------
    try:
        gt = load_ground_truth(rec_path)
    except InputError as exc:
        gt = None
        metrics["warnings"].append(f"no trajectory metrics: {exc}")
    al = None
    if gt is not None and len(traj):
        cmp = compare(traj.t_ns, traj.p, traj.q_xyzw, gt)
        al = fit_alignment(cmp.p_est, cmp.p_gt, align)
        R_est = quat_to_rot(cmp.q_est)
        p_al, R_al = al.apply_positions(cmp.p_est), al.apply_rotations(R_est)
        seg = traj.segment[cmp.assoc.idx] if traj.segment is not None else np.zeros(len(cmp.t_ns), np.int64)
        masks = segment_masks_from_ids(seg)
        metrics["prmse_m"] = prmse_by_segment(p_al, cmp.p_gt, masks)
        if cmp.q_gt is not None:
            R_gt = quat_to_rot(cmp.q_gt)
            metrics["ormse_deg"] = ormse_deg_by_segment(R_al, R_gt, masks)
            if (align == "none" or static_frame) and traj.cov is not None:
                # NEES of the body pose (the lever arm is zero for full-pose ground truth). In the static
                # initialiser's frame: after the alignment that is its gauge (yaw and position of the first pose
                # set to the ground truth's; the filter's covariance starts ~0 in them), not a fitted one (that
                # would take out error the covariance accounts for)
                ga = Alignment()
                if static_frame:
                    ga = initial_pose_alignment(R_est[0], cmp.p_est[0], R_gt[0], cmp.p_gt[0])
                    metrics["nees_alignment"] = "initial pose (yaw, position): the static initialiser's gauge"
                p_body = ga.apply_positions(traj.p[cmp.assoc.idx])
                A = np.eye(6)
                A[3:, 3:] = ga.R
                cov = A @ traj.cov[cmp.assoc.idx] @ A.T
                ne = pose_nees(ga.apply_rotations(R_est), p_body, cov, R_gt, cmp.p_gt)
                metrics["nees_pose"] = summarize_nees(ne.pose, 6)
                metrics["nees_orientation"] = summarize_nees(ne.orientation, 3)
                metrics["nees_position"] = summarize_nees(ne.position, 3)
                if series is not None:
                    series.update(
                        t_ns=cmp.t_ns,
                        nees_pose=ne.pose,
                        nees_orientation=ne.orientation,
                        nees_position=ne.position,
                    )
        metrics["matched_poses"] = int(len(cmp.t_ns))

    # -- anchors ---------------------------------------------------------------------------------------------
    cfg = tomllib.loads((run_dir / "config.toml").read_text())
    est = final_anchor_estimates(read_anchors_csv(run_dir), cfg.get("uwb", {}).get("init_method"))
    # anchors estimated in the static initialiser's frame: compared after the trajectory's alignment
    anchor_al = al if static_frame and ref_kind == "truth" and al is not None else None
    if anchor_al is not None:
        metrics["anchor_alignment"] = f"{align} alignment of the trajectory (static initialiser's frame)"
    if est:
        anchors = {
            aid: {"estimate": a["position"], "beta": a["beta"], "gamma": a["gamma"], "method": a["method"]}
            for aid, a in est.items()
        }
        if ref is not None:
            cmp_est = est
            if anchor_al is not None:
                cmp_est = {
                    aid: {
                        **a,
                        "position": anchor_al.apply_positions(np.asarray(a["position"], float)).tolist(),
                    }
                    if a.get("position") is not None
                    else a
                    for aid, a in est.items()
                }
            ae = anchor_errors(cmp_est, ref)
            for aid, row in ae.per_anchor.items():
                anchors[aid].update({k: v for k, v in row.items()})
            if ae.per_anchor:
                metrics["anchor_error_m"] = ae.mean_m
                metrics["anchor_reference"] = ref_kind
            if np.isfinite(ae.mean_abs_beta):
                metrics["beta_error"] = ae.mean_abs_beta
            if np.isfinite(ae.mean_abs_gamma):
                metrics["gamma_error"] = ae.mean_abs_gamma
            if ae.missing:
                metrics["warnings"].append(f"anchors not calibrated: {', '.join(ae.missing)}")
        init_path = run_dir / "init.json"
        if init_path.is_file():
            init = json.loads(init_path.read_text())
            for aid, r in init["methods"].get(init["chosen"], {}).items():
                if aid in anchors and "fim" in r:
                    anchors[aid]["fim"] = r["fim"]  # log det, condition number, weakest direction
        metrics["anchors"] = anchors
        state_path = run_dir / "anchor_states.json"
        if ref_kind == "truth" and state_path.is_file():
            states = json.loads(state_path.read_text())
            vals = []
            for aid, s in states.items():
                if aid in ref:
                    t = ref[aid]
                    truth_vec = np.r_[t["position"], t.get("beta", 1.0), t.get("gamma", 0.0)]
                    x, P = np.asarray(s["x"], float), np.asarray(s["P"], float)
                    if anchor_al is not None:
                        A = np.eye(len(x))
                        A[:3, :3] = anchor_al.s * anchor_al.R
                        x = np.r_[anchor_al.apply_positions(x[:3]), x[3:]]
                        P = A @ P @ A.T
                    v = float(anchor_nees(x, P, truth_vec))
                    anchors[aid]["nees"] = v
                    vals.append(v)
            if vals:
                metrics["nees_anchor"] = summarize_nees(np.asarray(vals), 5)
    metrics["evaluate_s"] = time.perf_counter() - t0
    return metrics


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
    anc = pl.DataFrame(
        {
            "anchor": ids,
            "method": [anchors[a].get("method", "") for a in ids],
            "x": [anchors[a]["estimate"][0] for a in ids],
            "y": [anchors[a]["estimate"][1] for a in ids],
            "z": [anchors[a]["estimate"][2] for a in ids],
            "beta": [anchors[a]["beta"] for a in ids],
            "gamma": [anchors[a]["gamma"] for a in ids],
            "error_m": [anchors[a].get("error_m") for a in ids],
        },
        schema_overrides={"error_m": pl.Float64},
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
    for key in ("nees_pose", "nees_anchor"):
        if key in metrics and "mean" in metrics[key]:
            n = metrics[key]
            lo, hi = n["bounds"]
            lines.append(f"{key}: mean {n['mean']:.2f} (dof {n['dof']}, 95% bounds [{lo:.2f}, {hi:.2f}])")
    lines += [f"warning: {w}" for w in metrics.get("warnings", [])]
    return "\n\n".join(parts + (["\n".join(lines)] if lines else []))


def evaluate_run_cli(
    run_dir: Path, align: str | None = None, fmt: str = "md", series: dict | None = None
) -> str:
    metrics = evaluate_run(run_dir, align, series)
    write_text_atomic(Path(run_dir) / "metrics.json", json.dumps(metrics, indent=2) + "\n")
    text = render_metrics(metrics, fmt)
    write_text_atomic(
        Path(run_dir) / f"results.{ {'md': 'md', 'csv': 'csv', 'latex': 'tex'}[fmt] }", text + "\n"
    )
    return text
