"""What the estimators expose, drawn into a stage's run log: logging observes the filters from outside.

The driver calls `log_span` once a span is processed (trajectory, covariance, 3-sigma series and the pose
source's own series); the refine and localize stages call `log_uwb_updates` with their updater; the frontend
stage passes `frame_logger` as the front-end's per-frame observer."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from uwbcal.pipeline.core.state import Kind, chi2_ppf
from uwbcal.pipeline.uwb.updater import UwbUpdater
from uwbcal.pipeline.vio.estimator import Estimator, Span
from uwbcal.pipeline.vio.msckf import MsckfEstimator
from uwbcal.pipeline.viz import runlog as rl
from uwbcal.pipeline.viz.runlog import RunLog


def log_span(log: RunLog, est: Estimator, span: Span) -> None:
    """world/vio: the span's poses, their position covariance and 3-sigma series; the MSCKF's own series."""
    log_trajectory(log, est.history().arrays(), span.first_record)
    if isinstance(est, MsckfEstimator):
        log_msckf(log, est)


def log_trajectory(log: RunLog, hist: dict[str, np.ndarray], first: int) -> None:
    """world/vio: the poses from index ``first`` on, their position covariance and 3-sigma series."""
    t, p, q, cov = (hist[k][first:] for k in ("t_ns", "p", "q_xyzw", "cov"))
    if not len(t):
        return
    sig3 = 3.0 * np.sqrt(np.maximum(np.diagonal(cov, axis1=1, axis2=2), 0))
    step = max(1, len(t) // 500)
    log.trajectory(rl.VIO, t, p, q)
    log.ellipsoid_series(rl.VIO_COV, t[::step], p[::step], cov[::step, 3:6, 3:6])
    log.scalars(f"{rl.SIGMA}/vio_p3sigma", t, sig3[:, 3:6], ["x", "y", "z"])
    log.scalars(f"{rl.SIGMA}/vio_theta3sigma_deg", t, np.degrees(sig3[:, 0:3]), ["x", "y", "z"])


def log_msckf(log: RunLog, est: MsckfEstimator) -> None:
    """The MSCKF's own series of the span: features used / rejected, NIS, ZUPTs, the last triangulated points,
    the clone window and the SLAM features in the state."""
    trace = est.take_frame_trace()
    if trace is None:
        return
    if trace["t"]:
        tt = np.asarray(trace["t"], np.int64)
        cols = np.column_stack([trace["used"], trace["rejected"]]).astype(float)
        log.scalars(f"{rl.FILTER}/vio/features", tt, cols, ["used", "rejected_chi2"])
        log.scalars(f"{rl.FILTER}/vio/nis_sum", tt, np.asarray(trace["nis"], float))
    if trace["zupt"]:
        tz = np.asarray(trace["zupt"], np.int64)
        log.scalars(f"{rl.FILTER}/vio/zupt", tz, np.ones(len(tz)))
    if trace["points"]:
        log.points3d(rl.FEATURES, np.concatenate(trace["points"][-100:]), None, 0.03, None, est.t_ns)
    clones = est.clone_positions()
    if len(clones):
        log.points3d(f"{rl.VIO}/clones", clones, None, 0.05, None, est.t_ns)
    landmarks = est.state.of_kind(Kind.LANDMARK)
    if landmarks:
        pts = np.stack([est.state.value(n).x for _, n in landmarks])
        log.points3d(f"{rl.VIO}/slam_features", pts, None, 0.05, None, est.t_ns)


def log_uwb_updates(log: RunLog | None, updater: UwbUpdater) -> None:
    """Column-wise series per anchor: uwb/<id>/{residual,band,nis,nis_gate,rejected}, anchors/<id>/{beta,gamma};
    filter/nis_uwb: the moving-average NIS of all anchors with its chi2 band."""
    if log is None:
        return
    quantile = updater.chi2_quantile
    arrays = updater.arrays()
    for a, arr in arrays.items():
        t = arr["t_ns"]
        log.scalars(rl.uwb(a, "residual"), t, arr["residual"])
        log.scalars(rl.uwb(a, "nis"), t, arr["nis"])
        if quantile is not None and len(t):
            log.constant(rl.uwb(a, "nis_gate"), t, chi2_ppf(quantile, 1), ["gate"])
        rej = arr["rejected"].astype(bool)  # the gated-out ranges as red points at their residual
        log.scalars(rl.uwb(a, "rejected"), t[rej], arr["residual"][rej])
        if rej.any():
            log.series_static_style(rl.uwb(a, "rejected"), ["rejected"], [rl.COLORS["rejected"]], points=True)
        gate = float(np.sqrt(chi2_ppf(quantile, 1))) if quantile is not None else 3.0
        _log_residual_band(log, a, t, arr["residual"], arr["nis"], n_sigma=gate)
        log.scalars(rl.anchor_param(a, "beta"), t, arr["x"][:, 3])
        log.scalars(rl.anchor_param(a, "gamma"), t, arr["x"][:, 4])
    _log_nis_average(log, arrays)


def frame_logger(log: RunLog) -> Callable[[int, np.ndarray, np.ndarray, np.ndarray], None]:
    """The front-end's per-frame observer: cam0/image and cam0/tracks."""

    def on_frame(t_ns: int, img: np.ndarray, uv: np.ndarray, ids: np.ndarray) -> None:
        log.image("cam0/image", t_ns, img)
        log.tracks("cam0/tracks", t_ns, uv, ids)

    return on_frame


def _log_nis_average(log: RunLog, arrays: dict[int, dict[str, np.ndarray]]) -> None:
    """The NIS of the accepted updates, all anchors pooled, as a moving average with its chi2 band."""
    arrs = [arr for arr in arrays.values() if len(arr["t_ns"])]
    if arrs:
        keep = ~np.concatenate([arr["rejected"] for arr in arrs]).astype(bool)
        t_all = np.concatenate([arr["t_ns"] for arr in arrs])
        nis = np.concatenate([arr["nis"] for arr in arrs])[keep]
        t, avg, lo, hi = rl.moving_nis(t_all[keep], nis, 1, 50)
        if len(t):
            log.scalars(rl.NIS_UWB, t, avg, names=["NIS avg of 50"])
            log.constant(f"{rl.NIS_UWB}_bounds", t, [lo, hi], names=["χ² 2.5 %", "χ² 97.5 %"])


def _log_residual_band(log: RunLog, anchor: object, t_ns, residual, nis, n_sigma: float) -> None:
    """±n·σ of the range innovation beside the residual: σ = |r| / sqrt(NIS) (NIS = r²/S), at `uwb/<id>/band`;
    with n = sqrt(the chi2 gate) a range is rejected exactly when its residual leaves the band."""
    r = np.asarray(residual, dtype=np.float64).reshape(-1)
    nis = np.asarray(nis, dtype=np.float64).reshape(-1)
    ok = np.isfinite(r) & np.isfinite(nis) & (nis > 0)
    t = np.asarray(t_ns, dtype=np.int64).reshape(-1)[ok]
    sig = n_sigma * np.abs(r[ok]) / np.sqrt(nis[ok])
    entity = rl.uwb(anchor, "band")
    log.scalars(entity, t, np.c_[sig, -sig])
    log.series_static_style(entity, [f"+{n_sigma:.3g}σ", f"-{n_sigma:.3g}σ"], [rl.COLORS["gate"]] * 2)
