"""The MSCKF's counters and its per-update chi-squared record, shared by the manager and its updaters."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass
class VioStats:
    frames: int = 0
    updates: int = 0
    frames_before_imu: int = 0
    frames_without_features: int = 0
    imu_gaps: int = 0
    imu_max_gap_s: float = 0.0
    features_used: int = 0
    features_rejected_chi2: int = 0
    features_failed_triangulation: int = 0
    zupt_updates: int = 0
    zupt_time_s: float = 0.0
    slam_initialized: int = 0  # tracks made SLAM features
    slam_used: int = 0  # SLAM feature observations used / failing the chi2 test (the feature is then dropped)
    slam_rejected: int = 0
    # per feature update: stamp, tracks that passed / failed the chi2 gate (the consistency warning's input)
    update_t: list[int] = field(default_factory=list)
    update_used: list[int] = field(default_factory=list)
    update_rejected: list[int] = field(default_factory=list)

    def warnings(self) -> list[str]:
        out = []
        if self.frames_before_imu:
            out.append(f"vio: {self.frames_before_imu} camera frame(s) before the first IMU sample skipped")
        if self.imu_gaps:
            out.append(f"vio: {self.imu_gaps} IMU gap(s) > threshold (longest {self.imu_max_gap_s:.3f} s)")
        if self.frames and self.frames_without_features > 0.1 * self.frames:
            out.append(f"vio: {self.frames_without_features} of {self.frames} frames had no usable features")
        total = self.features_used + self.features_rejected_chi2
        if total and self.features_rejected_chi2 > 0.2 * total:
            out.append(f"vio: {self.features_rejected_chi2} of {total} feature tracks failed the chi2 test")
        return out

    def rejection_rate(
        self, window_s: float, min_tracks: int, start_ns: int | None = None, end_ns: int | None = None
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Per feature update in ``[start_ns, end_ns)`` (None: open; a stage's stretch when the stats carry over
        through a checkpoint): its stamp, the fraction of the tracks tested in the trailing ``window_s`` (inside
        the stretch) that failed the chi2 gate, and how many were tested (NaN fraction below ``min_tracks``)."""
        t = np.asarray(self.update_t, np.int64)
        lo = 0 if start_ns is None else int(np.searchsorted(t, start_ns, "left"))
        hi = len(t) if end_ns is None else int(np.searchsorted(t, end_ns, "left"))
        t = t[lo:hi]
        c_used = np.concatenate([[0], np.cumsum(self.update_used[lo:hi])])
        c_rej = np.concatenate([[0], np.cumsum(self.update_rejected[lo:hi])])
        j = np.searchsorted(t, t - int(window_s * 1e9), "right")  # first update inside each window
        i = np.arange(1, len(t) + 1)
        rej = c_rej[i] - c_rej[j]
        n = rej + c_used[i] - c_used[j]
        frac = np.where(n >= min_tracks, rej / np.maximum(n, 1), np.nan)
        return t, frac, n

    def consistency_warnings(
        self,
        window_s: float,
        min_tracks: int,
        max_rejected: float,
        stage: str,
        start_ns: int | None,
        end_ns: int | None,
        t0_ns: int,
    ) -> list[str]:
        """A warning when the filter's own feature updates say it is inconsistent (no ground truth needed): in
        some trailing window of ``[start_ns, end_ns)`` (the stretch ``stage`` filtered) more than ``max_rejected``
        of the tracks tested failed the chi2 gate (a consistent filter rejects 1 - chi2_quantile of them,
        outliers aside). Times in s after ``t0_ns`` (the run's start)."""
        t, frac, n = self.rejection_rate(window_s, min_tracks, start_ns, end_ns)
        bad = frac > max_rejected  # NaN compares False
        if not bad.any():
            return []
        t0 = t0_ns
        k = int(np.nanargmax(np.where(bad, frac, np.nan)))
        first, last = (t[bad][[0, -1]] - t0) * 1e-9
        return [
            f"{stage}: inconsistent visual updates from {first:.1f} s to {last:.1f} s after the start: up to "
            f"{frac[k]:.0%} of the feature tracks of a {window_s:g} s window failed the chi2 test ({int(n[k])} "
            f"tested at {(t[k] - t0) * 1e-9:.1f} s; threshold vio.consistency_max_rejected = {max_rejected:g}); "
            "the MSCKF has likely diverged (its pose and covariance are not to be trusted there): check the "
            "IMU noise, the static start / zero-velocity updates and the camera calibration"
        ]
