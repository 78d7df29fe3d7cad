"""Smooth continuous-time trajectories for the simulator: a cumulative cubic B-spline on SO(3) x R^3.

The spline has uniform knots ``dt`` apart and control poses ``(R_k, p_k)``; segment ``i`` (``t`` in
``[i dt, (i+1) dt)`` relative to the start) is built from control points ``i .. i+3``:

    R(t) = R_i Exp(b1 W_{i+1}) Exp(b2 W_{i+2}) Exp(b3 W_{i+3}),   W_j = Log(R_{j-1}^T R_j)
    p(t) = p_i + b1 d_{i+1} + b2 d_{i+2} + b3 d_{i+3},             d_j = p_j - p_{j-1}

with the cumulative basis ``b(u)`` (Sommer et al. 2020, "Efficient derivative computation for cumulative
B-splines on Lie groups"). Pose, body angular velocity, world velocity and world acceleration are analytic,
so IMU readings simulated from them are exact derivatives. The spline is C2: acceleration and angular velocity
are continuous.

Sources: EuRoC ground truth (TUM ``.txt`` or EuRoC ``.csv``), by path or by sequence name, and built-in
trajectories that need no data (`BUILTIN`): the figure-8 with vertical motion (`default_trajectory`, the demo),
a planar ground trolley (`planar_trajectory`, "planar"), a campus drive over ~400 m (`campus_trajectory`,
"campus"), a drone climbing and descending on the spot (`climb_trajectory`, "climb"), an outdoor drive out to
~50 m and back (`far_field_trajectory`, "far-field") and a handheld rig carried around a room
(`handheld_trajectory`, "handheld").
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from uwbcal.convert.datasets import data_root
from uwbcal.pipeline.core.errors import InputError
from uwbcal.pipeline.core.geometry import exp_so3, log_so3, quat_slerp, quat_to_rot, rot_to_quat

DEFAULT_NAME = "default"
DEFAULT_KNOT_DT = 0.1
DEFAULT_T0_NS = 1_000_000_000  # stamps of the built-in trajectory start at 1 s (0 is a suspicious stamp)

# cumulative cubic B-spline basis: b(u) = C @ [1, u, u^2, u^3]; row 0 is always 1
_C = (
    np.array([[6.0, 0.0, 0.0, 0.0], [5.0, 3.0, -3.0, 1.0], [1.0, 3.0, 3.0, -2.0], [0.0, 0.0, 0.0, 1.0]]) / 6.0
)


@dataclass(frozen=True)
class TrajectorySample:
    """The trajectory at times ``t`` [N]: R world_from_body [N,3,3], p/v/a world [N,3], w body [N,3]."""

    t: np.ndarray
    R: np.ndarray
    p: np.ndarray
    v: np.ndarray
    a: np.ndarray
    w: np.ndarray

    @property
    def q_xyzw(self) -> np.ndarray:
        return rot_to_quat(self.R)


@dataclass(frozen=True)
class SplineTrajectory:
    """Uniform cumulative cubic B-spline in SO(3) x R^3; times in seconds relative to ``t0_ns``."""

    dt: float
    R_ctrl: np.ndarray  # [K,3,3]
    p_ctrl: np.ndarray  # [K,3]
    t0_ns: int = 0
    name: str = ""
    source: Path | None = None

    def __post_init__(self) -> None:
        if len(self.p_ctrl) < 4 or len(self.R_ctrl) != len(self.p_ctrl):
            raise ValueError(
                "a cubic B-spline needs at least 4 control poses (as many rotations as positions)"
            )
        # increments between consecutive control points, computed once
        object.__setattr__(self, "_W", log_so3(np.einsum("kji,kjl->kil", self.R_ctrl[:-1], self.R_ctrl[1:])))
        object.__setattr__(self, "_d", np.diff(self.p_ctrl, axis=0))

    @property
    def duration(self) -> float:
        """Valid time span [0, duration] in seconds."""
        return (len(self.p_ctrl) - 3) * self.dt

    def t_ns(self, t: np.ndarray) -> np.ndarray:
        return self.t0_ns + np.round(np.asarray(t, float) * 1e9).astype(np.int64)

    def _segments(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        s = np.asarray(t, float) / self.dt
        i = np.clip(np.floor(s).astype(np.int64), 0, len(self.p_ctrl) - 4)
        return i, s - i

    def evaluate(self, t: np.ndarray) -> TrajectorySample:
        """Pose and derivatives at times ``t`` (seconds from the start; outside the span it extrapolates)."""
        t = np.atleast_1d(np.asarray(t, float))
        i, u = self._segments(t)
        U = np.stack([np.ones_like(u), u, u * u, u**3], axis=1)
        dU = np.stack([np.zeros_like(u), np.ones_like(u), 2 * u, 3 * u * u], axis=1) / self.dt
        ddU = np.stack([np.zeros_like(u), np.zeros_like(u), 2 * np.ones_like(u), 6 * u], axis=1) / self.dt**2
        b, db, ddb = U @ _C.T, dU @ _C.T, ddU @ _C.T  # [N,4]

        p = self.p_ctrl[i].copy()
        v = np.zeros_like(p)
        a = np.zeros_like(p)
        R = self.R_ctrl[i].copy()
        w = np.zeros_like(p)
        for j in (1, 2, 3):
            d = self._d[i + j - 1]
            p += b[:, j, None] * d
            v += db[:, j, None] * d
            a += ddb[:, j, None] * d
            W = self._W[i + j - 1]
            A = exp_so3(b[:, j, None] * W)
            R = R @ A
            w = np.einsum("nji,nj->ni", A, w) + db[:, j, None] * W  # w <- A^T w + b' W
        return TrajectorySample(t=t, R=R, p=p, v=v, a=a, w=w)

    def pose(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        s = self.evaluate(t)
        return s.R, s.p

    @staticmethod
    def fit(
        t: np.ndarray,
        p: np.ndarray,
        q_xyzw: np.ndarray,
        *,
        knot_dt: float = DEFAULT_KNOT_DT,
        t0_ns: int = 0,
        name: str = "",
        source: Path | None = None,
    ) -> SplineTrajectory:
        """Fit to pose samples at times ``t`` [s, increasing, relative to ``t0_ns``]; the spline starts at t[0].

        Positions: linear least squares over all samples (smooths ground-truth noise). Rotations: control
        rotations sampled (slerp) at the knot times; the cubic B-spline smooths them.
        """
        t = np.asarray(t, float) - float(t[0])
        span = float(t[-1])
        n_seg = max(int(np.floor(span / knot_dt + 1e-9)), 1)
        K = n_seg + 3
        tau = (np.arange(K) - 1.0) * knot_dt  # control point k sits (roughly) at time (k-1) dt
        tc = np.clip(tau, 0.0, span)
        idx = np.clip(np.searchsorted(t, tc, side="right") - 1, 0, len(t) - 2)
        frac = np.clip((tc - t[idx]) / np.maximum(t[idx + 1] - t[idx], 1e-12), 0.0, 1.0)
        q = quat_slerp(q_xyzw[idx], q_xyzw[idx + 1], frac)
        R_ctrl = quat_to_rot(q)
        p_init = p[idx] + frac[:, None] * (p[idx + 1] - p[idx])
        p_ctrl = _fit_positions(t, p, knot_dt, K, p_init)
        return SplineTrajectory(knot_dt, R_ctrl, p_ctrl, t0_ns=t0_ns, name=name, source=source)


def _fit_positions(t: np.ndarray, p: np.ndarray, dt: float, K: int, p_init: np.ndarray) -> np.ndarray:
    """argmin_c sum |B(t_m) c - p_m|^2 + lam |c - p_init|^2 (the prior only pins control points without data)."""
    from scipy import sparse
    from scipy.sparse.linalg import spsolve

    s = t / dt
    i = np.clip(np.floor(s).astype(np.int64), 0, K - 4)
    u = s - i
    U = np.stack([np.ones_like(u), u, u * u, u**3], axis=1)
    bc = U @ _C.T  # cumulative basis -> plain basis: B_j = b_j - b_{j+1}
    B = bc - np.concatenate([bc[:, 1:], np.zeros((len(u), 1))], axis=1)
    rows = np.repeat(np.arange(len(t)), 4)
    cols = (i[:, None] + np.arange(4)).reshape(-1)
    A = sparse.csr_matrix((B.reshape(-1), (rows, cols)), shape=(len(t), K))
    lam = 1e-6 * max(len(t) / K, 1.0)
    N = (A.T @ A + lam * sparse.identity(K)).tocsc()
    rhs = A.T @ p + lam * p_init
    return np.stack([spsolve(N, rhs[:, k]) for k in range(3)], axis=1)


# ---------------------------------------------------------------------------------------------------------------
# sources
# ---------------------------------------------------------------------------------------------------------------
def groundtruth_dir() -> Path:
    return data_root() / "euroc" / "groundtruth"


def available_names() -> list[str]:
    d = groundtruth_dir()
    return sorted({f.stem for f in d.glob("*.txt")} | {f.stem for f in d.glob("*.csv")})


def resolve_trajectory(name_or_path: str | Path) -> Path:
    """An existing file path, or a EuRoC sequence name under ``data_root()/euroc/groundtruth`` (.txt, then .csv)."""
    p = Path(name_or_path)
    if p.is_file():
        return p
    if p.suffix not in (".txt", ".csv") and len(p.parts) == 1:
        for ext in (".txt", ".csv"):
            cand = groundtruth_dir() / f"{p.name}{ext}"
            if cand.is_file():
                return cand
    names = available_names()
    have = (
        ", ".join([*BUILTIN, *names])
        if names
        else f"{', '.join(BUILTIN)} (EuRoC: none in {groundtruth_dir()})"
    )
    raise InputError(
        f"{name_or_path}: trajectory not found; give a TUM .txt / EuRoC .csv ground-truth file or one of: {have}"
    )


def _parse_rows(path: Path, sep: str | None, min_cols: int) -> tuple[list[str] | None, np.ndarray]:
    """(first column as text, numeric rows) of a table (``#`` comments skipped); InputError naming a bad line.

    Fast path: numpy's parser (first column not returned as text); on any problem the slow line-by-line parse
    finds and names the bad line.
    """
    import warnings

    try:
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            d = np.loadtxt(path, delimiter=sep, comments="#", usecols=range(min_cols), ndmin=2)
        if len(d) >= 4 and np.all(np.isfinite(d)):
            return None, d
    except (ValueError, UserWarning, IndexError):
        pass
    try:
        text = path.read_text()
    except (OSError, UnicodeDecodeError) as e:
        raise InputError(f"{path}: cannot read ({e}); give a readable text file") from e
    rows: list[list[float]] = []
    first: list[str] = []
    for lineno, line in enumerate(text.splitlines(), start=1):
        s = line.strip()
        if not s or s.startswith("#") or (lineno == 1 and s[0].isalpha()):
            continue
        fields = [f.strip() for f in s.split(sep)] if sep else s.split()
        try:
            vals = [float(f) for f in fields]
        except ValueError:
            vals = []
        if len(vals) < min_cols or not np.all(np.isfinite(vals[:min_cols])):
            raise InputError(
                f"{path}: line {lineno}: expected {min_cols} numeric columns, got {s[:80]!r}; fix or remove the line"
            )
        rows.append(vals[:min_cols])
        first.append(fields[0])
    if len(rows) < 4:
        raise InputError(f"{path}: only {len(rows)} poses; a trajectory needs at least 4")
    return first, np.asarray(rows, float)


def load_groundtruth(path: str | Path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(t_ns [N] int64, p [N,3], q_xyzw [N,4]) from a TUM ``t x y z qx qy qz qw`` (s) or EuRoC CSV (ns, wxyz)."""
    path = Path(path)
    if path.suffix == ".csv":
        first, d = _parse_rows(path, ",", 8)
        # float64 holds ns stamps only to ~0.25 us: read the integer column exactly
        try:
            if first is None:
                t_ns = np.loadtxt(path, delimiter=",", comments="#", usecols=0, dtype=np.int64, ndmin=1)
            else:
                t_ns = np.array([int(f) for f in first], np.int64)
        except ValueError:
            t_ns = np.round(d[:, 0]).astype(np.int64)
        p, q = d[:, 1:4], d[:, [5, 6, 7, 4]]
    else:
        _, d = _parse_rows(path, None, 8)
        t_ns = np.round(d[:, 0] * 1e9).astype(np.int64)
        p, q = d[:, 1:4], d[:, 4:8]
    qn = np.linalg.norm(q, axis=1)
    bad = np.flatnonzero(qn < 0.5)
    if len(bad):
        raise InputError(
            f"{path}: pose {bad[0] + 1}: quaternion norm {qn[bad[0]]:.3g}; expected a unit quaternion"
        )
    order = np.argsort(t_ns, kind="stable")
    if np.any(order != np.arange(len(t_ns))):
        k = int(np.flatnonzero(np.diff(t_ns) < 0)[0])
        raise InputError(f"{path}: pose {k + 2}: time goes backwards; sort the file by time")
    keep = np.concatenate([[True], np.diff(t_ns) > 0])  # drop repeated stamps
    return t_ns[keep], p[keep], (q / qn[:, None])[keep]


def load_trajectory(
    name_or_path: str | Path | None = None, knot_dt: float = DEFAULT_KNOT_DT
) -> SplineTrajectory:
    """The built-in default (None or ``"default"``), another built-in name (`BUILTIN`), a EuRoC sequence name, or a
    ground-truth file."""
    if name_or_path is None or str(name_or_path) == DEFAULT_NAME:
        return default_trajectory(knot_dt=knot_dt)
    if str(name_or_path) in BUILTIN and not Path(name_or_path).is_file():
        return BUILTIN[str(name_or_path)](knot_dt=knot_dt)
    path = resolve_trajectory(name_or_path)
    t_ns, p, q = load_groundtruth(path)
    t = (t_ns - t_ns[0]) * 1e-9
    if t[-1] < 4 * knot_dt:
        raise InputError(f"{path}: spans only {t[-1]:.3f} s; need at least {4 * knot_dt:.1f} s of poses")
    return SplineTrajectory.fit(t, p, q, knot_dt=knot_dt, t0_ns=int(t_ns[0]), name=path.stem, source=path)


def default_trajectory(duration: float = 120.0, knot_dt: float = DEFAULT_KNOT_DT) -> SplineTrajectory:
    """A ~120 s figure-8 (8 m x 5 m, 24 s per loop) with 1.8 m vertical swings, heading along the velocity.

    Still for the first second, then eases into motion over 3 s (static IMU initialisation is possible).
    The body axes follow EuRoC: IMU x up, IMU z (the camera's optical axis) forward and tilted down ~10 deg.
    """
    t = np.arange(0.0, duration + 1e-9, 0.02)
    t_still, t_ramp = 1.0, 3.0
    x = np.clip((t - t_still) / t_ramp, 0.0, 1.0)
    # phase with phase' = smoothstep: starts at rest, C2
    phase = np.where(t < t_still + t_ramp, t_ramp * (x**3 - x**4 / 2), t - t_still - t_ramp / 2)
    w = 2 * np.pi / 24.0
    # figure-8 + vertical swing, plus small fast wiggles so the accelerometer sees ~2 m/s^2 (scale observability)
    wig = 2 * np.pi * 0.4
    p = np.stack(
        [
            4.0 * np.sin(w * phase) + 0.12 * np.sin(wig * phase),
            2.5 * np.sin(2 * w * phase) + 0.12 * np.sin(1.3 * wig * phase + 1.0),
            1.6 - 0.9 * np.cos(2 * np.pi * phase / 15.0) + 0.08 * np.sin(1.7 * wig * phase),
        ],
        axis=1,
    )
    vx = 4.0 * w * np.cos(w * phase)
    vy = 5.0 * w * np.cos(2 * w * phase)
    yaw = np.unwrap(np.arctan2(vy, vx))
    roll = 0.08 * np.sin(2 * np.pi * phase / 7.0)
    pitch = 0.17 + 0.08 * np.sin(2 * np.pi * phase / 11.0)  # camera looks slightly down
    # world_from_body = Rz(yaw) Ry(pitch) Rx(roll) @ R_base, R_base: body x -> world z, body z -> world x
    R_base = np.array([[0.0, 0.0, 1.0], [0.0, -1.0, 0.0], [1.0, 0.0, 0.0]])
    R = (
        exp_so3(np.stack([np.zeros_like(t), np.zeros_like(t), yaw], 1))
        @ exp_so3(np.stack([np.zeros_like(t), pitch, np.zeros_like(t)], 1))
        @ exp_so3(np.stack([roll, np.zeros_like(t), np.zeros_like(t)], 1))
        @ R_base
    )
    return SplineTrajectory.fit(
        t, p, rot_to_quat(R), knot_dt=knot_dt, t0_ns=DEFAULT_T0_NS, name=DEFAULT_NAME, source=None
    )


# EuRoC body axes (as `default_trajectory`): IMU x up, IMU z (the camera's optical axis) forward
_R_BASE = np.array([[0.0, 0.0, 1.0], [0.0, -1.0, 0.0], [1.0, 0.0, 0.0]])


def _eased_phase(t: np.ndarray, t_still: float, t_ramp: float) -> np.ndarray:
    """Time-like phase that is still until ``t_still``, then eases in (C2) over ``t_ramp`` to unit rate."""
    x = np.clip((t - t_still) / t_ramp, 0.0, 1.0)
    return np.where(t < t_still + t_ramp, t_ramp * (x**3 - x**4 / 2), t - t_still - t_ramp / 2)


def _yaw_only(yaw: np.ndarray) -> np.ndarray:
    z = np.zeros_like(yaw)
    return exp_so3(np.stack([z, z, yaw], 1)) @ _R_BASE


def planar_trajectory(duration: float = 150.0, knot_dt: float = DEFAULT_KNOT_DT) -> SplineTrajectory:
    """A ground trolley: the IMU at a constant 0.3 m height, Lissajous loops over ~7 m x 5 m at up to ~0.6 m/s,
    heading along the velocity, no roll or pitch (a lever arm with zero IMU-x component stays in one plane)."""
    t = np.arange(0.0, duration + 1e-9, 0.02)
    phase = _eased_phase(t, 1.0, 3.0)
    w = 2 * np.pi / 45.0
    p = np.stack(
        [
            2.8 * np.sin(w * phase) + 0.4 * np.sin(3.1 * w * phase),
            2.0 * np.sin(2 * w * phase + 0.6) - 2.0 * np.sin(0.6),
            np.full_like(t, 0.3),
        ],
        axis=1,
    )
    vx = 2.8 * w * np.cos(w * phase) + 0.4 * 3.1 * w * np.cos(3.1 * w * phase)
    vy = 4.0 * w * np.cos(2 * w * phase + 0.6)
    yaw = np.unwrap(np.arctan2(vy, vx))
    return SplineTrajectory.fit(
        t, p, rot_to_quat(_yaw_only(yaw)), knot_dt=knot_dt, t0_ns=DEFAULT_T0_NS, name="planar", source=None
    )


def campus_trajectory(duration: float = 260.0, knot_dt: float = DEFAULT_KNOT_DT) -> SplineTrajectory:
    """A campus vehicle at 4 m/s: one ~190 m x 120 m block (left turns at 50, 80, 130, 160 s, 6 s each), then
    straight on east to ~380 m; the road undulates by +-0.3 m (motion nearly planar)."""
    dt = 0.02
    t = np.arange(0.0, duration + 1e-9, dt)
    x = np.clip((t - 1.0) / 4.0, 0.0, 1.0)
    speed = 4.0 * (x**3 * (10 - 15 * x + 6 * x**2))  # smoothstep 0 -> 4 m/s over 1-5 s
    yaw = np.zeros_like(t)
    for t_turn in (50.0, 80.0, 130.0, 160.0):
        u = np.clip((t - t_turn) / 6.0, 0.0, 1.0)
        yaw += 0.5 * np.pi * u**3 * (10 - 15 * u + 6 * u**2)
    v = speed[:, None] * np.stack([np.cos(yaw), np.sin(yaw)], 1)
    xy = np.concatenate([[[0.0, 0.0]], np.cumsum(0.5 * (v[1:] + v[:-1]) * dt, axis=0)])
    p = np.column_stack([xy, 0.3 * np.sin(2 * np.pi * t / 90.0)])
    return SplineTrajectory.fit(
        t, p, rot_to_quat(_yaw_only(yaw)), knot_dt=knot_dt, t0_ns=DEFAULT_T0_NS, name="campus", source=None
    )


def _euler(yaw: np.ndarray, pitch: np.ndarray, roll: np.ndarray) -> np.ndarray:
    """world_from_body = Rz(yaw) Ry(pitch) Rx(roll) @ `_R_BASE`."""
    z = np.zeros_like(yaw)
    return (
        exp_so3(np.stack([z, z, yaw], 1))
        @ exp_so3(np.stack([z, pitch, z], 1))
        @ exp_so3(np.stack([roll, z, z], 1))
        @ _R_BASE
    )


def climb_trajectory(duration: float = 100.0, knot_dt: float = DEFAULT_KNOT_DT) -> SplineTrajectory:
    """A quadrotor climbing and descending on the spot: height 0.1 -> 1.9 m and back every 25 s (it takes off
    after 1 s), the horizontal position wandering within ~0.2 m about (0.2, -0.1), the tilt a few degrees with
    the horizontal acceleration, the heading swinging slowly by +-20 deg."""
    t = np.arange(0.0, duration + 1e-9, 0.02)
    phase = _eased_phase(t, 1.0, 3.0)
    a = 2 * np.pi * phase
    p = np.stack(
        [
            0.2 + 0.1 * np.sin(a / 13.0) + 0.02 * np.sin(a / 3.1),
            -0.1 + 0.1 * np.sin(a / 17.0 + 0.7) + 0.02 * np.sin(a / 2.3),
            1.0 - 0.9 * np.cos(a / 25.0),
        ],
        axis=1,
    )
    yaw = 0.35 * np.sin(a / 40.0)
    tilt = 0.04
    pitch = tilt * np.sin(a / 13.0 + 0.5 * np.pi)  # leans into the horizontal acceleration
    roll = tilt * np.sin(a / 17.0 + 0.7)
    return SplineTrajectory.fit(
        t, p, rot_to_quat(_euler(yaw, pitch, roll)), knot_dt=knot_dt, t0_ns=DEFAULT_T0_NS, name="climb"
    )


def far_field_trajectory(duration: float = 60.0, knot_dt: float = DEFAULT_KNOT_DT) -> SplineTrajectory:
    """An outdoor ground platform at 2.5 m/s from (4, -4): east along a gentle curve out to ~50 m, a wide U-turn
    to the left (16-32 s) and back west ~13 m further north, past the start and beyond; the ground undulates by
    +-0.2 m (motion nearly planar), the body at 0.5 m (the EuRoC axes, yaw only)."""
    dt = 0.02
    t = np.arange(0.0, duration + 1e-9, dt)
    x = np.clip((t - 1.0) / 3.0, 0.0, 1.0)
    speed = 2.5 * (x**3 * (10 - 15 * x + 6 * x**2))
    yaw = 0.15 * np.sin(2 * np.pi * t / 30.0)
    for t_turn, span, angle in ((16.0, 16.0, np.pi),):
        u = np.clip((t - t_turn) / span, 0.0, 1.0)
        yaw += angle * u**3 * (10 - 15 * u + 6 * u**2)
    v = speed[:, None] * np.stack([np.cos(yaw), np.sin(yaw)], 1)
    xy = np.array([4.0, -4.0]) + np.concatenate(
        [[[0.0, 0.0]], np.cumsum(0.5 * (v[1:] + v[:-1]) * dt, axis=0)]
    )
    p = np.column_stack([xy, 0.5 + 0.2 * np.sin(2 * np.pi * t / 35.0)])
    return SplineTrajectory.fit(
        t, p, rot_to_quat(_yaw_only(yaw)), knot_dt=knot_dt, t0_ns=DEFAULT_T0_NS, name="far-field"
    )


def handheld_trajectory(duration: float = 120.0, knot_dt: float = DEFAULT_KNOT_DT) -> SplineTrajectory:
    """A handheld sensor rig carried around a ~6 m x 5 m room at up to ~1 m/s: a wandering clockwise loop (30 s
    per lap), the rig raised and lowered between ~0.9 and ~1.7 m, heading round the loop with +-35 deg pans,
    pitch and roll swinging by ~12 deg, and the walk's bounce."""
    t = np.arange(0.0, duration + 1e-9, 0.02)
    phase = _eased_phase(t, 1.0, 3.0)
    a = 2 * np.pi * phase

    p = np.stack(
        [
            2.6 * np.sin(a / 30.0) + 0.5 * np.sin(a / 11.0),
            2.0 * np.cos(a / 30.0) * np.cos(a / 47.0) + 0.3 * np.sin(a / 7.0),
            1.3 - 0.35 * np.cos(a / 9.0) + 0.03 * np.sin(a / 0.55),
        ],
        axis=1,
    )
    yaw = -a / 30.0 + 0.6 * np.sin(a / 5.0)  # along the (clockwise) loop, panning
    pitch = 0.1 + 0.2 * np.sin(a / 6.3)
    roll = 0.2 * np.sin(a / 4.1 + 1.0)
    return SplineTrajectory.fit(
        t, p, rot_to_quat(_euler(yaw, pitch, roll)), knot_dt=knot_dt, t0_ns=DEFAULT_T0_NS, name="handheld"
    )


BUILTIN = {
    DEFAULT_NAME: default_trajectory,
    "planar": planar_trajectory,
    "campus": campus_trajectory,
    "climb": climb_trajectory,
    "far-field": far_field_trajectory,
    "handheld": handheld_trajectory,
}
