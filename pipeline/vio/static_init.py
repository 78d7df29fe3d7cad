"""Static IMU initialiser for real data: the recording must start with the sensor at rest.

The still period runs from the first sample to the start of the first ``window_s`` window whose spread of the
accelerometer norm or of the gyroscope is too large (rotor vibration on a MAV standing on the ground passes, a
hand-held or flying start does not). Over that prefix:

- gravity direction: the mean specific force ``f`` points up in the body frame, so roll and pitch follow from
  ``R^T e_z = f / |f|``; yaw is unobservable and set to 0 (the world frame's heading is the body's at rest);
- gyroscope bias = mean gyroscope (the earth rate, 7e-5 rad/s, is below the noise of MEMS gyros);
- accelerometer bias = 0, or with ``accel_bias = "gravity_residual"`` the part along gravity,
  ``(|f| - g) f/|f|`` (the only accelerometer bias component a static period reveals);
- the images agree (OpenVINS' ``init_max_disparity``): with feature tracks, the still period also ends before
  the first frame whose tracks moved more than ``max_disparity_px`` since the first frame (a hand-held rig can
  start moving while the IMU still passes as quiet);
- p = 0, v = 0; covariance from the configured sigmas, with the roll/pitch sigma not below what the
  accelerometer noise over the window allows.

The result is the initial `ImuState` and 15x15 covariance for the MSCKF (``initial=`` of `MsckfEstimator`).
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from uwbcal.pipeline.core.errors import InputError
from uwbcal.pipeline.core.geometry import exp_so3
from uwbcal.pipeline.core.state import ImuState
from uwbcal.pipeline.core.topics import TOPIC_FEATURES

if TYPE_CHECKING:
    from uwbcal.convert.recording import RecordingReader

GRAVITY = 9.81


class StaticInitConfig(BaseModel):
    model_config = ConfigDict(extra="forbid")

    window_s: float = Field(1.0, gt=0, description="length of the windows tested for stillness")
    min_still_s: float = Field(1.0, gt=0, description="shortest still prefix accepted")
    max_still_s: float | None = Field(None, gt=0, description="use at most this much of the still prefix")
    acc_norm_std_max: float = Field(
        0.5, gt=0, description="max std of |acc| in a window [m/s^2] (MAV rotor vibration ~0.3)"
    )
    gyro_std_max: float = Field(
        0.15, gt=0, description="max norm of the per-axis gyro std in a window [rad/s]"
    )
    gravity: float = Field(GRAVITY, gt=0)
    gravity_tolerance: float = Field(0.5, gt=0, description="max | |mean acc| - g | [m/s^2]")
    accel_bias: Literal["zero", "gravity_residual"] = "zero"
    sigma_roll_pitch_deg: float = Field(1.0, gt=0)
    sigma_yaw_deg: float = Field(0.1, gt=0, description="yaw is a gauge: small, it defines the world heading")
    sigma_p: float = Field(1e-3, gt=0)
    sigma_v: float = Field(0.02, gt=0)
    sigma_bg_min: float = Field(1e-3, gt=0, description="floor of the gyro bias sigma [rad/s]")
    sigma_ba: float = Field(0.1, gt=0, description="accelerometer bias sigma [m/s^2]")
    max_disparity_px: float | None = Field(
        5.0,
        gt=0,
        description="the images must agree: the still period ends before the first frame whose tracks moved more "
        "than this (median, since the first frame) [px]: well above the noise (1 px per axis in two frames gives a "
        "median of 1.7 px) (OpenVINS' init_max_disparity; None: IMU only)",
    )
    min_disparity_tracks: int = Field(
        10, ge=1, description="tracks a frame needs in common with the first one"
    )


@dataclass
class StaticInitResult:
    state: ImuState
    P: np.ndarray  # 15x15, ordering [dtheta, dp, dv, dbg, dba]
    t_start_ns: int  # still period [t_start_ns, t_end_ns]; the state holds anywhere in it
    t_end_ns: int
    samples: int
    acc_norm_mean: float
    acc_norm_std: float
    gyro_std: float
    image_check: str = ""  # what the images said about the still period ("" when not checked)

    @property
    def t_ns(self) -> int:
        """Where a filter should start: the end of the still period."""
        return self.t_end_ns

    def astuple(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        s = self.state
        return s.R, s.p, s.v, s.bg, s.ba

    def summary(self) -> dict:
        """JSON-ready record of the initialisation (the run directory's ``static_init.json``)."""
        s = self.state
        return {
            "t_start_ns": self.t_start_ns,
            "t_end_ns": self.t_end_ns,
            "samples": self.samples,
            "acc_norm_mean": self.acc_norm_mean,
            "acc_norm_std": self.acc_norm_std,
            "gyro_std": self.gyro_std,
            "roll_pitch_deg": np.degrees(roll_pitch(s.R)).tolist(),
            "R": s.R.tolist(),
            "bg": s.bg.tolist(),
            "ba": s.ba.tolist(),
            "sigma": np.sqrt(np.diag(self.P)).tolist(),
            "world_frame": "gravity-aligned, yaw 0 and origin at the start (not the ground truth's frame)",
            "image_check": self.image_check,
        }

    def __str__(self) -> str:
        return (
            f"still for {(self.t_end_ns - self.t_start_ns) * 1e-9:.2f} s ({self.samples} samples): "
            f"|acc| {self.acc_norm_mean:.3f} ± {self.acc_norm_std:.3f} m/s², gyro std {self.gyro_std:.4f} rad/s, "
            f"roll/pitch {np.degrees(roll_pitch(self.state.R)).round(2).tolist()} deg, "
            f"bg {self.state.bg.round(4).tolist()} rad/s"
            + (f"; {self.image_check}" if self.image_check else "")
        )


def gravity_aligned_rotation(f_body: np.ndarray) -> np.ndarray:
    """world_from_body with yaw 0 such that ``R @ f/|f| = e_z`` (specific force at rest points up)."""
    f = np.asarray(f_body, float)
    f = f / np.linalg.norm(f)
    roll = np.arctan2(f[1], f[2])
    pitch = np.arctan2(-f[0], np.hypot(f[1], f[2]))
    return exp_so3(np.array([0.0, pitch, 0.0])) @ exp_so3(np.array([roll, 0.0, 0.0]))


def roll_pitch(R: np.ndarray) -> np.ndarray:
    """(roll, pitch) of a world_from_body rotation R = Rz(yaw) Ry(pitch) Rx(roll)."""
    return np.array([np.arctan2(R[2, 1], R[2, 2]), np.arcsin(np.clip(-R[2, 0], -1.0, 1.0))])


def still_prefix(t_ns: np.ndarray, gyro: np.ndarray, acc: np.ndarray, config: StaticInitConfig) -> int:
    """Number of leading samples in which every ``window_s`` window is still (0 when the first is not)."""
    t = (np.asarray(t_ns, np.int64) - int(t_ns[0])) * 1e-9
    n = len(t)
    an = np.linalg.norm(acc, axis=1)
    # windows [t_i, t_i + window) via cumulative sums: mean and variance of |acc| and of each gyro axis
    j = np.searchsorted(t, t + config.window_s, side="left")
    full = t + config.window_s <= t[-1] + 1e-9
    cols = np.column_stack([an, gyro])
    c1 = np.vstack([np.zeros((1, 4)), np.cumsum(cols, axis=0)])
    c2 = np.vstack([np.zeros((1, 4)), np.cumsum(cols**2, axis=0)])
    i = np.arange(n)
    cnt = np.maximum(j - i, 1)[:, None]
    mean = (c1[j] - c1[i]) / cnt
    var = np.maximum((c2[j] - c2[i]) / cnt - mean**2, 0.0)
    still = (np.sqrt(var[:, 0]) <= config.acc_norm_std_max) & (
        np.sqrt(var[:, 1:].sum(axis=1)) <= config.gyro_std_max
    )
    still &= full
    if not still[0]:
        return 0
    # first window that is not still (windows past the data end never are); the still period ends where it
    # starts: the motion that spoils it may lie anywhere inside it, so later samples are not trusted
    k = int(np.argmin(still))
    if k == int(np.flatnonzero(full)[-1]) + 1:  # still to the end of the data
        return int(j[k - 1])
    return k


@dataclass(frozen=True)
class ImageStill:
    """Until when the feature tracks say the camera rests: ``t_end_ns`` (None: moving from the first frame)."""

    t_end_ns: int | None
    disparity_px: float  # median track motion since the first frame at the frame that ended it (or the last)
    frames: int
    moved: bool

    def __str__(self) -> str:
        if not self.moved:
            return f"images still over {self.frames} frame(s) (disparity {self.disparity_px:.2f} px)"
        return f"images move after frame {self.frames} (disparity {self.disparity_px:.2f} px)"


def image_still(frames: Iterable[tuple[int, np.ndarray, np.ndarray]], config: StaticInitConfig) -> ImageStill:
    """The rest the images allow: frames ``(t_ns, ids, uv)`` until the median motion of the tracks in common with
    the first frame exceeds ``max_disparity_px`` (too few tracks in common count as motion)."""
    first: dict[int, np.ndarray] = {}
    last, disp, n = None, 0.0, 0
    for t, ids, uv in frames:
        if n == 0:
            first = dict(zip(ids.tolist(), np.asarray(uv, float), strict=True))
            last, n = int(t), 1
            continue
        keep = [i for i, k in enumerate(ids.tolist()) if k in first]
        if len(keep) < config.min_disparity_tracks:
            return ImageStill(last, float("inf"), n, True)
        ref = np.array([first[int(ids[i])] for i in keep])
        disp = float(np.median(np.linalg.norm(np.asarray(uv, float)[keep] - ref, axis=1)))
        if disp > float(config.max_disparity_px or np.inf):
            return ImageStill(last, disp, n, True)
        last, n = int(t), n + 1
    return ImageStill(last, disp, n, False)


def static_initialize(
    t_ns: np.ndarray,
    gyro: np.ndarray,
    acc: np.ndarray,
    config: StaticInitConfig | None = None,
    source: str = "imu",
    images: ImageStill | None = None,
) -> StaticInitResult:
    """Initial IMU state and covariance from a still period at the start of ``(t_ns, gyro, acc)`` (ended earlier
    where ``images`` say the camera moved)."""
    c = config or StaticInitConfig()
    t_ns = np.asarray(t_ns, np.int64)
    gyro = np.asarray(gyro, float)
    acc = np.asarray(acc, float)
    hint = (
        "use ground-truth initialisation (vio.init_from_groundtruth) or a recording that starts with the "
        "sensor at rest"
    )
    if len(t_ns) < 2 or (t_ns[-1] - t_ns[0]) * 1e-9 < c.window_s:
        raise InputError(
            f"{source}: {len(t_ns)} IMU sample(s) over less than {c.window_s} s; too short for a static "
            f"initialisation; {hint}"
        )
    bad = ~(np.isfinite(gyro).all(1) & np.isfinite(acc).all(1))
    if bad.any():
        raise InputError(
            f"{source}: IMU @ {int(t_ns[np.flatnonzero(bad)[0]])}: NaN/inf sample; repair the IMU data"
        )
    n = still_prefix(t_ns, gyro, acc, c)
    why = ""
    if images is not None and images.moved:
        cut = 0 if images.t_end_ns is None else int(np.searchsorted(t_ns, images.t_end_ns, side="right"))
        if cut < n:
            n, why = cut, f"; the {images}"
    still_s = (t_ns[n - 1] - t_ns[0]) * 1e-9 if n > 0 else 0.0
    if n == 0 or still_s < c.min_still_s - 1e-9:
        m = np.searchsorted(t_ns, t_ns[0] + int(c.window_s * 1e9))
        an = np.linalg.norm(acc[:m], axis=1)
        raise InputError(
            f"{source}: the IMU is not still at the start (first {c.window_s:g} s: |acc| std "
            f"{an.std():.3f} m/s² (max {c.acc_norm_std_max:g}), gyro std {np.linalg.norm(gyro[:m].std(0)):.4f} "
            f"rad/s (max {c.gyro_std_max:g}); still for {still_s:.2f} s < {c.min_still_s:g} s{why}); {hint} "
            "(convert bag --start trims a moving start)"
        )
    if c.max_still_s is not None:
        n = min(n, int(np.searchsorted(t_ns, t_ns[0] + int(c.max_still_s * 1e9), side="right")))
    f = acc[:n].mean(axis=0)
    fn = float(np.linalg.norm(f))
    if abs(fn - c.gravity) > c.gravity_tolerance:
        raise InputError(
            f"{source}: mean specific force over the still period is {fn:.3f} m/s², not g = {c.gravity:g} "
            f"(± {c.gravity_tolerance:g}); check the accelerometer units/scale or {hint}"
        )
    R = gravity_aligned_rotation(f)
    bg = gyro[:n].mean(axis=0)
    ba = (fn - c.gravity) * f / fn if c.accel_bias == "gravity_residual" else np.zeros(3)
    an = np.linalg.norm(acc[:n], axis=1)
    gstd = gyro[:n].std(axis=0)
    # roll/pitch: not better than the accelerometer noise of the mean allows
    sig_rp = max(np.radians(c.sigma_roll_pitch_deg), float(an.std()) / np.sqrt(n) / c.gravity)
    # body-frame error dtheta = R^T dtheta_world; world-frame sigmas (roll/pitch about x,y; yaw about z)
    P_th = R.T @ np.diag([sig_rp**2, sig_rp**2, np.radians(c.sigma_yaw_deg) ** 2]) @ R
    P = np.zeros((15, 15))
    P[0:3, 0:3] = P_th
    P[3:6, 3:6] = np.eye(3) * c.sigma_p**2
    P[6:9, 6:9] = np.eye(3) * c.sigma_v**2
    P[9:12, 9:12] = np.diag(np.maximum(gstd / np.sqrt(n), c.sigma_bg_min) ** 2)
    P[12:15, 12:15] = np.eye(3) * c.sigma_ba**2
    state = ImuState(R, np.zeros(3), np.zeros(3), bg, ba)
    return StaticInitResult(
        state,
        P,
        int(t_ns[0]),
        int(t_ns[n - 1]),
        n,
        float(an.mean()),
        float(an.std()),
        float(np.linalg.norm(gstd)),
        "" if images is None else str(images),
    )


def static_init_from_recording(
    reader: RecordingReader,
    config: StaticInitConfig | None = None,
    start_ns: int | None = None,
    topic: str = "/imu",
) -> StaticInitResult:
    """Static initialisation from the recording's IMU, starting at ``start_ns`` (default: the first sample); with
    feature tracks in the recording, the images must rest too (`image_still`)."""
    c = config or StaticInitConfig()
    src = str(getattr(reader, "path", "recording"))
    topics = reader.topics()
    if topic not in topics:
        raise InputError(f"{src}: no '{topic}' topic; the static initialiser needs IMU data")
    t0 = start_ns if start_ns is not None else topics[topic].start_ns
    horizon = max(c.max_still_s or 0.0, 30.0 * c.window_s, c.min_still_s + c.window_s)
    imu = reader.read_imu(topic, t0, t0 + int(horizon * 1e9))
    images = None
    if c.max_disparity_px is not None and TOPIC_FEATURES in topics:
        images = image_still(reader.iter_features(TOPIC_FEATURES, t0, t0 + int(horizon * 1e9)), c)
    return static_initialize(imu.t_ns, imu.gyro, imu.acc, c, f"{src}: {topic}", images)


__all__ = [
    "ImageStill",
    "StaticInitConfig",
    "StaticInitResult",
    "gravity_aligned_rotation",
    "image_still",
    "roll_pitch",
    "static_init_from_recording",
    "static_initialize",
    "still_prefix",
]
