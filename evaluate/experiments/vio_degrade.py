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

A real VIO's reported noise is commonly not its true noise (datasheet figures for a better IMU, no allowance for
vibration, temperature or a worn mount). The second knob ``vio_noise_told`` = t is that mis-tuning on its own:
the simulation keeps its factor k, the filter is told t times the EuRoC-like IMU figures instead
(``vio.imu_noise_inflation`` = t/k on the recording's calibration). Left unset, t = k (the consistent tuning
above); t < k is an IMU believed better than it is, so a VIO whose covariance under-reports its drift. The pixel
noise is told correctly (k px) whatever t is: the MSCKF's per-feature chi-squared gate is set by it, and telling
it 1-2 px of a true 4 px rejects every feature (measured on MH_01: 40 m of VIO error), which is a failure, not a
degraded VIO.
"""

from __future__ import annotations

import dataclasses

from pydantic import BaseModel, ConfigDict, Field

from uwbcal.convert.simulator import SimConfig
from uwbcal.pipeline.core.errors import InputError
from uwbcal.pipeline.vio.config import VioConfig


class VioDegrade(BaseModel):
    """``noise_scale`` k and ``told`` t (see the module doc): 1 = the simulator's EuRoC-like sensors; t = None
    means t = k."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    noise_scale: float = Field(
        1.0, gt=0, le=100, description="factor on the IMU noise densities, random walks and pixel noise"
    )
    told: float | None = Field(
        None,
        gt=0,
        le=100,
        description="the factor on the IMU figures the filter is told (None: the simulated one)",
    )

    @property
    def told_scale(self) -> float:
        """The factor the filter is told (``told``, or ``noise_scale`` when unset)."""
        return self.noise_scale if self.told is None else self.told

    @classmethod
    def of(cls, noise_scale: float, told: float | None = None, what: str = "vio_noise_scale") -> VioDegrade:
        """Validated; InputError naming the parameter otherwise."""
        for name, v in ((what, noise_scale), ("vio_noise_told", told)):
            if v is None and name != what:
                continue
            if not (isinstance(v, (int, float)) and not isinstance(v, bool) and 0 < v <= 100):
                raise InputError(f"{name}={v!r}: must be a number in (0, 100] (1 = the unchanged VIO)")
        return cls(noise_scale=float(noise_scale), told=None if told is None else float(told))

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
        """Pipeline config overrides: the MSCKF's pixel noise scaled like the simulated one; its IMU figures reach
        it through the recording's calibration (scaled like the simulation), so a told factor that differs from
        the simulated one is applied to them as ``imu_noise_inflation`` (told / simulated)."""
        base = base or VioConfig()
        out = {"pixel_sigma": base.pixel_sigma * self.noise_scale, "on_failure": "warn"}
        if self.told_scale != self.noise_scale:
            out["imu_noise_inflation"] = base.imu_noise_inflation * self.told_scale / self.noise_scale
        return {"vio": out}
