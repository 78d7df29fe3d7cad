"""The experiments' VIO-degrade knob: a worse visual-inertial sensor suite, simulated and believed alike.

Real VIO drifts more when its sensors are worse: a consumer MEMS IMU has noise densities and bias random walks
several times those of EuRoC's ADIS16448, and a blurred, low-resolution or rolling-shutter camera measures its
features with a larger pixel noise. The knob ``vio_noise_scale`` = k multiplies all four IMU noise figures
(white noise and random walk, gyroscope and accelerometer) and the feature pixel noise by k — in the simulated
data *and* in what the filter is told (the recording's calibration carries the IMU figures; ``vio.pixel_sigma``
the pixel noise), so the extra drift is drift the MSCKF's covariance accounts for, not a hidden bias. With every
noise scaled by one factor the (linearised) estimation error scales by that factor too, so the VIO's position
error and its own position sigma grow about linearly in k. k = 1 is the unchanged simulation (the default of
every experiment, so the regression references stay as they are).
"""

from __future__ import annotations

import dataclasses

from pydantic import BaseModel, ConfigDict, Field

from convert.simulator import SimConfig
from pipeline.core.errors import InputError
from pipeline.msckf import VioConfig


class VioDegrade(BaseModel):
    """``noise_scale`` k (see the module doc): 1 = the simulator's EuRoC-like sensors."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    noise_scale: float = Field(
        1.0, gt=0, le=100, description="factor on the IMU noise densities, random walks and pixel noise"
    )

    @classmethod
    def of(cls, noise_scale: float, what: str = "vio_noise_scale") -> VioDegrade:
        """Validated; InputError naming the parameter otherwise."""
        if not (isinstance(noise_scale, (int, float)) and 0 < noise_scale <= 100):
            raise InputError(f"{what}={noise_scale!r}: must be a number in (0, 100] (1 = unchanged VIO)")
        return cls(noise_scale=float(noise_scale))

    def sim(self, base: SimConfig) -> SimConfig:
        """``base`` with its IMU and pixel noise scaled."""
        k = self.noise_scale
        return dataclasses.replace(
            base,
            gyro_noise_density=base.gyro_noise_density * k,
            gyro_random_walk=base.gyro_random_walk * k,
            acc_noise_density=base.acc_noise_density * k,
            acc_random_walk=base.acc_random_walk * k,
            pixel_sigma=base.pixel_sigma * k,
        )

    def config(self, base: VioConfig | None = None) -> dict:
        """Pipeline config overrides: the MSCKF's pixel noise scaled like the simulated one (the IMU figures
        reach it through the recording's calibration)."""
        return {"vio": {"pixel_sigma": (base or VioConfig()).pixel_sigma * self.noise_scale}}
