"""MSCKF visual-inertial odometry with first-estimate Jacobians (FEJ).

State: the navigation variable ``"imu"`` (ImuState, ``Kind.NAV``) plus stochastic clones ``"clone/<t_ns>"``
(``Kind.CLONE``: the pose of the IMU at each camera frame). The estimator is fed by `driver.run_estimator`
(`open` reads the IMU, `process_frame` per camera frame, `process_range` per UWB range). Per camera frame:
propagate to the frame, clone, update with the selected feature tracks, marginalise the oldest clone when the
window is full.

Feature selection (OpenVINS style): a track is used once, when it is lost (not seen in the current frame) or
when the oldest clone is about to be marginalised and the track has an observation in it; in both cases with at
least ``min_track_length`` observations. A used track is deleted from the database (a feature id that keeps
being tracked starts a new track), so no observation is used twice.

Per update, all selected features are processed in batches: linear triangulation (sum of the projectors orthogonal
to the bearings) and Gauss-Newton in world xyz, Jacobians in distorted pixel space (clone columns at the clones'
first estimates when FEJ is on, feature at its triangulated value), left-nullspace projection of the feature
Jacobian (batched QR per track length), a chi-squared test per feature, stacking, QR compression when there are
more rows than clone columns, and one ``ekf_update``.

SLAM features (``max_slam_features`` > 0, OpenVINS): a selected track that is still seen in the current frame and
reached the oldest clone becomes a landmark in the state (``Kind.LANDMARK``, world xyz) instead of an MSCKF
feature, while there is room: its feature Jacobian's invertible part defines the landmark and its
cross-covariances, the rest updates the state (`State.initialize`). It is then updated in every frame that sees it
(residual at the current estimates, Jacobians at the first estimates of clone and landmark), and marginalised when
its track ends or fails the chi-squared test. OpenVINS keeps SLAM features in anchored inverse depth, which
linearises well at any depth; in world xyz the first estimate must be close, so a track becomes a landmark only
when its pixels fix its depth to ``slam_max_depth_sigma`` of its distance (`landmark_sigma`): the tracks of a
rotation in place or of a slow start (depth uncertain by its own size) stay MSCKF features.
"""

from __future__ import annotations

import logging
from collections import deque
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np
from scipy.linalg.lapack import dpstrf, dtrtrs

from uwbcal.pipeline.core.errors import InputError
from uwbcal.pipeline.core.geometry import I3, exp_so3, quat_slerp, quat_to_rot, skew
from uwbcal.pipeline.core.state import (
    ImuState,
    Kind,
    Pose,
    State,
    Vec,
    add_probe,
    chi2_ppf,
    chi2_quantile,
    ekf_update,
    remove_probes,
)
from uwbcal.pipeline.core.topics import (
    TOPIC_FEATURES,
    TOPIC_GT_IMU_BIAS,
    TOPIC_GT_POSE,
    TOPIC_IMU,
    TOPIC_RANGE,
)
from uwbcal.pipeline.vio.camera import Camera
from uwbcal.pipeline.vio.config import VioConfig
from uwbcal.pipeline.vio.estimator import RangeHandler, RangeMeasurement, Span, TrajectoryRecord
from uwbcal.pipeline.vio.imu import GRAVITY, ImuNoise, imu_intervals, propagate, propagate_static

if TYPE_CHECKING:
    from uwbcal.convert.recording import RecordingReader

_log = logging.getLogger(__name__)


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


# ---------------------------------------------------------------------------------------------------------------
# feature database
# ---------------------------------------------------------------------------------------------------------------
@dataclass
class FeatureDatabase:
    """Observations in the window as columns: frame stamp, track id, raw pixels, undistorted normalised."""

    t: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    ids: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    uv: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    xy: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))

    def add(self, t_ns: int, ids: np.ndarray, uv: np.ndarray, xy: np.ndarray) -> None:
        self.t = np.concatenate([self.t, np.full(len(ids), t_ns, np.int64)])
        self.ids = np.concatenate([self.ids, ids])
        self.uv = np.concatenate([self.uv, uv])
        self.xy = np.concatenate([self.xy, xy])

    def keep(self, mask: np.ndarray) -> None:
        self.t, self.ids, self.uv, self.xy = self.t[mask], self.ids[mask], self.uv[mask], self.xy[mask]

    def select(
        self, t_now: int, t_oldest: int | None, min_len: int, max_features: int
    ) -> tuple[np.ndarray, np.ndarray]:
        """Observation rows of the tracks to use now, and a mask of the rows to delete afterwards."""
        if len(self.ids) == 0:
            return np.zeros(0, np.int64), np.zeros(0, bool)
        uid, inv, counts = np.unique(self.ids, return_inverse=True, return_counts=True)
        seen_now = np.zeros(len(uid), bool)
        seen_now[inv[self.t == t_now]] = True
        lost = ~seen_now
        cand = lost.copy()
        if t_oldest is not None:
            in_oldest = np.zeros(len(uid), bool)
            in_oldest[inv[self.t == t_oldest]] = True
            cand |= in_oldest
        use = cand & (counts >= min_len)
        if use.sum() > max_features:
            order = np.argsort(-counts[use], kind="stable")
            idx = np.flatnonzero(use)[order[:max_features]]
            use = np.zeros(len(uid), bool)
            use[idx] = True
        rows = np.flatnonzero(use[inv])
        drop = (lost | use)[inv]
        return rows, drop


# ---------------------------------------------------------------------------------------------------------------
# batched feature math
# ---------------------------------------------------------------------------------------------------------------
def triangulate(
    R_wc: np.ndarray,
    p_wc: np.ndarray,
    C: np.ndarray,
    xy: np.ndarray,
    valid: np.ndarray,
    iterations: int = 4,
    min_parallax_rad: float = 0.0,
) -> tuple[np.ndarray, np.ndarray]:
    """Batched triangulation of F features on the padded layout.

    ``R_wc, p_wc``: camera poses (world_from_camera) per clone; ``C`` (F, M): clone index of each observation
    slot, ``xy`` (F, M, 2) normalised undistorted observations, ``valid`` (F, M) which slots hold one. Linear
    solution (sum of the projectors orthogonal to the bearings), then Gauss-Newton on the normalised
    reprojection error in world xyz. Returns points (F, 3) and a mask of well-conditioned features (F,): the
    RMS angle of the bearings about their mean, sqrt(min/max eigenvalue of the projector sum), must exceed
    ``min_parallax_rad`` (small-parallax tracks linearise badly and make the filter overconfident).
    """
    F, M = C.shape
    wv = valid.astype(float)[..., None, None]
    Rw = R_wc[C]  # (F, M, 3, 3)
    pw = p_wc[C]
    b = np.einsum("fmij,fmj->fmi", Rw, np.concatenate([xy, np.ones((F, M, 1))], axis=-1))
    b /= np.linalg.norm(b, axis=-1, keepdims=True)
    A = (I3 - b[..., :, None] * b[..., None, :]) * wv
    As = A.sum(axis=1)
    rhs = np.einsum("fmij,fmj->fi", A, pw)
    ev = np.linalg.eigvalsh(As)
    ok = ev[:, 0] > max(1e-7, min_parallax_rad**2) * np.maximum(ev[:, 2], 1e-12)
    As[~ok] = I3
    pf = np.linalg.solve(As, rhs[..., None])[..., 0]
    Rcw = np.swapaxes(Rw, -1, -2)
    Rcw_xy, Rcw_z = Rcw[..., :2, :], Rcw[..., 2:3, :]
    w_r, w_z = wv[..., 0], wv[..., 0, 0]
    eye_eps = 1e-9 * I3
    for _ in range(iterations):
        pc = np.einsum("fmij,fmj->fmi", Rcw, pf[:, None, :] - pw)
        z = pc[..., 2]
        zs = np.where(np.abs(z) < 1e-9, 1e-9, z)
        nrm = pc[..., :2] / zs[..., None]
        r = (xy - nrm) * w_r
        # d normalised / d pf = ([[1, 0, -x], [0, 1, -y]] / z) R_cw, written out row by row
        J = (Rcw_xy - nrm[..., None] * Rcw_z) * (w_z / zs)[..., None, None]
        J2 = J.reshape(F, 2 * M, 3)
        J2t = np.swapaxes(J2, 1, 2)
        Hn = J2t @ J2
        Hn += (1e-9 * np.trace(Hn, axis1=1, axis2=2))[:, None, None] * I3 + eye_eps
        g = (J2t @ r.reshape(F, 2 * M, 1))[..., 0]
        bad = ~(ok & np.isfinite(Hn).all(axis=(1, 2)) & np.isfinite(g).all(axis=1))
        if bad.any():
            Hn[bad] = I3
            g[bad] = 0.0
        try:
            step = np.linalg.solve(Hn, g[..., None])[..., 0]
        except np.linalg.LinAlgError:
            step = (np.linalg.pinv(Hn) @ g[..., None])[..., 0]
        pf = pf + step
    ok &= np.isfinite(pf).all(axis=1)
    return pf, ok


def compress_normal(H: np.ndarray, r: np.ndarray, rel_tol: float = 1e-12) -> tuple[np.ndarray, np.ndarray]:
    """Measurement compression through the information matrix: ``Hc^T Hc = H^T H``, ``Hc^T rc = H^T r``.

    Same information as the QR compression (`compress`) with one Gram product and a pivoted Cholesky
    factorisation ``G = P U^T U P^T`` (LAPACK ``dpstrf``, rank-revealing) instead of a QR of all stacked rows:
    ``Hc = U P^T`` with the rank's rows. Directions without information (the MSCKF gauge, clones no feature
    saw), i.e. pivots below ``rel_tol`` times the largest diagonal of G, are dropped. 4x cheaper than an
    eigendecomposition of G (0.3 vs 1.3 ms at 90 clone columns on one core).
    """
    if H.shape[0] <= H.shape[1]:
        return H, r
    G = H.T @ H
    b = H.T @ r
    U, piv, rank, info = dpstrf(G, tol=rel_tol * max(float(G.diagonal().max()), 1e-300), lower=0)
    if info < 0:
        raise FloatingPointError(f"dpstrf failed (info {info})")
    piv = piv - 1  # Fortran's 1-based permutation
    U = np.triu(U[:rank])
    Hc = np.empty_like(U)
    Hc[:, piv] = U
    # U[:, :rank]^T rc = b[piv]: the LAPACK call scipy's ``solve_triangular(..., trans="T")`` makes, without its
    # ~30 us of wrappers (a C-ordered matrix goes in transposed, as scipy passes it: the same numbers)
    Ur = U[:, :rank]
    if Ur.flags.f_contiguous:
        rc, info = dtrtrs(Ur, b[piv[:rank]], lower=0, trans=1)
    else:
        rc, info = dtrtrs(Ur.T, b[piv[:rank]], lower=1, trans=0)
    if info != 0:
        raise FloatingPointError(f"dtrtrs failed (info {info})")
    return Hc, rc


def _camera_points(
    cam: Camera, R_wi: np.ndarray, p_wi: np.ndarray, pf: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """IMU-frame and camera-frame points (K, 3) of world points ``pf`` seen from IMU poses ``R_wi, p_wi``, and
    ``R_wi^T``."""
    Rt = np.swapaxes(R_wi, 1, 2)
    p_i = np.einsum("kij,kj->ki", Rt, pf - p_wi)
    p_c = (p_i - cam.p_imu_cam) @ cam.R_imu_cam
    return p_i, p_c, Rt


def predict_pixels(
    cam: Camera, R_wi: np.ndarray, p_wi: np.ndarray, pf: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Pixel prediction (K, 2) and camera-frame points (K, 3): `feature_jacobians` without the Jacobians (the
    residual at the current estimates when the Jacobians are taken at the first estimates)."""
    p_c = _camera_points(cam, R_wi, p_wi, pf)[1]
    return cam.project(p_c), p_c


def feature_jacobians(
    cam: Camera,
    R_wi: np.ndarray,
    p_wi: np.ndarray,
    pf: np.ndarray,
    pixels: bool = True,
) -> tuple[np.ndarray | None, np.ndarray, np.ndarray, np.ndarray]:
    """Pixel prediction and Jacobians of one observation per row.

    ``R_wi, p_wi`` (K, 3, 3)/(K, 3): the clone (IMU) pose of each observation; ``pf`` (K, 3): the feature in the
    world. Returns ``uv`` (K, 2; None with ``pixels=False``), ``H_pose`` (K, 2, 6) wrt the clone error
    [dtheta, dp] (right perturbation), ``H_f`` (K, 2, 3) wrt the feature, and the camera-frame points (K, 3).
    """
    p_i, p_c, Rt = _camera_points(cam, R_wi, p_wi, pf)
    Rci = cam.R_imu_cam.T
    uv, Jp = cam.project_jacobian(p_c, pixels)
    JR = Jp @ Rci
    H_pose = np.empty((len(pf), 2, 6))
    H_pose[:, :, 0:3] = JR @ skew(p_i)
    H_f = JR @ Rt
    H_pose[:, :, 3:6] = -H_f
    return uv, H_pose, H_f, p_c


def observe(
    cam: Camera,
    R_wi: np.ndarray,
    p_wi: np.ndarray,
    pf: np.ndarray,
    at: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """`feature_jacobians` with FEJ: the pixel prediction and camera-frame points at the current estimates
    (``R_wi, p_wi, pf``), the Jacobians at the linearisation point ``at`` = (R_wi, p_wi, pf) of the first
    estimates, or at the current estimates when ``at`` is None."""
    if at is None:
        return feature_jacobians(cam, R_wi, p_wi, pf)
    uv, p_c = predict_pixels(cam, R_wi, p_wi, pf)
    _, H_pose, H_f, _ = feature_jacobians(cam, *at, pixels=False)
    return uv, H_pose, H_f, p_c


def landmark_sigma(H_f: np.ndarray) -> np.ndarray:
    """The largest standard deviation of a landmark on its observations alone: ``H_f`` (k, 2m, 3) whitened
    Jacobians of each track wrt its point; (H_f^T H_f)^-1 is the point's covariance with the poses known, its
    weakest direction the depth (inf when the track does not fix the point)."""
    ev = np.linalg.eigvalsh(np.swapaxes(H_f, 1, 2) @ H_f)[:, 0]
    with np.errstate(divide="ignore"):
        return 1.0 / np.sqrt(np.maximum(ev, 0.0))


def nullspace_project(
    H_f: np.ndarray,
    H_pose: np.ndarray,
    C: np.ndarray,
    n_clones: int,
    r: np.ndarray,
    valid: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Project K features' stacked measurements onto the left nullspace of their feature Jacobians.

    ``H_f`` (K, 2m, 3); ``H_pose`` (K, m, 2, 6): observation j of feature k wrt the error of its clone
    ``C[k, j]`` (a clone at most once per feature; slots with ``valid`` False are ignored); ``r`` (K, 2m).
    Returns ``Ho`` (K, 2m-3, 6 n_clones) and ``ro`` (K, 2m-3). The projection is applied to the m 2x6 blocks
    and the clone columns are assembled afterwards, i.e. without the product with a dense (2m, 6 n_clones)
    Jacobian that is zero outside the feature's clones.
    """
    K, two_m, _ = H_f.shape
    m, q = two_m // 2, two_m - 3
    Qm = np.linalg.qr(H_f, mode="complete")[0]
    Nt = np.swapaxes(Qm[:, :, 3:], 1, 2)  # (K, q, 2m)
    N4 = Nt.reshape(K, q, m, 2)
    # (K, q, m, 6): the projected 2x6 block of each observation, its two products written out in the layout of
    # Ho (the numbers of einsum "kqmi,kmij->kqmj", at half its cost)
    blocks = N4[..., 0, None] * H_pose[:, None, :, 0, :] + N4[..., 1, None] * H_pose[:, None, :, 1, :]
    if m == n_clones and (valid is None or valid.all()) and (C == np.arange(m)).all():
        # every feature seen in every clone, in clone order (the usual case at a full window): Ho is the blocks
        return blocks.reshape(K, q, 6 * n_clones), (Nt @ r[..., None])[..., 0]
    cols = C if valid is None else np.where(valid, C, n_clones)  # ignored slots go to a dropped column
    Ho = np.zeros((K, q, n_clones + 1, 6))
    Ho[np.arange(K)[:, None], :, cols] = np.swapaxes(blocks, 1, 2)
    Ho = Ho[:, :, :n_clones].reshape(K, q, 6 * n_clones)
    return Ho, (Nt @ r[..., None])[..., 0]


def compress(H: np.ndarray, r: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """QR measurement compression: same information with at most ``H.shape[1]`` rows."""
    n = H.shape[1]
    if H.shape[0] <= n:
        return H, r
    Rm = np.linalg.qr(np.column_stack([H, r]), mode="r")
    return Rm[:n, :n], Rm[:n, n]


# ---------------------------------------------------------------------------------------------------------------
# estimator
# ---------------------------------------------------------------------------------------------------------------
@dataclass
class _Tracks:
    """Feature tracks linearised on the padded (feature, observation) layout (`MsckfEstimator._linearize`)."""

    ids: np.ndarray  # (F,) track ids
    counts: np.ndarray  # (F,) observations
    rows: np.ndarray  # (F, M) database rows (slots past counts repeat the first)
    C: np.ndarray  # (F, M) clone index of each slot
    valid: np.ndarray  # (F, M) slot holds an observation
    last_t: np.ndarray  # (F,) stamp of the last observation
    pts: np.ndarray  # (F, 3) triangulated world points
    good: np.ndarray  # (F,) triangulated, in front of every camera
    r: np.ndarray  # (F, 2M) residuals / pixel_sigma (0 in empty slots)
    H_f: np.ndarray  # (F, 2M, 3) wrt the feature
    H_pose: np.ndarray  # (F, M, 2, 6) wrt the slot's clone
    names: list[str]  # clone names, in clone-index order


def _landmark_name(track_id: int) -> str:
    return f"landmark/{track_id}"


def _clone_name(t_ns: int) -> str:
    return f"clone/{t_ns}"


def _interp_pose(t: np.ndarray, p: np.ndarray, q: np.ndarray, t0: int) -> tuple[np.ndarray, np.ndarray]:
    i = int(np.clip(np.searchsorted(t, t0) - 1, 0, len(t) - 2))
    s = float(np.clip((t0 - t[i]) / max(t[i + 1] - t[i], 1), 0.0, 1.0))
    pos = (1 - s) * p[i] + s * p[i + 1]
    quat = quat_slerp(q[i : i + 1], q[i + 1 : i + 2], np.array([s]))[0]
    return quat_to_rot(quat), pos


def _truth_biases(truth: dict | None) -> tuple[np.ndarray, np.ndarray]:
    bg = np.zeros(3)
    ba = np.zeros(3)
    if not truth:
        return bg, ba
    src = truth.get("imu", truth)
    for key in ("gyroscope_bias", "gyro_bias", "bias_gyro", "bg"):
        if key in src:
            bg = np.asarray(src[key], float).reshape(3)
            break
    for key in ("accelerometer_bias", "accel_bias", "acc_bias", "bias_acc", "ba"):
        if key in src:
            ba = np.asarray(src[key], float).reshape(3)
            break
    return bg, ba


def groundtruth_state(reader: RecordingReader, t0_ns: int) -> ImuState:
    """IMU state at ``t0_ns`` from /groundtruth/pose (velocity: local quadratic fit) and the biases of
    /groundtruth/imu_bias (real data, e.g. EuRoC's estimate; interpolated at t0) or of uwbcal.truth (simulation);
    zero when neither is there."""
    topics = reader.topics()
    if TOPIC_GT_POSE not in topics:
        raise InputError(
            f"{reader.path}: vio.init_from_groundtruth is set but there is no '{TOPIC_GT_POSE}' topic; "
            "use the static initialiser (vio.init_from_groundtruth = false)"
        )
    gt = reader.read_poses(TOPIC_GT_POSE)
    if len(gt.t_ns) < 3 or t0_ns < gt.t_ns[0] or t0_ns > gt.t_ns[-1]:
        raise InputError(f"{reader.path}: {TOPIC_GT_POSE}: does not cover the start time {t0_ns}")
    R, p = _interp_pose(gt.t_ns, gt.p, gt.q_xyzw, t0_ns)
    ts = (gt.t_ns - gt.t_ns[0]) * 1e-9
    i = int(np.clip(np.searchsorted(gt.t_ns, t0_ns), 1, len(ts) - 2))
    # velocity: slope of a local least-squares line over ~ +-20 ms (robust to GT stamp jitter)
    tc = (t0_ns - gt.t_ns[0]) * 1e-9
    sel = np.flatnonzero(np.abs(ts - tc) <= max(0.02, 1.5 * (ts[i + 1] - ts[i - 1])))
    tt = ts[sel] - tc
    v = (
        np.polyfit(tt, gt.p[sel], 2)[1]
        if len(sel) >= 3
        else (gt.p[i + 1] - gt.p[i - 1]) / (ts[i + 1] - ts[i - 1])
    )
    lever = np.asarray(reader.calibration.get("groundtruth", {}).get("lever_arm", [0, 0, 0]), float)
    p = p - R @ lever
    bg, ba = _truth_biases(reader.truth)
    if TOPIC_GT_IMU_BIAS in topics:
        b = reader.read_imu(TOPIC_GT_IMU_BIAS)
        if len(b.t_ns):
            j = int(np.clip(np.searchsorted(b.t_ns, t0_ns) - 1, 0, max(len(b.t_ns) - 2, 0)))
            k = min(j + 1, len(b.t_ns) - 1)
            s = float(np.clip((t0_ns - b.t_ns[j]) / max(b.t_ns[k] - b.t_ns[j], 1), 0.0, 1.0))
            bg = (1 - s) * b.gyro[j] + s * b.gyro[k]
            ba = (1 - s) * b.acc[j] + s * b.acc[k]
    return ImuState(R, p, np.asarray(v, float), bg, ba)


class MsckfEstimator:
    """The MSCKF pose source (Estimator protocol)."""

    keeps_probes = True

    def __init__(
        self,
        config: VioConfig,
        camera: Camera,
        noise: ImuNoise,
        initial: ImuState | None = None,
        initial_cov: np.ndarray | None = None,
    ) -> None:
        self.config = config
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
        self._chi2 = chi2_quantile(config.chi2_quantile, np.maximum(np.arange(2 * config.max_clones + 8), 1))
        self._static: tuple[int, int] | None = None  # (t0, t1): propagate with the zero-motion model in it
        # disparity reference: ids, pixels and the IMU orientation estimate of the last MSCKF frame
        self._last_frame: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None
        self._last_frame_t = -1
        # the recent frames (t, ids, pixels, orientation), every frame, static or not: the disparity reference when
        # the last MSCKF frame is younger than vio.zupt_disparity_baseline_s
        self._recent: deque[tuple[int, np.ndarray, np.ndarray, np.ndarray]] = deque()
        self._ref_xy: tuple[np.ndarray, np.ndarray] | None = None  # `_undistorted`: ids of the frame, its xy
        self.source = "recording"
        self._probe_period_ns: int | None = None  # pose probes for the UWB initialisation (start_probes)
        self._last_probe_ns: int | None = None

    # -- construction ------------------------------------------------------------------------------------------
    @classmethod
    def from_recording(
        cls,
        reader: RecordingReader,
        config: VioConfig | None = None,
        initial: ImuState | None = None,
        initial_cov: np.ndarray | None = None,
    ) -> MsckfEstimator:
        """``initial`` (and its 15x15 covariance ``initial_cov``, e.g. from the static initialiser) replaces
        the ground-truth initial state; without ``initial_cov`` the vio.sigma_*0 settings are used."""
        config = config or VioConfig()
        src = str(getattr(reader, "path", "recording"))
        calib = reader.calibration
        cam = Camera.from_calibration(calib, "cam0", src)
        noise = ImuNoise.from_calibration(calib, src, config.imu_noise_inflation)
        est = cls(config, cam, noise, initial, initial_cov)
        est.source = src
        if initial is None and not config.init_from_groundtruth:
            raise InputError(
                f"{src}: the MSCKF needs an initial IMU state: set vio.init_from_groundtruth (simulation) or "
                "pass one from the static initialiser"
            )
        return est

    def _initialize(self, reader: RecordingReader, t0_ns: int) -> None:
        x0 = self.initial if self.initial is not None else groundtruth_state(reader, t0_ns)
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

    # -- zero-velocity update ----------------------------------------------------------------------------------
    def _zupt_model(
        self, gyro: np.ndarray, acc: np.ndarray, x: ImuState, fej_R: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Per-sample residuals (n, 6) of the IMU at rest, their Jacobian (6, 15) and noise variances (6,).

        At rest ``w_m = b_g + n_g`` and ``a_m = b_a - R^T g + n_a``; with ``R = R_hat Exp(dtheta)`` the
        residual ``[w_m - b_g_hat, a_m - b_a_hat + R_hat^T g]`` is ``[dbg, dba - [R^T g]x dtheta] + n``. The
        orientation column is taken at the first estimate (FEJ): it has no component along the global yaw.
        """
        r = np.concatenate([gyro - x.bg, acc - x.ba + x.R.T @ GRAVITY], axis=1)
        H = np.zeros((6, 15))
        H[0:3, 9:12] = np.eye(3)
        H[3:6, 0:3] = -skew(fej_R.T @ GRAVITY)
        H[3:6, 12:15] = np.eye(3)
        k = self.config.zupt_noise_inflation**2 * self.noise.rate_hz  # sigma^2 / dt per sample, inflated
        var = np.repeat([k * self.noise.sigma_g**2, k * self.noise.sigma_a**2], 3)
        return r, H, var

    def _imu_samples(self, t0: int, t1: int, imu_t: np.ndarray) -> slice:
        return slice(int(np.searchsorted(imu_t, t0, "right")), int(np.searchsorted(imu_t, t1, "right")))

    def _detect_static(
        self, t_ns: int, ids: np.ndarray, uv: np.ndarray, imu_t: np.ndarray, gyro: np.ndarray, acc: np.ndarray
    ) -> bool:
        """Zero velocity over (t_ref, t_ns]? (t_ref: the last frame, `_zupt_reference`; the tests use the state
        there.) All of:

        - the estimated speed is small and v = 0 passes a chi-squared test with the state covariance (a slow
          constant velocity looks like rest to the IMU);
        - the IMU samples pass a chi-squared test of the at-rest model (with the state covariance);
        - with at least ``zupt_min_features`` tracks in common with the reference frame, their disparity is
          pixel noise (chi-squared). The reference is the last frame that went through the MSCKF (static frames
          do not replace it), so that a slow drift accumulates disparity instead of hiding below the noise, and
          at least ``zupt_disparity_baseline_s`` before this frame (`_disparity_reference`): the first frame of a
          slow motion must not be compared with the frame just before it only. The reference pixels are turned by
          the rotation between the frames (`_derotate`): zero velocity, not zero rotation, is tested.

        The disparity test alone is not enough: with 1 px noise and tracks ~10 m away, slow flight (a few cm/s)
        passes it (false ZUPTs; docs/results/measurements.md). The IMU test rejects rotor vibration of a MAV
        standing on the ground (far above the white-noise model), so there the ZUPT only fires in the quieter
        intervals.
        """
        cfg = self.config
        t_ref, x, fej_R, P_imu = self._zupt_ref
        if float(np.linalg.norm(x.v)) > cfg.zupt_max_velocity:
            return False
        v_cov = P_imu[6:9, 6:9] + cfg.zupt_sigma_v**2 * np.eye(3)
        if float(x.v @ np.linalg.solve(v_cov, x.v)) > chi2_ppf(cfg.zupt_chi2_quantile, 3):
            return False
        sl = self._imu_samples(t_ref, t_ns, imu_t)
        n = sl.stop - sl.start
        if n < 2:
            return False
        r, H, var = self._zupt_model(gyro[sl], acc[sl], x, fej_R)
        # The stacked residual splits into two independent parts (no 6n x 6n matrix): the deviations from the
        # sample mean are white, sum |r_i - r_mean|^2_R ~ chi2(6 (n - 1)), and the mean carries the state
        # uncertainty, r_mean^T (H P H^T + R / n)^-1 r_mean ~ chi2(6). Their sum is the test of the at-rest model
        # (vibration shows in the deviations); the mean is also tested on its own: a mean angular rate or
        # acceleration is motion, and in the 6n-dof sum its 6 dof drown: the slow start of a motion
        # (acceleration growing from zero) passed as rest for several frames, the ZUPT pinning v = 0 while the
        # platform already moved at centimetres per second.
        rm = r.mean(axis=0)
        S = H @ P_imu @ H.T + np.diag(var / n)
        mean = float(rm @ np.linalg.solve(S, rm))
        q = cfg.zupt_chi2_quantile
        if mean > chi2_ppf(q, 6) or mean + float((((r - rm) ** 2) / var).sum()) > chi2_ppf(q, 6 * n):
            return False
        ref = self._disparity_reference(t_ns)
        if ref is not None and len(ids):
            ids0, uv0, R0 = ref
            common, i0, i1 = np.intersect1d(ids0, ids, assume_unique=False, return_indices=True)
            if len(common) >= cfg.zupt_min_features:
                # the orientation now: the state's at the last frame and the mean gyro since (a few samples)
                R1 = x.R @ exp_so3((gyro[sl].mean(axis=0) - x.bg) * ((t_ns - t_ref) * 1e-9))
                uv_ref = self._derotate(self._undistorted(ids0, uv0)[i0], R0, R1)
                d2 = float(((uv[i1] - uv_ref) ** 2).sum()) / (2.0 * cfg.pixel_sigma**2)
                return d2 < chi2_ppf(cfg.zupt_chi2_quantile, 2 * len(common))
        return True

    def _undistorted(self, ids: np.ndarray, uv: np.ndarray) -> np.ndarray:
        """``camera.undistort(uv)`` of a reference frame, once per frame (in a static stretch the reference
        stays the same frame for many frames)."""
        if self._ref_xy is None or self._ref_xy[0] is not ids:
            self._ref_xy = (ids, self.camera.undistort(uv))
        return self._ref_xy[1]

    def _derotate(self, xy: np.ndarray, R_ref: np.ndarray, R_now: np.ndarray) -> np.ndarray:
        """Undistorted points ``xy`` of the reference frame in pixels as the camera would see them now after a
        rotation only (IMU orientations ``R_ref`` -> ``R_now``): the disparity test is of zero *velocity*, and a
        platform at rest still turns a little (V1_01 on the ground: 0.05-0.08 deg in 0.3 s, 0.4-0.6 px, enough
        to fail the test over that baseline); the camera's displacement from the rotation about the IMU (lever
        arm x angle) is left out."""
        Ric = self.camera.R_imu_cam
        R = Ric.T @ R_now.T @ R_ref @ Ric  # camera_now <- camera_ref
        b = np.column_stack([xy, np.ones(len(xy))]) @ R.T
        return self.camera.project(b)

    def _disparity_reference(self, t_ns: int) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
        """The frame the disparity test compares with: the last MSCKF frame, or, when that one is younger than
        ``zupt_disparity_baseline_s``, the newest recent frame at least that old (the oldest kept at the start).

        Over one frame (50 ms at 20 Hz) a platform that has just started to move at 0.1 m/s shifts features a
        few metres away by ~0.5 px, inside the 1 px noise of the two frames: the test passed and the ZUPT pinned
        v = 0 while the MAV was climbing at 0.1 m/s (hybrid V1_01 take-off, the MSCKF then diverged). Over
        0.3 s the same motion shows as ~4 px."""
        if self._last_frame is None:
            return None
        if t_ns - self._last_frame_t >= self.config.zupt_disparity_baseline_s * 1e9 or not self._recent:
            return self._last_frame
        t_old = t_ns - self.config.zupt_disparity_baseline_s * 1e9
        ref = self._recent[0]
        for fr in self._recent:  # a handful of frames, oldest first
            if fr[0] > t_old:
                break
            ref = fr
        return ref[1:]

    def _keep_recent(self, t_ns: int, ids: np.ndarray, uv: np.ndarray, R: np.ndarray) -> None:
        """Append the frame to the recent ones; drop those no longer needed as a disparity reference."""
        self._recent.append((t_ns, ids, uv, R))
        t_old = t_ns - self.config.zupt_disparity_baseline_s * 1e9
        while len(self._recent) > 1 and self._recent[1][0] <= t_old:
            self._recent.popleft()

    def _zupt(self, t0: int, t1: int, imu_t: np.ndarray, gyro: np.ndarray, acc: np.ndarray) -> None:
        """The zero-velocity update of (t0, t1] through `ekf_update`: the mean of the at-rest residuals (same
        Jacobian for every sample, so the mean carries all their information) and v = 0."""
        Hz = np.zeros((3, 15))
        Hz[:, 6:9] = np.eye(3)
        rz = -self.state.value("imu").v
        Rz = np.full(3, self.config.zupt_sigma_v**2)
        if self.config.zupt_imu:
            sl = self._imu_samples(t0, t1, imu_t)
            r, H, var = self._zupt_model(gyro[sl], acc[sl], self.state.value("imu"), self.state.fej("imu").R)
            Hz = np.vstack([H, Hz])
            rz = np.concatenate([r.mean(axis=0), rz])
            Rz = np.concatenate([var / len(r), Rz])
        ekf_update(self.state, {"imu": Hz}, rz, np.diag(Rz))
        self.stats.zupt_updates += 1
        self.stats.zupt_time_s += (t1 - t0) * 1e-9

    # -- camera update -----------------------------------------------------------------------------------------
    def _camera_frame(self, t_ns: int, ids: np.ndarray, uv: np.ndarray, trace: dict | None) -> None:
        self.stats.frames += 1
        x = self.state.value("imu")
        J = np.zeros((6, 15))
        J[:, :6] = np.eye(6)
        self.state.augment(_clone_name(t_ns), Pose(x.R, x.p), {"imu": J}, kind=Kind.CLONE, key=int(t_ns))
        ok = np.isfinite(uv).all(axis=1)
        if not ok.all():
            ids, uv = ids[ok], uv[ok]
        if len(ids) > 1 and not (ids[1:] > ids[:-1]).all():  # unsorted or duplicate ids: keep the first
            _, first = np.unique(ids, return_index=True)
            ids, uv = ids[first], uv[first]
        ids, uv = self._slam_frame(t_ns, ids, uv)
        if len(ids) == 0:
            self.stats.frames_without_features += 1
        else:
            self.db.add(t_ns, ids, uv, self.camera.undistort(uv))
        oldest = self.clones[0] if len(self.clones) > self.config.max_clones else None
        rows, drop = self.db.select(
            t_ns, oldest, self.config.min_track_length, self.config.max_features_per_update
        )
        if len(rows):
            self._update(rows, t_ns, trace)
        keep = ~drop
        if oldest is not None:
            self.state.remove(_clone_name(oldest))
            keep &= self.db.t != oldest
        self.db.keep(keep)

    def _linearize(self, rows: np.ndarray) -> _Tracks:
        """Triangulate the tracks of the database ``rows`` at the current clone estimates and linearise their
        observations (residuals at the current estimates, Jacobians at the first estimates when FEJ is on), in
        pixels divided by ``pixel_sigma`` (unit noise)."""
        cfg = self.config
        db = self.db
        rows = rows[np.lexsort((db.t[rows], db.ids[rows]))]
        # the ids sorted: the tracks' lengths from where the id changes (np.unique without its sort)
        sid = db.ids[rows]
        new_track = np.empty(len(sid), bool)
        new_track[:1] = True
        np.not_equal(sid[1:], sid[:-1], out=new_track[1:])
        starts = np.flatnonzero(new_track)
        counts = np.diff(starts, append=len(sid))
        nf = len(starts)
        M = int(counts.max())
        # padded (feature, observation) layout: slot j < counts[f] holds an observation, the rest are masked
        valid = np.arange(M)[None, :] < counts[:, None]
        O = np.where(valid, starts[:, None] + np.arange(M)[None, :], starts[:, None])
        orow = rows[O]
        clones = self.state.clones
        clone_t = np.array([t for t, _ in clones], np.int64)
        C = np.searchsorted(clone_t, db.t[orow])  # (F, M) clone index
        names = [n for _, n in clones]
        cur = [self.state.value(n) for n in names]
        Rc = np.stack([c.R for c in cur])
        pc = np.stack([c.p for c in cur])
        cam = self.camera
        pts, ok = triangulate(
            Rc @ cam.R_imu_cam,
            pc + Rc @ cam.p_imu_cam,
            C,
            db.xy[orow],
            valid,
            cfg.triangulation_iterations,
            np.radians(cfg.min_parallax_deg),
        )
        Cf = C.reshape(-1)
        pf_rep = np.repeat(pts, M, axis=0)
        at = None
        if self.state.use_fej:  # the clones' first estimates; a feature has none (triangulated anew)
            fej = [self.state.fej(n) for n in names]
            at = (np.stack([c.R for c in fej])[Cf], np.stack([c.p for c in fej])[Cf], pf_rep)
        uv_hat, H_pose, H_f, p_c = observe(cam, Rc[Cf], pc[Cf], pf_rep, at)
        vflat = valid.reshape(-1)
        depth_ok = ((p_c[:, 2] > cfg.min_depth) & (p_c[:, 2] < cfg.max_depth)) | ~vflat
        good = ok & np.isfinite(pts).all(axis=1) & depth_ok.reshape(nf, M).all(axis=1)
        w = (vflat / cfg.pixel_sigma)[:, None]
        return _Tracks(
            ids=sid[starts],
            counts=counts,
            rows=orow,
            C=C,
            valid=valid,
            last_t=db.t[rows[starts + counts - 1]],
            pts=pts,
            good=good,
            r=((db.uv[orow].reshape(-1, 2) - uv_hat) * w).reshape(nf, 2 * M),
            H_f=(H_f * w[:, :, None]).reshape(nf, 2 * M, 3),
            H_pose=(H_pose * w[:, :, None]).reshape(nf, M, 2, 6),
            names=names,
        )

    def _update(self, rows: np.ndarray, t_ns: int, trace: dict | None) -> None:
        """MSCKF update with the selected tracks; tracks still seen now and long enough to have reached the
        oldest clone become SLAM features while there is room (`_slam_initialize`) instead."""
        cfg = self.config
        tr = self._linearize(rows)
        good = tr.good
        self.stats.features_failed_triangulation += int((~good).sum())
        if trace is not None:
            trace["t"].append(t_ns)
        if not good.any():
            self._trace(trace, 0, 0, 0.0, None)
            return
        nc = len(tr.names)
        Ho, ro = nullspace_project(tr.H_f[good], tr.H_pose[good], tr.C[good], nc, tr.r[good], tr.valid[good])
        Sidx = self.state.index(tr.names)
        Pcc = self.state.P[Sidx][:, Sidx]  # rows first: a row gather is a copy of rows
        HoP = (Ho.reshape(-1, 6 * nc) @ Pcc).reshape(Ho.shape)  # one GEMM instead of k small ones
        S = HoP @ np.swapaxes(Ho, 1, 2) + np.eye(Ho.shape[1])
        nis = np.einsum("ki,ki->k", ro, np.linalg.solve(S, ro[..., None])[..., 0])
        counts = tr.counts[good]
        accept = nis < self._chi2[2 * counts - 3]
        k = len(ro)
        n_used = int(accept.sum())
        n_rej = k - n_used
        st = self.stats
        st.features_used += n_used
        st.features_rejected_chi2 += n_rej
        st.update_t.append(t_ns)
        st.update_used.append(n_used)
        st.update_rejected.append(n_rej)
        self._trace(trace, n_used, n_rej, float(nis[accept].sum()), tr.pts[good][accept])
        if not n_used:
            return
        slam = np.zeros(k, bool)
        room = cfg.max_slam_features - len(self.state.of_kind(Kind.LANDMARK))
        if room > 0:
            cand = np.flatnonzero(accept & (tr.last_t[good] == t_ns))
            if len(cand):
                cand = cand[self._depth_determined(tr.H_f[good][cand], tr.pts[good][cand], t_ns)]
            slam[cand[np.argsort(-counts[cand], kind="stable")[:room]]] = True
        H, rr = compress_normal(Ho[accept].reshape(-1, 6 * nc), ro[accept].reshape(-1))
        ekf_update(self.state, {n: H[:, 6 * j : 6 * j + 6] for j, n in enumerate(tr.names)}, rr, 1.0)
        self.stats.updates += 1
        if slam.any():
            self._slam_initialize(tr.rows[good][slam], tr.valid[good][slam])

    # -- SLAM features -----------------------------------------------------------------------------------------
    def _depth_determined(self, H_f: np.ndarray, pts: np.ndarray, t_ns: int) -> np.ndarray:
        """Which tracks (their whitened feature Jacobians ``H_f`` (k, 2M, 3) and points) fix their landmark to
        ``slam_max_depth_sigma`` of its distance from the camera, on their pixels alone: a landmark in the state
        keeps the Jacobians of its first estimate, which must be close (a track from a rotation or a slow start
        triangulates with its depth uncertain by its own size, and its next residual is tens of pixels)."""
        x = self.state.value(_clone_name(t_ns))
        depth = np.linalg.norm(pts - (x.p + x.R @ self.camera.p_imu_cam), axis=1)
        return landmark_sigma(H_f) < self.config.slam_max_depth_sigma * depth

    def _slam_initialize(self, orow: np.ndarray, valid: np.ndarray) -> None:
        """Each track of the padded database rows ``orow`` (F, M) becomes a SLAM feature (OpenVINS' delayed
        initialisation, `State.initialize`): its feature Jacobian's invertible part defines the landmark and its
        cross-covariances. The rest of its rows, the left nullspace of the feature Jacobian, is what the MSCKF
        update used just before: with the update first and the landmark defined from the updated state
        (relinearised there) the joint posterior is the one of the landmark first and the rest after (its rows
        carry no information on the old state), at one update per frame instead of one per landmark. Its
        Jacobians are at the first estimates from then on, the landmark's its initial value."""
        tr = self._linearize(orow[valid])
        for f in np.flatnonzero(tr.good):
            m = int(tr.counts[f])  # observations in slots 0..m-1 (the padded layout), one clone each
            H_old: dict[str, np.ndarray] = {}
            for j in range(m):
                Hb = np.zeros((2 * m, 6))
                Hb[2 * j : 2 * j + 2] = tr.H_pose[f, j]
                H_old[tr.names[tr.C[f, j]]] = Hb
            self.state.initialize(
                _landmark_name(int(tr.ids[f])),
                Vec(tr.pts[f]),
                H_old,
                tr.H_f[f, : 2 * m],
                tr.r[f, : 2 * m],
                np.ones(2 * m),
                update_rest=False,
                kind=Kind.LANDMARK,
                key=int(tr.ids[f]),
            )
            self.stats.slam_initialized += 1

    def _slam_frame(self, t_ns: int, ids: np.ndarray, uv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Update with the SLAM features seen in this frame (its clone is in the state), marginalise those not
        seen (lost tracks) and those failing the chi-squared test; returns the other observations."""
        landmarks = dict(self.state.of_kind(Kind.LANDMARK))
        if not landmarks:
            return ids, uv
        seen = np.isin(ids, np.fromiter(landmarks, np.int64, len(landmarks)))
        for key in set(landmarks) - set(ids[seen].tolist()):
            self.state.remove(landmarks.pop(key))
        if seen.any():
            self._slam_update(t_ns, ids[seen], uv[seen], [landmarks[int(i)] for i in ids[seen]])
        return ids[~seen], uv[~seen]

    def _slam_update(self, t_ns: int, ids: np.ndarray, uv: np.ndarray, names: list[str]) -> None:
        cfg = self.config
        st = self.state
        cam = self.camera
        clone = _clone_name(t_ns)
        K = len(ids)
        x = st.value(clone)
        pf = np.stack([st.value(n).x for n in names])
        at = None
        if st.use_fej:  # the clone's and the landmarks' first estimates
            xf = st.fej(clone)
            at = (
                np.broadcast_to(xf.R, (K, 3, 3)),
                np.broadcast_to(xf.p, (K, 3)),
                np.stack([st.fej(n).x for n in names]),
            )
        uv_hat, H_pose, H_f, p_c = observe(
            cam, np.broadcast_to(x.R, (K, 3, 3)), np.broadcast_to(x.p, (K, 3)), pf, at
        )
        s = 1.0 / cfg.pixel_sigma
        r = (uv - uv_hat) * s
        H_pose, H_f = H_pose * s, H_f * s
        # per feature: S = [H_pose H_f] P[(clone, feature)] [H_pose H_f]^T + I, its NIS against chi2(2)
        ic = st.index([clone])
        il = np.stack([st.index([n]) for n in names])  # (K, 3)
        P = st.P
        H9 = np.concatenate([H_pose, H_f], axis=2)  # (K, 2, 9)
        idx = np.concatenate([np.broadcast_to(ic, (K, 6)), il], axis=1)  # (K, 9)
        Pk = P[idx[:, :, None], idx[:, None, :]]
        S = H9 @ Pk @ np.swapaxes(H9, 1, 2) + np.eye(2)
        nis = np.einsum("ki,ki->k", r, np.linalg.solve(S, r[..., None])[..., 0])
        depth_ok = (p_c[:, 2] > cfg.min_depth) & (p_c[:, 2] < cfg.max_depth)
        accept = depth_ok & (nis < self._chi2[2])
        self.stats.slam_used += int(accept.sum())
        self.stats.slam_rejected += int((~accept).sum())
        # a SLAM feature failing the test is dropped (its track goes on unused)
        for k in np.flatnonzero(~accept):
            st.remove(names[k])
        a = np.flatnonzero(accept)
        if not len(a):
            return
        H: dict[str, np.ndarray] = {clone: H_pose[a].reshape(-1, 6)}
        for i, k in enumerate(a):
            Hb = np.zeros((2 * len(a), 3))
            Hb[2 * i : 2 * i + 2] = H_f[k]
            H[names[k]] = Hb
        ekf_update(st, H, r[a].reshape(-1), 1.0)

    def _trace(
        self, trace: dict | None, used: int, rejected: int, nis: float, pts: np.ndarray | None
    ) -> None:
        if trace is None:
            return
        trace["used"].append(used)
        trace["rejected"].append(rejected)
        trace["nis"].append(nis)
        if pts is not None and len(pts):
            trace["points"].append(pts[:50])

    # -- fed by the driver (pipeline/run/driver.py) -------------------------------------------------------------------
    def open(self, reader: RecordingReader, start_ns: int | None, end_ns: int | None, *, trace: bool) -> Span:
        """Read and check the IMU of ``[start_ns, end_ns)`` (with a margin), initialise on the first call; the
        span's frames are the camera feature frames, its ranges those from the state time on."""
        src = str(getattr(reader, "path", self.source))
        topics = reader.topics()
        if TOPIC_IMU not in topics:
            raise InputError(f"{src}: no '{TOPIC_IMU}' topic; the MSCKF needs IMU data")
        first_imu = topics[TOPIC_IMU].start_ns
        start = max(start_ns if start_ns is not None else first_imu, first_imu)
        if self.initialized:
            start = max(start, self.t_ns)
        end = end_ns if end_ns is not None else topics[TOPIC_IMU].end_ns + 1
        margin = int(0.5e9)
        imu = reader.read_imu(TOPIC_IMU, (self.t_ns if self.initialized else start) - margin, end + margin)
        self._check_imu(imu.t_ns, imu.gyro, imu.acc, src)
        if len(imu.t_ns) < 2:
            raise InputError(
                f"{src}: {TOPIC_IMU}: fewer than 2 samples in [{start}, {end}); nothing to run on"
            )
        first_run = not self.initialized
        if first_run:
            i0 = int(np.searchsorted(imu.t_ns, start))
            if i0 >= len(imu.t_ns) or imu.t_ns[i0] >= end:
                raise InputError(f"{src}: {TOPIC_IMU}: no IMU sample in [{start}, {end}); nothing to run on")
            self._initialize(reader, int(imu.t_ns[i0]))
        self._imu = (imu.t_ns, imu.gyro, imu.acc)
        self._first_imu = first_imu
        self._frame_trace = (
            {k: [] for k in ("t", "used", "rejected", "nis", "points", "zupt")} if trace else None
        )
        self._zupt_reference()
        f_start = start_ns if first_run else start
        frames = reader.iter_features(TOPIC_FEATURES, f_start, end) if TOPIC_FEATURES in topics else iter(())
        ranges = reader.read_ranges(TOPIC_RANGE, self.t_ns, end) if TOPIC_RANGE in topics else None
        return Span(
            src, end, frames, ranges if ranges is not None and len(ranges) else None, len(self._history)
        )

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
        t_prev = self._zupt_ref[0]  # the previous frame: ranges since then moved the state time
        static = self.config.zupt and self._detect_static(t_ns, ids, uv, *args)
        self._static = (t_prev, t_ns) if static and self.config.zupt_imu else None
        self.propagate_to(t_ns)
        if static:  # no clone: a static frame adds no parallax, only degenerate feature updates
            self.stats.frames += 1
            if not np.isfinite(uv).all(axis=1).any():
                self.stats.frames_without_features += 1
            self._zupt(t_prev, t_ns, *args)
            if self._frame_trace is not None:
                self._frame_trace["zupt"].append(t_ns)
        else:
            self._camera_frame(t_ns, ids, uv, self._frame_trace)
        self._static = None
        ok = np.isfinite(uv).all(axis=1) if len(uv) else np.zeros(0, bool)
        frame_ok = (ids[ok], uv[ok], self.state.value("imu").R)
        if not static or self._last_frame is None:
            self._last_frame = frame_ok
            self._last_frame_t = t_ns
        if self.config.zupt_disparity_baseline_s > 0:
            self._keep_recent(t_ns, *frame_ok)
        self._record()
        self._maybe_probe()
        self._zupt_reference()

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

    def _zupt_reference(self) -> None:
        """The state the next frame's zero-velocity test is about: time, velocity and IMU covariance at the last
        frame (or the span start); ranges between two frames do not enter the test."""
        im = self.state.slice("imu")
        x = self.state.value("imu")  # values are replaced, never changed in place: a reference is a snapshot
        self._zupt_ref = (self.t_ns, x, self.state.fej("imu").R, self.state.P[im, im].copy())

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
        return np.stack([self.state.value(_clone_name(c)).p for c in self.clones])


__all__ = [
    "FeatureDatabase",
    "MsckfEstimator",
    "VioStats",
    "compress",
    "feature_jacobians",
    "groundtruth_state",
    "landmark_sigma",
    "nullspace_project",
    "observe",
    "triangulate",
]
