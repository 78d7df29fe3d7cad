"""Whether a pose source's estimate over a stretch can be trusted: the checks that tell a diverged filter.

A filter that has diverged does not say so by itself (its pose keeps coming, km away). Over the stretch a
stage filtered, three checks on what the filter recorded, without ground truth:

- ``chi2``: the fraction of the feature tracks of a trailing window that fail the chi-squared gate
  (`stats.VioStats.rejection_rate`) exceeds ``vio.consistency_max_rejected``: the filter's covariance no longer
  explains its own measurements (overconfident: e.g. the IMU noise told far too small);
- ``velocity``: the speed over ``health_speed_baseline_s`` exceeds ``vio.max_speed``: the pose runs away;
- ``covariance``: the position sigma exceeds ``vio.max_position_sigma``: the filter says itself that it lost
  track (e.g. no usable features for a long time);
- ``range_nis``: in the localisation stage (anchors frozen), the median normalised innovation squared of the
  UWB ranges of a trailing ``vio.range_nis_window_s`` window (all anchors pooled; `windowed_median_nis`)
  exceeds ``vio.max_range_nis``: the ranges no longer fit the pose within the covariance the filter claims,
  which catches a diverged pose the visual chi2 test misses (a filter whose feature tracks all fail
  triangulation, or too few to be judged). The median: a stretch of NLOS ranges on some anchors is not a
  divergence, every range off is.

The earliest failure is the one reported (`Failure`: which check, when, the figure against its threshold).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from uwbcal.pipeline.vio.config import VioConfig


@dataclass(frozen=True)
class Failure:
    check: str  # "chi2" | "velocity" | "covariance" | "range_nis"
    t_ns: int
    value: float
    threshold: float
    key: str  # the config key of the threshold

    def message(self, stage: str, t0_ns: int) -> str:
        what = {
            "chi2": f"{self.value:.0%} of the feature tracks failed the chi2 test",
            "velocity": f"speed {self.value:.3g} m/s",
            "covariance": f"position sigma {self.value:.3g} m",
            "range_nis": f"median NIS {self.value:.3g} of the UWB ranges of a window",
        }[self.check]
        return (
            f"{stage}: the VIO diverged at {(self.t_ns - t0_ns) * 1e-9:.1f} s after the start ({self.check} check: "
            f"{what} > {self.key} = {self.threshold:g}); check the IMU noise of the calibration, the camera "
            'calibration and the static start (or set vio.on_failure = "warn" to keep the estimate)'
        )

    def summary(self, stage: str, t0_ns: int) -> dict:
        return {
            "failed": True,
            "stage": stage,
            "check": self.check,
            "t_s": (self.t_ns - t0_ns) * 1e-9,
            "value": self.value,
            "threshold": self.threshold,
            "key": self.key,
            "message": self.message(stage, t0_ns),
        }


def _first(t: np.ndarray, value: np.ndarray, threshold: float, check: str, key: str) -> Failure | None:
    bad = np.flatnonzero(value > threshold)  # NaN compares False
    if not len(bad):
        return None
    i = int(bad[0])
    return Failure(check, int(t[i]), float(value[i]), threshold, key)


def speed(t_ns: np.ndarray, p: np.ndarray, baseline_s: float) -> np.ndarray:
    """Speed at each pose over the trailing ``baseline_s`` (NaN before a full baseline)."""
    t = np.asarray(t_ns, np.int64)
    j = np.searchsorted(t, t - int(baseline_s * 1e9), "right") - 1
    ok = j >= 0
    out = np.full(len(t), np.nan)
    jj = j[ok]
    dt = (t[ok] - t[jj]) * 1e-9
    out[ok] = np.linalg.norm(p[ok] - p[jj], axis=1) / np.maximum(dt, 1e-9)
    return out


def windowed_median_nis(
    t_ns: np.ndarray, nis: np.ndarray, window_s: float, min_ranges: int
) -> tuple[np.ndarray, np.ndarray]:
    """(stamps, median NIS of the ranges in the trailing ``window_s`` up to each) for the ranges ``t_ns``
    (any order, all anchors pooled); NaN where a window holds fewer than ``min_ranges``. Evaluated at no more
    than ~2000 stamps (a window holds hundreds of ranges: neighbouring medians barely differ)."""
    order = np.argsort(np.asarray(t_ns, np.int64), kind="stable")
    t, v = np.asarray(t_ns, np.int64)[order], np.asarray(nis, float)[order]
    ok = np.isfinite(v)
    t, v = t[ok], v[ok]
    at = np.arange(0, len(t), max(1, len(t) // 2000))
    lo = np.searchsorted(t, t[at] - int(window_s * 1e9), "right")
    med = np.array(
        [np.median(v[a : i + 1]) if i + 1 - a >= min_ranges else np.nan for a, i in zip(lo, at, strict=True)]
    )
    return t[at], med


def assess(
    hist: dict[str, np.ndarray],
    config: VioConfig,
    rejection: tuple[np.ndarray, np.ndarray, np.ndarray] | None,
    start_ns: int | None = None,
    end_ns: int | None = None,
    ranges: tuple[np.ndarray, np.ndarray] | None = None,
) -> Failure | None:
    """The earliest failing check over ``[start_ns, end_ns)`` of a pose history (``t_ns``, ``p``, ``cov``:
    `TrajectoryRecord.arrays`), for the MSCKF its chi2 rejection rate ``(t, fraction, tested)`` and, in the
    localisation stage, the NIS of its range updates ``(t, nis)``."""
    t = np.asarray(hist["t_ns"], np.int64)
    lo = 0 if start_ns is None else int(np.searchsorted(t, start_ns, "left"))
    hi = len(t) if end_ns is None else int(np.searchsorted(t, end_ns, "left"))
    found = []
    if hi > lo:
        t, p, cov = t[lo:hi], hist["p"][lo:hi], hist["cov"][lo:hi]
        v = speed(t, p, config.health_speed_baseline_s)
        found.append(_first(t, v, config.max_speed, "velocity", "vio.max_speed"))
        sig = np.sqrt(np.maximum(np.trace(cov[:, 3:6, 3:6], axis1=1, axis2=2), 0.0))
        found.append(_first(t, sig, config.max_position_sigma, "covariance", "vio.max_position_sigma"))
    if rejection is not None:
        tr, frac, _ = rejection
        big = np.iinfo(np.int64).max
        keep = (tr >= (-big if start_ns is None else start_ns)) & (tr < (big if end_ns is None else end_ns))
        tr, frac = tr[keep], frac[keep]
        found.append(
            _first(tr, frac, config.consistency_max_rejected, "chi2", "vio.consistency_max_rejected")
        )
    if ranges is not None:
        tr, nis = ranges
        keep = (tr >= (start_ns or 0)) & (tr < (np.iinfo(np.int64).max if end_ns is None else end_ns))
        tm, med = windowed_median_nis(
            tr[keep], nis[keep], config.range_nis_window_s, config.range_nis_min_ranges
        )
        found.append(_first(tm, med, config.max_range_nis, "range_nis", "vio.max_range_nis"))
    found = [f for f in found if f is not None]
    return min(found, key=lambda f: f.t_ns) if found else None


__all__ = ["Failure", "assess", "speed", "windowed_median_nis"]
