"""What `uwbcal check` reads from a recording: the ranges, one pose source, the lever arms and (optionally) the anchors'
truth, with the tag position of any range at any clock shift (`CheckData.tag_positions`)."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from uwbcal.convert.anchor_truth import POSE_FRAMES, read_anchor_truth
from uwbcal.convert.calibration import parse_calibration
from uwbcal.convert.recording import (
    TOPIC_GT_POSE,
    TOPIC_GT_POSITION,
    TOPIC_ODOM,
    TOPIC_RANGE,
    RangeData,
    RecordingReader,
)
from uwbcal.pipeline.core.errors import InputError
from uwbcal.pipeline.core.geometry import quat_to_rot
from uwbcal.pipeline.core.series import interpolate_positions, interpolate_quats

POSE_GAP_S = 0.5  # a range inside a longer gap of the poses has no pose to compare with
DEFAULT_SIGMA_RANGE = 0.1


@dataclass
class Poses:
    source: str  # the topic
    t_ns: np.ndarray
    p: np.ndarray
    q_xyzw: np.ndarray | None  # None: positions only (no attitude, lever arms cannot act)


@dataclass
class CheckData:
    path: Path
    ranges: RangeData  # stamp order
    file_order_t_ns: np.ndarray  # the range stamps as written
    poses: Poses | None
    levers: dict[tuple[int, int], np.ndarray]  # (tag, antenna) -> lever arm in the body frame
    truth: dict[int, np.ndarray] | None  # anchor id -> position, in the poses' frame
    truth_label: str = ""
    sigma_range: float = DEFAULT_SIGMA_RANGE
    dropped: list[dict] = field(default_factory=list)  # the converter's drops of range rows
    notes: list[str] = field(default_factory=list)

    def lever_of(self, tag: np.ndarray, antenna: np.ndarray, levers=None) -> np.ndarray:
        """(N, 3) lever arm of each range's antenna (``levers`` overrides the recording's)."""
        levers = self.levers if levers is None else levers
        out = np.zeros((len(tag), 3))
        for (t, a), arm in levers.items():
            out[(tag == t) & (antenna == a)] = arm
        return out

    def covered(self, t_ns: np.ndarray) -> np.ndarray:
        """Stamps with a pose on either side closer than POSE_GAP_S."""
        if self.poses is None or len(self.poses.t_ns) < 2:
            return np.zeros(len(t_ns), bool)
        tp = self.poses.t_ns
        inside = (t_ns >= tp[0]) & (t_ns <= tp[-1])
        i1 = np.clip(np.searchsorted(tp, t_ns), 1, len(tp) - 1)
        return inside & ((tp[i1] - tp[i1 - 1]) <= POSE_GAP_S * 1e9)

    def tag_positions(
        self, idx: np.ndarray, shift_s: float = 0.0, levers=None
    ) -> tuple[np.ndarray, np.ndarray | None]:
        """Tag positions of the ranges ``idx`` with the poses taken ``shift_s`` later, and the rotations (None for
        position-only poses). The stamps must be `covered` at that shift."""
        r, ps = self.ranges, self.poses
        t = r.t_ns[idx] + round(shift_s * 1e9)
        p = interpolate_positions(ps.t_ns, ps.p, t)
        if ps.q_xyzw is None:
            return p, None
        R = quat_to_rot(interpolate_quats(ps.t_ns, ps.q_xyzw, t))
        arm = self.lever_of(r.tag[idx], r.antenna[idx], levers)
        return p + np.einsum("nij,nj->ni", R, arm), R


def _poses(reader: RecordingReader, frame: str | None) -> tuple[Poses | None, str]:
    """The pose source the anchors' frame names (odometry / world), else ground truth, odometry, positions."""
    topics = reader.topics()
    order = [TOPIC_GT_POSE, TOPIC_ODOM, TOPIC_GT_POSITION]
    if frame == "odometry":
        order = [TOPIC_ODOM, TOPIC_GT_POSE, TOPIC_GT_POSITION]
    for topic in order:
        if topic not in topics or topics[topic].count < 2:
            continue
        if topic == TOPIC_GT_POSITION:
            d = reader.read_positions()
            return Poses(topic, d.t_ns, d.p, None), ""
        d = reader.read_odometry() if topic == TOPIC_ODOM else reader.read_poses()
        if np.ptp(d.q_xyzw, axis=0).max() < 1e-9:  # one attitude throughout: positions written as poses
            return Poses(topic, d.t_ns, d.p, None), f"{topic}: one attitude throughout (positions only)"
        return Poses(topic, d.t_ns, d.p, d.q_xyzw), ""
    return None, "no poses in the recording (no ground truth or odometry): the pose checks need a VIO run"


def _levers(calibration: dict) -> dict[tuple[int, int], np.ndarray]:
    out = {}
    tags = (calibration.get("uwb") or {}).get("tags") or {}
    for tag, spec in tags.items():
        for k, arm in enumerate((spec or {}).get("antennas") or []):
            out[(int(tag), k)] = np.asarray(arm, float)
    return out


def _truth(reader: RecordingReader, anchors_truth: Path | None) -> tuple[dict | None, str, str | None]:
    if anchors_truth is not None:
        rows = read_anchor_truth(anchors_truth)
        return {int(a): np.asarray(v["position"], float) for a, v in rows.items()}, anchors_truth.name, None
    truth = reader.truth or {}
    anchors = truth.get("anchors") or {}
    if not anchors:
        return None, "", None
    frame = str(truth.get("anchors_frame", "world"))
    label = str(truth.get("kind", "truth"))
    if frame not in POSE_FRAMES:
        return None, f"{label} anchors in frame {frame!r} (not the poses'): not compared", frame
    return {int(a): np.asarray(v["position"], float) for a, v in anchors.items()}, label, frame


def load_check_data(recording: str | Path, anchors_truth: str | Path | None = None) -> CheckData:
    path = Path(recording)
    if not path.is_file():
        raise InputError(f"{path}: no such recording; convert the data first (uwbcal convert ...)")
    reader = RecordingReader(path)
    parse_calibration(reader.calibration, f"{path}: uwbcal.calibration")  # what run refuses, check refuses
    if TOPIC_RANGE not in reader.topics():
        raise InputError(f"{path}: no UWB ranges ({TOPIC_RANGE}); nothing to check")
    truth, label, frame = _truth(reader, Path(anchors_truth) if anchors_truth is not None else None)
    poses, why = _poses(reader, frame)
    notes = [why] if why else []
    if truth is None and label:
        notes.append(label)
    cal = reader.calibration
    dropped = [d for d in reader.source.get("dropped") or [] if d.get("topic") == TOPIC_RANGE]
    return CheckData(
        path=path,
        ranges=reader.read_ranges(),
        file_order_t_ns=reader.read_ranges(file_order=True).t_ns,
        poses=poses,
        levers=_levers(cal),
        truth=truth,
        truth_label=label if truth is not None else "",
        sigma_range=float((cal.get("uwb") or {}).get("sigma_range") or DEFAULT_SIGMA_RANGE),
        dropped=dropped,
        notes=notes,
    )
