"""KLT visual front-end: images -> persistent feature tracks.

Per frame: track the previous features with pyramidal Lucas-Kanade (forward and backward; a track survives
when the backward flow returns within ``fb_threshold_px``), reject outliers with a RANSAC/USAC fundamental
matrix on undistorted points (scaled to pixels so that the threshold is in pixels), then top the set up to
``max_features`` with Shi-Tomasi corners bucketed on a grid (at most ``max_features / cells`` per cell, at least
``min_distance_px`` from any live track). Tracks keep their id as long as they survive. Coordinates are the raw
(distorted) pixels of the input image; the MSCKF undistorts them itself.

Optional stereo (``stereo = true``): the cam0 features are tracked into the cam1 image (KLT) and kept when they
lie within ``stereo_epipolar_px`` of their epipolar line; the matches are available as ``last_stereo`` and
summarised in the statistics (the recording format has no cam1 feature topic).
"""

from __future__ import annotations

import itertools
import logging
import math
import time
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from uwbcal.convert import msgs
from uwbcal.convert.recording import (
    META_CALIBRATION,
    TOPIC_CAM0,
    TOPIC_CAM1,
    TOPIC_IMU,
    RecordingReader,
    RecordingWriter,
)
from uwbcal.pipeline.core.errors import InputError
from uwbcal.pipeline.core.geometry import exp_so3
from uwbcal.pipeline.core.progress import progress
from uwbcal.pipeline.vio.camera import Camera
from uwbcal.pipeline.vio.config import FrontendConfig

# sees every logged frame: (t_ns, image, uv (n, 2), track ids (n,))
FrameObserver = Callable[[int, np.ndarray, np.ndarray, np.ndarray], None]

_log = logging.getLogger(__name__)

_USAC = {
    "magsac": getattr(cv2, "USAC_MAGSAC", cv2.FM_RANSAC),
    "usac": getattr(cv2, "USAC_DEFAULT", cv2.FM_RANSAC),
    "ransac": cv2.FM_RANSAC,
}


@dataclass
class FrontendStats:
    """Per-run summary; ``str()`` is the one-line stage summary."""

    frames: int = 0
    frames_corrupt: int = 0
    frames_missing: int = 0
    features: list[int] = field(default_factory=list)
    tracked: list[int] = field(default_factory=list)
    inlier_ratio: list[float] = field(default_factory=list)
    new: list[int] = field(default_factory=list)
    stereo_ratio: list[float] = field(default_factory=list)
    track_lengths: list[int] = field(default_factory=list)
    wall_s: float = 0.0
    corrupt_examples: list[str] = field(default_factory=list)

    @property
    def features_mean(self) -> float:
        return float(np.mean(self.features)) if self.features else 0.0

    @property
    def features_min(self) -> int:
        return int(np.min(self.features)) if self.features else 0

    @property
    def inlier_ratio_mean(self) -> float:
        return float(np.mean(self.inlier_ratio)) if self.inlier_ratio else float("nan")

    @property
    def track_length_mean(self) -> float:
        return float(np.mean(self.track_lengths)) if self.track_lengths else 0.0

    def summary(self) -> dict[str, Any]:
        out = {
            "frames": self.frames,
            "frames_corrupt": self.frames_corrupt,
            "frames_missing": self.frames_missing,
            "features_mean": self.features_mean,
            "features_min": self.features_min,
            "tracked_mean": float(np.mean(self.tracked)) if self.tracked else 0.0,
            "new_mean": float(np.mean(self.new)) if self.new else 0.0,
            "inlier_ratio_mean": self.inlier_ratio_mean,
            "track_length_mean": self.track_length_mean,
            "wall_s": self.wall_s,
            "ms_per_frame": 1e3 * self.wall_s / max(self.frames, 1),
        }
        if self.stereo_ratio:
            out["stereo_ratio_mean"] = float(np.mean(self.stereo_ratio))
        if self.corrupt_examples:
            out["corrupt_examples"] = list(self.corrupt_examples)
        return out

    def __str__(self) -> str:
        s = (
            f"{self.frames} frames, {self.features_mean:.0f} features/frame (min {self.features_min}), "
            f"RANSAC inliers {100 * self.inlier_ratio_mean:.1f} %, mean track length "
            f"{self.track_length_mean:.1f}, {1e3 * self.wall_s / max(self.frames, 1):.1f} ms/frame"
        )
        if self.stereo_ratio:
            s += f", stereo matches {100 * float(np.mean(self.stereo_ratio)):.0f} %"
        if self.frames_corrupt or self.frames_missing:
            s += f"; {self.frames_corrupt} corrupt and {self.frames_missing} missing frame(s) skipped"
        return s


def _camera(calib: Camera | dict, name: str) -> Camera:
    if isinstance(calib, Camera):
        return calib
    full = calib if "cameras" in calib else {"cameras": {name: calib}}
    return Camera.from_calibration(full, name)


def bucket_select(pts: np.ndarray, need: np.ndarray, cols: int, rows: int, w: int, h: int) -> np.ndarray:
    """Indices of ``pts`` (sorted by decreasing quality) keeping at most ``need[cell]`` per grid cell."""
    if len(pts) == 0:
        return np.zeros(0, np.int64)
    cx = np.clip((pts[:, 0] * cols / w).astype(np.int64), 0, cols - 1)
    cy = np.clip((pts[:, 1] * rows / h).astype(np.int64), 0, rows - 1)
    cell = cy * cols + cx
    order = np.argsort(cell, kind="stable")  # keeps the quality order inside a cell
    sc = cell[order]
    first = np.searchsorted(sc, sc, side="left")
    rank = np.arange(len(sc)) - first
    keep = order[rank < need[sc]]
    return np.sort(keep)


class KltFrontend:
    """Persistent KLT tracks on one camera; ``process`` once per image, in time order."""

    def __init__(
        self,
        calib_cam0: Camera | dict,
        config: FrontendConfig | None = None,
        calib_cam1: Camera | dict | None = None,
    ) -> None:
        self.config = config or FrontendConfig()
        self.camera = _camera(calib_cam0, "cam0")
        self.camera1 = _camera(calib_cam1, "cam1") if calib_cam1 is not None else None
        c = self.config
        self._clahe = cv2.createCLAHE(clipLimit=2.0, tileGridSize=(8, 8)) if c.equalize else None
        self._win = (c.klt_window, c.klt_window)
        self._criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, c.klt_iterations, 0.01)
        self._prev: np.ndarray | None = None  # previous (equalised) frame
        self._prev_shape: tuple[int, ...] = ()
        self._prev_t = -1
        self._pts = np.zeros((0, 2), np.float32)
        self._ids = np.zeros(0, np.int64)
        self._age = np.zeros(0, np.int64)
        self._next_id = 0
        self.stats = FrontendStats()
        self.last_stereo: tuple[np.ndarray, np.ndarray] | None = None
        self._E: np.ndarray | None = None
        if self.camera1 is not None:
            # p_cam1 = R10 p_cam0 + t10 from T_imu_cam of both cameras; E = [t10]x R10
            R0, t0 = self.camera.R_imu_cam, self.camera.p_imu_cam
            R1, t1 = self.camera1.R_imu_cam, self.camera1.p_imu_cam
            R10 = R1.T @ R0
            t10 = R1.T @ (t0 - t1)
            tx = np.array([[0, -t10[2], t10[1]], [t10[2], 0, -t10[0]], [-t10[1], t10[0], 0]])
            self._E = tx @ R10

    # -- helpers -------------------------------------------------------------------------------------------------
    def _lk(
        self, pyr0, pyr1, p0: np.ndarray, p1_guess: np.ndarray | None = None
    ) -> tuple[np.ndarray, np.ndarray]:
        flags = cv2.OPTFLOW_USE_INITIAL_FLOW if p1_guess is not None else 0
        p1, st, _ = cv2.calcOpticalFlowPyrLK(
            pyr0,
            pyr1,
            p0.reshape(-1, 1, 2),
            None if p1_guess is None else p1_guess.reshape(-1, 1, 2).copy(),
            winSize=self._win,
            maxLevel=self.config.klt_levels,
            criteria=self._criteria,
            flags=flags,
        )
        return p1.reshape(-1, 2), st.reshape(-1).astype(bool)

    def _inside(self, p: np.ndarray, shape: tuple[int, ...]) -> np.ndarray:
        b = self.config.border_px
        h, w = shape[:2]
        return (p[:, 0] >= b) & (p[:, 1] >= b) & (p[:, 0] < w - 1 - b) & (p[:, 1] < h - 1 - b)

    def _undistorted_px(self, uv: np.ndarray) -> np.ndarray:
        n = self.camera.undistort(uv.astype(float))
        return (n * self.camera.focal).astype(np.float64)

    def ransac_inliers(self, uv0: np.ndarray, uv1: np.ndarray) -> np.ndarray:
        """Fundamental-matrix RANSAC/USAC on undistorted points; boolean inlier mask."""
        c = self.config
        n = len(uv0)
        if not c.ransac or n < 8:
            return np.ones(n, bool)
        a, b = self._undistorted_px(uv0), self._undistorted_px(uv1)
        ok = np.isfinite(a).all(1) & np.isfinite(b).all(1)
        if ok.sum() < 8:
            return ok
        try:
            _, mask = cv2.findFundamentalMat(
                a[ok], b[ok], _USAC[c.ransac_method], c.ransac_threshold_px, c.ransac_confidence
            )
        except cv2.error:
            mask = None
        out = np.zeros(n, bool)
        if mask is None or mask.size != ok.sum():
            # degenerate (e.g. no motion: every point fits); keep the KLT result
            out[ok] = True
            return out
        out[np.flatnonzero(ok)] = mask.reshape(-1).astype(bool)
        return out

    def _cell_room(self, pts: np.ndarray, w: int, h: int) -> np.ndarray:
        """New corners each grid cell may take: its share of ``max_features`` less the live tracks in it."""
        c = self.config
        cells = c.grid_cols * c.grid_rows
        cap = math.ceil(c.max_features / cells)
        have = np.zeros(cells, np.int64)
        if len(pts):
            cx = np.clip((pts[:, 0] * c.grid_cols / w).astype(np.int64), 0, c.grid_cols - 1)
            cy = np.clip((pts[:, 1] * c.grid_rows / h).astype(np.int64), 0, c.grid_rows - 1)
            have = np.bincount(cy * c.grid_cols + cx, minlength=cells)
        return np.maximum(cap - have, 0)

    def _detect(self, img: np.ndarray, pts: np.ndarray) -> np.ndarray:
        c = self.config
        h, w = img.shape[:2]
        room = c.max_features - len(pts)
        if room <= 0:
            return np.zeros((0, 2), np.float32)
        mask = np.zeros((h, w), np.uint8)
        b = c.border_px
        mask[b : h - b, b : w - b] = 255
        r = int(round(c.min_distance_px))
        for x, y in np.round(pts).astype(int):
            cv2.circle(mask, (int(x), int(y)), r, 0, -1)
        corners = cv2.goodFeaturesToTrack(
            img,
            maxCorners=4 * c.max_features,
            qualityLevel=c.quality_level,
            minDistance=max(c.min_distance_px, 1.0),
            mask=mask,
            blockSize=3,
        )
        if corners is None:
            return np.zeros((0, 2), np.float32)
        corners = corners.reshape(-1, 2)
        sel = bucket_select(corners, self._cell_room(pts, w, h), c.grid_cols, c.grid_rows, w, h)
        new = corners[sel]
        if len(new) > room:  # best first across cells: gftt order is by quality
            new = new[:room]
        return new.astype(np.float32)

    def _keep(self, idx: np.ndarray, p1: np.ndarray) -> None:
        """Tracks ``idx`` live on at ``p1`` (their new pixels); the others end (their lengths are recorded)."""
        gone = np.ones(len(self._pts), bool)
        gone[idx] = False
        self.stats.track_lengths.extend(self._age[gone].tolist())
        self._pts, self._ids, self._age = p1.astype(np.float32), self._ids[idx], self._age[idx] + 1

    def _track(self, gray: np.ndarray, t_ns: int) -> int:
        """Follow the live tracks into ``gray``; returns how many were found before the RANSAC."""
        p0 = self._pts
        p1, ok = self._lk(self._prev, gray, p0)
        p0b, okb = self._lk(gray, self._prev, p1, p0)
        fb = np.linalg.norm(p0b - p0, axis=1)
        good = ok & okb & (fb < self.config.fb_threshold_px) & self._inside(p1, gray.shape)
        idx = np.flatnonzero(good)
        idx = idx[self._ransac_recorded(p0[idx], p1[idx])]
        self._keep(idx, p1[idx])
        return int(good.sum())

    def _ransac_recorded(self, uv0: np.ndarray, uv1: np.ndarray) -> np.ndarray:
        inl = self.ransac_inliers(uv0, uv1)
        if self.config.ransac and len(uv0) >= 8:
            self.stats.inlier_ratio.append(float(inl.mean()))
        return inl

    # -- main entry ----------------------------------------------------------------------------------------------
    def process(
        self, t_ns: int, img: np.ndarray, img_right: np.ndarray | None = None
    ) -> tuple[np.ndarray, np.ndarray]:
        """Track into ``img`` (mono8 HxW); returns (track ids int64 [N], raw pixel uv float64 [N,2])."""
        if img.ndim != 2 or img.dtype != np.uint8:
            raise ValueError(f"frame {t_ns}: expected a mono8 HxW uint8 image, got {img.dtype} {img.shape}")
        if t_ns <= self._prev_t:
            raise ValueError(f"frame {t_ns}: stamps must increase (previous {self._prev_t})")
        gray = self._clahe.apply(img) if self._clahe is not None else img
        n_tracked = 0
        if self._prev is not None and self._prev_shape == gray.shape and len(self._pts):
            n_tracked = self._track(gray, t_ns)
        elif len(self._pts):
            self.stats.track_lengths.extend(self._age.tolist())  # image size changed: restart
            self._keep(np.zeros(0, np.int64), self._pts[:0])
        new = self._detect(gray, self._pts)
        if len(new):
            ids = np.arange(self._next_id, self._next_id + len(new), dtype=np.int64)
            self._next_id += len(new)
            self._pts = np.vstack([self._pts, new])
            self._ids = np.concatenate([self._ids, ids])
            self._age = np.concatenate([self._age, np.ones(len(new), np.int64)])
        self._prev = gray  # (the Python binding does not take prebuilt pyramids)
        self._prev_shape = gray.shape
        self._prev_t = t_ns
        st = self.stats
        st.frames += 1
        st.features.append(len(self._pts))
        st.tracked.append(n_tracked)
        st.new.append(len(new))
        self.last_stereo = None
        if self.config.stereo and img_right is not None and self.camera1 is not None:
            self.last_stereo = self.match_stereo(gray, img_right)
            st.stereo_ratio.append(len(self.last_stereo[0]) / max(len(self._pts), 1))
        return self._ids.copy(), self._pts.astype(np.float64)

    def match_stereo(self, gray_left: np.ndarray, img_right: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Current cam0 tracks matched into cam1: (ids, raw cam1 uv) that pass the epipolar check."""
        if self.camera1 is None or self._E is None or not len(self._pts):
            return np.zeros(0, np.int64), np.zeros((0, 2))
        right = self._clahe.apply(img_right) if self._clahe is not None else img_right
        p0 = self._pts
        p1, ok = self._lk(gray_left, right, p0)
        p0b, okb = self._lk(right, gray_left, p1, p0)
        ok &= (
            okb
            & (np.linalg.norm(p0b - p0, axis=1) < self.config.fb_threshold_px)
            & self._inside(p1, right.shape)
        )
        n0 = self.camera.undistort(p0.astype(float))
        n1 = self.camera1.undistort(p1.astype(float))
        x0 = np.column_stack([n0, np.ones(len(n0))])
        x1 = np.column_stack([n1, np.ones(len(n1))])
        lines = x0 @ self._E.T  # epipolar lines in cam1 (normalised)
        dist = np.abs(np.sum(x1 * lines, axis=1)) / np.maximum(np.linalg.norm(lines[:, :2], axis=1), 1e-12)
        ok &= np.isfinite(dist) & (dist * self.camera1.focal < self.config.stereo_epipolar_px)
        return self._ids[ok].copy(), p1[ok].astype(np.float64)

    def finish(self) -> FrontendStats:
        """Close the live tracks (their lengths go into the statistics) and return the statistics."""
        self.stats.track_lengths.extend(self._age.tolist())
        self._age = np.zeros(len(self._pts), np.int64)
        return self.stats


class GyroRotation:
    """Camera rotation between two stamps from the integrated gyroscope: ``R_c0_c1`` (bearings
    ``x_c0 = R_c0_c1 x_c1`` under pure rotation). The gyro bias is left out: over one frame interval it moves a
    prediction by a pixel or so, well inside the matching window."""

    def __init__(self, t_ns: np.ndarray, gyro: np.ndarray, R_imu_cam: np.ndarray) -> None:
        self._t = np.asarray(t_ns, np.int64)
        self._w = np.asarray(gyro, float)
        self._R_ic = np.asarray(R_imu_cam, float)
        dt = np.diff(self._t) * 1e-9
        R = [np.eye(3)]  # world_from_imu at each sample (arbitrary start)
        for w, h in zip(self._w[:-1], dt, strict=True):
            R.append(R[-1] @ exp_so3(w * h))
        self._R = np.asarray(R)

    def _at(self, t_ns: int) -> np.ndarray:
        k = int(np.clip(np.searchsorted(self._t, t_ns, side="right") - 1, 0, len(self._t) - 1))
        return self._R[k] @ exp_so3(self._w[k] * (t_ns - self._t[k]) * 1e-9)

    def __call__(self, t0_ns: int, t1_ns: int) -> np.ndarray:
        if len(self._t) < 2:
            return np.eye(3)
        R_i0_i1 = self._at(t0_ns).T @ self._at(t1_ns)
        return self._R_ic.T @ R_i0_i1 @ self._R_ic


def hamming(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamming distances (n, m) between binary descriptors (n, k) and (m, k) uint8 (bits as a matrix product)."""
    A = np.unpackbits(a, axis=1).astype(np.float32)
    B = np.unpackbits(b, axis=1).astype(np.float32)
    return (A @ (1.0 - B).T + (1.0 - A) @ B.T).astype(np.float64)


class DescriptorFrontend(KltFrontend):
    """Tracks for low frame rates and fast turns: IMU-predicted KLT with descriptor re-acquisition.

    Per frame: every live track is first followed by KLT started where the camera rotation since the previous
    frame (`GyroRotation`, when given) moves it, so a fast turn does not throw it out of the pyramid's reach. The
    tracks KLT loses are matched by ORB descriptor (OpenVINS' TrackDescriptor) to the frame's FAST corners
    (bucketed on the grid, sub-pixel) within ``match_radius_px`` of the prediction: a Hamming distance of at most
    ``match_max_hamming``, the ratio test against the second best, mutual. One fundamental-matrix RANSAC over
    both; the corners away from live tracks start new ones. A track carries the descriptor of its latest pixel.

    Measured on a 3 Hz hand-held camera, descriptor matching alone re-finds fewer tracks than the predicted
    KLT (corner repeatability); it recovers the ones KLT drops (docs/results/measurements.md)."""

    def __init__(
        self,
        calib_cam0: Camera | dict,
        config: FrontendConfig | None = None,
        calib_cam1: Camera | dict | None = None,
        rotation: Callable[[int, int], np.ndarray] | None = None,
    ) -> None:
        super().__init__(calib_cam0, config, calib_cam1)
        self.rotation = rotation
        self._fast = cv2.FastFeatureDetector_create(threshold=self.config.fast_threshold)
        self._orb = cv2.ORB_create(edgeThreshold=19, patchSize=19)
        self._desc = np.zeros((0, 32), np.uint8)
        self._frame: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None  # corners, descriptors, unused

    def _corners(self, gray: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        c = self.config
        h, w = gray.shape[:2]
        b = c.border_px
        mask = np.zeros((h, w), np.uint8)
        mask[b : h - b, b : w - b] = 255
        kps = sorted(self._fast.detect(gray, mask), key=lambda k: -k.response)
        if not kps:
            return np.zeros((0, 2), np.float32), np.zeros((0, 32), np.uint8)
        cells = c.grid_cols * c.grid_rows
        need = np.full(cells, 3 * math.ceil(c.max_features / cells))  # room to match and to start tracks
        sel = bucket_select(np.array([k.pt for k in kps]), need, c.grid_cols, c.grid_rows, w, h)
        kps, desc = self._orb.compute(gray, [kps[i] for i in sel])
        if desc is None or not kps:
            return np.zeros((0, 2), np.float32), np.zeros((0, 32), np.uint8)
        uv = np.array([k.pt for k in kps], np.float32).reshape(-1, 1, 2)
        crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 10, 0.03)
        uv = cv2.cornerSubPix(gray, uv, (3, 3), (-1, -1), crit).reshape(-1, 2)
        return uv, desc

    def _predict(self, uv: np.ndarray, t0_ns: int, t1_ns: int) -> np.ndarray:
        """Where the camera rotation alone moves pixels ``uv`` of frame ``t0_ns`` in frame ``t1_ns``."""
        if self.rotation is None or not len(uv):
            return uv.astype(np.float64)
        n = self.camera.undistort(uv.astype(float))
        x = np.column_stack([n, np.ones(len(n))]) @ self.rotation(t0_ns, t1_ns)  # rows: R^T x
        z = np.maximum(x[:, 2:3], 1e-3)
        return self.camera.normalised_to_pixel(x[:, :2] / z)

    def _match(
        self, tracks: np.ndarray, pred: np.ndarray, uv: np.ndarray, desc: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """(track index, corner index) of the accepted matches of ``tracks`` predicted at ``pred``."""
        c = self.config
        if not len(tracks) or not len(desc):
            return np.zeros(0, np.int64), np.zeros(0, np.int64)
        d = hamming(self._desc[tracks], desc)
        far = ((pred[:, None, :] - uv[None, :, :].astype(float)) ** 2).sum(-1) > c.match_radius_px**2
        d[far] = np.inf
        best = np.argmin(d, axis=1)
        rows = np.arange(len(d))
        d1 = d[rows, best]
        d[rows, best] = np.inf
        d2 = d.min(axis=1)
        d[rows, best] = d1
        ok = (d1 <= c.match_max_hamming) & (d1 < c.match_ratio * d2)
        ok &= np.argmin(d, axis=0)[best] == rows  # mutual
        return tracks[ok], best[ok]

    def _describe(self, gray: np.ndarray, uv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """ORB descriptors at pixels ``uv``: (descriptors of those it could describe, their indices)."""
        kps = [cv2.KeyPoint(float(x), float(y), 19, -1, 0, 0, i) for i, (x, y) in enumerate(uv)]
        kps, desc = self._orb.compute(gray, kps)
        if desc is None or not kps:
            return np.zeros((0, 32), np.uint8), np.zeros(0, np.int64)
        return desc, np.array([k.class_id for k in kps], np.int64)

    def _track(self, gray: np.ndarray, t_ns: int) -> int:
        """KLT from the rotation-predicted positions; the tracks it loses are searched for by descriptor among
        the frame's corners; one RANSAC over both."""
        p0 = self._pts
        pred = self._predict(p0, self._prev_t, t_ns)
        p1, ok = self._lk(self._prev, gray, p0, pred.astype(np.float32))
        p0b, okb = self._lk(gray, self._prev, p1, p0)
        fb = np.linalg.norm(p0b - p0, axis=1)
        good = ok & okb & (fb < self.config.fb_threshold_px) & self._inside(p1, gray.shape)
        uv, desc = self._corners(gray)
        lost = np.flatnonzero(~good)
        ti, ci = self._match(lost, pred[lost], uv, desc)
        p1 = p1.astype(np.float64)
        p1[ti] = uv[ci]
        idx = np.sort(np.concatenate([np.flatnonzero(good), ti]))
        inl = self._ransac_recorded(p0[idx], p1[idx])
        idx = idx[inl]
        d_new, have = self._describe(gray, p1[idx])
        desc_kept = self._desc[idx].copy()
        desc_kept[have] = d_new
        self._keep(idx, p1[idx])
        self._desc = desc_kept
        self._frame = (uv, desc, np.ones(len(uv), bool))
        return int(good.sum()) + len(ti)

    def _keep(self, idx: np.ndarray, p1: np.ndarray) -> None:
        super()._keep(idx, p1)
        self._desc = self._desc[idx]

    def _detect(self, img: np.ndarray, pts: np.ndarray) -> np.ndarray:
        """New tracks from the frame's unmatched corners: bucketed, away from live tracks, up to max_features."""
        c = self.config
        if self._frame is None:  # first frame (or after a restart): no matching ran
            uv, desc = self._corners(img)
            self._frame = (uv, desc, np.ones(len(uv), bool))
        uv, desc, unused = self._frame
        self._frame = None
        h, w = img.shape[:2]
        room = c.max_features - len(pts)
        cand = np.flatnonzero(unused)
        if room <= 0 or not len(cand):
            return np.zeros((0, 2), np.float32)
        if len(pts):
            d2 = ((uv[cand, None, :] - pts[None, :, :]) ** 2).sum(-1).min(axis=1)
            cand = cand[d2 >= c.min_distance_px**2]
        need = self._cell_room(pts, w, h)
        sel = cand[bucket_select(uv[cand], need, c.grid_cols, c.grid_rows, w, h)][:room]
        self._desc = np.vstack([self._desc, desc[sel]])
        return uv[sel].astype(np.float32)


def make_frontend(
    config: FrontendConfig,
    cam0: Camera,
    cam1: Camera | None = None,
    rotation: Callable[[int, int], np.ndarray] | None = None,
) -> KltFrontend:
    """The front-end ``config.tracker`` names ("auto" here: KLT; `choose_tracker` decides it for a recording)."""
    if config.tracker == "descriptor":
        return DescriptorFrontend(cam0, config, cam1, rotation)
    return KltFrontend(cam0, config, cam1)


# ---------------------------------------------------------------------------------------------------------------
# images in, tracks out
# ---------------------------------------------------------------------------------------------------------------
def decode_image(msg: Any) -> tuple[np.ndarray | None, str]:
    """A sensor_msgs/Image as mono8 HxW, or (None, reason) when it cannot be decoded."""
    try:
        h, w, step = int(msg.height), int(msg.width), int(msg.step)
        enc = str(msg.encoding).lower()
        data = np.asarray(msg.data, np.uint8)
        ch = {"mono8": 1, "8uc1": 1, "rgb8": 3, "bgr8": 3, "rgba8": 4, "bgra8": 4}.get(enc)
        if ch is None:
            return None, f"encoding {msg.encoding!r} not supported (mono8, rgb8, bgr8)"
        if h <= 0 or w <= 0 or step < w * ch or data.size < h * step:
            return None, f"{data.size} bytes for {w}x{h} (step {step})"
        img = data[: h * step].reshape(h, step)[:, : w * ch]
        if ch == 1:
            return np.ascontiguousarray(img), ""
        img = img.reshape(h, w, ch)
        code = {
            "rgb8": cv2.COLOR_RGB2GRAY,
            "bgr8": cv2.COLOR_BGR2GRAY,
            "rgba8": cv2.COLOR_RGBA2GRAY,
            "bgra8": cv2.COLOR_BGRA2GRAY,
        }[enc]
        return cv2.cvtColor(np.ascontiguousarray(img), code), ""
    except (AttributeError, ValueError, TypeError) as exc:
        return None, f"undecodable image ({exc})"


def _count_missing(t: np.ndarray) -> int:
    """Frames missing from a stream judged by the median period (a gap of k periods misses k-1 frames)."""
    if len(t) < 3:
        return 0
    dt = np.diff(np.asarray(t, np.int64)).astype(float)
    period = float(np.median(dt))
    if period <= 0:
        return 0
    k = np.round(dt / period)
    return int(np.sum(np.where(dt > 1.5 * period, k - 1, 0)))


def track_frames(
    frontend: KltFrontend,
    frames: Iterable[tuple[int, np.ndarray | None] | tuple[int, np.ndarray | None, np.ndarray | None]],
    on_frame: FrameObserver | None = None,
) -> Iterator[tuple[int, np.ndarray, np.ndarray]]:
    """Run the front-end over ``(t_ns, image[, right image])``; ``None`` images count as corrupt and are skipped.
    ``on_frame(t_ns, image, uv, ids)`` sees every ``frontend.log_every``-th tracked frame."""
    st = frontend.stats
    stamps: list[int] = []
    every = frontend.config.log_every
    for item in frames:
        t_ns, img = int(item[0]), item[1]
        right = item[2] if len(item) > 2 else None
        stamps.append(t_ns)
        if img is None:
            st.frames_corrupt += 1
            continue
        if t_ns <= frontend._prev_t:
            st.frames_corrupt += 1
            if len(st.corrupt_examples) < 3:
                st.corrupt_examples.append(f"{t_ns}: stamp not after the previous frame")
            continue
        t0 = time.perf_counter()
        ids, uv = frontend.process(t_ns, img, right)
        st.wall_s += time.perf_counter() - t0
        if on_frame is not None and (st.frames - 1) % every == 0:
            on_frame(t_ns, img, uv, ids)
        yield t_ns, ids, uv
    st.frames_missing += _count_missing(np.unique(np.asarray(stamps, np.int64)))
    frontend.finish()


def _image_stream(
    reader: RecordingReader,
    topic: str,
    stats: FrontendStats,
    start_ns: int | None = None,
    end_ns: int | None = None,
) -> Iterator[tuple[int, np.ndarray | None]]:
    ts = msgs.typestore()
    for _, t_log, raw in reader.messages([topic], start_ns, end_ns, raw=True):
        t = int(t_log)
        try:
            m = ts.deserialize_cdr(bytes(raw), msgs.IMAGE)
        except Exception as exc:  # a damaged message is counted, not fatal
            img, why = None, f"undecodable message ({type(exc).__name__})"
        else:
            img, why = decode_image(m)
            if img is not None:  # a damaged image's header may be damaged too: keep the log time then
                t = int(m.header.stamp.sec) * 1_000_000_000 + int(m.header.stamp.nanosec)
        if img is None and len(stats.corrupt_examples) < 3:
            stats.corrupt_examples.append(f"{t}: {why}")
        yield t, img


def _stereo_stream(
    left: Iterator[tuple[int, np.ndarray | None]], right: Iterator[tuple[int, np.ndarray | None]], tol_ns: int
) -> Iterator[tuple[int, np.ndarray | None, np.ndarray | None]]:
    """Pair two time-ordered image streams by stamp (within ``tol_ns``); unmatched left frames come alone."""
    r = next(right, None)
    for t, img in left:
        while r is not None and r[0] < t - tol_ns:
            r = next(right, None)
        if r is not None and abs(r[0] - t) <= tol_ns:
            yield t, img, r[1]
            r = next(right, None)
        else:
            yield t, img, None


def klt_survival(reader: RecordingReader, config: FrontendConfig, pairs: int = 12) -> np.ndarray:
    """Fraction of KLT tracks (after RANSAC) that survive from one frame to the next, over ``pairs`` pairs of
    consecutive cam0 frames spread evenly over the recording."""
    span = reader.topics()[TOPIC_CAM0]
    cam = Camera.from_calibration(reader.calibration, "cam0", str(getattr(reader, "path", "recording")))
    out = []
    for t in np.linspace(span.start_ns, span.end_ns, pairs + 2)[1:-1].astype(np.int64):
        stream = (f for f in _image_stream(reader, TOPIC_CAM0, FrontendStats(), int(t)) if f[1] is not None)
        frames = list(itertools.islice(stream, 2))
        if len(frames) < 2:
            break
        fe = KltFrontend(cam, config)
        fe.process(*frames[0])
        born = len(fe._pts)
        fe.process(*frames[1])
        out.append(float(np.sum(fe._age > 1)) / born if born else 0.0)
    return np.asarray(out)


def choose_tracker(reader: RecordingReader, config: FrontendConfig) -> tuple[str, str]:
    """``frontend.tracker = "auto"`` for a recording with cam0 images: (tracker, reason)."""
    span = reader.topics()[TOPIC_CAM0]
    rate = (span.count - 1) / max((span.end_ns - span.start_ns) * 1e-9, 1e-9) if span.count > 1 else 0.0
    if rate < config.descriptor_below_hz:
        return (
            "descriptor",
            f"camera at {rate:.1f} Hz < {config.descriptor_below_hz:g} Hz (descriptor_below_hz)",
        )
    surv = klt_survival(reader, config)
    q = float(np.quantile(surv, 0.25)) if len(surv) else 1.0
    if q < config.klt_min_survival:
        return "descriptor", (
            f"KLT keeps {100 * q:.0f} % of the tracks (lower quartile over {len(surv)} frame pairs) "
            f"< {100 * config.klt_min_survival:.0f} % (klt_min_survival)"
        )
    return "klt", f"camera at {rate:.1f} Hz, KLT keeps {100 * q:.0f} % of the tracks (lower quartile)"


def gyro_rotation(reader: RecordingReader, camera: Camera) -> GyroRotation | None:
    """The camera's gyro-predicted rotation between frames, when the recording has an IMU."""
    if TOPIC_IMU not in reader.topics():
        return None
    imu = reader.read_imu(TOPIC_IMU)
    return GyroRotation(imu.t_ns, imu.gyro, camera.R_imu_cam)


def run_frontend(
    reader: RecordingReader,
    writer_or_path: RecordingWriter | str | Path,
    config: FrontendConfig | None = None,
    on_frame: FrameObserver | None = None,
) -> FrontendStats:
    """Read ``/cam0/image_raw``, write ``/cam0/features`` (ids + raw pixel uv) into a recording."""
    config = config or FrontendConfig()
    src = str(getattr(reader, "path", "recording"))
    topics = reader.topics()
    if TOPIC_CAM0 not in topics or topics[TOPIC_CAM0].count == 0:
        have = ", ".join(sorted(topics)) or "none"
        raise InputError(
            f"{src}: no images on '{TOPIC_CAM0}' (topics: {have}); the front-end needs camera images"
        )
    calib = reader.calibration
    cam0 = Camera.from_calibration(calib, "cam0", src)
    cam1 = None
    stereo = config.stereo and TOPIC_CAM1 in topics
    if config.stereo and not stereo:
        _log.warning("%s: frontend.stereo set but there is no '%s' topic; running mono", src, TOPIC_CAM1)
    if stereo:
        try:
            cam1 = Camera.from_calibration(calib, "cam1", src)
        except InputError as exc:
            _log.warning("%s; running mono", exc)
            stereo = False
    if config.tracker == "auto":
        tracker, why = choose_tracker(reader, config)
        _log.info("%s: frontend.tracker = %s: %s", src, tracker, why)
        config = config.model_copy(update={"tracker": tracker})
    rotation = gyro_rotation(reader, cam0) if config.tracker == "descriptor" else None
    fe = make_frontend(config, cam0, cam1, rotation)
    frames: Iterable = _image_stream(reader, TOPIC_CAM0, fe.stats)
    if stereo:
        frames = _stereo_stream(frames, _image_stream(reader, TOPIC_CAM1, FrontendStats()), tol_ns=1_000_000)

    def write_all(w: RecordingWriter) -> None:
        with progress("frontend", topics[TOPIC_CAM0].count) as advance:
            for t_ns, ids, uv in track_frames(fe, frames, on_frame):
                w.write_features(t_ns, ids, uv)
                advance(1)
        if fe.stats.frames == 0:
            raise InputError(
                f"{src}: {TOPIC_CAM0}: none of the {fe.stats.frames_corrupt} image(s) could be decoded "
                f"({'; '.join(fe.stats.corrupt_examples)}); re-convert the recording"
            )
        w.set_metadata("uwbcal.frontend", {"stats": fe.stats.summary(), "config": config.model_dump()})
        w.set_metadata(META_CALIBRATION, calib)

    if isinstance(writer_or_path, RecordingWriter):
        write_all(writer_or_path)
    else:
        with RecordingWriter(writer_or_path) as w:
            write_all(w)
    st = fe.stats
    if st.frames_corrupt:
        _log.warning(
            "%s: %s: %d corrupt image(s) skipped (%s)",
            src,
            TOPIC_CAM0,
            st.frames_corrupt,
            "; ".join(st.corrupt_examples),
        )
    return st


__all__ = [
    "DescriptorFrontend",
    "FrontendStats",
    "GyroRotation",
    "KltFrontend",
    "choose_tracker",
    "klt_survival",
    "make_frontend",
    "bucket_select",
    "decode_image",
    "run_frontend",
    "track_frames",
]
