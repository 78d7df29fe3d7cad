"""The MSCKF's feature tracks: the window's observation database and the batched feature math.

Feature selection (OpenVINS style, `FeatureDatabase.select`): a track is used once, when it is lost (not seen in
the current frame) or when the oldest clone is about to be marginalised and the track has an observation in it; in
both cases with at least ``min_track_length`` observations. A used track is deleted from the database (a feature
id that keeps being tracked starts a new track), so no observation is used twice.

Per update, all selected features are processed in batches: linear triangulation (sum of the projectors orthogonal
to the bearings) and Gauss-Newton in world xyz (`triangulate`), Jacobians in distorted pixel space (clone columns
at the clones' first estimates when FEJ is on, feature at its triangulated value; `observe`), left-nullspace
projection of the feature Jacobian (batched QR per track length; `nullspace_project`) and measurement compression
(`compress_normal`).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.linalg.lapack import dpstrf, dtrtrs

from uwbcal.pipeline.core.geometry import I3, skew
from uwbcal.pipeline.vio.camera import Camera


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


@dataclass
class Tracks:
    """Feature tracks linearised on the padded (feature, observation) layout (`MsckfUpdater.linearize`)."""

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


def landmark_name(track_id: int) -> str:
    return f"landmark/{track_id}"


def clone_name(t_ns: int) -> str:
    return f"clone/{t_ns}"
