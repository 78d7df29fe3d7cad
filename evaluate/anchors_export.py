"""Calibrated anchors out of a run directory, for other tools (``uwbcal export RUN --format anchors-json|anchors-yaml``).

The source is ``anchor_states.json`` (stage refine: the filter's anchor states and covariances), else the chosen
initialiser of ``init.pkl`` (stage init). Each anchor's state vector is read generically: position first, then the
ranging parameters; with the model d = β‖p_a − p_tag‖ + γ these are (β, γ) for one bias per anchor, or one (β, γ)
pair per link when the run estimated per-link biases (names from the entry's ``names``/``links`` when present).

- ``anchors.json``: every anchor with position, β, γ (per link), the state's parameter names, the full covariance,
  sigmas, stage, method and the run's model.
- ``uwb_anchors.yaml`` (UVIO / uwb_init style): a list of anchors with ``id``, ``p_AinG``, the constant and
  distance-proportional biases (``gamma``, ``beta``), and ``cov`` (row-major, the state order of ``names``).
- ``localization.yaml``: a ROS 2 parameter file (``/**: ros__parameters:``, so any node can load it) with
  ``anchor_ids``, ``anchor_positions`` (flat x, y, z per anchor), ``anchor_beta``, ``anchor_gamma``.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from uwbcal.pipeline.core.atomic import write_text_atomic
from uwbcal.pipeline.core.errors import InputError
from uwbcal.pipeline.run import artefacts
from uwbcal.pipeline.run.config import run_config
from uwbcal.pipeline.run.provenance import check_recording
from uwbcal.pipeline.run.rundir import RunDir

STATES = "anchor_states.json"
MODEL = "d = beta * |p_anchor - p_tag| + gamma (+ noise)"


def parameter_names(entry: dict, n: int) -> list[str]:
    """Names of the state vector's components: from the entry, else position + (beta, gamma) per link."""
    names = entry.get("names") or entry.get("params")
    if names is not None:
        if len(names) != n:
            raise ValueError(f"{len(names)} names for {n} state components")
        return [str(x) for x in names]
    if n < 5 or (n - 3) % 2:
        raise ValueError(f"state of {n} components: expected position (3) + (beta, gamma) per link")
    k = (n - 3) // 2
    if k == 1:
        return ["x", "y", "z", "beta", "gamma"]
    links = [str(x) for x in entry.get("links") or range(k)]
    if len(links) != k:
        raise ValueError(f"{len(links)} links for {k} (beta, gamma) pairs")
    return ["x", "y", "z", *(f"{w}/{link}" for link in links for w in ("beta", "gamma"))]


def _anchor_record(aid: str, entry: dict, where: str) -> dict:
    try:
        x = np.asarray(entry["x"], float).reshape(-1)
        P = np.asarray(entry["P"], float)
        n = len(x)
        if P.shape != (n, n):
            raise ValueError(f"P is {P.shape}, x has {n} components")
        names = parameter_names(entry, n)
    except (KeyError, ValueError, TypeError) as exc:
        raise InputError(f"{where}: anchor {aid}: {exc}; re-run the refine stage") from None
    out: dict[str, Any] = {
        "position": x[:3].tolist(),
        "names": names,
        "x": x.tolist(),
        "covariance": P.tolist(),
        "sigma": np.sqrt(np.clip(np.diag(P), 0.0, None)).tolist(),
    }
    betas = {
        nm.split("/", 1)[1] if "/" in nm else "": float(v)
        for nm, v in zip(names, x, strict=True)
        if nm.startswith("beta")
    }
    gammas = {
        nm.split("/", 1)[1] if "/" in nm else "": float(v)
        for nm, v in zip(names, x, strict=True)
        if nm.startswith("gamma")
    }
    if set(betas) == {""}:
        out["beta"], out["gamma"] = betas[""], gammas.get("")
    else:
        out["beta"] = betas  # per link
        out["gamma"] = gammas
    for k, v in entry.items():
        if k not in ("x", "P", "names", "params"):
            out[k] = v
    return out


def load_anchors(run_dir: str | Path) -> dict:
    """The run's anchors as exported: ``{"stage", "method", "model", "frame", "anchors": {id: record}}``."""
    run_dir = Path(run_dir)
    cfg = run_config(run_dir)
    rec = Path(cfg.run.recording).expanduser() if cfg.run.recording else None
    if rec is not None and not rec.is_absolute() and not rec.exists():
        rec = run_dir / rec
    check_recording(RunDir(run_dir), rec if rec is not None and rec.is_file() else None)
    uwb = cfg.uwb
    init_m, refine_m = uwb.init_method, uwb.refine_method
    states_path = run_dir / STATES
    if artefacts.present(states_path):
        states = artefacts.read_anchor_states(states_path)
        anchors = {str(a): _anchor_record(str(a), e, str(states_path)) for a, e in states.items()}
        stage, method = "refine", f"{init_m}+{refine_m}"
    elif artefacts.present(run_dir / "init.pkl"):
        results = artefacts.read_pickle(run_dir / "init.pkl")
        results = results.get(init_m, {}) if isinstance(results, dict) else {}
        anchors = {
            str(a): _anchor_record(str(a), {"x": r.x, "P": r.cov}, str(run_dir / "init.pkl"))
            for a, r in results.items()
            if r.ok
        }
        stage, method = "init", init_m
    else:
        raise InputError(f"{states_path}: missing (and no init.pkl); run the init/refine stages first")
    if not anchors:
        raise InputError(f"{run_dir}: no anchor was determined; nothing to export")
    return {
        "stage": stage,
        "method": method,
        "model": MODEL,
        "frame": "the recording's world frame",
        "source": str(states_path if stage == "refine" else run_dir / "init.pkl"),
        "anchors": anchors,
    }


def _flow_lists(data: Any) -> str:
    """YAML with numeric lists on one line (readable covariance rows)."""

    class Dumper(yaml.SafeDumper):
        pass

    def repr_list(d, seq):
        flow = all(isinstance(v, (int, float, str)) for v in seq)
        return d.represent_sequence("tag:yaml.org,2002:seq", seq, flow_style=flow)

    Dumper.add_representer(list, repr_list)
    return yaml.dump(data, Dumper=Dumper, sort_keys=False, width=200)


def uvio_yaml(doc: dict) -> str:
    anchors = []
    for aid, a in doc["anchors"].items():
        anchors.append(
            {
                "id": int(aid) if aid.isdigit() else aid,
                "p_AinG": a["position"],
                "gamma": a["gamma"],
                "beta": a["beta"],
                "names": a["names"],
                "cov": a["covariance"],
            }
        )
    head = (
        f"# uwbcal anchors (UVIO / uwb_init style), stage {doc['stage']}, method {doc['method']}\n"
        f"# model: {doc['model']}; gamma = constant bias [m], beta = distance scale;\n"
        "# cov: covariance of the state (rows and columns in the order of 'names'); frame: the recording's world frame\n"
    )
    return head + _flow_lists({"stage": doc["stage"], "method": doc["method"], "anchors": anchors})


def localization_yaml(doc: dict) -> str:
    ids = list(doc["anchors"])
    per_link = any(isinstance(a["beta"], dict) for a in doc["anchors"].values())
    params: dict[str, Any] = {
        "anchor_ids": [int(a) if a.isdigit() else a for a in ids],
        "anchor_positions": [float(v) for a in ids for v in doc["anchors"][a]["position"]],
    }
    if not per_link:
        params["anchor_beta"] = [float(doc["anchors"][a]["beta"]) for a in ids]
        params["anchor_gamma"] = [float(doc["anchors"][a]["gamma"]) for a in ids]
    head = (
        f"# uwbcal anchors for a localisation node (ROS 2 parameters), stage {doc['stage']}, "
        f"method {doc['method']}\n# anchor_positions: x, y, z per anchor in the order of anchor_ids; "
        f"model {doc['model']}\n"
        + ("# per-link biases: see uwb_anchors.yaml / anchors.json\n" if per_link else "")
    )
    return head + _flow_lists({"/**": {"ros__parameters": params}})


def export_anchors(run_dir: str | Path, output: str | Path, fmt: str) -> str:
    """Write anchors.json (anchors-json) or uwb_anchors.yaml + localization.yaml (anchors-yaml); a summary."""
    doc = load_anchors(run_dir)
    out = Path(output)
    if fmt == "anchors-json":
        paths = [out / "anchors.json"]
        write_text_atomic(paths[0], json.dumps(doc, indent=2) + "\n")
    else:
        paths = [out / "uwb_anchors.yaml", out / "localization.yaml"]
        write_text_atomic(paths[0], uvio_yaml(doc))
        write_text_atomic(paths[1], localization_yaml(doc))
    return (
        f"wrote {', '.join(map(str, paths))}: {len(doc['anchors'])} anchors "
        f"(stage {doc['stage']}, method {doc['method']}, from {doc['source']})"
    )
