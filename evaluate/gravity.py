"""The ground truth of a recording in the gravity-aligned frame (`pipeline.core.gravity`).

A filter started by the static initialiser estimates in a gravity-aligned frame and is compared with the ground
truth after a position + yaw alignment (its unobservable directions). Against a ground truth whose frame
is not level (motion capture), a perfect filter would show the tilt as a constant orientation error its
covariance rightly does not hold, and position errors growing with the distance from the alignment's centre. The
evaluator therefore first turns the ground truth and the reference anchors into the gravity-aligned frame fitted
to the recording's own IMU (`level_truth`; a rotation without yaw).
"""

from __future__ import annotations

from dataclasses import replace
from typing import TYPE_CHECKING

import numpy as np

from uwbcal.convert.recording import TOPIC_GT_IMU_BIAS, TOPIC_IMU
from uwbcal.pipeline.core.geometry import quat_to_rot
from uwbcal.pipeline.core.gravity import GravityFit, fit_gravity

if TYPE_CHECKING:
    from uwbcal.convert.recording import RecordingReader
    from uwbcal.evaluate.anchor_report import AnchorReference
    from uwbcal.evaluate.export import GroundTruth


def recording_gravity(reader: RecordingReader, gt: GroundTruth) -> GravityFit | None:
    """`fit_gravity` on a recording: its ``/imu`` against the ground-truth poses ``gt`` (moved from the
    ground-truth point to the IMU by the lever arm), with ``/groundtruth/imu_bias`` when the recording has it.
    None without an IMU or ground-truth orientations."""

    topics = reader.topics()
    if gt.q_xyzw is None or TOPIC_IMU not in topics or len(gt.t_ns) < 4:
        return None
    lo, hi = int(gt.t_ns[0]), int(gt.t_ns[-1]) + 1
    imu = reader.read_imu(TOPIC_IMU, lo, hi)
    bias = None
    if TOPIC_GT_IMU_BIAS in topics:
        b = reader.read_imu(TOPIC_GT_IMU_BIAS, lo, hi)
        if len(b.t_ns) >= 2:
            bias = np.stack([np.interp(imu.t_ns, b.t_ns, b.acc[:, k]) for k in range(3)], axis=1)
    p_imu = gt.p - np.einsum("nij,j->ni", quat_to_rot(gt.q_xyzw), gt.lever_arm)
    return fit_gravity(imu.t_ns, imu.acc, gt.t_ns, p_imu, gt.q_xyzw, bias)


def level_truth(
    reader: RecordingReader, gt: GroundTruth, ref: AnchorReference | None
) -> tuple[GroundTruth, AnchorReference | None, dict]:
    """The ground truth and the reference anchors in the gravity-aligned frame (`recording_gravity`), and what
    was done (metrics.json ``truth_levelled``). Left as they are when the fit is undetermined or its tilt is
    within 3 sigma of zero."""
    fit = recording_gravity(reader, gt)
    if fit is None:
        return (
            gt,
            ref,
            {"levelled": False, "why": "gravity not determined (no IMU, or a platform that never turns)"},
        )
    info = {"levelled": False, **fit.summary()}
    if fit.tilt_deg <= 3 * fit.tilt_sigma_deg:
        info["why"] = "tilt within 3 sigma of zero"
        return gt, ref, info
    lev = fit.level()
    gt = replace(gt, p=lev.positions(gt.p), q_xyzw=lev.quats(gt.q_xyzw))
    if ref is not None and ref.same_frame:
        anchors = {
            k: {**v, "position": [float(c) for c in lev.positions(np.asarray(v["position"], float))]}
            for k, v in ref.anchors.items()
        }
        ref = replace(ref, anchors=anchors)
    info["levelled"] = True
    return gt, ref, info
