"""Anchor estimates of a run against the recording's anchor truth (simulated, surveyed or published).

Reads ``anchors.csv`` (an anchor the run could not determine is a row with empty ``x,y,z``; its reason comes from
an optional ``reason`` column, else from ``init.json``), the covariances (``anchor_states.json`` after refinement,
else the chosen initialiser's ``cov`` in ``init.json``) and ``uwbcal.truth``. Produces the ``metrics.json`` parts:

- ``anchors[<id>]``: ``estimate``, ``beta``, ``gamma``, ``method``, ``determined`` and, against truth,
  ``error_m`` (3-D), ``error_horizontal_m``, ``error_xyz``, ``sigma_xyz`` (1σ from the covariance),
  ``z_error_sigmas`` (|z error| / σz), ``nees_position`` (3 dof); undetermined anchors: ``determined: false``,
  ``reason`` and no estimate or error.
- ``anchor_truth``: ``kind``, ``reference``, ``n_truth``, ``n_estimated``, ``error_3d_m`` / ``error_horizontal_m``
  ``{mean, max}``, ``inter_anchor_distance_error_m`` ``{pairs, mean_abs, max_abs, per_pair}`` (frame-free),
  ``not_determined`` (the ids; each reason is in ``anchors[<id>].reason``, stated once), ``missing`` (truth anchors the run neither estimated nor declared).
- ``nees_anchor_position``: ANEES of the anchor positions over the anchors with a covariance, with the χ² bounds
  of a mean of that many 3-dof values (``consistency.chi2_bounds(n, 3)``).
  A run in a static initialiser's own frame is compared after the trajectory's fitted alignment, but its NEES
  are taken in the filter's gauge (`align.initial_pose`), as the pose NEES: the fitted alignment
  is a transform of its own, whose error (the trajectory's drift averaged over the flight) the anchors'
  covariance does not hold; ``nees_anchor_position_fitted`` keeps the ANEES after the fitted alignment.
When the truth is not in the run's frame (``anchors_frame`` not odometry/world), only the frame-free distances
are reported.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from uwbcal.convert.anchor_truth import POSE_FRAMES
from uwbcal.convert.datasets import data_root
from uwbcal.convert.recording import RecordingReader
from uwbcal.evaluate.consistency import anchor_nees, chi2_bounds
from uwbcal.evaluate.metrics import anchor_errors, inter_anchor_distance_errors
from uwbcal.pipeline.core.errors import InputError
from uwbcal.pipeline.run import artefacts


@dataclass
class AnchorReference:
    anchors: dict[str, dict]  # id -> {"position": [x, y, z], "beta"?, "gamma"?}
    kind: str  # simulated | surveyed | published
    label: str  # for results.md / metrics.json "anchor_reference"
    same_frame: bool  # absolute errors are meaningful (truth in the run's world frame)


def reference_anchors(reader: RecordingReader) -> AnchorReference | None:
    """``uwbcal.truth`` anchors; for NTU-VIRAL recordings converted without them, the published anchors of the
    sequence's site from ``<data>/ntu_viral/published_anchors.csv`` (SLICT frame)."""
    truth = reader.truth
    if truth and truth.get("anchors"):
        kind = str(truth.get("kind", "simulated"))
        frame = str(truth.get("anchors_frame", "world"))
        label = kind
        if truth.get("anchors_file"):
            label += f" ({Path(truth['anchors_file'].get('path', '')).name})"
        return AnchorReference(
            {str(k): v for k, v in truth["anchors"].items()}, kind, label, frame in POSE_FRAMES
        )
    src = reader.source
    seq = str(src.get("sequence", ""))
    if "ntu" in str(src.get("dataset", "")).lower() and seq:
        import polars as pl

        site = seq.split("_")[0]
        path = data_root() / "ntu_viral" / "published_anchors.csv"
        if path.is_file():
            rows = pl.read_csv(path).filter(pl.col("site") == site)
            if len(rows):
                anchors = {
                    str(r["anchor"]): {"position": [r["x"], r["y"], r["z"]]}
                    for r in rows.iter_rows(named=True)
                }
                same = "/odometry" in reader.topics()
                return AnchorReference(anchors, "published", f"published ({path.name}, site {site})", same)
    return None


@dataclass
class RunAnchors:
    estimates: dict[str, dict] = field(default_factory=dict)  # id -> position, beta, gamma, method
    undetermined: dict[str, dict] = field(default_factory=dict)  # id -> {"reason", "method"}
    states: dict[str, tuple[np.ndarray, np.ndarray]] = field(default_factory=dict)  # id -> (x, P), p_a first


def _number(text: str | None, where: str = "") -> float:
    """A number of anchors.csv: empty = not determined (NaN); anything else that is not a number is damage."""
    if text in (None, ""):
        return float("nan")
    try:
        return float(text)
    except ValueError:
        raise InputError(
            f"{where}: {text!r} is not a number; the run directory is damaged — re-run init/refine"
        ) from None


def _key(s: str) -> tuple[int, str]:
    return (len(s), s)


def read_run_anchors(run_dir: Path, init_method: str | None) -> RunAnchors:
    """The run's calibrated anchors (refine rows, else the chosen initialiser's), its undetermined anchors with
    their reasons, and the covariance of each estimate where one was saved."""
    run_dir = Path(run_dir)
    out = RunAnchors()
    path = run_dir / "anchors.csv"
    rows = []
    if artefacts.present(path):
        rows = artefacts.read_anchor_rows(path)
    refine = [r for r in rows if r.get("stage") == "refine"]
    init = [r for r in rows if r.get("stage") == "init" and r.get("method") == init_method]
    init_json = run_dir / "init.json"
    init_info = artefacts.read_json(init_json, artefacts.INIT) if artefacts.present(init_json) else {}
    chosen = (init_info.get("methods") or {}).get(init_info.get("chosen", init_method)) or {}
    for r in (refine or init) + (init if refine else []):
        aid = str(r["anchor"])
        if aid in out.estimates or aid in out.undetermined:
            continue
        where = f"{path}: line {r['_line']}"
        xyz = np.array([_number(r.get(c), where) for c in ("x", "y", "z")])
        if np.isfinite(xyz).all():
            out.estimates[aid] = {
                "position": xyz.tolist(),
                "beta": _number(r.get("beta"), where),
                "gamma": _number(r.get("gamma"), where),
                "method": r.get("method", ""),
            }
        else:
            out.undetermined[aid] = {"reason": r.get("reason") or "", "method": r.get("method", "")}
    for aid, info in chosen.items():  # initialiser verdicts: refused / skipped anchors have no row at all
        if (
            aid not in out.estimates
            and aid not in out.undetermined
            and info.get("status") not in ("ok", "warning")
        ):
            out.undetermined[aid] = {"reason": "", "method": info.get("method", init_info.get("chosen", ""))}
    for aid, u in out.undetermined.items():
        if not u["reason"]:
            info = chosen.get(aid, {})
            head = info.get("reason") or info.get("status") or ""
            # the init warning repeats a stated reason ("<id>: not determined: <reason>"): add it only when new
            extra = [
                w
                for w in list(info.get("warnings", []))[:1]
                if not (info.get("reason") and info["reason"] in w)
            ]
            u["reason"] = (
                "; ".join(p for p in [head, *extra] if p) or "not determined (no reason given by the run)"
            )
    if refine:
        out.states = _refine_states(run_dir, out, refine)
    for aid in out.estimates if not refine else ():
        info = chosen.get(aid) or {}
        if info.get("cov") is not None:
            x, P = np.asarray(info.get("x", info.get("estimate")), float), np.asarray(info["cov"], float)
            if P.ndim == 2 and P.shape[0] >= 3 and P.shape[0] == P.shape[1] and np.isfinite(P[:3, :3]).all():
                out.states[aid] = (x, P)
    return out


def _refine_states(
    run_dir: Path, out: RunAnchors, refine: list[dict]
) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """The refined anchors' states (`artefacts.read_anchor_states`: anchor_states.json read with anchors.csv's
    refine rows, which the refinement writes together)."""
    path = run_dir / "anchor_states.json"
    if not artefacts.present(path):
        raise artefacts.corrupt(
            path,
            "missing, but anchors.csv holds refine rows",
            f"re-run the refinement (uwbcal run REC -o {run_dir} --stages refine,localize,evaluate)",
        )
    states = artefacts.read_anchor_states(path)
    lines = {str(r["anchor"]) for r in refine}
    return {
        aid: (np.asarray(states[aid]["x"], float), np.asarray(states[aid]["P"], float))
        for aid in out.estimates
        if aid in lines and aid in states
    }


def aligned_anchors(run: RunAnchors, al) -> RunAnchors:
    """``run`` with the anchor positions (and their covariance blocks) mapped by the alignment ``al``
    (`evaluate.align.Alignment`: p -> s R p + t), e.g. from a static-initialised VIO's frame to the ground truth's."""
    A = al.s * al.R
    est = {
        aid: {**e, "position": al.apply_positions(np.asarray(e["position"], float)).tolist()}
        for aid, e in run.estimates.items()
    }
    states = {}
    for aid, (x, P) in run.states.items():
        T = np.eye(len(x))
        T[:3, :3] = A
        states[aid] = (np.r_[al.apply_positions(x[:3]), x[3:]], T @ P @ T.T)
    return RunAnchors(est, dict(run.undetermined), states)


def anchor_metrics(
    run: RunAnchors, ref: AnchorReference | None, nees_states: dict | None = None
) -> tuple[dict, dict, list[str]]:
    """(metrics["anchors"], the top-level anchor keys of metrics.json, warnings); see the module docstring.
    ``nees_states``: the (x, P) the NEES are taken of when they live in another frame than the errors' (a
    static-initialised run: errors after the trajectory's fitted alignment, NEES in the filter's own gauge);
    default ``run.states``."""
    anchors = _anchor_entries(run)
    top: dict = {}
    if ref is None:
        return anchors, top, []
    summary, warns = _truth_summary(run, ref)
    if not ref.same_frame:
        warns.append(
            f"anchor truth ({ref.label}) is not in this run's frame: only inter-anchor distances are compared"
        )
        top["anchor_truth"] = summary
        return anchors, top, warns
    top.update(_absolute_errors(run, ref, anchors, summary))
    top.update(_position_nees(run.states if nees_states is None else nees_states, ref, anchors))
    top["anchor_truth"] = summary
    return anchors, top, warns


def _anchor_entries(run: RunAnchors) -> dict[str, dict]:
    """metrics["anchors"] without truth: the estimate, its 1-sigma and the method; the reason of an anchor not
    determined."""
    anchors: dict[str, dict] = {}
    for aid, a in run.estimates.items():
        anchors[aid] = {
            "estimate": a["position"],
            "beta": a["beta"],
            "gamma": a["gamma"],
            "method": a["method"],
            "determined": True,
        }
        if aid in run.states:
            P = run.states[aid][1]
            anchors[aid]["sigma_xyz"] = np.sqrt(np.clip(np.diag(P)[:3], 0.0, None)).tolist()
    for aid, u in run.undetermined.items():
        anchors[aid] = {"determined": False, "reason": u["reason"], "method": u["method"]}
    return anchors


def _truth_summary(run: RunAnchors, ref: AnchorReference) -> tuple[dict, list[str]]:
    """``anchor_truth`` as far as it needs no common frame (counts, the frame-free inter-anchor distances), and
    a warning naming the truth anchors the run did not calibrate."""
    truth = ref.anchors
    summary: dict = {
        "kind": ref.kind,
        "reference": ref.label,
        "n_truth": len(truth),
        "n_estimated": sum(a in truth for a in run.estimates),
        "not_determined": sorted(run.undetermined, key=_key),
        "missing": sorted(set(truth) - set(run.estimates) - set(run.undetermined), key=_key),
    }
    dist = inter_anchor_distance_errors(run.estimates, truth)
    if dist.per_pair:
        summary["inter_anchor_distance_error_m"] = {
            "pairs": len(dist.per_pair),
            "mean_abs": dist.mean_abs_m,
            "max_abs": dist.max_abs_m,
            "per_pair": dist.per_pair,
        }
    warns = [f"anchors not calibrated: {', '.join(summary['missing'])}"] if summary["missing"] else []
    return summary, warns


def _absolute_errors(run: RunAnchors, ref: AnchorReference, anchors: dict, summary: dict) -> dict:
    """Per-anchor errors against truth in the run's frame (into ``anchors`` and ``summary``); the top-level
    means."""
    top: dict = {}
    ae = anchor_errors(run.estimates, ref.anchors)
    for aid, row in ae.per_anchor.items():
        anchors[aid].update(row)
        sig = anchors[aid].get("sigma_xyz")
        if sig is not None and sig[2] > 0:
            anchors[aid]["z_error_sigmas"] = abs(row["error_xyz"][2]) / sig[2]
    if ae.per_anchor:
        top["anchor_error_m"] = ae.mean_m
        top["anchor_reference"] = ref.label
        summary["error_3d_m"] = {"mean": ae.mean_m, "max": ae.max_m}
        summary["error_horizontal_m"] = {"mean": ae.mean_horizontal_m, "max": ae.max_horizontal_m}
    if np.isfinite(ae.mean_abs_beta):
        top["beta_error"] = ae.mean_abs_beta
    if np.isfinite(ae.mean_abs_gamma):
        top["gamma_error"] = ae.mean_abs_gamma
    return top


def _position_nees(states: dict, ref: AnchorReference, anchors: dict) -> dict:
    """Each anchor's position NEES (and, simulated, the NEES of its whole state) into ``anchors``; their mean
    with the chi-square bounds as ``nees_anchor_position``."""
    truth = ref.anchors
    vals = []
    for aid, (x, P) in states.items():
        if aid not in truth:
            continue
        p_true = np.asarray(truth[aid]["position"], float)
        v = float(anchor_nees(x[:3], P[:3, :3], p_true))
        if np.isfinite(v):
            anchors[aid]["nees_position"] = v
            vals.append(v)
        t = truth[aid]
        if (
            ref.kind == "simulated" and len(x) == 5 and P.shape == (5, 5)
        ):  # (p_a, beta, gamma) with known truth
            full = np.r_[p_true, t.get("beta", 1.0), t.get("gamma", 0.0)]
            anchors[aid]["nees"] = float(anchor_nees(x, P, full))
    if not vals:
        return {}
    return {
        "nees_anchor_position": {
            "mean": float(np.mean(vals)),
            "dof": 3,
            "n_runs": len(vals),
            "bounds": list(chi2_bounds(len(vals), 3)),
        }
    }
