"""Noise models the filters assume and the simulator draws from (one definition for both).

Odometry drift (a random walk per increment, so that the added variance does not depend on the odometry rate),
per axis:

    var_theta += sigma_theta_per_sqrt_rad^2 |dtheta| + sigma_theta_per_sqrt_m^2 |dp| + sigma_theta_per_sqrt_s^2 dt
    var_p     += sigma_p_per_sqrt_m^2 |dp|         + sigma_p_per_sqrt_s^2 dt
"""

from __future__ import annotations

import math
from typing import Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field


class OdometryFilterConfig(BaseModel):
    model_config = ConfigDict(extra="forbid")

    topic: str = Field("/odometry", description="the recording topic of the external odometry")
    sigma_p_per_sqrt_m: float = Field(
        0.02, ge=0, description="position random walk per metre travelled [m/√m]"
    )
    sigma_theta_per_sqrt_rad: float = Field(
        0.01, ge=0, description="rotation random walk per radian rotated [rad/√rad]"
    )
    sigma_theta_per_sqrt_m: float = Field(
        0.002, ge=0, description="rotation random walk per metre travelled [rad/√m]"
    )
    sigma_p_per_sqrt_s: float = Field(0.002, ge=0, description="position noise floor over time [m/√s]")
    sigma_theta_per_sqrt_s: float = Field(0.0005, ge=0, description="rotation noise floor over time [rad/√s]")
    initial_sigma_p: float = Field(0.01, gt=0, description="initial position sigma [m]")
    initial_sigma_theta_deg: float = Field(0.5, gt=0, description="initial orientation sigma [deg]")
    initial_from_message: bool = Field(
        False, description="take the initial covariance from the first message instead of the sigmas"
    )
    gap_warn_s: float = Field(1.0, gt=0, description="warn about odometry gaps longer than this")
    error_model: Literal["auto", "drift", "bounded"] = Field(
        "auto",
        description="drift: random walk (odometry); bounded: Gauss-Markov around a SLAM output in the world "
        "frame; auto: calibration odometry.error_model, else drift",
    )
    correlation_time_s: float | None = Field(
        None, gt=0, description="bounded model: error correlation time [s]; default calibration or 10 s"
    )


NOISE_KEYS = (
    "sigma_p_per_sqrt_m",
    "sigma_theta_per_sqrt_rad",
    "sigma_theta_per_sqrt_m",
    "sigma_p_per_sqrt_s",
    "sigma_theta_per_sqrt_s",
    "initial_sigma_p",
    "initial_sigma_theta_deg",
)


def increment_noise(config: OdometryFilterConfig, dR: np.ndarray, dp: np.ndarray, dt: float) -> np.ndarray:
    """Diagonal 6x6 covariance of the increment noise ``[n_theta, n_p]`` (see the module docstring)."""
    c = config
    angle = math.acos(max(-1.0, min(1.0, 0.5 * (dR[0, 0] + dR[1, 1] + dR[2, 2] - 1.0))))
    dist = math.sqrt(float(dp @ dp))
    dt = max(dt, 0.0)
    q_th = (
        c.sigma_theta_per_sqrt_rad**2 * angle
        + c.sigma_theta_per_sqrt_m**2 * dist
        + c.sigma_theta_per_sqrt_s**2 * dt
    )
    q_p = c.sigma_p_per_sqrt_m**2 * dist + c.sigma_p_per_sqrt_s**2 * dt
    return np.diag([q_th] * 3 + [q_p] * 3)
