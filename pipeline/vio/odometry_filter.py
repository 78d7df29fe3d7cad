"""Pose-only error-state filter driven by an external odometry (``/odometry``, nav_msgs/Odometry).

For users whose poses come from another estimator (NTU-VIRAL SLICT lidar odometry, OpenVINS, a TUM file), the
odometry is turned into relative increments ``dT_k = T_{k-1}^-1 T_k`` that drive the filter state ``"pose"``, a
`Pose` with error ``[dtheta, dp]`` (``R = R_hat Exp(dtheta)``, ``p = p_hat + dp``). Without other updates the
estimate equals the odometry and its covariance grows like the odometry's drift; after a UWB update
(``on_range`` calling `ekf_update`) the following increments are applied to the corrected pose.

Increment noise (a random walk, so that the added variance does not depend on the odometry rate), per axis:

    var_theta += sigma_theta_per_sqrt_rad^2 |dtheta| + sigma_theta_per_sqrt_m^2 |dp| + sigma_theta_per_sqrt_s^2 dt
    var_p     += sigma_p_per_sqrt_m^2 |dp|         + sigma_p_per_sqrt_s^2 dt

i.e. after travelling L metres the position standard deviation is sigma_p_per_sqrt_m * sqrt(L) (plus the floor
over time). The noise enters in the frame of the increment (body frame at T_{k-1}) for rotation; the position
noise is isotropic, so its frame does not matter.

That ``drift`` model fits dead-reckoning odometry (VIO, wheel or lidar odometry without a map), whose error
grows without bound. A SLAM output expressed in the world frame of the calibration (NTU-VIRAL SLICT: the anchors
are published in its frame) has a *bounded* error: it stays near the message covariance (measured on SLICT:
docs/results/measurements.md), while the drift model lets the filter believe it grows to metres. The
``bounded`` model treats the odometry's error as a first-order Gauss-Markov process around the odometry,
with stationary covariance P_ss (the message covariance, else the initial sigmas) and correlation time tau:
world-frame errors decay as e_k+1 = phi e_k + w, phi = exp(-dt / tau), Q = (1 - phi^2) P_ss. An estimate
corrected by UWB updates relaxes back to the odometry with the same factor. ``auto`` takes the model from the
recording's calibration (``odometry.error_model``), else ``drift``.

Between odometry messages the pose at a range stamp is the SE(3) interpolation of the increment,
``T(t) = T_{k-1} Exp(s Log(T_{k-1}^-1 T_k))`` with ``s = (t - t_{k-1}) / (t_k - t_{k-1})``; the next increment
starts from the interpolated odometry pose, so interpolation never changes where the filter ends up.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from uwbcal.pipeline.core.errors import InputError
from uwbcal.pipeline.core.geometry import (
    compose,
    compose_jacobians,
    exp_so3_rodrigues,
    log_so3_one,
    quat_to_rot,
    relative,
    se3_interpolate,
)
from uwbcal.pipeline.core.noise import NOISE_KEYS, OdometryFilterConfig, increment_noise
from uwbcal.pipeline.core.state import Kind, Pose, State
from uwbcal.pipeline.vio.estimator import RangeHandler, RangeMeasurement, Span, TrajectoryRecord

if TYPE_CHECKING:
    from collections.abc import Iterator

    from uwbcal.convert.recording import OdometryData

OdometryFrame = tuple[int, np.ndarray, np.ndarray, np.ndarray]  # t_ns, R, p, ROS covariance (or None)

_log = logging.getLogger(__name__)

POSE = "pose"  # the navigation variable
# nav_msgs/Odometry pose covariance order (x, y, z, rx, ry, rz) -> ours (dtheta, dp)
_ROS_TO_OURS = np.r_[3:6, 0:3]


@dataclass
class OdometryStats:
    messages: int = 0
    duplicates: int = 0
    out_of_order: int = 0
    ranges: int = 0
    ranges_before_odometry: int = 0
    ranges_after_odometry: int = 0
    ranges_in_gaps: int = 0
    gaps: int = 0
    max_gap_s: float = 0.0

    def warnings(self) -> list[str]:
        w = []
        if self.duplicates:
            w.append(f"odometry: {self.duplicates} message(s) with a duplicate stamp skipped")
        if self.out_of_order:
            w.append(f"odometry: {self.out_of_order} message(s) out of stamp order (sorted by stamp)")
        if self.ranges_before_odometry or self.ranges_after_odometry:
            w.append(
                f"odometry: {self.ranges_before_odometry + self.ranges_after_odometry} range(s) outside the "
                "odometry time span skipped"
            )
        if self.gaps:
            w.append(
                f"odometry: {self.gaps} gap(s) longer than the warning limit (longest {self.max_gap_s:.2f} s); "
                f"{self.ranges_in_gaps} range(s) interpolated across them"
            )
        return w


# ---------------------------------------------------------------------------------------------------------------
# pure math (the SE(3) helpers live in core.geometry)
# ---------------------------------------------------------------------------------------------------------------
def bounded_step(
    R_ref: np.ndarray,
    p_ref: np.ndarray,
    R_x: np.ndarray,
    p_x: np.ndarray,
    R_odom: np.ndarray,
    p_odom: np.ndarray,
    phi: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Bounded (Gauss-Markov) model: the estimate's offset from the odometry at the reference stamp, expressed
    as world-frame errors, decays by ``phi``; returns (R_new, p_new, F) with F the error-state transition
    (``[dtheta_body, dp]``: dtheta' = phi dR^T dtheta, dp' = phi dp; no position-from-attitude coupling, the SLAM
    error does not accumulate)."""
    dR = R_ref.T @ R_odom
    theta = log_so3_one(R_ref.T @ R_x)  # body-frame offset of the estimate at the reference stamp
    theta_new = phi * (dR.T @ theta)
    R_new = R_odom @ exp_so3_rodrigues(theta_new)
    p_new = p_odom + phi * (p_x - p_ref)
    F = np.zeros((6, 6))
    F[0:3, 0:3] = phi * dR.T
    F[3:6, 3:6] = phi * np.eye(3)
    return R_new, p_new, F


def clean_odometry(
    t_ns: np.ndarray,
    p: np.ndarray,
    q_xyzw: np.ndarray,
    cov: np.ndarray,
    src: str,
    topic: str,
    stats: OdometryStats,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Check finiteness, sort by stamp, drop duplicate stamps (counted); returns (t, R, p, cov)."""
    t_ns = np.asarray(t_ns, np.int64)
    bad = ~(np.isfinite(p).all(axis=1) & np.isfinite(q_xyzw).all(axis=1))
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        raise InputError(
            f"{src}: {topic} @ {int(t_ns[i])}: NaN/inf in the odometry pose ({int(bad.sum())} message(s)); "
            "drop or repair these messages"
        )
    qn = np.linalg.norm(q_xyzw, axis=1)
    if (qn < 1e-6).any():
        i = int(np.flatnonzero(qn < 1e-6)[0])
        raise InputError(f"{src}: {topic} @ {int(t_ns[i])}: zero quaternion; repair the odometry orientation")
    stats.out_of_order += int(np.sum(np.diff(t_ns) < 0))
    order = np.argsort(t_ns, kind="stable")
    t_ns = t_ns[order]
    keep = np.ones(len(t_ns), bool)
    keep[1:] = np.diff(t_ns) > 0
    stats.duplicates += int((~keep).sum())
    idx = order[keep]
    cov = np.nan_to_num(np.asarray(cov, float)[idx])
    return t_ns[keep], quat_to_rot(q_xyzw[idx]), np.asarray(p, float)[idx], cov


def resolve_error_model(config: OdometryFilterConfig, calibration: dict | None) -> tuple[str, float]:
    """(error model, correlation time [s]): config, else the recording's calibration ``odometry`` section."""
    odo = ((calibration or {}).get("odometry") or {}) if isinstance(calibration, dict) else {}
    model = config.error_model
    if model == "auto":
        model = str(odo.get("error_model") or "drift")
        if model not in ("drift", "bounded"):
            raise InputError(f"calibration: odometry.error_model {model!r}; expected drift or bounded")
    tau = config.correlation_time_s or float(odo.get("correlation_time_s") or 10.0)
    return model, tau


def declared_noise(calibration: dict | None) -> dict[str, float]:
    """The drift sigmas the recording declares (calibration ``odometry.noise``, e.g. the simulator's odometry).
    Unknown keys are an error naming them."""
    noise = (
        (((calibration or {}).get("odometry") or {}).get("noise") or {})
        if isinstance(calibration, dict)
        else {}
    )
    bad = sorted(set(noise) - set(NOISE_KEYS))
    if bad:
        raise InputError(f"calibration: odometry.noise: unknown key(s) {bad}; known: {', '.join(NOISE_KEYS)}")
    return {k: float(noise[k]) for k in NOISE_KEYS if k in noise}


def fit_drift_noise(traj: dict[str, np.ndarray]) -> dict[str, float]:
    """Drift sigmas (`NOISE_KEYS`) of a random walk per metre travelled that reaches, at the end of ``traj``
    (``t_ns, p, q_xyzw, cov`` with 6x6 ``[dtheta, dp]`` covariances, e.g. an MSCKF history), the same per-axis
    position variance and world-yaw variance; the initial sigmas are those of the first pose. Rotation noise is
    isotropic in the body frame (the drift model has one sigma), position noise isotropic."""
    p = np.asarray(traj["p"], float)
    cov = np.asarray(traj["cov"], float)
    if len(p) < 2:
        raise InputError("fit_drift_noise: need at least two poses")
    length = max(float(np.linalg.norm(np.diff(p, axis=0), axis=1).sum()), 1e-9)
    var_p0 = float(np.trace(cov[0, 3:6, 3:6])) / 3.0
    var_p1 = float(np.trace(cov[-1, 3:6, 3:6])) / 3.0
    var_th0 = float(np.trace(cov[0, 0:3, 0:3])) / 3.0
    R1 = quat_to_rot(np.asarray(traj["q_xyzw"][-1], float))
    var_yaw1 = float((R1 @ cov[-1, 0:3, 0:3] @ R1.T)[2, 2])
    return {
        "sigma_p_per_sqrt_m": math.sqrt(max(var_p1 - var_p0, 0.0) / length),
        "sigma_theta_per_sqrt_rad": 0.0,
        "sigma_theta_per_sqrt_m": math.sqrt(max(var_yaw1 - var_th0, 0.0) / length),
        "sigma_p_per_sqrt_s": 0.0,
        "sigma_theta_per_sqrt_s": 0.0,
        "initial_sigma_p": math.sqrt(max(var_p0, 1e-12)),
        "initial_sigma_theta_deg": math.degrees(math.sqrt(max(var_th0, 1e-12))),
    }


# ---------------------------------------------------------------------------------------------------------------
# the estimator
# ---------------------------------------------------------------------------------------------------------------
class OdometryEstimator:
    """External-odometry pose source (Estimator protocol); its navigation variable ``"pose"`` is a `Pose`."""

    keeps_probes = False  # the anchors' initial covariance comes without pose cross-terms

    def __init__(
        self,
        config: OdometryFilterConfig | None = None,
        source: str = "recording",
        calibration: dict | None = None,
    ) -> None:
        self.config = config or OdometryFilterConfig()
        self.source = source
        self.error_model, self.correlation_time_s = resolve_error_model(self.config, calibration)
        self._P_ss: np.ndarray | None = None  # bounded model: stationary covariance (latest message)
        self.state = State(use_fej=False)
        self.t_ns = -1
        self.initialized = False
        self.stats = OdometryStats()
        self._history = TrajectoryRecord()
        # odometry pose at self.t_ns (raw or interpolated): increments are taken from here
        self._R_ref = np.eye(3)
        self._p_ref = np.zeros(3)

    @property
    def warnings(self) -> list[str]:
        return self.stats.warnings()

    def span_warnings(self, stage: str, start_ns: int | None, end_ns: int | None, t0_ns: int) -> list[str]:
        return []  # no update of its own to judge (the odometry is its only input)

    def history(self) -> TrajectoryRecord:
        return self._history

    @property
    def pose_correlation_s(self) -> float | None:
        """Bounded error model: the correlation time [s] of the pose errors (the UWB initialisation models the
        window's pose errors as Gauss-Markov with it); drift: None (random walk)."""
        return self.correlation_time_s if self.error_model == "bounded" else None

    def start_probes(self, period_s: float) -> None:
        """No probes (``keeps_probes`` is False)."""

    def add_probe(self) -> None:
        """No probes (``keeps_probes`` is False)."""

    def stop_probes(self, remove: bool = True) -> None:
        """No probes (``keeps_probes`` is False)."""

    @property
    def pose(self) -> Pose:
        return self.state.value(POSE)

    # -- filter steps ----------------------------------------------------------------------------------------------
    def _config_P0(self) -> np.ndarray:
        c = self.config
        return np.diag([np.radians(c.initial_sigma_theta_deg) ** 2] * 3 + [c.initial_sigma_p**2] * 3)

    def _stationary(self, cov_ros: np.ndarray | None) -> np.ndarray:
        """Bounded model: the message covariance (ours order) when it has one, else the initial sigmas."""
        if cov_ros is not None and np.all(np.diag(cov_ros) > 0):
            return np.asarray(cov_ros, float)[np.ix_(_ROS_TO_OURS, _ROS_TO_OURS)]
        return self._config_P0()

    def initialize(self, t_ns: int, R: np.ndarray, p: np.ndarray, cov_ros: np.ndarray | None = None) -> None:
        c = self.config
        if self.error_model == "bounded":
            P0 = self._P_ss = self._stationary(cov_ros)
        elif c.initial_from_message and cov_ros is not None and np.any(np.diag(cov_ros) > 0):
            P0 = np.asarray(cov_ros, float)[np.ix_(_ROS_TO_OURS, _ROS_TO_OURS)]
        else:
            P0 = self._config_P0()
        self.state.add(POSE, Pose(R, p), P0, kind=Kind.NAV)
        self._R_ref, self._p_ref = np.array(R, float), np.array(p, float)
        self.t_ns = int(t_ns)
        self.initialized = True

    def advance(
        self, t_ns: int, R_odom: np.ndarray, p_odom: np.ndarray, cov_ros: np.ndarray | None = None
    ) -> None:
        """Apply the odometry increment from the reference pose to ``(R_odom, p_odom)`` at ``t_ns``
        (``cov_ros``: that message's covariance, used by the bounded model)."""
        x = self.state.value(POSE)
        if self.error_model == "bounded":
            if cov_ros is not None:
                self._P_ss = self._stationary(cov_ros)
            P_ss = self._P_ss if self._P_ss is not None else self._config_P0()
            phi = math.exp(-max(t_ns - self.t_ns, 0) * 1e-9 / self.correlation_time_s)
            R_new, p_new, F = bounded_step(self._R_ref, self._p_ref, x.R, x.p, R_odom, p_odom, phi)
            self.state.propagate(POSE, F, (1.0 - phi * phi) * P_ss, symmetrize=True)
            self.state.set_value(POSE, Pose(R_new, p_new))
            self._R_ref, self._p_ref = np.array(R_odom, float), np.array(p_odom, float)
            self.t_ns = int(t_ns)
            return
        dR, dp = relative(self._R_ref, self._p_ref, R_odom, p_odom)
        F, G = compose_jacobians(x.R, dR, dp)
        Q = G @ increment_noise(self.config, dR, dp, (t_ns - self.t_ns) * 1e-9) @ G.T
        self.state.propagate(POSE, F, Q, symmetrize=True)
        R_new, p_new = compose(x.R, x.p, dR, dp)
        self.state.set_value(POSE, Pose(R_new, p_new))
        self._R_ref, self._p_ref = np.array(R_odom, float), np.array(p_odom, float)
        self.t_ns = int(t_ns)

    def _record(self) -> None:
        x = self.state.value(POSE)
        self._history.append(self.t_ns, x.R, x.p, self.state.cov(POSE))

    # -- fed by the driver (pipeline/run/driver.py) -------------------------------------------------------------------
    def feed_odometry(self, od: OdometryData, src: str, start: int, end: int) -> Iterator[OdometryFrame]:
        """The odometry from the state time on (no end: the message after ``end`` interpolates ranges just
        before it), cleaned; initialise on the first call (at the first message from ``start``). Returns the
        messages after the state time and before ``end``, the frames `process_frame` takes."""
        c = self.config
        stats = OdometryStats()
        t, Rs, ps, covs = clean_odometry(od.t_ns, od.p, od.q_xyzw, od.cov, src, c.topic, stats)
        for k in ("duplicates", "out_of_order"):
            setattr(self.stats, k, getattr(self.stats, k) + getattr(stats, k))
        if not self.initialized:
            i0 = int(np.searchsorted(t, start))
            if i0 >= len(t) or t[i0] >= end:
                raise InputError(f"{src}: {c.topic}: no odometry in [{start}, {end}); nothing to run on")
            self.initialize(int(t[i0]), Rs[i0], ps[i0], covs[i0])
            self.stats.messages += 1
            self._record()
        self._odom = (t, Rs, ps)
        i = int(np.searchsorted(t, self.t_ns, side="right"))
        i_end = int(np.searchsorted(t, end, side="left"))
        return ((int(t[k]), Rs[k], ps[k], covs[k]) for k in range(i, i_end))

    def process_frame(self, frame: OdometryFrame) -> None:
        """One odometry message: the increment from the reference pose, recorded."""
        t_ns, R, p, cov = frame
        if t_ns - self.t_ns > int(self.config.gap_warn_s * 1e9):
            self.stats.gaps += 1
            self.stats.max_gap_s = max(self.stats.max_gap_s, (t_ns - self.t_ns) * 1e-9)
        self.advance(t_ns, R, p, cov)
        self.stats.messages += 1
        self._record()

    def propagate_to(self, t_ns: int) -> bool:
        """The odometry interpolated to ``t_ns`` (SE(3), between the reference and the next message) applied as
        an increment; False when ``t_ns`` is outside the odometry (after its last message)."""
        if t_ns <= self.t_ns:
            return True
        t, Rs, ps = self._odom
        k = int(np.searchsorted(t, t_ns, side="left"))  # next odometry at or after t_ns
        if k >= len(t):
            return False
        if t[k] - self.t_ns > int(self.config.gap_warn_s * 1e9):
            self.stats.ranges_in_gaps += 1
        s = (t_ns - self.t_ns) / float(t[k] - self.t_ns)
        R_i, p_i = se3_interpolate(self._R_ref, self._p_ref, Rs[k], ps[k], s)
        self.advance(t_ns, R_i, p_i)
        return True

    def process_range(self, m: RangeMeasurement, on_range: RangeHandler | None) -> None:
        """A range inside the odometry's span: the pose at its stamp is recorded, then ``on_range`` updates."""
        self.stats.ranges += 1
        if m.t_ns < self.t_ns:
            self.stats.ranges_before_odometry += 1
            return
        if not self.propagate_to(m.t_ns):
            self.stats.ranges_after_odometry += 1
            return
        self._record()
        if on_range is not None:
            on_range(self, m)

    def process_ranges(self, batch: list[RangeMeasurement], on_range: RangeHandler) -> None:
        """Ranges of one stamp for an epoch handler: the pose at the stamp recorded once, one epoch update."""
        self.stats.ranges += len(batch)
        t_ns = batch[0].t_ns
        if t_ns < self.t_ns:
            self.stats.ranges_before_odometry += len(batch)
            return
        gaps = self.stats.ranges_in_gaps
        if not self.propagate_to(t_ns):
            self.stats.ranges_after_odometry += len(batch)
            return
        self.stats.ranges_in_gaps += (self.stats.ranges_in_gaps - gaps) * (len(batch) - 1)
        self._record()
        on_range.epoch(self, batch)

    def close(self, span: Span) -> None:
        for w in self.stats.warnings():
            _log.warning("%s: %s", span.source, w)
        self._odom = None
