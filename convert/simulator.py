"""The built-in simulator: IMU, camera feature tracks, UWB ranges and ground truth from a smooth trajectory.

Generation is pure (`simulate` returns arrays in a `SimData`); `simulate_to_file` writes them as a recording.
Every sensor draws from its own random sub-stream of the seed, so changing one sensor's settings leaves the
others' samples unchanged.

Models (world z up, gravity (0, 0, -g), R = world_from_IMU):
- IMU: gyro = w_body + b_g + n_g, acc = R^T (a_world - g) + b_a + n_a; white noise sigma_c / sqrt(dt), biases
  random walks with per-sample steps sigma_rw sqrt(dt).
- Camera cam0 (EuRoC intrinsics, radtan, T_imu_cam): landmarks on the faces of a box room around the flight
  volume; raw (distorted) pixels + Gaussian noise of the visible ones, track id = landmark id.
- UWB: d = beta (|p + R p_T - p_a| + n) + gamma + o_{a,t}, n ~ N(0, sigma^2), one link per (anchor a, tag t)
  (``tags``: several tags with their lever arms; ``link_gamma_offset``: per-link offsets o_{a,t}, default 0);
  optional NLOS (+Exp(mean) bias, at ``nlos_rate`` or per link ``link_nlos_rate``), dropouts, maximum range and
  per-anchor visibility windows. Stamps staggered across links. Two real-hardware effects, off by default:
  ``antenna_pattern``, a direction-dependent bias b = b0 + b1 cos(az - phi) + b2 sin(el) per anchor added to its
  ranges (az, el: the direction from the anchor to the tag in the world frame), and ``range_latency_s``, ranges
  stamped that long after they were measured (the poses stay on time; ranges stamped outside the recording are
  dropped).
"""

from __future__ import annotations

import zlib
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from uwbcal.convert.euroc import EUROC_CAMERAS
from uwbcal.convert.recording import (
    META_CALIBRATION,
    META_SOURCE,
    META_TRUTH,
    TOPIC_GT_IMU_BIAS,
    TOPIC_GT_POSE,
    TOPIC_ODOM,
    RecordingWriter,
)
from uwbcal.convert.sources import converter_name, sha256_file
from uwbcal.convert.trajectory import SplineTrajectory, load_trajectory
from uwbcal.pipeline.core.errors import InputError
from uwbcal.pipeline.core.geometry import compose, exp_so3, relative, rot_to_quat
from uwbcal.pipeline.core.noise import NOISE_KEYS, OdometryFilterConfig, increment_noise
from uwbcal.pipeline.core.progress import progress

NS = 1_000_000_000
PROBE_DENSITY = 4.0  # landmarks / m^2 for probing how many are visible
MAX_DENSITY = 40.0
MAX_LATENCY_S = 5.0  # a range stamp's latency beyond this is a broken clock, not a latency


def _bad(name: str, value, what: str) -> InputError:
    return InputError(f"simulate: {name}={value!r}: {what}; fix the simulation settings")


@dataclass
class SimConfig:
    trajectory: str | Path | None = None  # None = built-in default; EuRoC name or ground-truth file
    duration: float | None = None  # seconds from the trajectory start; None = all of it
    seed: int = 0
    n_anchors: int = 4
    anchors: Sequence[Sequence[float]] | None = None  # explicit anchor positions [n,3] (overrides n_anchors)
    imu_rate: float = 200.0
    cam_rate: float = 20.0
    uwb_rate: float = 10.0  # per anchor
    gyro_noise_density: float = 1.6968e-4  # rad/s/sqrt(Hz)
    gyro_random_walk: float = 1.9393e-5  # rad/s^2/sqrt(Hz)
    acc_noise_density: float = 2.0e-3  # m/s^2/sqrt(Hz)
    acc_random_walk: float = 3.0e-3  # m/s^3/sqrt(Hz)
    gyro_bias_init: Sequence[float] = (0.0, 0.0, 0.0)
    acc_bias_init: Sequence[float] = (0.0, 0.0, 0.0)
    gravity: float = 9.81
    camera: bool = True
    pixel_sigma: float = 1.0
    landmark_density: float | None = None  # landmarks per m^2 of room surface; None: automatic (min_features)
    min_features: int = (
        100  # automatic density: this many visible in 90 % of the frames (density <= 40 / m^2)
    )
    max_features: int | None = 200  # per frame cap: the visible landmarks with the lowest (fixed) random rank
    room_margin: float = (
        3.0  # walls this far outside the trajectory's bounding box (floor/ceiling: 2/3 of it)
    )
    max_feature_range: float = 20.0
    sigma_range: float = 0.1
    beta: float | Sequence[float] = 0.9
    gamma: float | Sequence[float] = -0.3
    nlos_rate: float = 0.0
    nlos_bias_mean: float = 1.0  # mean of the positive exponential NLOS bias [m]
    dropout_rate: float = 0.0
    max_range: float | None = None
    tag_id: int = 1
    tag_lever_arm: Sequence[float] = (0.05, 0.0, 0.1)  # p_T in the IMU frame
    # several tags (ids tag_id, tag_id + 1, ...; antenna 0 each) with their lever arms; None: one tag_lever_arm
    tags: Sequence[Sequence[float]] | None = None
    link_gamma_offset: Sequence[Sequence[float]] | None = None  # [n_anchors, n_tags] added to gamma per link
    link_nlos_rate: Sequence[Sequence[float]] | None = None  # [n_anchors, n_tags]; replaces nlos_rate
    # anchor index -> [(start_s, end_s), ...] from the start: the only times it can be ranged (absent: always)
    visibility: dict[int, Sequence[Sequence[float]]] | None = None
    # per anchor [b0, b1, phi_deg, b2] ([m], [m], [deg], [m]): the direction-dependent antenna bias
    # b0 + b1 cos(az - phi) + b2 sin(el) added to each range, az / el the azimuth / elevation of the tag seen from
    # the anchor (world frame). None: no pattern
    antenna_pattern: Sequence[Sequence[float]] | None = None
    # [s] the ranges' stamps lag their measurement by this (a driver's filter, a radio link): a range measured at
    # t is stamped t + range_latency_s, the poses are not (negative: stamped early). 0: stamped when measured
    range_latency_s: float = 0.0
    # the calibration record declares the paper's offset and scale priors (gamma ~ N(0, 1), beta ~ N(1, 0.2^2)), as
    # the paper's simulations do; False: it declares none, as a converted real recording does
    declared_priors: bool = True
    scenario: str | None = None  # the `convert.scenarios` name this config came from (recorded in the truth)
    knot_dt: float = 0.1  # B-spline knot spacing when fitting a ground-truth file
    # external odometry (/odometry) drifting exactly as the odometry filter's drift model says (its default
    # sigmas times odometry_noise_scale): a pose source whose noise the filter models correctly. None: none
    odometry_rate: float | None = None
    odometry_noise_scale: float = 1.0
    # "bounded": poses with a bounded, time-correlated error instead (SLAM with a map, GNSS/INS: the odometry
    # filter's bounded model): a Gauss-Markov error of stationary sigmas odometry_sigma_p [m] and
    # odometry_sigma_theta_deg per axis and correlation time odometry_correlation_s, declared in the calibration
    odometry_error: str = "drift"
    odometry_sigma_p: float = 0.05
    odometry_sigma_theta_deg: float = 0.5
    odometry_correlation_s: float = 5.0

    def __post_init__(self) -> None:
        self._check_numbers()
        self._check_anchors_and_tags()

    def _check_numbers(self) -> None:
        """Rates, noises, fractions and counts in their ranges."""
        if self.duration is not None and not (np.isfinite(self.duration) and self.duration > 0):
            raise _bad("duration", self.duration, "must be a positive number of seconds")
        for name in ("imu_rate", "cam_rate", "uwb_rate", "knot_dt", "gravity", "max_feature_range"):
            v = getattr(self, name)
            if not (np.isfinite(v) and v > 0):
                raise _bad(name, v, "must be positive")
        for name in (
            "gyro_noise_density",
            "gyro_random_walk",
            "acc_noise_density",
            "acc_random_walk",
            "pixel_sigma",
            "room_margin",
            "sigma_range",
            "nlos_bias_mean",
        ):
            v = getattr(self, name)
            if not (np.isfinite(v) and v >= 0):
                raise _bad(name, v, "must be >= 0")
        if self.odometry_rate is not None and not (
            np.isfinite(self.odometry_rate) and self.odometry_rate > 0
        ):
            raise _bad("odometry_rate", self.odometry_rate, "must be positive (or None for no odometry)")
        if not (np.isfinite(self.odometry_noise_scale) and self.odometry_noise_scale >= 0):
            raise _bad("odometry_noise_scale", self.odometry_noise_scale, "must be >= 0")
        if self.odometry_error not in ("drift", "bounded"):
            raise _bad("odometry_error", self.odometry_error, "expected drift or bounded")
        for name in ("odometry_sigma_p", "odometry_sigma_theta_deg", "odometry_correlation_s"):
            v = getattr(self, name)
            if not (np.isfinite(v) and v > 0):
                raise _bad(name, v, "must be positive")
        for name in ("nlos_rate", "dropout_rate"):
            v = getattr(self, name)
            if not (0.0 <= v <= 1.0):
                raise _bad(name, v, "must be a fraction in [0, 1]")
        if self.landmark_density is not None and not (
            np.isfinite(self.landmark_density) and self.landmark_density > 0
        ):
            raise _bad("landmark_density", self.landmark_density, "must be positive (or None for automatic)")
        if self.min_features < 1:
            raise _bad("min_features", self.min_features, "must be at least 1")
        if self.max_features is not None and self.max_features < 1:
            raise _bad("max_features", self.max_features, "must be at least 1 (or None for no cap)")
        if self.max_range is not None and not self.max_range > 0:
            raise _bad("max_range", self.max_range, "must be positive (or None for no limit)")
        if not (np.isfinite(self.range_latency_s) and abs(self.range_latency_s) <= MAX_LATENCY_S):
            raise _bad(
                "range_latency_s",
                self.range_latency_s,
                f"must be a number of seconds within +-{MAX_LATENCY_S:g}",
            )

    def _check_anchors_and_tags(self) -> None:
        """Anchors (their count from ``anchors`` when given), their beta/gamma, the tags and the per-link settings
        in shape."""
        if self.anchors is not None:
            a = np.asarray(self.anchors, float)
            if a.ndim != 2 or a.shape[1] != 3 or len(a) == 0 or not np.all(np.isfinite(a)):
                raise _bad("anchors", self.anchors, "must be a list of [x, y, z] positions")
            self.n_anchors = len(a)
        if self.n_anchors < 1:
            raise _bad("n_anchors", self.n_anchors, "must be at least 1")
        for name in ("beta", "gamma"):
            v = np.atleast_1d(np.asarray(getattr(self, name), float))
            if len(v) not in (1, self.n_anchors) or not np.all(np.isfinite(v)):
                raise _bad(
                    name, getattr(self, name), f"must be one number or one per anchor ({self.n_anchors})"
                )
        for name in ("gyro_bias_init", "acc_bias_init", "tag_lever_arm"):
            v = np.asarray(getattr(self, name), float)
            if v.shape != (3,) or not np.all(np.isfinite(v)):
                raise _bad(name, getattr(self, name), "must be 3 numbers")
        if self.tags is not None:
            v = np.asarray(self.tags, float)
            if v.ndim != 2 or v.shape[1] != 3 or len(v) == 0 or not np.all(np.isfinite(v)):
                raise _bad("tags", self.tags, "must be a list of [x, y, z] lever arms")
        shape = (self.n_anchors, len(self.lever_arms()))
        for name, lo, hi in (("link_gamma_offset", -np.inf, np.inf), ("link_nlos_rate", 0.0, 1.0)):
            v = getattr(self, name)
            if v is not None:
                a = np.asarray(v, float)
                if a.shape != shape or not np.all((a >= lo) & (a <= hi)):
                    raise _bad(
                        name, v, f"must be {shape[0]} x {shape[1]} (anchors x tags) values in [{lo}, {hi}]"
                    )
        if self.antenna_pattern is not None:
            a = np.asarray(self.antenna_pattern, float)
            if a.shape != (self.n_anchors, 4) or not np.all(np.isfinite(a)):
                raise _bad(
                    "antenna_pattern",
                    self.antenna_pattern,
                    f"must be {self.n_anchors} x 4 (per anchor [b0, b1, phi_deg, b2]) finite values",
                )
        for a, wins in (self.visibility or {}).items():
            w = np.asarray(wins, float).reshape(-1, 2) if len(wins) else np.zeros((0, 2))
            if not 0 <= int(a) < self.n_anchors or not np.all(np.isfinite(w)) or np.any(w[:, 1] < w[:, 0]):
                raise _bad("visibility", {a: wins}, "must map an anchor index to [(start_s, end_s), ...]")

    def lever_arms(self) -> np.ndarray:
        """[n_tags, 3] lever arms; tag i has id ``tag_id + i``."""
        return np.asarray(self.tags if self.tags is not None else [self.tag_lever_arm], float).reshape(-1, 3)

    def per_anchor(self, name: str) -> np.ndarray:
        return np.broadcast_to(
            np.atleast_1d(np.asarray(getattr(self, name), float)), (self.n_anchors,)
        ).copy()


# ---------------------------------------------------------------------------------------------------------------
# results
# ---------------------------------------------------------------------------------------------------------------
@dataclass
class ImuSim:
    t_ns: np.ndarray  # [N] int64
    gyro: np.ndarray  # [N,3] rad/s
    acc: np.ndarray  # [N,3] m/s^2
    bg: np.ndarray  # [N,3] true gyro bias
    ba: np.ndarray  # [N,3] true accelerometer bias


@dataclass
class FeatureSim:
    t_ns: np.ndarray  # [F] frame stamps
    offsets: np.ndarray  # [F+1]: frame f holds rows offsets[f]:offsets[f+1]
    ids: np.ndarray  # [M] landmark (= track) ids
    uv: np.ndarray  # [M,2] raw distorted pixels (noisy)

    def frame(self, f: int) -> tuple[int, np.ndarray, np.ndarray]:
        a, b = self.offsets[f], self.offsets[f + 1]
        return int(self.t_ns[f]), self.ids[a:b], self.uv[a:b]

    @property
    def counts(self) -> np.ndarray:
        return np.diff(self.offsets)


@dataclass
class RangeSim:
    t_ns: np.ndarray  # [N] int64, time ordered: the stamps (measured at t_ns - range_latency_s)
    anchor: np.ndarray  # [N] int64
    distance: np.ndarray  # [N] measured
    true_distance: np.ndarray  # [N] |p + R p_T - p_a| when measured
    nlos: np.ndarray  # [N] bool: an NLOS bias was added
    candidates: int = 0  # stamps before dropouts / range limit
    tag: np.ndarray | None = None  # [N] int64 tag id (None: all cfg.tag_id)


@dataclass
class GroundTruthSim:
    t_ns: np.ndarray
    p: np.ndarray
    q_xyzw: np.ndarray
    v: np.ndarray


@dataclass
class OdometrySim:
    t_ns: np.ndarray
    p: np.ndarray  # [N,3] odometry (drifting) position
    q_xyzw: np.ndarray  # [N,4]


@dataclass
class SimData:
    config: SimConfig
    trajectory: SplineTrajectory
    imu: ImuSim
    features: FeatureSim | None
    ranges: RangeSim
    groundtruth: GroundTruthSim
    anchors: np.ndarray  # [n,3]
    beta: np.ndarray  # [n]
    gamma: np.ndarray  # [n]
    landmarks: np.ndarray  # [L,3]
    odometry: OdometrySim | None = None
    metadata: dict[str, dict] = field(default_factory=dict)  # name -> JSON record
    groundtruth_bias: ImuSim | None = (
        None  # written as /groundtruth/imu_bias (hybrid recordings: real biases)
    )

    @classmethod
    def from_world(cls, world: WorldSim, **streams) -> SimData:
        """The world's landmarks, anchors and measurements beside the given streams (config, trajectory, imu,
        groundtruth, ...): the one assembly `simulate` and the hybrid recordings share."""
        return cls(
            features=world.features,
            ranges=world.ranges,
            anchors=world.anchors,
            beta=world.beta,
            gamma=world.gamma,
            landmarks=world.landmarks,
            **streams,
        )


# ---------------------------------------------------------------------------------------------------------------
# pure generation
# ---------------------------------------------------------------------------------------------------------------
def stream(seed: int, name: str) -> np.random.Generator:
    """An independent random stream per (seed, sensor name)."""
    return np.random.default_rng(np.random.SeedSequence(int(seed), spawn_key=(zlib.crc32(name.encode()),)))


def sample_times(t0_ns: int, duration: float, rate: float, offset_ns: int = 0) -> np.ndarray:
    """Stamps t0 + offset + k * period (integer ns) inside [t0, t0 + duration]."""
    period = round(NS / rate)
    n = int(np.floor((duration * NS - offset_ns) / period + 1e-9)) + 1
    return t0_ns + offset_ns + period * np.arange(max(n, 0), dtype=np.int64)


def rel_seconds(traj: SplineTrajectory, t_ns: np.ndarray) -> np.ndarray:
    return (np.asarray(t_ns, np.int64) - traj.t0_ns) * 1e-9


def simulate_imu(
    traj: SplineTrajectory, t_ns: np.ndarray, cfg: SimConfig, rng: np.random.Generator
) -> ImuSim:
    s = traj.evaluate(rel_seconds(traj, t_ns))
    n = len(t_ns)
    dt = 1.0 / cfg.imu_rate
    g = np.array([0.0, 0.0, -cfg.gravity])
    w_true = s.w
    f_true = np.einsum("nji,nj->ni", s.R, s.a - g)
    white_g = rng.standard_normal((n, 3)) * (cfg.gyro_noise_density / np.sqrt(dt))
    white_a = rng.standard_normal((n, 3)) * (cfg.acc_noise_density / np.sqrt(dt))
    step_g = rng.standard_normal((n, 3)) * (cfg.gyro_random_walk * np.sqrt(dt))
    step_a = rng.standard_normal((n, 3)) * (cfg.acc_random_walk * np.sqrt(dt))
    step_g[0] = step_a[0] = 0.0
    bg = np.asarray(cfg.gyro_bias_init, float) + np.cumsum(step_g, axis=0)
    ba = np.asarray(cfg.acc_bias_init, float) + np.cumsum(step_a, axis=0)
    return ImuSim(t_ns=t_ns, gyro=w_true + bg + white_g, acc=f_true + ba + white_a, bg=bg, ba=ba)


def bounding_box(traj: SplineTrajectory, duration: float) -> tuple[np.ndarray, np.ndarray]:
    p = traj.evaluate(np.linspace(0.0, duration, max(int(duration * 10), 2))).p
    return p.min(axis=0), p.max(axis=0)


def make_landmarks(
    lo: np.ndarray, hi: np.ndarray, margin: float, density: float, rng: np.random.Generator
) -> np.ndarray:
    """Points on the 6 faces of the room [lo - m, hi + m] (floor/ceiling m * 2/3), up to 0.5 m in from the face."""
    m = np.array([margin, margin, 2.0 * margin / 3.0])
    a, b = lo - m, hi + m
    size = b - a
    out = []
    for axis in range(3):
        u, v = [k for k in range(3) if k != axis]
        n = int(round(density * size[u] * size[v]))
        for side, sign in ((a[axis], 1.0), (b[axis], -1.0)):
            P = np.empty((n, 3))
            P[:, u] = a[u] + rng.random(n) * size[u]
            P[:, v] = a[v] + rng.random(n) * size[v]
            P[:, axis] = side + sign * rng.random(n) * min(0.5, 0.25 * size[axis])
            out.append(P)
    return rng.permutation(np.concatenate(out))  # random order: the index is a random priority


def room_landmarks(
    traj: SplineTrajectory,
    t_cam: np.ndarray,
    lo: np.ndarray,
    hi: np.ndarray,
    cam: dict,
    cfg: SimConfig,
    rng: np.random.Generator,
) -> np.ndarray:
    """Room landmarks at ``cfg.landmark_density``, or dense enough that ``min_features`` are visible in 90 % of
    the frames (probed on up to 200 frames; the density is capped at `MAX_DENSITY`)."""
    density = cfg.landmark_density
    if density is None:
        probe_set = make_landmarks(lo, hi, cfg.room_margin, PROBE_DENSITY, rng)
        probe = t_cam[np.linspace(0, len(t_cam) - 1, min(len(t_cam), 200)).astype(int)]
        counts = simulate_features(traj, probe, probe_set, cam, 0.0, cfg.max_feature_range, None).counts
        p10 = max(float(np.percentile(counts, 10)), 1.0)
        density = float(np.clip(PROBE_DENSITY * cfg.min_features / p10, 0.05, MAX_DENSITY))
    return make_landmarks(lo, hi, cfg.room_margin, density, rng)


def project_radtan(P_c: np.ndarray, intrinsics: Sequence[float], distortion: Sequence[float]) -> np.ndarray:
    """Pinhole + radial-tangential (OpenCV's k1, k2, p1, p2) projection of camera-frame points [..., 3]."""
    fu, fv, cu, cv = intrinsics
    k1, k2, p1, p2 = distortion
    x = P_c[..., 0] / P_c[..., 2]
    y = P_c[..., 1] / P_c[..., 2]
    r2 = x * x + y * y
    radial = 1.0 + r2 * (k1 + k2 * r2)
    xy2 = 2.0 * x * y
    xd = x * radial + p1 * xy2 + p2 * (r2 + 2.0 * x * x)
    yd = y * radial + p1 * (r2 + 2.0 * y * y) + p2 * xy2
    return np.stack([fu * xd + cu, fv * yd + cv], axis=-1)


def camera_model() -> dict:
    return dict(EUROC_CAMERAS["cam0"])


def simulate_features(
    traj: SplineTrajectory,
    t_ns: np.ndarray,
    landmarks: np.ndarray,
    cam: dict,
    pixel_sigma: float,
    max_range: float,
    rng: np.random.Generator | None,
    max_features: int | None = None,
    chunk: int = 32,
    advance=None,
) -> FeatureSim:
    """Visible landmarks per frame: in front (z > 0.1 m), within ``max_range``, inside the image after noise.

    With ``max_features``, a frame keeps the visible landmarks with the lowest indices (landmarks are stored in
    random order, so this is a fixed random priority and tracks persist while their landmark stays visible).
    """
    T = np.asarray(cam["T_imu_cam"], float)
    R_ic, p_ic = T[:3, :3], T[:3, 3]
    w, h = cam["resolution"]
    intr, dist = cam["intrinsics"], cam["distortion"]
    s = traj.evaluate(rel_seconds(traj, t_ns))
    R_wc = s.R @ R_ic
    p_wc = s.p + s.R @ p_ic
    frames, ids, uvs = [], [], []
    for f0 in range(0, len(t_ns), chunk):
        sl = slice(f0, f0 + chunk)
        D = landmarks[None, :, :] - p_wc[sl, None, :]  # [F,L,3]
        Pc = np.einsum("fji,flj->fli", R_wc[sl], D)
        z = Pc[..., 2]
        ok = (z > 0.1) & (np.einsum("fli,fli->fl", Pc, Pc) <= max_range**2)
        # the radtan polynomial is only meaningful near the image: cut at |x|, |y| < 1.5 before projecting
        zs = np.where(ok, z, 1.0)
        ok &= (np.abs(Pc[..., 0]) < 1.5 * zs) & (np.abs(Pc[..., 1]) < 1.5 * zs)
        f, l = np.nonzero(ok)
        uv = project_radtan(Pc[f, l], intr, dist)
        inside = (uv[:, 0] >= 0) & (uv[:, 0] < w) & (uv[:, 1] >= 0) & (uv[:, 1] < h)
        frames.append(f[inside] + f0)
        ids.append(l[inside])
        uvs.append(uv[inside])
        if advance is not None:
            advance(min(chunk, len(t_ns) - f0))
    frame = np.concatenate(frames) if frames else np.zeros(0, np.int64)
    idv = np.concatenate(ids) if ids else np.zeros(0, np.int64)
    uv = np.concatenate(uvs) if uvs else np.zeros((0, 2))
    if rng is not None:
        uv = uv + rng.standard_normal(uv.shape) * pixel_sigma
    keep = (uv[:, 0] >= 0) & (uv[:, 0] < w) & (uv[:, 1] >= 0) & (uv[:, 1] < h)
    frame, idv, uv = frame[keep], idv[keep], uv[keep]
    offsets = np.searchsorted(frame, np.arange(len(t_ns) + 1))
    if max_features is not None:  # rows are sorted by (frame, id): keep each frame's first max_features
        keep = np.arange(len(frame)) - offsets[frame] < max_features
        frame, idv, uv = frame[keep], idv[keep], uv[keep]
        offsets = np.searchsorted(frame, np.arange(len(t_ns) + 1))
    return FeatureSim(t_ns=t_ns, offsets=offsets, ids=idv.astype(np.int64), uv=uv)


def default_anchors(lo: np.ndarray, hi: np.ndarray, n: int) -> np.ndarray:
    """n anchors around the flight volume, 1.5 m outside its box horizontally, at well-spread heights."""
    c = 0.5 * (lo + hi)
    half = 0.5 * (hi - lo) + 1.5
    ang = np.pi / 4 + 2 * np.pi * np.arange(n) / n
    height = lo[2] - 0.3 + (hi[2] - lo[2] + 1.5) * ((0.618034 * np.arange(n) + 0.15) % 1.0)
    return np.stack([c[0] + half[0] * np.cos(ang), c[1] + half[1] * np.sin(ang), height], axis=1)


def odometry_noise(scale: float = 1.0) -> dict[str, float]:
    """The odometry filter's default drift sigmas (`NOISE_KEYS`) times ``scale``: what the simulated odometry
    follows and declares in its calibration (``odometry.noise``)."""

    c = OdometryFilterConfig()
    return {k: float(getattr(c, k)) * scale for k in NOISE_KEYS}


def simulate_odometry(
    traj: SplineTrajectory, t_ns: np.ndarray, scale: float, rng: np.random.Generator
) -> OdometrySim:
    """Odometry that drifts as the odometry filter's drift model assumes: the first pose is off by a draw of its
    initial covariance, every increment T_k-1^-1 T_k by a draw of `increment_noise` (dR = dR_hat Exp(n_theta),
    dp = dp_hat + n_p), composed like dead reckoning."""

    c = OdometryFilterConfig().model_copy(update=odometry_noise(scale))  # unvalidated: scale 0 is the truth
    s = traj.evaluate(rel_seconds(traj, t_ns))
    n = len(t_ns)
    R_hat = np.empty((n, 3, 3))
    p_hat = np.empty((n, 3))
    th0, p0 = np.radians(c.initial_sigma_theta_deg), c.initial_sigma_p
    R_hat[0] = s.R[0] @ exp_so3(-th0 * rng.standard_normal(3))
    p_hat[0] = s.p[0] - p0 * rng.standard_normal(3)
    z = rng.standard_normal((n, 6))
    for k in range(1, n):
        dR, dp = relative(s.R[k - 1], s.p[k - 1], s.R[k], s.p[k])
        sd = np.sqrt(np.diag(increment_noise(c, dR, dp, (t_ns[k] - t_ns[k - 1]) * 1e-9)))
        nk = sd * z[k]
        R_hat[k], p_hat[k] = compose(R_hat[k - 1], p_hat[k - 1], dR @ exp_so3(-nk[0:3]), dp - nk[3:6])
    return OdometrySim(t_ns=t_ns, p=p_hat, q_xyzw=rot_to_quat(R_hat))


def gauss_markov_errors(
    dt_s: np.ndarray, sigmas: np.ndarray, tau_s: float, rng: np.random.Generator
) -> np.ndarray:
    """(N, d) stationary Gauss-Markov errors with the stationary sigmas ``sigmas`` (d,), at stamps ``dt_s`` [s]
    after each one before (the first's ignored): e_k = phi e_(k-1) + sqrt(1 - phi^2) z_k, phi = exp(-dt /
    ``tau_s``), e_0 = z_0."""
    phi = np.exp(-np.asarray(dt_s, float) / tau_s)
    z = rng.standard_normal((len(phi), len(sigmas))) * sigmas
    e = np.empty_like(z)
    e[0] = z[0]
    for k in range(1, len(z)):
        e[k] = phi[k] * e[k - 1] + np.sqrt(1.0 - phi[k] ** 2) * z[k]
    return e


def simulate_bounded_odometry(
    traj: SplineTrajectory,
    t_ns: np.ndarray,
    sigma_p: float,
    sigma_theta: float,
    tau_s: float,
    rng: np.random.Generator,
) -> OdometrySim:
    """Poses with a bounded error, as the odometry filter's bounded model assumes: world-frame attitude and
    position errors e_k = phi e_(k-1) + sqrt(1 - phi^2) sigma z_k (phi = exp(-dt / tau), stationary from the
    first pose), R_hat = Exp(-e_theta) R, p_hat = p - e_p (so the filter's [dtheta_body, dp] = [R^T e_theta, e_p])."""

    s = traj.evaluate(rel_seconds(traj, t_ns))
    sig = np.r_[np.full(3, sigma_theta), np.full(3, sigma_p)]
    e = gauss_markov_errors(np.diff(np.asarray(t_ns, np.int64), prepend=t_ns[0]) * 1e-9, sig, tau_s, rng)
    R_hat = exp_so3(-e[:, 0:3]) @ s.R
    return OdometrySim(t_ns=t_ns, p=s.p - e[:, 3:6], q_xyzw=rot_to_quat(R_hat))


def simulate_ranges(
    traj: SplineTrajectory,
    t0_ns: int,
    duration: float,
    anchors: np.ndarray,
    beta: np.ndarray,
    gamma: np.ndarray,
    cfg: SimConfig,
    rng: np.random.Generator,
) -> RangeSim:
    """One stream per link (anchor a, tag k), link index l = k n_a + a, staggered by l / n_links of a period
    (with one tag: the anchors' streams, as before multi-tag support: same stamps and draws)."""
    n_a = len(anchors)
    arms = cfg.lever_arms()
    n_t = len(arms)
    n_l = n_a * n_t
    period = round(NS / cfg.uwb_rate)
    stamps = [sample_times(t0_ns, duration, cfg.uwb_rate, offset_ns=(l * period) // n_l) for l in range(n_l)]
    link = np.concatenate([np.full(len(s), l, np.int64) for l, s in enumerate(stamps)])
    t_ns = np.concatenate(stamps)
    order = np.argsort(t_ns, kind="stable")
    t_ns, link = t_ns[order], link[order]
    anchor, tag_i = link % n_a, link // n_a
    s = traj.evaluate(rel_seconds(traj, t_ns))
    tag = s.p + (s.R @ arms[0] if n_t == 1 else np.einsum("nij,nj->ni", s.R, arms[tag_i]))
    true = np.linalg.norm(tag - anchors[anchor], axis=1)
    n = len(t_ns)
    noise = rng.standard_normal(n) * cfg.sigma_range
    nlos_u = rng.random(n)
    nlos_bias = rng.exponential(1.0, n) * cfg.nlos_bias_mean
    drop_u = rng.random(n)
    rate = (
        np.asarray(cfg.link_nlos_rate, float)[anchor, tag_i]
        if cfg.link_nlos_rate is not None
        else cfg.nlos_rate
    )
    nlos = nlos_u < rate
    offset = (
        np.asarray(cfg.link_gamma_offset, float)[anchor, tag_i] if cfg.link_gamma_offset is not None else 0.0
    )
    d = beta[anchor] * (true + noise) + gamma[anchor] + offset + np.where(nlos, nlos_bias, 0.0)
    if cfg.antenna_pattern is not None:
        d = d + antenna_bias(np.asarray(cfg.antenna_pattern, float)[anchor], tag - anchors[anchor])
    keep = drop_u >= cfg.dropout_rate
    if cfg.max_range is not None:
        keep &= true <= cfg.max_range
    if cfg.visibility:
        rel = (t_ns - t0_ns) * 1e-9
        for a, wins in cfg.visibility.items():
            sel = anchor == int(a)
            seen = np.zeros(n, bool)
            for lo, hi in np.asarray(wins, float).reshape(-1, 2):
                seen |= (rel >= lo) & (rel <= hi)
            keep &= ~sel | seen
    if cfg.range_latency_s:  # stamped late (or early); the recording holds only stamps inside its span
        t_ns = t_ns + round(cfg.range_latency_s * NS)
        keep &= (t_ns >= t0_ns) & (t_ns <= t0_ns + round(duration * NS))
    return RangeSim(
        t_ns=t_ns[keep],
        anchor=anchor[keep],
        distance=d[keep],
        true_distance=true[keep],
        nlos=nlos[keep],
        candidates=n,
        tag=(cfg.tag_id + tag_i[keep]).astype(np.int64),
    )


def antenna_bias(pattern: np.ndarray, u: np.ndarray) -> np.ndarray:
    """b0 + b1 cos(az - phi) + b2 sin(el) per row of ``pattern`` (N, 4: b0, b1, phi_deg, b2) for the directions
    ``u`` (N, 3, anchor to tag, any length; world frame)."""
    az = np.arctan2(u[:, 1], u[:, 0])
    sin_el = u[:, 2] / np.maximum(np.linalg.norm(u, axis=1), 1e-9)
    b0, b1, phi, b2 = pattern.T
    return b0 + b1 * np.cos(az - np.radians(phi)) + b2 * sin_el


@dataclass
class WorldSim:
    """What the simulator places around a trajectory and measures along it: landmarks and their feature tracks,
    anchors and their ranges."""

    landmarks: np.ndarray
    features: FeatureSim | None
    anchors: np.ndarray
    beta: np.ndarray
    gamma: np.ndarray
    ranges: RangeSim


def simulate_world(
    traj: SplineTrajectory, duration: float, cam: dict, cfg: SimConfig, *, advance=None
) -> WorldSim:
    """Landmarks in a room around the whole trajectory, camera tracks (``cam``: calibration with ``rate_hz``)
    and UWB ranges over ``[start, start + duration]`` of ``traj``; each from its own random stream of the seed.
    Shared by `simulate` and the real-IMU hybrid recordings (`convert.hybrid`)."""
    t0 = traj.t0_ns
    # the world (room, landmarks, default anchors) depends on the whole trajectory, not on the duration simulated
    lo, hi = bounding_box(traj, traj.duration)
    rate = float(cam["rate_hz"])
    landmarks = room_landmarks(
        traj, sample_times(t0, traj.duration, rate), lo, hi, cam, cfg, stream(cfg.seed, "landmarks")
    )
    features = None
    if cfg.camera:
        features = simulate_features(
            traj,
            sample_times(t0, duration, rate),
            landmarks,
            cam,
            cfg.pixel_sigma,
            cfg.max_feature_range,
            stream(cfg.seed, "camera"),
            max_features=cfg.max_features,
            advance=advance,
        )
    anchors = (
        np.asarray(cfg.anchors, float) if cfg.anchors is not None else default_anchors(lo, hi, cfg.n_anchors)
    )
    beta, gamma = cfg.per_anchor("beta"), cfg.per_anchor("gamma")
    ranges = simulate_ranges(traj, t0, duration, anchors, beta, gamma, cfg, stream(cfg.seed, "uwb"))
    return WorldSim(landmarks, features, anchors, beta, gamma, ranges)


def simulate(cfg: SimConfig, *, advance=None) -> SimData:
    """All sensor streams as arrays (no files written)."""
    traj = load_trajectory(cfg.trajectory, knot_dt=cfg.knot_dt)
    duration = traj.duration if cfg.duration is None else float(cfg.duration)
    if duration > traj.duration + 1e-9:
        raise InputError(
            f"{traj.source or traj.name}: duration {duration:g} s: the trajectory lasts {traj.duration:.1f} s; "
            "give a shorter --duration"
        )
    t0 = traj.t0_ns
    t_imu = sample_times(t0, duration, cfg.imu_rate)
    imu = simulate_imu(traj, t_imu, cfg, stream(cfg.seed, "imu"))
    gt_s = traj.evaluate(rel_seconds(traj, t_imu))
    gt = GroundTruthSim(t_ns=t_imu, p=gt_s.p, q_xyzw=rot_to_quat(gt_s.R), v=gt_s.v)

    cam = camera_model()
    cam["rate_hz"] = float(cfg.cam_rate)
    world = simulate_world(traj, duration, cam, cfg, advance=advance)

    odometry = None
    if cfg.odometry_rate is not None:
        t_odo = sample_times(t0, duration, cfg.odometry_rate)
        rng_odo = stream(cfg.seed, "odometry")
        if cfg.odometry_error == "bounded":
            odometry = simulate_bounded_odometry(
                traj,
                t_odo,
                cfg.odometry_sigma_p,
                np.radians(cfg.odometry_sigma_theta_deg),
                cfg.odometry_correlation_s,
                rng_odo,
            )
        else:
            odometry = simulate_odometry(traj, t_odo, cfg.odometry_noise_scale, rng_odo)

    data = SimData.from_world(world, config=cfg, odometry=odometry, trajectory=traj, imu=imu, groundtruth=gt)
    data.metadata = _metadata(data, cam, duration)
    return data


def _links_truth(data: SimData) -> list[dict]:
    """Per link (anchor, tag, antenna 0): the total offset gamma + o_{a,t} (d = beta |.| + gamma_link), the
    offset o_{a,t}, the NLOS rate and the number of ranges kept (and of those with an NLOS bias)."""
    cfg, r = data.config, data.ranges
    n_t = len(cfg.lever_arms())
    off = (
        np.zeros((len(data.anchors), n_t))
        if cfg.link_gamma_offset is None
        else np.asarray(cfg.link_gamma_offset)
    )
    rate = (
        np.full((len(data.anchors), n_t), cfg.nlos_rate)
        if cfg.link_nlos_rate is None
        else np.asarray(cfg.link_nlos_rate, float)
    )
    tags = r.tag if r.tag is not None else np.full(len(r.t_ns), cfg.tag_id)
    out = []
    for a in range(len(data.anchors)):
        for k in range(n_t):
            sel = (r.anchor == a) & (tags == cfg.tag_id + k)
            out.append(
                {
                    "anchor": a,
                    "tag": cfg.tag_id + k,
                    "antenna": 0,
                    "gamma": float(data.gamma[a] + off[a, k]),
                    "offset": float(off[a, k]),
                    "nlos_rate": float(rate[a, k]),
                    "ranges": int(sel.sum()),
                    "nlos_count": int((sel & r.nlos).sum()),
                }
            )
    return out


def uwb_calibration(cfg: SimConfig) -> dict:
    """The calibration record of the simulated tags: lever arms, range noise, the priors a user would declare
    (``cfg.declared_priors``)."""
    priors = {"gamma_prior": {"mean": 0.0, "sigma": 1.0}, "beta_prior": {"mean": 1.0, "sigma": 0.2}}
    return {
        "tags": {str(cfg.tag_id + i): {"antennas": [arm.tolist()]} for i, arm in enumerate(cfg.lever_arms())},
        "sigma_range": cfg.sigma_range,
        **(priors if cfg.declared_priors else {}),
        "antenna_pattern_sigma": pattern_sigma(cfg.antenna_pattern),
    }


def pattern_sigma(pattern: Sequence[Sequence[float]] | None) -> float:
    """The per-component size of the simulated antennas' direction-dependent bias (rows b0, b1, phi, b2: the
    direction-dependent part b1 cos(az - phi) + b2 sin(el)), 0 without one."""
    if pattern is None:
        return 0.0
    a = np.asarray(pattern, float)
    return float(np.sqrt(np.mean(a[:, 1] ** 2 + a[:, 3] ** 2) / 3.0))


def world_truth(data: SimData, duration: float) -> dict:
    """``uwbcal.truth`` of the simulated world (anchors, links, noise levels, trajectory, duration)."""
    cfg = data.config
    return {
        "kind": "simulated",
        "anchors_frame": "world",
        "anchors": {
            str(i): {
                "position": data.anchors[i].tolist(),
                "beta": float(data.beta[i]),
                "gamma": float(data.gamma[i]),
            }
            for i in range(len(data.anchors))
        },
        "sigma_range": cfg.sigma_range,
        "nlos_rate": cfg.nlos_rate,
        "nlos_bias_mean": cfg.nlos_bias_mean,
        "dropout_rate": cfg.dropout_rate,
        "max_range": cfg.max_range,
        "seed": int(cfg.seed),
        "gravity": cfg.gravity,
        "pixel_sigma": cfg.pixel_sigma,
        "landmarks": len(data.landmarks),
        "tag": {"id": cfg.tag_id, "antenna": 0, "lever_arm": cfg.lever_arms()[0].tolist()},
        "links": _links_truth(data),
        **({"scenario": cfg.scenario} if cfg.scenario else {}),
        **({"range_latency_s": float(cfg.range_latency_s)} if cfg.range_latency_s else {}),
        **(
            {"antenna_pattern": np.asarray(cfg.antenna_pattern, float).tolist()}
            if cfg.antenna_pattern is not None
            else {}
        ),
        **(
            {"visibility": {str(a): np.asarray(w, float).tolist() for a, w in cfg.visibility.items()}}
            if cfg.visibility
            else {}
        ),
        "trajectory": data.trajectory.name,
        "duration": duration,
        "nlos_count": int(data.ranges.nlos.sum()),
    }


def _metadata(data: SimData, cam: dict, duration: float) -> dict[str, dict]:

    cfg, traj = data.config, data.trajectory
    calibration = {
        "imu": {
            "gyroscope_noise_density": cfg.gyro_noise_density,
            "gyroscope_random_walk": cfg.gyro_random_walk,
            "accelerometer_noise_density": cfg.acc_noise_density,
            "accelerometer_random_walk": cfg.acc_random_walk,
            "rate_hz": float(cfg.imu_rate),
        },
        "uwb": uwb_calibration(cfg),
        "groundtruth": {"lever_arm": [0.0, 0.0, 0.0], "frame": "body"},
    }
    if data.odometry is not None:
        if cfg.odometry_error == "bounded":
            calibration["odometry"] = {
                "error_model": "bounded",
                "correlation_time_s": float(cfg.odometry_correlation_s),
                "noise": {
                    "initial_sigma_p": float(cfg.odometry_sigma_p),
                    "initial_sigma_theta_deg": float(cfg.odometry_sigma_theta_deg),
                },
            }
        else:
            calibration["odometry"] = {
                "error_model": "drift",
                "noise": odometry_noise(cfg.odometry_noise_scale),
            }
    if data.features is not None:
        calibration["cameras"] = {"cam0": cam}
    truth = world_truth(data, duration)
    truth["imu"] = {  # biases at the first IMU sample (they random-walk afterwards)
        "gyro_bias": list(map(float, cfg.gyro_bias_init)),
        "accel_bias": list(map(float, cfg.acc_bias_init)),
    }
    files = [{"path": str(traj.source), "sha256": sha256_file(traj.source)}] if traj.source else []
    source = {
        "dataset": "simulation",
        "sequence": traj.name,
        "files": files,
        "converter": converter_name(),
        "dropped": [],
        "seed": int(cfg.seed),
    }
    return {META_CALIBRATION: calibration, META_TRUTH: truth, META_SOURCE: source}


# ---------------------------------------------------------------------------------------------------------------
# file output
# ---------------------------------------------------------------------------------------------------------------
def write_recording(data: SimData, output: str | Path, advance=None) -> dict[str, int]:

    with RecordingWriter(output) as w:
        w.write_imu_batch(data.imu.t_ns, data.imu.gyro, data.imu.acc)
        if data.features is not None:
            fs = data.features
            for f in range(len(fs.t_ns)):
                t, ids, uv = fs.frame(f)
                w.write_features(t, ids, uv)
                if advance is not None:
                    advance(1)
        r = data.ranges
        w.write_range_batch(
            r.t_ns, r.tag if r.tag is not None else data.config.tag_id, 0, r.anchor, r.distance
        )
        gt = data.groundtruth
        w.write_pose_batch(gt.t_ns, gt.p, gt.q_xyzw, topic=TOPIC_GT_POSE)
        if data.groundtruth_bias is not None:
            b = data.groundtruth_bias
            w.write_imu_batch(b.t_ns, b.gyro, b.acc, topic=TOPIC_GT_IMU_BIAS)
        if data.odometry is not None:
            o = data.odometry
            w.write_odometry_batch(o.t_ns, o.p, o.q_xyzw, topic=TOPIC_ODOM)
        for name, record in data.metadata.items():
            w.set_metadata(name, record)
        counts = dict(w.counts)
    return counts


def simulate_to_file(cfg: SimConfig, output: str | Path) -> str:
    """Simulate and write the recording; returns a short human-readable summary."""

    with progress("simulating camera", None) as advance:
        data = simulate(cfg, advance=advance)
    n_frames = len(data.features.t_ns) if data.features is not None else 0
    with progress("writing", n_frames or None) as advance:
        counts = write_recording(data, output, advance=advance)
    r = data.ranges
    lines = [
        f"simulated {data.trajectory.name} ({data.metadata['uwbcal.truth']['duration']:.1f} s, seed {cfg.seed})"
        f" -> {output}",
        *(f"  {topic:<24} {n:>9} messages" for topic, n in sorted(counts.items())),
    ]
    if data.features is not None:
        c = data.features.counts
        lines.append(f"  features per frame: mean {c.mean():.0f}, min {c.min()}, max {c.max()}")
    lines.append(
        f"  anchors: {len(data.anchors)}; ranges kept {len(r.t_ns)} of {r.candidates}"
        f" (NLOS {int(r.nlos.sum())}, dropout rate {cfg.dropout_rate:g}, max range {cfg.max_range})"
    )
    return "\n".join(lines)
