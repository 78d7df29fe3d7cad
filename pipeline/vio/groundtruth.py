"""The IMU state at a stamp from a recording's ground truth (simulation, or a real recording's reference)."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from uwbcal.pipeline.core.errors import InputError
from uwbcal.pipeline.core.geometry import quat_slerp, quat_to_rot
from uwbcal.pipeline.core.state import ImuState
from uwbcal.pipeline.core.topics import TOPIC_GT_IMU_BIAS, TOPIC_GT_POSE

if TYPE_CHECKING:
    from uwbcal.convert.recording import RecordingReader


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
