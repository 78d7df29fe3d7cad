"""MSCKF visual-inertial odometry with first-estimate Jacobians (FEJ): the manager (OpenVINS' VioManager).

State: the navigation variable ``"imu"`` (ImuState, ``Kind.NAV``) plus stochastic clones ``"clone/<t_ns>"``
(``Kind.CLONE``: the pose of the IMU at each camera frame), and the SLAM landmarks. The manager is fed by
`driver.run_estimator`, which reads the recording: `feed_imu` (the span's IMU samples, checked), `initialize` (on
the first span), `begin`, then `process_frame` per camera frame and `process_range` per UWB range. Per camera
frame: propagate to the frame; when the interval since the last frame was static, the zero-velocity update
(`update_zupt.ZuptUpdater`); else clone, the SLAM features seen (`update_slam.SlamUpdater`), the MSCKF update
with the selected feature tracks (`update_msckf.MsckfUpdater`, the tracks in `features.FeatureDatabase`), and
the oldest clone marginalised when the window is full. All updaters count into one `stats.VioStats`. After
each frame the online health checks (`health.OnlineHealth`); when one fires, the window is re-initialised from
the IMU estimate (`state.reset_window`), at most ``vio.max_reinits`` times (``reinits``: the checks that fired).
"""

from __future__ import annotations

import logging

import numpy as np

from uwbcal.pipeline.core.errors import InputError
from uwbcal.pipeline.core.state import (
    ImuState,
    Kind,
    Pose,
    State,
    add_probe,
    remove_probes,
    reset_window,
)
from uwbcal.pipeline.core.topics import TOPIC_IMU
from uwbcal.pipeline.vio.camera import Camera
from uwbcal.pipeline.vio.config import VioConfig
from uwbcal.pipeline.vio.estimator import RangeHandler, RangeMeasurement, Span, TrajectoryRecord
from uwbcal.pipeline.vio.features import FeatureDatabase, clone_name
from uwbcal.pipeline.vio.health import Failure, OnlineHealth
from uwbcal.pipeline.vio.imu import ImuNoise, imu_intervals, propagate, propagate_static
from uwbcal.pipeline.vio.stats import VioStats
from uwbcal.pipeline.vio.update_msckf import MsckfUpdater
from uwbcal.pipeline.vio.update_slam import SlamUpdater
from uwbcal.pipeline.vio.update_zupt import ZuptUpdater

_log = logging.getLogger(__name__)


class MsckfEstimator:
    """The MSCKF pose source (Estimator protocol): state, propagation, clones, pose probes and the feed; the
    updates are its updaters' (``msckf``, ``slam``, ``zupt``)."""

    keeps_probes = True

    def __init__(
        self,
        config: VioConfig,
        camera: Camera,
        noise: ImuNoise,
        initial: ImuState | None = None,
        initial_cov: np.ndarray | None = None,
        source: str = "recording",
    ) -> None:
        self.initial_cov = None if initial_cov is None else np.asarray(initial_cov, float).reshape(15, 15)
        self.camera = camera
        self.noise = noise
        self.state = State(use_fej=config.fej)
        self.t_ns = -1
        self.initial = initial
        self.initialized = False
        self.db = FeatureDatabase()
        self.stats = VioStats()
        self._history = TrajectoryRecord()
        self.msckf = MsckfUpdater(config, camera, self.stats)
        self.slam = SlamUpdater(config, camera, self.stats)
        self.zupt = ZuptUpdater(config, camera, noise, self.stats)
        self.health = OnlineHealth(config)
        self.reinits: list[Failure] = []  # the online failures the window was re-initialised after
        self.config = config
        self._static: tuple[int, int] | None = None  # (t0, t1): propagate with the zero-motion model in it
        self.source = source
        self._probe_period_ns: int | None = None  # pose probes for the UWB initialisation (start_probes)
        self._last_probe_ns: int | None = None

    @property
    def config(self) -> VioConfig:
        return self._config

    @config.setter
    def config(self, config: VioConfig) -> None:
        """The manager's and its updaters' settings (one config for all)."""
        self._config = config
        for updater in (self.msckf, self.slam, self.zupt, self.health):
            updater.config = config

    def initialize(self, t0_ns: int, x0: ImuState) -> None:
        """The IMU state ``x0`` at ``t0_ns``: with ``initial_cov`` when the state is the given ``initial``, else
        the vio.sigma_*0 settings."""
        c = self.config
        sig = np.repeat([c.sigma_theta0, c.sigma_p0, c.sigma_v0, c.sigma_bg0, c.sigma_ba0], 3)
        P0 = (
            self.initial_cov if self.initial is not None and self.initial_cov is not None else np.diag(sig**2)
        )
        self.state.add("imu", x0, P0, kind=Kind.NAV)
        self.t_ns = int(t0_ns)
        self.initialized = True

    @property
    def warnings(self) -> list[str]:
        return self.stats.warnings()

    def span_warnings(self, stage: str, start_ns: int | None, end_ns: int | None, t0_ns: int) -> list[str]:
        """The consistency warning of the visual updates over ``[start_ns, end_ns)``, the stretch ``stage``
        filtered (the stats carry over through the checkpoints: each stage judges only its own updates)."""
        c = self.config
        return self.stats.consistency_warnings(
            c.consistency_window_s,
            c.consistency_min_tracks,
            c.consistency_max_rejected,
            stage,
            start_ns,
            end_ns,
            t0_ns,
        )

    @property
    def clones(self) -> list[int]:
        """Stamps of the clone window, oldest first."""
        return [t for t, _ in self.state.clones]

    def history(self) -> TrajectoryRecord:
        return self._history

    # -- pose probes (UWB initialisation window) ----------------------------------------------------------------
    def start_probes(self, period_s: float) -> None:
        """From now on keep the pose every ``period_s`` (at camera frames) as a considered variable
        (`state.add_probe`), so that the anchors initialised over this stretch get exact cross-covariances."""
        self._probe_period_ns = int(period_s * 1e9)
        self._last_probe_ns = None
        if self.initialized:
            self.add_probe()

    def add_probe(self) -> None:
        add_probe(self.state, self.t_ns)
        self._last_probe_ns = self.t_ns

    def stop_probes(self, remove: bool = True) -> None:
        """No more probes; ``remove``: also drop those in the state (False: they stay for the initialisation)."""
        self._probe_period_ns = None
        if remove:
            remove_probes(self.state)

    def _maybe_probe(self) -> None:
        if self._probe_period_ns is not None and (
            self._last_probe_ns is None or self.t_ns - self._last_probe_ns >= self._probe_period_ns
        ):
            self.add_probe()

    # -- propagation -------------------------------------------------------------------------------------------
    def _propagate_to(self, t_ns: int, imu_t: np.ndarray, gyro: np.ndarray, acc: np.ndarray) -> None:
        if t_ns <= self.t_ns:
            return
        step = int(self.config.max_propagation_s * 1e9)
        while self.t_ns < t_ns:
            t1 = min(t_ns, self.t_ns + step)
            x = self.state.value("imu")
            if self._static is not None and self._static[0] <= self.t_ns and t1 <= self._static[1]:
                prop = propagate_static(x, (t1 - self.t_ns) * 1e-9, self.noise, self.state.fej("imu"))
            else:
                dt, w, a = imu_intervals(imu_t, gyro, acc, self.t_ns, t1)
                prop = propagate(x, dt, w, a, self.noise, self.state.fej("imu"))
            self.state.propagate("imu", prop.Phi, prop.Q)
            self.state.set_propagated("imu", prop.state)
            self.t_ns = t1

    def _record(self) -> None:
        x = self.state.value("imu")
        sl = self.state.slice("imu")
        P6 = self.state.P[sl.start : sl.start + 6, sl.start : sl.start + 6]
        self._history.append(self.t_ns, x.R, x.p, P6)

    # -- camera update -----------------------------------------------------------------------------------------
    def _camera_frame(self, t_ns: int, ids: np.ndarray, uv: np.ndarray, trace: dict | None) -> None:
        self.stats.frames += 1
        x = self.state.value("imu")
        J = np.zeros((6, 15))
        J[:, :6] = np.eye(6)
        self.state.augment(clone_name(t_ns), Pose(x.R, x.p), {"imu": J}, kind=Kind.CLONE, key=int(t_ns))
        ok = np.isfinite(uv).all(axis=1)
        if not ok.all():
            ids, uv = ids[ok], uv[ok]
        if len(ids) > 1 and not (ids[1:] > ids[:-1]).all():  # unsorted or duplicate ids: keep the first
            _, first = np.unique(ids, return_index=True)
            ids, uv = ids[first], uv[first]
        ids, uv = self.slam.frame(self.state, t_ns, ids, uv)
        if len(ids) == 0:
            self.stats.frames_without_features += 1
        else:
            self.db.add(t_ns, ids, uv, self.camera.undistort(uv))
        oldest = self.clones[0] if len(self.clones) > self.config.max_clones else None
        rows, drop = self.db.select(
            t_ns, oldest, self.config.min_track_length, self.config.max_features_per_update
        )
        if len(rows):
            chosen = self.msckf.update(self.state, self.db, rows, t_ns, trace, self.slam)
            if chosen is not None:
                orow, valid = chosen
                self.slam.initialize(self.state, self.msckf.linearize(self.state, self.db, orow[valid]))
        keep = ~drop
        if oldest is not None:
            self.state.remove(clone_name(oldest))
            keep &= self.db.t != oldest
        self.db.keep(keep)

    # -- fed by the driver (pipeline/run/driver.py) ------------------------------------------------------------
    def feed_imu(
        self,
        imu_t: np.ndarray,
        gyro: np.ndarray,
        acc: np.ndarray,
        first_imu: int,
        src: str,
        start: int,
        end: int,
    ) -> int | None:
        """The span's IMU samples (``[start, end)`` with a margin; ``first_imu``: the recording's first), checked;
        before the first span: the stamp to initialise at (the first sample from ``start``), else None."""
        self._check_imu(imu_t, gyro, acc, src)
        if len(imu_t) < 2:
            raise InputError(
                f"{src}: {TOPIC_IMU}: fewer than 2 samples in [{start}, {end}); nothing to run on"
            )
        t0 = None
        if not self.initialized:
            i0 = int(np.searchsorted(imu_t, start))
            if i0 >= len(imu_t) or imu_t[i0] >= end:
                raise InputError(f"{src}: {TOPIC_IMU}: no IMU sample in [{start}, {end}); nothing to run on")
            t0 = int(imu_t[i0])
        self._imu = (imu_t, gyro, acc)
        self._first_imu = first_imu
        return t0

    def begin(self, trace: bool) -> None:
        """Start a span (after `feed_imu` and, on the first, `initialize`): ``trace`` records the per-frame
        series for an observer (`take_frame_trace`)."""
        self._frame_trace = (
            {k: [] for k in ("t", "used", "rejected", "nis", "points", "zupt")} if trace else None
        )
        self.zupt.set_reference(self.state, self.t_ns)

    def propagate_to(self, t_ns: int) -> None:
        """IMU propagation of the state to ``t_ns`` (no-op when the state is there already)."""
        self._propagate_to(t_ns, *self._imu)

    def process_range(self, m: RangeMeasurement, on_range: RangeHandler | None) -> None:
        """A range at or after the state time: propagate to its stamp, let ``on_range`` update, record the pose."""
        if m.t_ns < self.t_ns:
            return
        self.propagate_to(m.t_ns)
        if on_range is not None:
            on_range(self, m)
        self._record()  # after the handler: the pose including its update

    def process_ranges(self, batch: list[RangeMeasurement], on_range: RangeHandler) -> None:
        """Ranges of one stamp for an epoch handler: propagate once, one epoch update, record the pose."""
        if batch[0].t_ns < self.t_ns:
            return
        self.propagate_to(batch[0].t_ns)
        on_range.epoch(self, batch)
        self._record()

    def process_frame(self, frame: tuple[int, np.ndarray, np.ndarray]) -> None:
        """A camera frame: ZUPT when the interval since the last frame was static, else clone + MSCKF update."""
        t_ns, ids, uv = frame
        if t_ns < self.t_ns or (self.clones and t_ns <= self.clones[-1]):
            if t_ns < self._first_imu:
                self.stats.frames_before_imu += 1
            return
        args = self._imu
        t_prev = self.zupt.ref[0]  # the previous frame: ranges since then moved the state time
        static = self.config.zupt and self.zupt.detect(t_ns, ids, uv, *args)
        self._static = (t_prev, t_ns) if static and self.config.zupt_imu else None
        self.propagate_to(t_ns)
        if static:  # no clone: a static frame adds no parallax, only degenerate feature updates
            self.stats.frames += 1
            if not np.isfinite(uv).all(axis=1).any():
                self.stats.frames_without_features += 1
            self.zupt.update(self.state, t_prev, t_ns, *args)
            if self._frame_trace is not None:
                self._frame_trace["zupt"].append(t_ns)
        else:
            self._camera_frame(t_ns, ids, uv, self._frame_trace)
        self._static = None
        self.zupt.after_frame(t_ns, ids, uv, self.state.value("imu").R, static)
        self._record()
        self._recover()
        self._maybe_probe()
        self.zupt.set_reference(self.state, self.t_ns)

    def _recover(self) -> None:
        """The online health checks after a frame; a failure while re-initialisations are left: the window
        restarts from the IMU estimate with its pose and velocity covariance inflated (vio.reinit_sigma_*)."""
        c = self.config
        if len(self.reinits) >= c.max_reinits:
            return
        sl = self.state.slice("imu")
        pos_sigma = float(
            np.sqrt(
                max(np.trace(self.state.P[sl.start + 3 : sl.start + 6, sl.start + 3 : sl.start + 6]), 0.0)
            )
        )
        fail = self.health.check(self.t_ns, self.stats, self._history, pos_sigma)
        if fail is None:
            return
        sig = np.repeat([c.reinit_sigma_theta, c.reinit_sigma_p, c.reinit_sigma_v, 0.0, 0.0], 3)
        reset_window(self.state, np.diag(sig**2))
        self.db = FeatureDatabase()  # the tracks' earlier pixels belong to the dropped clones
        self.health.restart(self.t_ns)
        self.reinits.append(fail)
        _log.warning(
            "%s: VIO window re-initialised (%d of %d) after the %s check (%.3g > %s = %g)",
            self.source,
            len(self.reinits),
            c.max_reinits,
            fail.check,
            fail.value,
            fail.key,
            fail.threshold,
        )

    def close(self, span: Span) -> None:
        """End of a span: report, drop the span's IMU data (the estimator is pickled between stages)."""
        if self.stats.zupt_updates:
            _log.info(
                "%s: %d zero-velocity update(s) over %.1f s",
                span.source,
                self.stats.zupt_updates,
                self.stats.zupt_time_s,
            )
        if self.stats.frames_before_imu:
            _log.warning(
                "%s: %d camera frame(s) before the IMU start skipped",
                span.source,
                self.stats.frames_before_imu,
            )
        self._imu = None

    def _check_imu(self, t: np.ndarray, gyro: np.ndarray, acc: np.ndarray, src: str) -> None:
        bad = ~(np.isfinite(gyro).all(axis=1) & np.isfinite(acc).all(axis=1))
        if bad.any():
            i = int(np.flatnonzero(bad)[0])
            raise InputError(
                f"{src}: {TOPIC_IMU} @ {int(t[i])}: NaN/inf in the IMU measurement ({int(bad.sum())} sample(s)); "
                "drop or repair these samples"
            )
        if len(t) < 2:
            return
        gaps = np.diff(t) * 1e-9
        if (gaps <= 0).any():
            i = int(np.flatnonzero(gaps <= 0)[0])
            raise InputError(f"{src}: {TOPIC_IMU} @ {int(t[i + 1])}: stamps not increasing; fix the stamps")
        big = gaps > self.config.imu_gap_warn_s
        if big.any():
            self.stats.imu_gaps += int(big.sum())
            self.stats.imu_max_gap_s = max(self.stats.imu_max_gap_s, float(gaps.max()))
            i = int(np.argmax(gaps))
            if gaps[i] > self.config.imu_gap_max_s:
                raise InputError(
                    f"{src}: {TOPIC_IMU} @ {int(t[i])}: gap of {gaps[i]:.3f} s in the IMU data "
                    f"(> vio.imu_gap_max_s = {self.config.imu_gap_max_s}); split the recording"
                )
            _log.warning("%s: %d IMU gap(s) > %.3f s", src, int(big.sum()), self.config.imu_gap_warn_s)

    def take_frame_trace(self) -> dict | None:
        """The per-frame series recorded since `open(..., trace=True)` (features used / rejected, NIS, ZUPT
        stamps, triangulated points), handed over once to an observer (`viz.observers`)."""
        trace, self._frame_trace = self._frame_trace, None
        return trace

    def clone_positions(self) -> np.ndarray:
        """(n, 3) positions of the clones in the sliding window."""
        if not self.clones:
            return np.zeros((0, 3))
        return np.stack([self.state.value(clone_name(c)).p for c in self.clones])


__all__ = ["MsckfEstimator"]
