"""PNG plots (matplotlib, Agg; no pyplot global state, so safe in worker processes). Each function takes arrays and
an output path, writes the file atomically and returns the path."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from uwbcal.pipeline.core.atomic import atomic_path

DPI = 120
# one colour per initialiser / refinement across all plots
METHOD_COLORS = {
    "lsi": "tab:orange",
    "ri": "tab:blue",
    "ri-robust": "tab:green",
    "ekf": "tab:red",
    "skf": "tab:purple",
    "viro": "tab:brown",
}
AXES = ("x", "y", "z")


def _figure(rows: int, cols: int, size: tuple[float, float]) -> tuple[Figure, np.ndarray]:
    fig = Figure(figsize=size, dpi=DPI, layout="constrained")
    FigureCanvasAgg(fig)
    axs = np.atleast_1d(fig.subplots(rows, cols, squeeze=False)).reshape(-1)
    return fig, axs


def _save(fig: Figure, path: str | Path) -> Path:
    path = Path(path)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png", dpi=DPI)
    return path


def _color(name: str, i: int) -> str:
    return METHOD_COLORS.get(name.lower(), f"C{i % 10}")


def _as_points(a) -> np.ndarray:
    """Anchors as (K, 3): an array or a mapping id -> position / {"position": ...}."""
    if isinstance(a, Mapping):
        vals = [v.get("position", v.get("estimate")) if isinstance(v, Mapping) else v for v in a.values()]
        return np.asarray(vals, float).reshape(-1, 3)
    return np.asarray(a, float).reshape(-1, 3)


def plot_trajectory(
    path: str | Path,
    p_gt: np.ndarray | None = None,
    p_est: np.ndarray | None = None,
    anchors_truth=None,
    anchors_init: Mapping[str, object] | None = None,
    anchors_refined=None,
    title: str = "",
) -> Path:
    """Top (x-y) and side (x-z) views: ground truth, estimate, true anchors, initial estimates per method
    (``{"lsi": (K, 3), "ri": ...}``) and refined anchors."""
    fig, axs = _figure(1, 2, (12, 5.5))
    for ax, (i, j), name in zip(axs, ((0, 1), (0, 2)), ("top (x-y)", "side (x-z)"), strict=True):
        if p_gt is not None:
            g = np.asarray(p_gt, float)
            ax.plot(g[:, i], g[:, j], "k-", lw=1.0, label="ground truth")
        if p_est is not None:
            e = np.asarray(p_est, float)
            ax.plot(e[:, i], e[:, j], "-", color="tab:cyan", lw=1.0, label="estimate")
        if anchors_truth is not None:
            a = _as_points(anchors_truth)
            ax.scatter(a[:, i], a[:, j], marker="*", s=160, c="k", label="anchors (truth)", zorder=5)
        for k, (method, pts) in enumerate((anchors_init or {}).items()):
            a = _as_points(pts)
            ax.scatter(
                a[:, i], a[:, j], marker="x", s=60, c=_color(method, k), label=f"init {method}", zorder=6
            )
        if anchors_refined is not None:
            a = _as_points(anchors_refined)
            ax.scatter(a[:, i], a[:, j], marker="o", s=50, facecolors="none", edgecolors="tab:red",
                       linewidths=1.5, label="refined", zorder=7)  # fmt: skip
        ax.set_xlabel(f"{AXES[i]} [m]")
        ax.set_ylabel(f"{AXES[j]} [m]")
        ax.set_title(name)
        ax.set_aspect("equal", adjustable="datalim")
        ax.grid(alpha=0.3)
    axs[0].legend(loc="best", fontsize=8)
    if title:
        fig.suptitle(title)
    return _save(fig, path)


def plot_error_bands(
    path: str | Path,
    t_s: np.ndarray,
    err: np.ndarray,
    sigma: np.ndarray | None = None,
    labels: Sequence[str] = AXES,
    unit: str = "m",
    title: str = "",
) -> Path:
    """One panel per component: error over time with the filter's ±3σ band (``sigma`` (N, d) std devs)."""
    t = np.asarray(t_s, float)
    e = np.asarray(err, float)
    e = e[:, None] if e.ndim == 1 else e
    if e.ndim != 2 or len(e) != len(t):
        raise ValueError(f"plot_error_bands: err has shape {e.shape}, expected ({len(t)}, d)")
    d = e.shape[1]
    fig, axs = _figure(d, 1, (10, 2.0 * d + 0.8))
    for k, ax in enumerate(axs):
        if sigma is not None:
            s3 = 3.0 * np.asarray(sigma, float).reshape(len(t), -1)[:, k]
            ax.fill_between(t, -s3, s3, color="tab:blue", alpha=0.2, lw=0, label="±3σ")
        ax.plot(t, e[:, k], color="tab:red", lw=0.9, label="error")
        ax.axhline(0.0, color="k", lw=0.5)
        ax.set_ylabel(f"{labels[k] if k < len(labels) else k} [{unit}]")
        ax.grid(alpha=0.3)
    axs[-1].set_xlabel("time [s]")
    axs[0].legend(loc="upper right", fontsize=8)
    if title:
        fig.suptitle(title)
    return _save(fig, path)


def plot_position_error(path, t_s, err, sigma=None, title: str = "position error") -> Path:
    """Position error (N, 3) (``p - p_hat``) with ±3σ from the (N, 3) position standard deviations."""
    return plot_error_bands(path, t_s, err, sigma, AXES, "m", title)


def plot_anchor_error(
    path: str | Path,
    t_s: np.ndarray,
    err: Mapping[str, np.ndarray] | np.ndarray,
    sigma: Mapping[str, np.ndarray] | np.ndarray | None = None,
    title: str = "anchor error",
) -> Path:
    """Anchor position error over time. ``err``: (N, 3) for one anchor, or ``{id: (N, 3)}`` for several (then
    the norm per anchor is drawn, with the ±3σ of the largest-σ axis as band when ``sigma`` is given)."""
    if not isinstance(err, Mapping):
        return plot_error_bands(path, t_s, err, sigma, AXES, "m", title)
    t = np.asarray(t_s, float)
    fig, axs = _figure(1, 1, (10, 4))
    ax = axs[0]
    for k, (aid, e) in enumerate(err.items()):
        c = f"C{k % 10}"
        ax.plot(t, np.linalg.norm(np.asarray(e, float), axis=1), color=c, lw=1.0, label=f"anchor {aid}")
        if sigma is not None and aid in sigma:
            ax.fill_between(
                t, 0, 3 * np.max(np.asarray(sigma[aid], float), axis=1), color=c, alpha=0.12, lw=0
            )
    ax.set_xlabel("time [s]")
    ax.set_ylabel("‖p̂_a − p_a‖ [m]")
    ax.grid(alpha=0.3)
    ax.legend(loc="upper right", fontsize=8)
    ax.set_title(title)
    return _save(fig, path)


def plot_nees(
    path: str | Path,
    t_s: np.ndarray,
    nees: Mapping[str, np.ndarray] | np.ndarray,
    bounds: Mapping[str, tuple[float, float]] | tuple[float, float] | None = None,
    dof: Mapping[str, int] | int | None = None,
    title: str = "NEES",
) -> Path:
    """NEES (or ANEES) over time, one panel per series, with the χ² bounds and the expected value (dof)."""
    series = dict(nees) if isinstance(nees, Mapping) else {"nees": nees}
    t = np.asarray(t_s, float)
    fig, axs = _figure(len(series), 1, (10, 2.4 * len(series) + 0.6))
    for k, (ax, (name, v)) in enumerate(zip(axs, series.items(), strict=True)):
        ax.plot(t, np.asarray(v, float), color=f"C{k}", lw=0.9, label=name)
        b = bounds.get(name) if isinstance(bounds, Mapping) else bounds
        if b is not None:
            ax.axhline(b[0], color="k", ls="--", lw=0.8, label="95 % χ² bounds")
            ax.axhline(b[1], color="k", ls="--", lw=0.8)
        d = dof.get(name) if isinstance(dof, Mapping) else dof
        if d is not None:
            ax.axhline(d, color="tab:green", lw=0.8, label=f"dof = {d}")
        ax.set_yscale("log")
        ax.set_ylabel(name)
        ax.grid(alpha=0.3, which="both")
        ax.legend(loc="upper right", fontsize=8)
    axs[-1].set_xlabel("time [s]")
    if title:
        fig.suptitle(title)
    return _save(fig, path)


def plot_ri_vs_lsi(
    path: str | Path,
    sigma_r: np.ndarray,
    errors: Mapping[str, np.ndarray],
    percentiles: tuple[float, float] = (25.0, 75.0),
    title: str = "anchor initialisation error vs localisation error",
) -> Path:
    """Anchor error vs σ_r per method: mean over runs with a percentile band. ``errors[method]`` is (S, runs)."""
    s = np.asarray(sigma_r, float)
    fig, axs = _figure(1, 1, (7, 4.5))
    ax = axs[0]
    for k, (method, e) in enumerate(errors.items()):
        e = np.asarray(e, float).reshape(len(s), -1)
        c = _color(method, k)
        lo, hi = np.nanpercentile(e, percentiles, axis=1)
        ax.fill_between(s, lo, hi, color=c, alpha=0.2, lw=0)
        ax.plot(s, np.nanmean(e, axis=1), "o-", color=c, lw=1.5, ms=4,
                label=f"{method.upper()} (mean, {percentiles[0]:g}–{percentiles[1]:g} %)")  # fmt: skip
    ax.set_xlabel("σ_r (localisation error) [m]")
    ax.set_ylabel("anchor error [m]")
    ax.grid(alpha=0.3)
    ax.legend(loc="upper left", fontsize=8)
    ax.set_title(title)
    return _save(fig, path)


def plot_ri_vs_lsi_drift(
    path: str | Path,
    table,
    methods: Sequence[str] = ("lsi", "ri"),
    title: str = "anchor initialisation error vs the VIO's own position σ",
) -> Path:
    """`ri_vs_lsi_drift.summarise` output: per method the mean (solid) and 90th percentile (dashed) anchor error
    against the VIO's mean own position σ over the initialisation window (log-log)."""
    x = table["vio_sigma_m"].to_numpy()
    fig, axs = _figure(1, 1, (7, 4.5))
    ax = axs[0]
    for k, m in enumerate(methods):
        c = _color(m, k)
        ax.plot(x, table[f"{m}_mean_m"].to_numpy(), "o-", color=c, lw=1.5, ms=4, label=f"{m.upper()} mean")
        ax.plot(x, table[f"{m}_p90_m"].to_numpy(), "s--", color=c, lw=1.0, ms=3, label=f"{m.upper()} 90 %")
    for xi, k in zip(x, table["vio_noise_scale"].to_numpy(), strict=True):
        ax.annotate(f"k={k:g}", (xi, 0.0), xycoords=("data", "axes fraction"), xytext=(0, 4),
                    textcoords="offset points", ha="center", fontsize=7, color="0.4")  # fmt: skip
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("VIO position σ over the init window (its own covariance, per axis) [m]")
    ax.set_ylabel("anchor error [m]")
    ax.grid(alpha=0.3, which="both")
    ax.legend(loc="upper left", fontsize=8)
    ax.set_title(title, fontsize=10)
    return _save(fig, path)


def plot_table1_vs_paper(path: str | Path, tables: Mapping[str, object]) -> Path:
    """Table 1 side by side: per metric (PRMSE, anchor error) one panel, per (σ_I, σ_U) cell a group of bars —
    EKF and SKF for each of our prior conventions (``tables[prior]`` = `table1_beside_paper`'s second frame)
    and for the paper (hatched)."""
    first = next(iter(tables.values()))
    cells = first.select("sigma_i", "sigma_u").unique(maintain_order=True).rows()
    panels = [("prmse_m", "PRMSE, refinement window [m]")]
    if "prmse_calib_m_ours" in first.columns:  # the paper's one PRMSE is set beside both windows
        panels.append(("prmse_calib_m", "PRMSE, calibration window [m]"))
    panels.append(("anchor_error_m", "anchor error [m]"))
    fig, axs = _figure(1, len(panels), (6 * len(panels), 4.5))
    series = [(prior, t, "ours") for prior, t in tables.items()] + [("paper", first, "paper")]
    width = 0.8 / (2 * len(series))
    x = np.arange(len(cells))
    for ax, (metric, label) in zip(axs, panels, strict=True):
        j = 0
        for name, t, col in series:
            for method in ("ekf", "skf"):
                vals = []
                for si, su in cells:
                    r = t.filter(
                        (t["method"] == method)
                        & ((t["sigma_i"] - si).abs() < 1e-9)
                        & ((t["sigma_u"] - su).abs() < 1e-9)
                    )
                    name_col = f"{metric}_{col}" if f"{metric}_{col}" in t.columns else f"prmse_m_{col}"
                    vals.append(r[name_col][0] if r.height else np.nan)
                ax.bar(x - 0.4 + (j + 0.5) * width, np.asarray(vals, float), width, color=_color(method, j),
                       alpha=0.45 if name == "paper" else (1.0 if j < 2 else 0.75),
                       hatch="//" if name == "paper" else ("" if j < 2 else ".."), edgecolor="k", lw=0.3,
                       label=f"{method.upper()} {name}")  # fmt: skip
                j += 1
        ax.set_xticks(x, [f"σ_I={si:g}\nσ_U={su:g}" for si, su in cells])
        ax.set_ylabel(label)
        ax.grid(alpha=0.3, axis="y")
    axs[1].legend(fontsize=7, ncol=2, loc="upper left")
    fig.suptitle("table1 at the paper's VIO drift: ours (per prior convention) beside the paper")
    return _save(fig, path)
