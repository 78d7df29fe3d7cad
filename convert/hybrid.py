"""Real-IMU hybrid recordings: a converted recording's real IMU and ground truth, with camera feature tracks and
UWB ranges simulated along its real ground-truth trajectory (``uwbcal simulate --imu-from REC.mcap``).

Real (copied from the source recording): ``/imu`` (every message inside the ground truth's time span, values and
stamps unchanged), ``/groundtruth/pose`` and, when present, ``/groundtruth/imu_bias``, and the IMU calibration
(noise densities as the dataset declares them). Simulated (`convert.simulator.simulate_world`, the simulator's
own generators): landmarks in a room around the trajectory, ``/cam0/features`` seen by the recording's cam0
calibration (intrinsics, radtan distortion, T_imu_cam, rate), anchors and ``/uwb/range``. ``uwbcal.source``
lists which topics are which.

The trajectory the tracks and ranges are simulated along is a cubic B-spline through the ground-truth poses of
the *IMU* frame: EuRoC's ground truth is the body frame B, which is imu0's frame (imu0 ``T_BS`` is the identity;
the converter expresses the ground truth in the IMU frame when it is not), and the calibration's ground-truth
lever arm, if any, is removed first. Its knots are ``knot_dt`` apart; at a knot spacing equal to the ground
truth's sample interval (EuRoC V1_01 at 20 Hz: 0.05 s) the spline passes through every ground-truth pose, so the
camera frames (at the same 20 Hz) sit at the real poses. Ground truth and IMU share one clock on EuRoC (the
ground truth is a batch fit of Vicon and this IMU; the gyro residual against the spline is smallest at 0-5 ms
lag), so no time offset is applied.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from uwbcal.convert.recording import (
    META_CALIBRATION,
    META_SOURCE,
    META_TRUTH,
    TOPIC_FEATURES,
    TOPIC_GT_IMU_BIAS,
    TOPIC_GT_POSE,
    TOPIC_IMU,
    TOPIC_RANGE,
    ImuData,
    RecordingReader,
)
from uwbcal.convert.simulator import (
    GroundTruthSim,
    ImuSim,
    SimConfig,
    SimData,
    WorldSim,
    camera_model,
    rel_seconds,
    simulate_world,
    uwb_calibration,
    world_truth,
    write_recording,
)
from uwbcal.convert.sources import sha256_file
from uwbcal.convert.trajectory import SplineTrajectory
from uwbcal.pipeline.core.errors import InputError
from uwbcal.pipeline.core.geometry import quat_to_rot
from uwbcal.pipeline.core.gravity import fit_gravity
from uwbcal.pipeline.core.series import sliding_mean

HYBRID_KNOT_DT = 0.05  # spline knots [s]: 20 Hz resolves a MAV's motion; equal to EuRoC V1_01's GT interval


def _gt_imu_frame(reader: RecordingReader) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(t_ns, p, q_xyzw) of the IMU frame from /groundtruth/pose and the calibration's ground-truth lever arm."""

    gt = reader.read_poses(TOPIC_GT_POSE)
    lever = np.asarray(reader.calibration.get("groundtruth", {}).get("lever_arm", [0.0, 0.0, 0.0]), float)
    p = gt.p - np.einsum("nij,j->ni", quat_to_rot(gt.q_xyzw), lever) if np.any(lever) else gt.p
    return gt.t_ns, p, gt.q_xyzw


def _camera(calibration: dict, source: str) -> tuple[dict, str]:
    cams = calibration.get("cameras") or {}
    if "cam0" not in cams:
        cam = camera_model()
        return cam, "the simulator's EuRoC cam0 (the recording has no cam0 calibration)"
    cam = dict(cams["cam0"])
    model = cam.get("distortion_model", "radtan")
    if model != "radtan":
        raise InputError(
            f"{source}: cam0 distortion model {model!r}: the simulator projects with radtan only; "
            "use a recording with a radtan cam0 calibration"
        )
    missing = [k for k in ("intrinsics", "distortion", "resolution", "T_imu_cam") if k not in cam]
    if missing:
        raise InputError(f"{source}: cam0 calibration lacks {missing}; re-convert the recording")
    cam.setdefault("rate_hz", 20.0)
    return cam, "the recording's cam0 calibration"


def imu_agreement(
    traj: SplineTrajectory,
    imu: ImuSim,
    gravity: float | np.ndarray,
    window_s: float = 1.0,
) -> dict:
    """How far the real IMU is from the trajectory its tracks are simulated along, over ``window_s`` means (the
    IMU's white noise averages out there; an attitude error of the ground truth relative to the IMU, a clock
    offset or the IMU's scale and misalignment do not): the angle between the measured specific force (its
    bias removed) and the one the trajectory's motion predicts, median and 90th percentile [deg], and the rms
    norm of the gyro's residual [rad/s]. ``gravity``: its magnitude (along -z of the trajectory's frame) or the
    vector in that frame (`pipeline.core.gravity.fit_gravity`: a motion-capture frame is not level)."""

    g_w = np.array([0.0, 0.0, -gravity]) if np.ndim(gravity) == 0 else np.asarray(gravity, float)
    s = traj.evaluate(rel_seconds(traj, imu.t_ns))
    f_pred = np.einsum("nji,nj->ni", s.R, s.a - g_w)
    dt = float(np.median(np.diff(imu.t_ns))) * 1e-9 if len(imu.t_ns) > 1 else window_s
    k = max(int(round(window_s / dt)), 1)
    if len(imu.t_ns) < k:
        return {}
    fm, fp = sliding_mean(imu.acc - imu.ba, k), sliding_mean(f_pred, k)
    cos = np.sum(fm * fp, axis=1) / (np.linalg.norm(fm, axis=1) * np.linalg.norm(fp, axis=1))
    tilt = np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))
    gyro = np.linalg.norm(sliding_mean(imu.gyro - imu.bg - s.w, k), axis=1)
    return {
        "window_s": window_s,
        "specific_force_angle_deg_median": float(np.median(tilt)),
        "specific_force_angle_deg_p90": float(np.percentile(tilt, 90)),
        "gyro_residual_rad_s_rms": float(np.sqrt(np.mean(gyro**2))),
    }


def groundtruth_level(
    t_gt: np.ndarray, p_gt: np.ndarray, q_gt: np.ndarray, imu: ImuSim, has_bias: bool, gravity: float
) -> tuple[np.ndarray, dict]:
    """Gravity in the ground truth's frame from the real IMU (`fit_gravity`; with the ground truth's bias when
    the recording has it) and what ``uwbcal.source`` says of it; (0, 0, -gravity) when undetermined."""
    fit = fit_gravity(imu.t_ns, imu.acc, t_gt, p_gt, q_gt, imu.ba if has_bias else None)
    if fit is None:
        return np.array([0.0, 0.0, -gravity]), {"determined": False}
    return fit.gravity, {"determined": True, **fit.summary()}


def hybrid_simulate(source: str | Path, cfg: SimConfig, knot_dt: float = HYBRID_KNOT_DT) -> SimData:
    """The hybrid recording's streams as arrays: real IMU and ground truth of ``source``, simulated tracks and
    ranges along its ground truth (``cfg``: the simulator's settings; its IMU and trajectory settings unused)."""

    source = Path(source)
    reader = RecordingReader(source)
    src = str(source)
    t_gt, p_gt, q_gt, imu_all, traj = _real_trajectory(reader, source, knot_dt)
    duration = traj.duration if cfg.duration is None else float(cfg.duration)
    if duration > traj.duration + 1e-9:
        raise InputError(
            f"{src}: duration {duration:g} s: IMU and ground truth overlap over {traj.duration:.1f} s; give a "
            "shorter --duration"
        )
    t_end = traj.t0_ns + int(round(duration * 1e9))
    imu, bias, gt = _real_streams(reader, imu_all, traj, t_end)
    m_gt = (t_gt >= traj.t0_ns) & (t_gt <= t_end)
    g_w, level = groundtruth_level(t_gt[m_gt], p_gt[m_gt], q_gt[m_gt], imu, bias is not None, cfg.gravity)

    calibration = reader.calibration
    cam, cam_note = _camera(calibration, src)
    world = simulate_world(traj, duration, cam, cfg)
    data = SimData.from_world(
        world, config=cfg, trajectory=traj, imu=imu, groundtruth=gt, groundtruth_bias=bias
    )
    cal = {
        "imu": dict(calibration["imu"]) if "imu" in calibration else {},
        "uwb": uwb_calibration(cfg),
        "groundtruth": dict(calibration.get("groundtruth", {"lever_arm": [0.0, 0.0, 0.0], "frame": "body"})),
    }
    if world.features is not None:
        cal["cameras"] = {"cam0": cam}
    truth = world_truth(data, duration)  # no "imu" biases: the real ones are on /groundtruth/imu_bias
    simulation = {
        "seed": int(cfg.seed),
        "camera": cam_note,
        "trajectory": f"cubic B-spline through {TOPIC_GT_POSE} (IMU frame), knots {knot_dt:g} s",
        "landmarks": len(world.landmarks),
        "anchors": len(world.anchors),
        # the camera and the ranges follow the ground truth's frame, the IMU feels gravity: off level by
        # groundtruth_gravity.tilt_deg (the evaluator levels the ground truth; pipeline.core.gravity)
        "groundtruth_gravity": level,
        "imu_vs_trajectory": imu_agreement(traj, imu, g_w),
    }
    data.metadata = {
        META_CALIBRATION: cal,
        META_TRUTH: truth,
        META_SOURCE: _hybrid_source(reader.source, source, cfg, world, bias is not None, simulation),
    }
    return data


def _real_trajectory(
    reader: RecordingReader, source: Path, knot_dt: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray, ImuData, SplineTrajectory]:
    """The ground truth (IMU frame) where it overlaps the IMU, all the IMU, and the spline through that ground
    truth (it starts at the first pose in the overlap)."""
    src = str(source)
    topics = reader.topics()
    for need, what in ((TOPIC_IMU, "a real IMU"), (TOPIC_GT_POSE, "ground-truth poses")):
        if need not in topics:
            raise InputError(
                f"{src}: no '{need}' topic; --imu-from needs a recording with {what} (e.g. uwbcal convert "
                "euroc FOLDER --groundtruth GT.csv)"
            )
    t_gt, p_gt, q_gt = _gt_imu_frame(reader)
    if len(t_gt) < 4:
        raise InputError(f"{src}: {TOPIC_GT_POSE}: {len(t_gt)} poses; a trajectory needs at least 4")
    imu_all = reader.read_imu(TOPIC_IMU)
    # the span where IMU and ground truth overlap; the spline starts at the first ground-truth pose in it
    lo = max(int(imu_all.t_ns[0]), int(t_gt[0]))
    hi = min(int(imu_all.t_ns[-1]), int(t_gt[-1]))
    keep = (t_gt >= lo) & (t_gt <= hi)
    if keep.sum() < 4 or (hi - lo) * 1e-9 < 4 * knot_dt:
        raise InputError(
            f"{src}: IMU and {TOPIC_GT_POSE} overlap over {max(hi - lo, 0) * 1e-9:.2f} s; need at least "
            f"{4 * knot_dt:g} s of both"
        )
    t_gt, p_gt, q_gt = t_gt[keep], p_gt[keep], q_gt[keep]
    traj = SplineTrajectory.fit(
        (t_gt - t_gt[0]) * 1e-9,
        p_gt,
        q_gt,
        knot_dt=knot_dt,
        t0_ns=int(t_gt[0]),
        name=f"{reader.source.get('sequence', source.stem)} (ground truth)",
        source=source,
    )
    return t_gt, p_gt, q_gt, imu_all, traj


def _real_streams(
    reader: RecordingReader, imu_all: ImuData, traj: SplineTrajectory, t_end: int
) -> tuple[ImuSim, ImuSim | None, GroundTruthSim]:
    """The recording's IMU (with its biases at the IMU stamps), biases and ground truth from the trajectory's
    start to ``t_end``."""
    m = (imu_all.t_ns >= traj.t0_ns) & (imu_all.t_ns <= t_end)
    bias = None
    if TOPIC_GT_IMU_BIAS in reader.topics():
        b = reader.read_imu(TOPIC_GT_IMU_BIAS)
        mb = (b.t_ns >= traj.t0_ns) & (b.t_ns <= t_end)
        bias = ImuSim(b.t_ns[mb], b.gyro[mb], b.acc[mb], b.gyro[mb], b.acc[mb])
    # biases at the IMU stamps (zero where the recording has none): kept with the IMU for reference
    if bias is not None and len(bias.t_ns) >= 2:
        bg = np.stack([np.interp(imu_all.t_ns[m], bias.t_ns, bias.gyro[:, k]) for k in range(3)], 1)
        ba = np.stack([np.interp(imu_all.t_ns[m], bias.t_ns, bias.acc[:, k]) for k in range(3)], 1)
    else:
        bg = ba = np.zeros((int(m.sum()), 3))
    imu = ImuSim(imu_all.t_ns[m], imu_all.gyro[m], imu_all.acc[m], bg, ba)
    gt_raw = reader.read_poses(TOPIC_GT_POSE)  # written as recorded (the lever arm stays in)
    g = (gt_raw.t_ns >= traj.t0_ns) & (gt_raw.t_ns <= t_end)
    v = traj.evaluate((gt_raw.t_ns[g] - traj.t0_ns) * 1e-9).v
    gt = GroundTruthSim(gt_raw.t_ns[g], gt_raw.p[g], gt_raw.q_xyzw[g], v)

    return imu, bias, gt


def _hybrid_source(
    orig: dict, source: Path, cfg: SimConfig, world: WorldSim, has_bias: bool, simulation: dict
) -> dict:
    """The hybrid recording's source metadata: which topics are real (from where) and which simulated."""
    src = str(source)
    real = [TOPIC_IMU, TOPIC_GT_POSE] + ([TOPIC_GT_IMU_BIAS] if has_bias else [])
    simulated = ([TOPIC_FEATURES] if world.features is not None else []) + [TOPIC_RANGE]
    return {
        "dataset": "hybrid",
        "sequence": str(orig.get("sequence", source.stem)),
        "real": real,
        "simulated": simulated,
        "real_from": {
            "path": src,
            "sha256": sha256_file(source),
            "dataset": orig.get("dataset"),
            "files": orig.get("files", []),
        },
        "simulation": simulation,
        "files": [{"path": src, "sha256": sha256_file(source)}],
        "converter": orig.get("converter"),
        "dropped": [],
        "seed": int(cfg.seed),
    }


def hybrid_to_file(source: str | Path, cfg: SimConfig, output: str | Path) -> str:
    """Write the hybrid recording; returns a short human-readable summary."""

    data = hybrid_simulate(source, cfg)
    counts = write_recording(data, output)
    src = data.metadata[META_SOURCE]
    lines = [
        f"hybrid {src['sequence']} ({data.metadata[META_TRUTH]['duration']:.1f} s, seed {cfg.seed}) -> {output}",
        f"  real: {', '.join(src['real'])} (from {source}); simulated: {', '.join(src['simulated'])}",
        *(f"  {topic:<24} {n:>9} messages" for topic, n in sorted(counts.items())),
    ]
    if data.features is not None:
        c = data.features.counts
        lines.append(f"  features per frame: mean {c.mean():.0f}, min {c.min()}, max {c.max()}")
    lines.append(f"  anchors: {len(data.anchors)}; ranges {len(data.ranges.t_ns)}")
    level = src["simulation"]["groundtruth_gravity"]
    if level.get("determined"):
        lines.append(
            f"  ground truth's frame {level['tilt_deg']:.3f}° ± {level['tilt_sigma_deg']:.3f}° off level (gravity "
            "fitted to the real IMU; tracks and ranges follow that frame, the evaluator levels it)"
        )
    agree = src["simulation"]["imu_vs_trajectory"]
    if agree:
        lines.append(
            f"  real IMU vs the trajectory ({agree['window_s']:g} s means, fitted gravity): specific force "
            f"{agree['specific_force_angle_deg_median']:.2f}° median / {agree['specific_force_angle_deg_p90']:.2f}° "
            f"p90 off its predicted direction, gyro residual {agree['gyro_residual_rad_s_rms']:.4f} rad/s rms"
        )
    return "\n".join(lines)
