"""Export a run's estimate and its ground truth as TUM files (``uwbcal export RUN --format tum -o DIR``); the
anchors formats live in `evaluate.anchors_export`.

``DIR/estimate.tum`` holds the estimate at the stamps where ground truth exists; ``DIR/groundtruth.tum`` the ground
truth interpolated at those same stamps. When the ground truth is of a point on the body (lever arm, e.g. the
NTU-VIRAL prism), the estimate is moved to that point: ``p_est + R_est @ lever``. Position-only ground truth is
written with the identity orientation (it has none). Lines: ``t x y z qx qy qz qw``, t in seconds ``%.9f``.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from uwbcal.convert.recording import TOPIC_GT_POSE, TOPIC_GT_POSITION, RecordingReader
from uwbcal.evaluate.anchors_export import export_anchors
from uwbcal.evaluate.association import Association, associate, lever_point
from uwbcal.pipeline.core.atomic import write_text_atomic
from uwbcal.pipeline.core.errors import InputError
from uwbcal.pipeline.run import artefacts
from uwbcal.pipeline.run.config import run_config
from uwbcal.pipeline.run.provenance import check_recording
from uwbcal.pipeline.run.rundir import RunDir

TRAJECTORY = "trajectory.npz"
VIO_TRAJECTORY = "vio.npz"
CONFIG = "config.toml"


@dataclass
class RunTrajectory:
    """The estimate of a run (``trajectory.npz``): pose, 6x6 ``[dtheta, dp]`` covariance, segment id per sample
    (0 init, 1 refine, 2 localize)."""

    t_ns: np.ndarray
    p: np.ndarray
    q_xyzw: np.ndarray
    cov: np.ndarray | None
    segment: np.ndarray | None

    def __len__(self) -> int:
        return len(self.t_ns)


@dataclass
class GroundTruth:
    t_ns: np.ndarray
    p: np.ndarray
    q_xyzw: np.ndarray | None  # None: position-only
    lever_arm: np.ndarray  # (3,) ground-truth point in the body (IMU) frame
    topic: str


def load_run_trajectory(run_dir: str | Path) -> RunTrajectory:
    """Read ``run_dir/trajectory.npz`` (arrays ``t_ns``, ``p``, ``q_xyzw`` and optionally ``cov``, ``segment``);
    a run stopped after the vio stage has only ``vio.npz`` (same arrays, no segments), used as a fallback."""
    path = Path(run_dir) / TRAJECTORY
    if not artefacts.present(path) and artefacts.present(Path(run_dir) / VIO_TRAJECTORY):
        path = Path(run_dir) / VIO_TRAJECTORY
    if not artefacts.present(path):
        raise InputError(f"{path}: missing; run the pipeline first (uwbcal run REC -o {run_dir})")
    arr = artefacts.read_trajectory(path)
    return RunTrajectory(
        t_ns=arr["t_ns"].astype(np.int64),
        p=arr["p"].astype(float),
        q_xyzw=arr["q_xyzw"].astype(float),
        cov=arr["cov"].astype(float) if "cov" in arr else None,
        segment=arr["segment"].astype(np.int64) if "segment" in arr else None,
    )


def run_recording_path(run_dir: str | Path) -> Path:
    """The recording of a run: ``[run] recording`` in ``run_dir/config.toml`` (relative paths tried against the
    working directory, then the run directory), which every stage recorded must have run on."""
    cfg_path = Path(run_dir) / CONFIG
    rec = run_config(Path(run_dir)).run.recording
    if not rec:
        raise InputError(f"{cfg_path}: [run] recording: not set; the run directory is incomplete")
    p = Path(rec).expanduser()
    if not p.is_absolute() and not p.exists() and (Path(run_dir) / p).exists():
        p = Path(run_dir) / p
    if not p.exists():
        raise InputError(f"{cfg_path}: [run] recording: {p} does not exist; was the recording moved?")
    check_recording(RunDir(Path(run_dir)), p)
    return p


def load_ground_truth(recording: str | Path) -> GroundTruth:
    """Ground truth of a recording: ``/groundtruth/pose`` if present, else ``/groundtruth/position``, with the
    lever arm from ``calibration["groundtruth"]["lever_arm"]`` (zero when absent)."""

    reader = RecordingReader(recording)
    topics = reader.topics()
    lever = np.asarray(
        (reader.calibration.get("groundtruth") or {}).get("lever_arm") or [0.0, 0.0, 0.0], float
    )
    if lever.shape != (3,):
        raise InputError(
            f"{recording}: uwbcal.calibration: groundtruth.lever_arm must be 3 numbers, got {lever}"
        )
    if TOPIC_GT_POSE in topics and topics[TOPIC_GT_POSE].count > 0:
        d = reader.read_poses(TOPIC_GT_POSE)
        return GroundTruth(d.t_ns, d.p, d.q_xyzw, lever, TOPIC_GT_POSE)
    if TOPIC_GT_POSITION in topics and topics[TOPIC_GT_POSITION].count > 0:
        d = reader.read_positions(TOPIC_GT_POSITION)
        return GroundTruth(d.t_ns, d.p, None, lever, TOPIC_GT_POSITION)
    raise InputError(
        f"{recording}: no ground truth ({TOPIC_GT_POSE} or {TOPIC_GT_POSITION}); nothing to compare"
    )


@dataclass
class Compared:
    """Estimate and ground truth at the same stamps, the estimate moved to the ground-truth point."""

    t_ns: np.ndarray
    p_est: np.ndarray  # at the ground-truth point (lever arm applied)
    q_est: np.ndarray
    p_gt: np.ndarray
    q_gt: np.ndarray | None
    assoc: Association


def compare(
    t_ns: np.ndarray, p: np.ndarray, q_xyzw: np.ndarray, gt: GroundTruth, max_gap_ns: int | None = None
) -> Compared:
    """Associate an estimate with ground truth (interpolated at the estimate stamps, lever arm applied)."""
    a = associate(t_ns, gt.t_ns, gt.p, gt.q_xyzw, max_gap_ns=max_gap_ns)
    if len(a) == 0:
        raise InputError(
            f"ground truth {gt.topic}: no overlap with the estimate "
            f"({a.n_outside} stamps outside its span, {a.n_gap} in gaps)"
        )
    q = np.asarray(q_xyzw, float)[a.idx]
    p_est = lever_point(np.asarray(p, float)[a.idx], q, gt.lever_arm)
    return Compared(a.t_ns, p_est, q, a.p, a.q_xyzw, a)


def format_stamps(t_ns: np.ndarray) -> list[str]:
    """Exact ``%.9f`` seconds from int64 nanoseconds (float64 would round the last digits)."""
    t = np.asarray(t_ns, np.int64)
    sign = np.where(t < 0, "-", "")
    a = np.abs(t)
    return [
        f"{s}{sec}.{ns:09d}"
        for s, sec, ns in zip(sign, (a // 1_000_000_000).tolist(), (a % 1_000_000_000).tolist(), strict=True)
    ]


def tum_text(t_ns: np.ndarray, p: np.ndarray, q_xyzw: np.ndarray) -> str:
    """TUM lines ``t x y z qx qy qz qw`` (positions and quaternions with round-trip precision)."""
    vals = np.concatenate(
        [np.asarray(p, float).reshape(-1, 3), np.asarray(q_xyzw, float).reshape(-1, 4)], axis=1
    )
    body = (" ".join(f"{v!r}" for v in row) for row in vals.tolist())
    return "".join(f"{t} {b}\n" for t, b in zip(format_stamps(t_ns), body, strict=True))


def export_tum(
    t_ns: np.ndarray,
    p: np.ndarray,
    q_xyzw: np.ndarray,
    gt: GroundTruth,
    out_dir: str | Path,
    max_gap_ns: int | None = None,
) -> tuple[Path, Path, Compared]:
    """Write ``out_dir/estimate.tum`` and ``out_dir/groundtruth.tum`` at the associated stamps (atomic)."""
    c = compare(t_ns, p, q_xyzw, gt, max_gap_ns)
    out_dir = Path(out_dir)
    q_gt = c.q_gt if c.q_gt is not None else np.tile([0.0, 0.0, 0.0, 1.0], (len(c.t_ns), 1))
    est_path, gt_path = out_dir / "estimate.tum", out_dir / "groundtruth.tum"
    write_text_atomic(est_path, tum_text(c.t_ns, c.p_est, c.q_est))
    write_text_atomic(gt_path, tum_text(c.t_ns, c.p_gt, q_gt))
    return est_path, gt_path, c


FORMATS = ("tum", "anchors-yaml", "anchors-json")


def export_run(run_dir: str | Path, output: str | Path, fmt: str = "tum") -> str:
    """``uwbcal export``: the TUM pair of a run (the estimate alone when the recording has no ground truth), or
    its anchors (`evaluate.anchors_export`); returns a one-paragraph summary."""
    if fmt not in FORMATS:
        raise InputError(f"--format {fmt}: unsupported; choose one of {', '.join(FORMATS)}")
    out = Path(output)
    if out.exists() and not out.is_dir():
        raise InputError(
            f"{out}: exists and is not a directory; export writes a folder (estimate.tum, groundtruth.tum, or the anchor files) — "
            "give a directory path"
        )
    if fmt != "tum":
        return export_anchors(run_dir, output, fmt)
    tr = load_run_trajectory(run_dir)
    try:
        gt = load_ground_truth(run_recording_path(run_dir))
    except InputError as exc:
        if "no ground truth" not in str(exc):
            raise
        est_path = Path(output) / "estimate.tum"
        write_text_atomic(est_path, tum_text(tr.t_ns, tr.p, tr.q_xyzw))
        return (
            f"wrote {est_path}: {len(tr.t_ns)} poses (the recording has no ground truth: the estimate alone)"
        )
    est_path, gt_path, c = export_tum(tr.t_ns, tr.p, tr.q_xyzw, gt, output)
    lines = [
        f"wrote {est_path} and {gt_path}: {len(c.t_ns)} poses "
        f"({c.assoc.n_outside} estimate stamps outside the ground truth, {c.assoc.n_gap} in ground-truth gaps)",
        f"ground truth: {gt.topic}, lever arm {np.round(gt.lever_arm, 4).tolist()} applied to the estimate",
    ]
    if c.assoc.n_gt_glitches:
        lines.append(
            f"ground truth: {c.assoc.n_gt_glitches} glitch sample(s) dropped before interpolating (a jump away "
            "and back no carrier can make in one sample interval)"
        )
    if gt.q_xyzw is None:
        lines.append("ground truth is position-only: groundtruth.tum carries the identity orientation")
    return "\n".join(lines)
