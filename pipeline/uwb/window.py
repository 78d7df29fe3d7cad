"""One anchor's ranges with the poses at their stamps (`InitWindow`), and what every fit of them shares: even
subsampling, the motion's principal frame, the time-correlation of the residuals."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from uwbcal.pipeline.uwb.model import tag_positions


@dataclass
class InitWindow:
    """The ranges of one anchor over the initialisation window, with the pose estimates at their stamps."""

    d: np.ndarray  # (N,) ranges [m]
    p_T: np.ndarray  # (N,3) antenna lever arm in the IMU frame
    R: np.ndarray  # (N,3,3) world_from_body estimates
    p: np.ndarray  # (N,3)
    P_pose: np.ndarray  # (N,6,6) pose covariance, error [dtheta, dp]
    t_ns: np.ndarray | None = None
    link: np.ndarray | None = None  # (N,) link id of each range (tag * 256 + antenna); None: one link

    def __post_init__(self) -> None:
        self.d = np.asarray(self.d, float).reshape(-1)
        n = self.d.shape[0]
        self.p_T = np.broadcast_to(np.asarray(self.p_T, float).reshape(-1, 3), (n, 3)).copy()
        self.R = np.asarray(self.R, float).reshape(n, 3, 3)
        self.p = np.asarray(self.p, float).reshape(n, 3)
        self.P_pose = np.broadcast_to(np.asarray(self.P_pose, float).reshape(-1, 6, 6), (n, 6, 6)).copy()
        if self.t_ns is not None:
            self.t_ns = np.asarray(self.t_ns, np.int64).reshape(n)
        if self.link is not None:
            self.link = np.asarray(self.link, np.int64).reshape(n)

    def __len__(self) -> int:
        return self.d.shape[0]

    def subset(self, mask: np.ndarray) -> InitWindow:
        """The ranges ``mask`` selects (a boolean mask or indices)."""
        t = None if self.t_ns is None else self.t_ns[mask]
        lk = None if self.link is None else self.link[mask]
        return InitWindow(self.d[mask], self.p_T[mask], self.R[mask], self.p[mask], self.P_pose[mask], t, lk)

    def links(self) -> np.ndarray:
        return np.zeros(len(self), np.int64) if self.link is None else self.link

    @property
    def tag_xyz(self) -> np.ndarray:
        return tag_positions(self.R, self.p, self.p_T)


def plane_frame(xyz: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Centroid, rows = principal axes (last = normal of the best-fit plane), principal extents (std dev)."""
    c = xyz.mean(axis=0)
    _, s, Vt = np.linalg.svd(xyz - c, full_matrices=False)
    if np.linalg.det(Vt) < 0:  # a proper rotation, so that mirroring is only the sign of the last axis
        Vt[-1] *= -1
    if Vt[-1, 2] < 0:  # normal up (world z) when it can be
        Vt[-1] *= -1
        Vt[0] *= -1
    return c, Vt, s / np.sqrt(len(xyz))


def subsample(n: int, max_n: int) -> np.ndarray:
    """Indices of at most ``max_n`` of ``n`` items, evenly spread (the items are in time order)."""
    if n <= max_n:
        return np.arange(n)
    return np.unique(np.linspace(0, n - 1, max_n).round().astype(np.int64))
