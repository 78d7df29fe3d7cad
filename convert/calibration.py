"""The recording's calibration (``uwbcal.calibration``) as typed, validated objects.

One model for every way a calibration comes in: the ``--calibration`` YAML of ``convert bag``, the values of EuRoC's
sensor.yaml files, the converters' and the simulator's built-in calibrations, and the metadata of a recording
(checked again by ``info`` and ``run``, so a recording converted before this check is refused at once, naming the
key). Sections (imu, cameras, uwb, groundtruth, odometry) are optional; within a section the keys the pipeline
cannot do without are required, the others have a default that `Calibration.defaults_used` names.

Transforms (``T_imu_cam``): a 4x4 nested list, 16 numbers row by row, or OpenCV's ``{rows: 4, cols: 4, data}``;
finite, last row ``0 0 0 1``, the rotation orthonormal with determinant +1 within `ROTATION_TOL` (a calibration
printed with 4-5 digits is off by ~1e-5; a scaled or mirrored matrix by ~1), the translation within
`MAX_OFFSET_M`. Values are kept as given (not re-orthonormalised).
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Any, Literal

import numpy as np
from pydantic import (
    BaseModel,
    BeforeValidator,
    ConfigDict,
    Field,
    PrivateAttr,
    ValidationError,
    field_validator,
    model_validator,
)

from uwbcal.convert.sources import load_yaml
from uwbcal.pipeline.core.errors import InputError
from uwbcal.pipeline.core.noise import NOISE_KEYS
from uwbcal.pipeline.core.validation import validation_message

ROTATION_TOL = 1e-3  # max |R^T R - I| and |det R - 1| of a rotation taken as one
MAX_OFFSET_M = 100.0  # no sensor or antenna of one rig is farther than this from its IMU
MAX_SIGMA_RANGE_M = 10.0  # a UWB range noise beyond this is a unit or typing error, not a sensor
MAX_NOISE = 10.0  # IMU noise densities / random walks (SI units) beyond this are no IMU's
MAX_VALUE = 1e6  # no other calibration number (rates, sigmas, times) is this large
ID_MAX = 2**32 - 1  # tag ids are uint32 in the recording

_STRICT = ConfigDict(extra="forbid", strict=True, allow_inf_nan=False)


def _matrix(value: Any) -> np.ndarray:
    """A 4x4 / 3x4 / ... nested list, flat list, or {rows, cols, data} -> a float array (its own shape)."""
    if isinstance(value, dict) and {"rows", "cols", "data"} <= set(value):
        rows, cols = value["rows"], value["cols"]
        data = np.asarray(value["data"], float)
        if not isinstance(rows, int) or not isinstance(cols, int) or data.size != rows * cols:
            raise ValueError(f"{{rows: {rows}, cols: {cols}}} with {data.size} numbers")
        return data.reshape(rows, cols)
    if (
        isinstance(value, (list, tuple))
        and all(isinstance(v, (int, float)) for v in value)
        and len(value) == 16
    ):
        return np.asarray(value, float).reshape(4, 4)
    if not isinstance(value, (list, tuple)) or not all(isinstance(r, (list, tuple)) for r in value):
        raise ValueError(f"a {type(value).__name__}")
    if len({len(r) for r in value}) != 1:
        raise ValueError("rows of different lengths")
    if not all(isinstance(v, (int, float)) and not isinstance(v, bool) for r in value for v in r):
        raise ValueError("non-numeric entries")
    return np.asarray(value, float)


def check_rigid(T: np.ndarray) -> str | None:
    """What is wrong with a 4x4 rigid transform, or None."""
    if T.shape != (4, 4):
        rows, cols = T.shape if T.ndim == 2 else (T.size, 1)
        extra = " (append the row 0, 0, 0, 1)" if (rows, cols) == (3, 4) else ""
        return f"a {rows}x{cols} matrix; give the 4x4 homogeneous transform{extra}"
    if not np.isfinite(T).all():
        return "NaN/inf entries; give finite numbers"
    if not np.allclose(T[3], [0.0, 0.0, 0.0, 1.0], atol=ROTATION_TOL):
        return f"last row {T[3].tolist()}, not 0, 0, 0, 1; give a homogeneous transform"
    R = T[:3, :3]
    det = float(np.linalg.det(R))
    off = float(np.abs(R.T @ R - np.eye(3)).max())
    if det < 0:
        return (
            f"its rotation is a reflection (det {det:.3g}): one axis is mirrored; check the axes' signs (a "
            "right-handed rotation has det +1)"
        )
    if off > ROTATION_TOL or abs(det - 1.0) > ROTATION_TOL:
        return (
            f"its rotation is not orthonormal (max |RᵀR − I| = {off:.3g}, det {det:.4g}; tolerance "
            f"{ROTATION_TOL:g}); give a rotation matrix with enough digits"
        )
    dist = float(np.linalg.norm(T[:3, 3]))
    if dist > MAX_OFFSET_M:
        return f"translation {dist:.4g} m (> {MAX_OFFSET_M:g} m); give it in metres"
    return None


def _transform(value: Any) -> list[list[float]]:
    try:
        T = _matrix(value)
    except (ValueError, TypeError) as exc:
        raise ValueError(
            f"not a matrix ({exc}); give the 4x4 transform as 4 rows of 4 numbers, 16 numbers, or "
            "{rows: 4, cols: 4, data: [16 numbers]}"
        ) from None
    problem = check_rigid(T)
    if problem:
        raise ValueError(problem)
    return T.tolist()


def rigid_transform(value: Any, source: str, key: str) -> np.ndarray:
    """A validated 4x4 rigid transform (see the module docstring); InputError ``<source>: <key>: ...``."""
    try:
        return np.asarray(_transform(value), float)
    except ValueError as exc:
        raise InputError(f"{source}: {key}: {exc}") from None


def _id_keys(value: Any) -> Any:
    """A mapping keyed by tag id with YAML integer keys (``0:`` unquoted) -> the same with text keys."""
    if isinstance(value, dict):
        return {str(k) if isinstance(k, int) and not isinstance(k, bool) else k: v for k, v in value.items()}
    return value


Transform = Annotated[list[list[float]], BeforeValidator(_transform)]
Positive = Annotated[float, Field(gt=0, le=MAX_VALUE)]
Noise = Annotated[float, Field(gt=0, le=MAX_NOISE)]
Vec3 = Annotated[list[float], Field(min_length=3, max_length=3)]


class ImuCalibration(BaseModel):
    model_config = _STRICT

    gyroscope_noise_density: Noise = Field(description="a gyroscope noise density > 0 [rad/s/sqrt(Hz)]")
    gyroscope_random_walk: Noise = Field(description="a gyroscope bias random walk > 0 [rad/s^2/sqrt(Hz)]")
    accelerometer_noise_density: Noise = Field(
        description="an accelerometer noise density > 0 [m/s^2/sqrt(Hz)]"
    )
    accelerometer_random_walk: Noise = Field(
        description="an accelerometer bias random walk > 0 [m/s^3/sqrt(Hz)]"
    )
    rate_hz: Positive | None = Field(None, description="the IMU rate > 0 [Hz] (default 200)")
    noise_origin: Literal["allan", "tuned"] | None = Field(
        None,
        description="where the noise values come from: allan (a static Allan-variance / datasheet figure, which "
        "leaves out vibration and scale-factor errors in motion: uwbcal run inflates it for a real IMU) or tuned "
        "(the values an estimator was tuned with on such data); unset: used as given",
    )


class CameraCalibration(BaseModel):
    model_config = _STRICT

    intrinsics: list[float] = Field(
        min_length=4, max_length=4, description="4 numbers [fu, fv, cu, cv] in pixels (fu, fv > 0)"
    )
    distortion_model: Literal["radtan", "none"] = Field(
        "radtan", description="radtan (k1, k2, p1, p2) or none; other models are not supported"
    )
    distortion: list[float] | None = Field(
        None, min_length=4, max_length=4, description="4 radtan coefficients [k1, k2, p1, p2]"
    )
    resolution: list[int] | None = Field(
        None, min_length=2, max_length=2, description="[width, height] in pixels, those of the images"
    )
    rate_hz: Positive | None = Field(None, description="the camera rate > 0 [Hz]")
    T_imu_cam: Transform = Field(
        description="the 4x4 pose of the camera in the IMU frame (p_imu = T_imu_cam p_cam; the inverse of "
        "Kalibr's T_cam_imu)"
    )
    topic: str | None = Field(None, description="the source topic of the images")

    @field_validator("intrinsics")
    @classmethod
    def _focal(cls, v: list[float]) -> list[float]:
        if v[0] <= 0 or v[1] <= 0:
            raise ValueError(f"focal lengths fu = {v[0]}, fv = {v[1]}; give positive focal lengths in pixels")
        if v[2] < 0 or v[3] < 0:
            raise ValueError(
                f"principal point cu = {v[2]}, cv = {v[3]}; give it in pixels from the top-left corner"
            )
        return v

    @model_validator(mode="after")
    def _centre_in_image(self) -> CameraCalibration:
        problem = self.centre_problem(self.resolution)
        if problem:
            raise ValueError(f"{problem}; check intrinsics [fu, fv, cu, cv] and resolution [width, height]")
        return self

    def centre_problem(self, size: list[int] | tuple[int, int] | None) -> str | None:
        """What is wrong with the principal point for images of ``size`` (width, height), or None."""
        cu, cv = self.intrinsics[2], self.intrinsics[3]
        if size is None or (cu <= size[0] and cv <= size[1]):
            return None
        return f"principal point ({cu}, {cv}) outside the {size[0]}x{size[1]} image"

    @field_validator("resolution")
    @classmethod
    def _size(cls, v: list[int] | None) -> list[int] | None:
        if v is not None and min(v) <= 0:
            raise ValueError(f"{v}; give [width, height] > 0 in pixels")
        return v

    @property
    def T(self) -> np.ndarray:
        return np.asarray(self.T_imu_cam, float)

    def check_image_size(self, size: tuple[int, int], images: str, source: str, key: str) -> None:
        """The images' (width, height) against ``resolution`` (intrinsics are per image size); InputError
        ``<source>: <key>: ...`` naming where the images are (``images``)."""
        if self.resolution is None:
            problem = self.centre_problem(size)
            if problem:  # no resolution to compare: the intrinsics must at least fit these images
                raise InputError(
                    f"{source}: {key.rsplit('.', 1)[0]}.intrinsics: {problem} {images}; give the calibration of "
                    "this camera at its image size (intrinsics scale with it), with its resolution"
                )
            return
        if tuple(self.resolution) == tuple(size):
            return
        raise InputError(
            f"{source}: {key}: {self.resolution[0]}x{self.resolution[1]}, but the images {images} are "
            f"{size[0]}x{size[1]}; give the calibration of this camera at its image size (intrinsics scale "
            "with it)"
        )


class TagCalibration(BaseModel):
    model_config = _STRICT

    antennas: list[Vec3] = Field(
        min_length=1, description="a list of antenna lever arms [[x, y, z], ...] in the IMU frame [m]"
    )

    @field_validator("antennas")
    @classmethod
    def _near(cls, v: list[list[float]]) -> list[list[float]]:
        far = [a for a in v if np.linalg.norm(a) > MAX_OFFSET_M]
        if far:
            raise ValueError(f"lever arm {far[0]} is > {MAX_OFFSET_M:g} m long; give it in metres")
        return v


class Prior(BaseModel):
    model_config = _STRICT

    mean: float = Field(ge=-MAX_OFFSET_M, le=MAX_OFFSET_M, description="the prior mean [m]")
    sigma: Positive = Field(description="the prior sigma > 0")


class ScalePrior(BaseModel):
    model_config = _STRICT

    mean: float = Field(
        gt=0.5, lt=2.0, description="the prior mean of the distance scale (near 1: a clock's ppm error)"
    )
    sigma: Positive = Field(description="the prior sigma > 0")


class UwbCalibration(BaseModel):
    model_config = _STRICT

    tags: Annotated[dict[str, TagCalibration], BeforeValidator(_id_keys)] = Field(
        default_factory=dict,
        description="a mapping tag id -> {antennas: [[x, y, z], ...]} (default: every tag at the IMU origin)",
    )
    sigma_range: Annotated[float, Field(gt=0, le=MAX_SIGMA_RANGE_M)] | None = Field(
        None, description=f"the range noise sigma > 0 [m], at most {MAX_SIGMA_RANGE_M:g} m (default 0.1)"
    )
    gamma_prior: Prior | None = Field(None, description="the ranging offset prior {mean [m], sigma > 0 [m]}")
    beta_prior: ScalePrior | None = Field(
        None, description="the distance scale prior {mean between 0.5 and 2, sigma > 0}"
    )
    antenna_pattern_sigma: Annotated[float, Field(ge=0, le=1)] | None = Field(
        None,
        description="the size between 0 and 1 [m] of the antennas' direction-dependent range bias, per component "
        "of a bias linear in the direction of arrival (default 0.05)",
    )
    ranging_bias_per_tag: Annotated[dict[str, float], BeforeValidator(_id_keys)] | None = Field(
        None, description="a mapping tag id -> ranging bias [m] (true = measured + bias)"
    )

    @field_validator("tags", "ranging_bias_per_tag")
    @classmethod
    def _tag_ids(cls, v: dict | None) -> dict | None:
        for k in v or {}:
            if not k.isdigit() or int(k) > ID_MAX:
                raise ValueError(f"tag id {k!r}; tag ids are integers 0..{ID_MAX}")
        return v


class GroundTruthCalibration(BaseModel):
    model_config = _STRICT

    lever_arm: Vec3 = Field(
        default_factory=lambda: [0.0, 0.0, 0.0],
        description="the ground-truth point in the IMU frame [x, y, z] in metres (e.g. a prism)",
    )
    frame: str = Field("body", description="what the ground truth tracks: body, prism, ...")

    @field_validator("lever_arm")
    @classmethod
    def _near(cls, v: list[float]) -> list[float]:
        if np.linalg.norm(v) > MAX_OFFSET_M:
            raise ValueError(f"lever arm {v} is > {MAX_OFFSET_M:g} m long; give it in metres")
        return v


class OdometryCalibration(BaseModel):
    model_config = _STRICT

    error_model: Literal["drift", "bounded"] = Field(
        "drift", description="drift (dead reckoning) or bounded (poses in the anchors' world frame)"
    )
    correlation_time_s: Positive | None = Field(None, description="the pose error's correlation time > 0 [s]")
    noise: dict[str, Positive] | None = Field(
        None, description=f"drift sigmas > 0 by name: {', '.join(NOISE_KEYS)}"
    )
    source: str | None = Field(None, description="what produced the poses")

    @field_validator("noise")
    @classmethod
    def _noise_keys(cls, v: dict | None) -> dict | None:
        bad = sorted(set(v or {}) - set(NOISE_KEYS))
        if bad:
            raise ValueError(f"unknown key(s) {', '.join(bad)}; known: {', '.join(NOISE_KEYS)}")
        return v


class Calibration(BaseModel):
    """``uwbcal.calibration``: sections for the sensors the recording has."""

    model_config = _STRICT

    imu: ImuCalibration | None = Field(
        None, description="the IMU noise (imu: {gyroscope_noise_density, ...})"
    )
    cameras: dict[str, CameraCalibration] = Field(
        default_factory=dict, description="a mapping camera name (cam0, cam1) -> its calibration"
    )
    uwb: UwbCalibration | None = Field(None, description="the UWB tags and range model")
    groundtruth: GroundTruthCalibration | None = Field(None, description="the ground truth's lever arm")
    odometry: OdometryCalibration | None = Field(None, description="the external odometry's error model")
    _source: str = PrivateAttr("calibration")

    def to_metadata(self) -> dict:
        """The JSON record of the recording (unset optional keys left out)."""
        out = self.model_dump(mode="json", exclude_none=True)
        if not out.get("cameras"):
            out.pop("cameras", None)
        return out

    def defaults_used(self) -> list[str]:
        """One note per default the pipeline will take for a key this calibration leaves out."""
        notes = []
        if self.imu is not None and self.imu.rate_hz is None:
            notes.append("imu.rate_hz not given: 200 Hz assumed")
        for name, c in self.cameras.items():
            if c.distortion is None and c.distortion_model != "none":
                notes.append(f"cameras.{name}.distortion not given: no distortion assumed")
            if c.resolution is None:
                notes.append(f"cameras.{name}.resolution not given: not checked against the images")
        if self.uwb is not None:
            if not self.uwb.tags:
                notes.append("uwb.tags not given: every tag at the IMU origin (zero lever arms)")
            if self.uwb.sigma_range is None:
                notes.append("uwb.sigma_range not given: 0.1 m assumed")
        return notes


def parse_calibration(data: Any, source: str) -> Calibration:
    """``data`` (a calibration mapping) validated; InputError ``<source>: <key.path>: <problem>; <fix>``."""
    if not isinstance(data, dict):
        raise InputError(
            f"{source}: expected a mapping with imu, cameras, uwb, groundtruth, odometry sections"
        )
    try:
        cal = Calibration.model_validate(data)
    except ValidationError as exc:
        raise InputError(validation_message(exc, Calibration, source)) from None
    cal._source = source
    return cal


def parse_section(model: type[BaseModel], data: dict, source: str, keys: dict[str, str] | None = None) -> Any:
    """One section of a calibration given in another layout (EuRoC's sensor.yaml) validated by its ``model``
    (`ImuCalibration`, `CameraCalibration`); ``keys``: model key -> the key as the file spells it, for the
    message (InputError ``<source>: <file key>: <problem>; <fix>``)."""
    try:
        return model.model_validate(data)
    except ValidationError as exc:
        raise InputError(validation_message(exc, model, source, keys)) from None


def load_calibration_yaml(path: str | Path) -> Calibration:
    """A calibration YAML in the layout of ``uwbcal.calibration`` (OpenCV's ``%YAML:1.0`` header tolerated)."""
    return parse_calibration(load_yaml(path, "calibration yaml"), str(path))
