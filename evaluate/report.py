"""``report.html`` of a run: one self-contained page (PNG figures embedded, no network) to look at a calibration on
a headless machine — the anchors on a plan view with their 3-sigma ellipses (and the truth where it is in the run's
frame), the range residuals over time per anchor with the gate, the NIS against its chi-square band, the model
chosen per anchor, the recording check's verdicts and the results table.

Every input is optional: a run stopped early, or an older run without ``range_updates.npz``, still gets a page
with what there is (and says what is missing); a damaged one is refused by the artefact reader, naming it.
"""

from __future__ import annotations

import base64
import html
import io
from pathlib import Path

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from matplotlib.patches import Ellipse

from uwbcal.convert.recording import RecordingReader
from uwbcal.evaluate.anchor_report import reference_anchors
from uwbcal.evaluate.export import TRAJECTORY, run_recording_path
from uwbcal.pipeline.core.atomic import write_text_atomic
from uwbcal.pipeline.core.errors import InputError
from uwbcal.pipeline.core.state import chi2_ppf
from uwbcal.pipeline.run import artefacts
from uwbcal.pipeline.run.config import run_config
from uwbcal.pipeline.run.stages.refine import RANGE_UPDATES

REPORT = "report.html"
NIS_WINDOW = 25  # ranges per NIS block mean


def _read_json(path: Path, shape: artefacts.Shape) -> dict:
    """An artefact the page shows ({} when absent: the stage did not run; damaged: `InputError` naming it)."""
    return artefacts.read_json(path, shape) if artefacts.present(path) else {}


def _png(fig: Figure) -> str:
    FigureCanvasAgg(fig)
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=90, bbox_inches="tight")
    return f'<img alt="" src="data:image/png;base64,{base64.b64encode(buf.getvalue()).decode()}">'


def _gate(run_dir: Path) -> float | None:
    q = run_config(run_dir).uwb.chi2_quantile if artefacts.present(run_dir / "config.toml") else 0.95
    return chi2_ppf(float(q), 1) if q else None


def plan_view(metrics: dict, states: dict, truth: dict[str, np.ndarray], track: np.ndarray | None) -> str:
    fig = Figure(figsize=(6.5, 5.5))
    ax = fig.add_subplot()
    if track is not None and len(track):
        ax.plot(track[:, 0], track[:, 1], color="0.75", lw=0.8, label="trajectory")
    for aid, a in (metrics.get("anchors") or {}).items():
        est = a.get("estimate")
        if not est or not a.get("determined", True):
            continue
        P = (states.get(aid) or {}).get("P")
        sig = np.asarray(a.get("sigma_xyz") or [0.0, 0.0, 0.0], float)
        cov = np.asarray(P, float)[:2, :2] if P is not None else np.diag(sig[:2] ** 2)
        w, V = np.linalg.eigh(cov)
        ang = float(np.degrees(np.arctan2(V[1, 1], V[0, 1])))
        ax.add_patch(
            Ellipse(est[:2], *(6 * np.sqrt(np.maximum(w[::-1], 0))), angle=ang, fill=False, color="tab:blue")
        )
        ax.plot(*est[:2], "o", color="tab:blue", ms=4)
        ax.annotate(str(aid), est[:2], textcoords="offset points", xytext=(5, 5), fontsize=8)
    for p in truth.values():
        ax.plot(p[0], p[1], "x", color="tab:red", ms=7)
    ax.plot([], [], "o", color="tab:blue", label="estimate (3σ ellipse)")
    if truth:
        ax.plot([], [], "x", color="tab:red", label="truth")
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.legend(fontsize=8, loc="best")
    ax.set_title("anchors, plan view")
    return _png(fig)


def residual_view(upd: dict[str, np.ndarray], gate: float | None) -> str:
    anchors = sorted(set(upd["anchor"].tolist()), key=lambda s: (len(s), s))[:12]
    cols = min(3, len(anchors))
    rows = -(-len(anchors) // cols)
    fig = Figure(figsize=(4.0 * cols, 2.4 * rows), layout="constrained")
    t0 = int(upd["t_ns"].min())
    for k, a in enumerate(anchors):
        ax = fig.add_subplot(rows, cols, k + 1)
        m = upd["anchor"] == a
        t = (upd["t_ns"][m] - t0) * 1e-9
        r, nis, rej = upd["residual"][m], upd["nis"][m], upd["rejected"][m].astype(bool)
        ax.plot(t[~rej], r[~rej], ".", ms=2, color="tab:blue")
        ax.plot(t[rej], r[rej], ".", ms=3, color="tab:red")
        lim = np.nanpercentile(np.abs(r), 99) * 1.5 if len(r) else 1.0
        if gate is not None:
            band = np.abs(r) * np.sqrt(gate / np.maximum(nis, 1e-12))  # sqrt(gate * S), S = r^2 / NIS
            o = np.argsort(t)
            ax.fill_between(t[o], -band[o], band[o], color="tab:green", alpha=0.15, lw=0)
            lim = max(lim, 1.2 * float(np.nanmedian(band)))
        ax.set_ylim(-lim, lim)
        ax.set_title(f"anchor {a}: {int(rej.sum())} of {len(r)} gated out", fontsize=8)
        ax.tick_params(labelsize=7)
    fig.supxlabel("s from the refinement start (red: gated out; green: the gate)", fontsize=8)
    fig.supylabel("range residual [m]", fontsize=8)
    return _png(fig)


def nis_view(upd: dict[str, np.ndarray]) -> str:
    from scipy.stats import chi2

    fig = Figure(figsize=(8, 3))
    ax = fig.add_subplot()
    t0 = int(upd["t_ns"].min())
    n = NIS_WINDOW
    lo, hi = chi2.ppf(0.025, n) / n, chi2.ppf(0.975, n) / n
    for a in sorted(set(upd["anchor"].tolist()), key=lambda s: (len(s), s)):
        m = upd["anchor"] == a
        nis = upd["nis"][m]
        if len(nis) < n:
            continue
        k = len(nis) // n  # block means (disjoint): each one is a draw the band applies to
        avg = nis[: k * n].reshape(k, n).mean(axis=1)
        t = (upd["t_ns"][m][: k * n].reshape(k, n).mean(axis=1) - t0) * 1e-9
        ax.plot(t, avg, ".-", lw=0.8, ms=4, label=str(a))
    ax.axhspan(lo, hi, color="tab:green", alpha=0.15, label=f"95% band of a mean of {n}")
    ax.axhline(1.0, color="0.4", lw=0.6)
    ax.set_yscale("log")
    ax.set_xlabel("s from the refinement start")
    ax.set_ylabel(f"NIS, mean of {n} ranges")
    ax.legend(fontsize=7, ncol=6, loc="upper right")
    ax.set_title("range NIS against its χ²(1) band")
    return _png(fig)


def _model_rows(init: dict, metrics: dict) -> list[list[str]]:
    """Per anchor: the initialiser's status and model (read defensively: the keys may grow), the estimate."""
    chosen = init.get("chosen")
    per = (init.get("methods") or {}).get(chosen) or {}
    rows = []
    for aid, a in (metrics.get("anchors") or {}).items():
        e = per.get(aid) or {}
        v = e.get("verdict") or {}
        model = e.get("model") or (v.get("bias") or {}).get("model") or v.get("model") or "?"
        if isinstance(model, dict):
            model = ", ".join(f"{k}={model[k]}" for k in model)
        sig = a.get("sigma_xyz") or []
        err = a.get("error_m")
        rows.append(
            [
                str(aid),
                str(a.get("method", chosen or "?")),
                str(model),
                "yes" if a.get("determined", True) else f"no: {a.get('reason', '')}",
                "" if v.get("height_observable", True) else "no",
                " ".join(f"{x:.3f}" for x in a.get("estimate") or []),
                " ".join(f"{x:.3f}" for x in sig),
                "" if err is None else f"{err:.3f}",
            ]
        )
    return rows


def _table(head: list[str], rows: list[list[str]]) -> str:
    th = "".join(f"<th>{html.escape(h)}</th>" for h in head)
    trs = "".join("<tr>" + "".join(f"<td>{html.escape(c)}</td>" for c in r) + "</tr>" for r in rows)
    return f"<table><tr>{th}</tr>{trs}</table>"


CSS = (
    "body{font-family:sans-serif;max-width:1100px;margin:1em auto;color:#222}"
    "table{border-collapse:collapse;font-size:13px}td,th{border:1px solid #ccc;padding:2px 6px;text-align:right}"
    "pre{background:#f6f6f6;padding:6px;font-size:12px;white-space:pre-wrap}img{max-width:100%}"
)


def run_truth(run_dir: Path) -> dict[str, np.ndarray]:
    """The anchors' truth of the run's recording where it is in the run's frame (else none: not drawn)."""
    try:
        ref = reference_anchors(RecordingReader(run_recording_path(run_dir)))
    except (InputError, OSError):
        return {}
    if ref is None or not ref.same_frame:
        return {}
    return {str(a): np.asarray(v["position"], float) for a, v in ref.anchors.items()}


def write_report(
    run_dir: str | Path,
    output: str | Path | None = None,
    *,
    truth: dict[str, np.ndarray] | None = None,
    check_text: str | None = None,
    title: str = "uwbcal calibration",
) -> Path:
    """Write the page (default ``run_dir/report.html``); returns its path. ``truth``: anchor positions in the
    run's frame (drawn on the plan view; default `run_truth`); ``check_text``: `uwbcal check`'s output (its
    verdicts are shown)."""
    run_dir = Path(run_dir)
    truth = run_truth(run_dir) if truth is None else truth
    out = Path(output) if output is not None else run_dir / REPORT
    metrics = _read_json(run_dir / "metrics.json", artefacts.METRICS)
    init = _read_json(run_dir / "init.json", artefacts.INIT)
    parts = [
        f"<h1>{html.escape(title)}</h1>",
        f"<p>run directory: <code>{html.escape(str(run_dir))}</code></p>",
    ]
    track = None
    if artefacts.present(run_dir / TRAJECTORY):
        p = artefacts.read_trajectory(run_dir / TRAJECTORY)["p"]
        track = p[:: max(1, len(p) // 5000)]
    states_path = run_dir / "anchor_states.json"
    states = artefacts.read_anchor_states(states_path) if artefacts.present(states_path) else {}
    parts += ["<h2>Anchors</h2>", plan_view(metrics, states, truth or {}, track)]
    head = ["anchor", "method", "model", "determined", "height seen", "x y z [m]", "σ x y z [m]", "error [m]"]
    parts.append(_table(head, _model_rows(init, metrics)))
    if artefacts.present(run_dir / RANGE_UPDATES):
        cols = artefacts.RANGE_UPDATES_ARRAYS
        upd = artefacts.read_npz(run_dir / RANGE_UPDATES, cols, tuple(cols), artefacts.RANGE_UPDATES_TEXT)
        if len(upd["t_ns"]):
            parts += ["<h2>Range residuals (refinement)</h2>", residual_view(upd, _gate(run_dir))]
            parts += ["<h2>NIS</h2>", nis_view(upd)]
    else:
        parts.append("<p>no range_updates.npz (the refine stage did not run): no residual or NIS plots</p>")
    if check_text:
        verdicts = check_text.split("verdict:\n", 1)[-1]
        parts += ["<h2>Recording check</h2>", f"<pre>{html.escape(verdicts)}</pre>"]
    if artefacts.present(run_dir / "results.md"):
        parts += [
            "<h2>Results</h2>",
            f"<pre>{html.escape(artefacts.read_text(run_dir / 'results.md'))}</pre>",
        ]
    warns = metrics.get("warnings") or []
    if warns:
        parts += [
            "<h2>Warnings</h2>",
            "<ul>" + "".join(f"<li>{html.escape(str(w))}</li>" for w in warns) + "</ul>",
        ]
    page = (
        f'<!DOCTYPE html><html><head><meta charset="utf-8"><title>{html.escape(title)}</title>'
        f"<style>{CSS}</style></head><body>{''.join(parts)}</body></html>\n"
    )
    write_text_atomic(out, page)
    return out
