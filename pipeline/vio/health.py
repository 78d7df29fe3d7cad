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

`OnlineHealth` makes the first three checks during the run, at each camera frame over the same trailing windows,
so that the MSCKF can re-initialise its window when one fires (``vio.max_reinits``); `assess` then judges those
three only after the last re-initialisation (what came before was judged online), the range NIS over all of it.
"""

from __future__ import annotations

from bisect import bisect_right
from dataclasses import dataclass

import numpy as np

from uwbcal.pipeline.vio.config import VioConfig
from uwbcal.pipeline.vio.estimator import TrajectoryRecord
from uwbcal.pipeline.vio.stats import VioStats


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

    def record(self, t0_ns: int) -> dict:
        """Which check fired, when (s after ``t0_ns``), the figure against its threshold."""
        return {
            "check": self.check,
            "t_s": (self.t_ns - t0_ns) * 1e-9,
            "value": self.value,
            "threshold": self.threshold,
            "key": self.key,
        }

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
    online_from_ns: int | None = None,
) -> Failure | None:
    """The earliest failing check over ``[start_ns, end_ns)`` of a pose history (``t_ns``, ``p``, ``cov``:
    `TrajectoryRecord.arrays`), for the MSCKF its chi2 rejection rate ``(t, fraction, tested)`` (computed over
    the same stretch) and, in the localisation stage, the NIS of its range updates ``(t, nis)``.
    ``online_from_ns``: the last online re-initialisation; the speed and position sigma are judged from it on
    (the rejection rate is the caller's, from the same stamp)."""
    t = np.asarray(hist["t_ns"], np.int64)
    pose_start = start_ns
    if online_from_ns is not None:
        pose_start = online_from_ns if start_ns is None else max(start_ns, online_from_ns)
    lo = 0 if pose_start is None else int(np.searchsorted(t, pose_start, "left"))
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
        keep = (tr >= (-big if pose_start is None else pose_start)) & (
            tr < (big if end_ns is None else end_ns)
        )
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


class OnlineHealth:
    """`assess`'s chi2, speed and position-sigma checks during the run, at a camera frame (``check``), over the
    trailing windows `assess` uses, none reaching back before the last `restart` (a re-initialisation). Pure: it
    reads the filter's stats, history and position sigma, keeps only the restart stamp."""

    def __init__(self, config: VioConfig) -> None:
        self.config = config
        self.since_ns: int | None = None

    def restart(self, t_ns: int) -> None:
        self.since_ns = int(t_ns)

    def check(self, t_ns: int, stats: VioStats, hist: TrajectoryRecord, pos_sigma: float) -> Failure | None:
        c = self.config
        since = -(2**62) if self.since_ns is None else self.since_ns
        frac = self._rejection(t_ns, stats, since)
        if frac is not None and frac > c.consistency_max_rejected:
            return Failure("chi2", t_ns, frac, c.consistency_max_rejected, "vio.consistency_max_rejected")
        t = hist.t_ns
        j = bisect_right(t, t_ns - int(c.health_speed_baseline_s * 1e9)) - 1
        if t and t[-1] == t_ns and j >= 0 and t[j] >= since:
            v = float(np.linalg.norm(hist.p[-1] - hist.p[j])) / max((t_ns - t[j]) * 1e-9, 1e-9)
            if v > c.max_speed:
                return Failure("velocity", t_ns, v, c.max_speed, "vio.max_speed")
        if pos_sigma > c.max_position_sigma:
            return Failure("covariance", t_ns, pos_sigma, c.max_position_sigma, "vio.max_position_sigma")
        return None

    def _rejection(self, t_ns: int, stats: VioStats, since: int) -> float | None:
        """The fraction of the tracks of the feature updates in ``(t_ns - window, t_ns]`` (and after ``since``)
        that failed the chi2 gate, when the last update is at ``t_ns`` and enough were tested."""
        c = self.config
        ts = stats.update_t
        if not ts or ts[-1] != t_ns:
            return None
        lo = max(t_ns - int(c.consistency_window_s * 1e9), since)  # the update that fired: before
        used = rej = 0
        i = len(ts) - 1
        while i >= 0 and ts[i] > lo:
            used += stats.update_used[i]
            rej += stats.update_rejected[i]
            i -= 1
        n = used + rej
        return rej / n if n >= c.consistency_min_tracks else None


__all__ = ["Failure", "OnlineHealth", "assess", "speed", "windowed_median_nis"]
