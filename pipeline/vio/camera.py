"""Pinhole camera with radial-tangential (radtan) distortion, vectorised over points.

Normalised coordinates ``n = (x/z, y/z)``; distorted normalised ``d = distort(n)``; pixels ``u = K d``.
All functions take (N, 2) / (N, 3) arrays and return batched Jacobians (N, 2, k).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from uwbcal.convert.calibration import parse_calibration
from uwbcal.pipeline.core.errors import InputError


@dataclass(frozen=True)
class Camera:
    fu: float
    fv: float
    cu: float
    cv: float
    k1: float = 0.0
    k2: float = 0.0
    p1: float = 0.0
    p2: float = 0.0
    R_imu_cam: np.ndarray = field(default_factory=lambda: np.eye(3))
    p_imu_cam: np.ndarray = field(default_factory=lambda: np.zeros(3))
    width: int = 0
    height: int = 0

    @classmethod
    def from_calibration(cls, calib: dict, name: str = "cam0", source: str = "recording") -> Camera:
        """Camera ``name`` of a ``uwbcal.calibration`` mapping (validated by `convert.calibration`)."""
        c = parse_calibration(calib, f"{source}: uwbcal.calibration").cameras.get(name)
        if c is None:
            raise InputError(
                f"{source}: uwbcal.calibration: cameras.{name}: missing; re-convert the recording with its camera "
                "calibration (uwbcal convert bag --calibration)"
            )
        fu, fv, cu, cv = c.intrinsics
        T = c.T
        w, h = c.resolution or (0, 0)
        dist = c.distortion if c.distortion is not None and c.distortion_model == "radtan" else [0.0] * 4
        return cls(
            fu, fv, cu, cv, *dist, R_imu_cam=T[:3, :3].copy(), p_imu_cam=T[:3, 3].copy(), width=w, height=h
        )

    @property
    def focal(self) -> float:
        return 0.5 * (self.fu + self.fv)

    # -- distortion ------------------------------------------------------------------------------------------
    def distort(self, n: np.ndarray) -> np.ndarray:
        x, y = n[..., 0], n[..., 1]
        r2 = x * x + y * y
        rad = 1.0 + self.k1 * r2 + self.k2 * r2 * r2
        xd = x * rad + 2 * self.p1 * x * y + self.p2 * (r2 + 2 * x * x)
        yd = y * rad + self.p1 * (r2 + 2 * y * y) + 2 * self.p2 * x * y
        return np.stack([xd, yd], axis=-1)

    def distort_jacobian(self, n: np.ndarray) -> np.ndarray:
        """d distort / d n, shape (N, 2, 2)."""
        x, y = n[..., 0], n[..., 1]
        r2 = x * x + y * y
        rad = 1.0 + self.k1 * r2 + self.k2 * r2 * r2
        drad = self.k1 + 2 * self.k2 * r2  # d rad / d r2
        J = np.empty(n.shape[:-1] + (2, 2))
        J[..., 0, 0] = rad + 2 * x * x * drad + 2 * self.p1 * y + 6 * self.p2 * x
        J[..., 0, 1] = 2 * x * y * drad + 2 * self.p1 * x + 2 * self.p2 * y
        J[..., 1, 0] = 2 * x * y * drad + 2 * self.p1 * x + 2 * self.p2 * y
        J[..., 1, 1] = rad + 2 * y * y * drad + 6 * self.p1 * y + 2 * self.p2 * x
        return J

    # -- projection ------------------------------------------------------------------------------------------
    def normalised_to_pixel(self, n: np.ndarray) -> np.ndarray:
        d = self.distort(n)
        return np.stack([self.fu * d[..., 0] + self.cu, self.fv * d[..., 1] + self.cv], axis=-1)

    def pixel_jacobian(self, n: np.ndarray) -> np.ndarray:
        """d pixel / d normalised, shape (N, 2, 2)."""
        J = self.distort_jacobian(n)
        J[..., 0, :] *= self.fu
        J[..., 1, :] *= self.fv
        return J

    def project(self, p_cam: np.ndarray) -> np.ndarray:
        """Camera-frame points (N, 3) -> pixels (N, 2)."""
        return self.normalised_to_pixel(p_cam[..., :2] / p_cam[..., 2:3])

    def project_jacobian(
        self, p_cam: np.ndarray, pixels: bool = True
    ) -> tuple[np.ndarray | None, np.ndarray]:
        """Pixels and d pixel / d p_cam (N, 2, 3); ``pixels=False``: the Jacobian only (pixels None)."""
        z = p_cam[..., 2]
        n = p_cam[..., :2] / z[..., None]
        # J_pix (2x2) @ [[1/z, 0, -x/z], [0, 1/z, -y/z]] written out (a batched 2x2 @ 2x3 matmul is slow)
        Jp = self.pixel_jacobian(n)
        iz = (1.0 / z)[..., None]
        J = np.empty(p_cam.shape[:-1] + (2, 3))
        J[..., 0] = Jp[..., 0] * iz
        J[..., 1] = Jp[..., 1] * iz
        J[..., 2] = Jp[..., 0] * (-n[..., 0] / z)[..., None] + Jp[..., 1] * (-n[..., 1] / z)[..., None]
        return (self.normalised_to_pixel(n) if pixels else None), J

    def undistort(self, uv: np.ndarray, iterations: int = 8) -> np.ndarray:
        """Raw pixels (N, 2) -> normalised undistorted coordinates (N, 2) (Gauss-Newton on the distortion).

        The distortion and its Jacobian of `distort` / `distort_jacobian` written out once per iteration on the
        two coordinate columns (the same expressions, so the same numbers, with a third of the array
        operations: this runs on every feature of every frame)."""
        uv = np.asarray(uv, float)
        d = np.stack([(uv[..., 0] - self.cu) / self.fu, (uv[..., 1] - self.cv) / self.fv], axis=-1)
        if self.k1 == self.k2 == self.p1 == self.p2 == 0.0:
            return d
        k1, k2, p1, p2 = self.k1, self.k2, self.p1, self.p2
        dx, dy = d[..., 0], d[..., 1]
        x, y = dx.copy(), dy.copy()
        for _ in range(iterations):
            xx, yy, xy = x * x, y * y, x * y
            r2 = xx + yy
            rad = 1.0 + k1 * r2 + k2 * r2 * r2
            # 2 * x * x == 2 * (x * x) etc. exactly (a factor 2 is exact); 2 * p1 * x * y is not 2 * p1 * xy
            ex = x * rad + 2 * p1 * x * y + p2 * (r2 + 2 * xx) - dx
            ey = y * rad + p1 * (r2 + 2 * yy) + 2 * p2 * x * y - dy
            drad = k1 + 2 * k2 * r2
            j00 = rad + 2 * xx * drad + 2 * p1 * y + 6 * p2 * x
            j01 = 2 * xy * drad + 2 * p1 * x + 2 * p2 * y  # = j10
            j11 = rad + 2 * yy * drad + 6 * p1 * y + 2 * p2 * x
            det = j00 * j11 - j01 * j01
            x -= (j11 * ex - j01 * ey) / det
            y -= (j00 * ey - j01 * ex) / det
            if np.abs(ex).max(initial=0.0) < 1e-13 and np.abs(ey).max(initial=0.0) < 1e-13:
                break
        return np.stack([x, y], axis=-1)
