"""EuRoC MAV -> recording: ASL folder (``mav0/...``) or ROS1 bag.

Folder: ``imu0/data.csv`` -> /imu, ``cam{0,1}/data.csv`` + PNGs -> /cam{0,1}/image_raw (pixels as in the PNG),
``state_groundtruth_estimate0/data.csv`` (or ``--groundtruth`` EuRoC CSV / TUM) -> /groundtruth/pose (and, from a
EuRoC CSV, its IMU bias columns b_w, b_a -> /groundtruth/imu_bias, sensor_msgs/Imu with the gyro bias as angular
velocity and the accelerometer bias as linear acceleration), and the
``sensor.yaml`` files -> ``uwbcal.calibration``. Bag: /imu0, /cam{0,1}/image_raw pass through as CDR (topic renamed,
header stamp as log time), /leica/position -> /groundtruth/position, /vicon/firefly_sbx/firefly_sbx -> body pose.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from uwbcal.convert import msgs, ros1_wire
from uwbcal.convert.calibration import CameraCalibration, ImuCalibration, parse_section, rigid_transform
from uwbcal.convert.recording import (
    META_CALIBRATION,
    META_SOURCE,
    TOPIC_CAM0,
    TOPIC_CAM1,
    TOPIC_GT_IMU_BIAS,
    TOPIC_GT_POSE,
    TOPIC_GT_POSITION,
    TOPIC_IMU,
    RecordingWriter,
)
from uwbcal.convert.sources import (
    BagRoute,
    Drop,
    Drops,
    Hasher,
    PoseTable,
    StampCheck,
    load_yaml,
    normalise_quaternions,
    order_and_dedup,
    read_csv_strings,
    read_tum,
    ros1_header_stamp,
    source_metadata,
    stream_bag,
    summary,
    to_float,
    to_int,
)
from uwbcal.pipeline.core.errors import InputError
from uwbcal.pipeline.core.geometry import quat_to_rot, rot_to_quat
from uwbcal.pipeline.core.progress import progress

CAM_TOPICS = {"cam0": TOPIC_CAM0, "cam1": TOPIC_CAM1}
DISTORTION_MODELS = {"radial-tangential": "radtan", "radtan": "radtan"}

# EuRoC bags carry no calibration: these are the sensor.yaml values shared by all EuRoC sequences.
EUROC_IMU = {
    "gyroscope_noise_density": 1.6968e-04,
    "gyroscope_random_walk": 1.9393e-05,
    "accelerometer_noise_density": 2.0e-3,
    "accelerometer_random_walk": 3.0e-3,
    "rate_hz": 200.0,
}
EUROC_CAMERAS = {
    "cam0": {
        "intrinsics": [458.654, 457.296, 367.215, 248.375],
        "distortion_model": "radtan",
        "distortion": [-0.28340811, 0.07395907, 0.00019359, 1.76187114e-05],
        "resolution": [752, 480],
        "rate_hz": 20.0,
        "T_imu_cam": [
            [0.0148655429818, -0.999880929698, 0.00414029679422, -0.0216401454975],
            [0.999557249008, 0.0149672133247, 0.025715529948, -0.064676986768],
            [-0.0257744366974, 0.00375618835797, 0.999660727178, 0.00981073058949],
            [0.0, 0.0, 0.0, 1.0],
        ],
    },
    "cam1": {
        "intrinsics": [457.587, 456.134, 379.999, 255.238],
        "distortion_model": "radtan",
        "distortion": [-0.28368365, 0.07451284, -0.00010473, -3.55590700e-05],
        "resolution": [752, 480],
        "rate_hz": 20.0,
        "T_imu_cam": [
            [0.0125552670891, -0.999755099723, 0.0182237714554, -0.0198435579556],
            [0.999598781151, 0.0130119051815, 0.0251588363115, 0.0453689425024],
            [-0.0253898008918, 0.0179005838253, 0.999517347078, 0.00786212447038],
            [0.0, 0.0, 0.0, 1.0],
        ],
    },
}
# leica0/sensor.yaml T_BS (translation only): prism in the body (= IMU) frame.
EUROC_LEICA_LEVER_ARM = [7.48903e-02, -1.84772e-02, -1.20209e-01]
# vicon0/sensor.yaml T_BS: the Vicon marker frame in the body frame; body pose = T_W_V inv(T_B_V).
EUROC_T_B_VICON = np.array(
    [
        [0.33638, -0.01749, 0.94156, 0.06901],
        [-0.02078, -0.99972, -0.01114, -0.02781],
        [0.94150, -0.01582, -0.33665, -0.12395],
        [0.0, 0.0, 0.0, 1.0],
    ]
)

BAG_IMU = "/imu0"
BAG_CAMS = {"/cam0/image_raw": TOPIC_CAM0, "/cam1/image_raw": TOPIC_CAM1}
BAG_LEICA = "/leica/position"
BAG_VICON = "/vicon/firefly_sbx/firefly_sbx"


# ---------------------------------------------------------------------------------------------------------------
# parsing (pure)
# ---------------------------------------------------------------------------------------------------------------
def find_mav0(path: Path) -> Path:
    path = Path(path)
    if not path.exists():
        raise InputError(f"{path}: not found")
    for cand in (path / "mav0", path):
        if (cand / "imu0").is_dir():
            return cand
    raise InputError(
        f"{path}: no EuRoC ASL layout (expected mav0/imu0/data.csv, mav0/cam0/...) and not a .bag"
    )


def sensor_T_BS(data: dict, path: Path) -> np.ndarray:
    """A sensor.yaml's T_BS (the sensor in the body frame), a validated rigid transform."""
    return rigid_transform(_field(data, "T_BS", path), str(path), "T_BS")


def _field(data: dict, key: str, path: Path):
    if key not in data:
        raise InputError(f"{path}: missing '{key}'; a EuRoC sensor.yaml needs it")
    return data[key]


IMU_KEYS = (
    "gyroscope_noise_density",
    "gyroscope_random_walk",
    "accelerometer_noise_density",
    "accelerometer_random_walk",
    "rate_hz",
)


def imu_calibration(path: Path) -> tuple[dict, np.ndarray]:
    """imu0/sensor.yaml -> (calibration.imu, T_B_imu), validated by the calibration model (`ImuCalibration`)."""
    d = load_yaml(path, "IMU sensor.yaml")
    # EuRoC's sensor.yaml: "inertial sensor noise model parameters (static)"
    values = {k: _field(d, k, path) for k in IMU_KEYS}
    imu = parse_section(ImuCalibration, {**values, "noise_origin": "allan"}, str(path))
    return imu.model_dump(exclude_none=True), sensor_T_BS(d, path)


# camera sensor.yaml key -> the calibration model's
CAMERA_KEYS = {"distortion_coefficients": "distortion", "T_BS": "T_imu_cam"}


def camera_calibration(path: Path, T_B_imu: np.ndarray) -> CameraCalibration:
    """camN/sensor.yaml -> calibration.cameras[camN] (T_imu_cam = inv(T_B_imu) T_B_cam), validated by the
    calibration model (`CameraCalibration`); a problem names the sensor.yaml's key."""
    d = load_yaml(path, "camera sensor.yaml")
    model = _field(d, "distortion_model", path)
    if model not in DISTORTION_MODELS:
        raise InputError(
            f"{path}: distortion_model: {model!r} not supported; uwbcal's camera model is radial-tangential"
        )
    T_imu_cam = np.linalg.solve(T_B_imu, sensor_T_BS(d, path))
    values = {
        "intrinsics": _field(d, "intrinsics", path),
        "distortion_model": DISTORTION_MODELS[model],
        "distortion": _field(d, "distortion_coefficients", path),
        "resolution": _field(d, "resolution", path),
        "T_imu_cam": T_imu_cam.tolist(),
        "rate_hz": _field(d, "rate_hz", path),
    }
    return parse_section(CameraCalibration, values, str(path), {v: k for k, v in CAMERA_KEYS.items()})


@dataclass
class ImuTable:
    t_ns: np.ndarray
    gyro: np.ndarray
    acc: np.ndarray


def read_imu_csv(path: Path) -> ImuTable:
    df = read_csv_strings(path, 7, what="EuRoC IMU CSV (#timestamp [ns], w_x, w_y, w_z, a_x, a_y, a_z)")
    if df.height == 0:
        raise InputError(f"{path}: no IMU samples (only a header); the VIO needs the IMU — check the export")
    cols = df.columns
    t = to_int(path, df, cols[0])
    v = np.column_stack([to_float(path, df, c) for c in cols[1:7]])
    return ImuTable(t, v[:, :3], v[:, 3:])


def read_image_list(path: Path) -> tuple[np.ndarray, list[str]]:
    df = read_csv_strings(path, 2, what="EuRoC camera CSV (#timestamp [ns], filename)")
    return to_int(path, df, df.columns[0]), [s.strip() for s in df[df.columns[1]].to_list()]


def read_groundtruth(path: Path) -> PoseTable:
    """EuRoC ground-truth CSV (t_ns, p, q_wxyz, ...) or TUM (t_s, p, q_xyzw), detected from the content."""
    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: ground truth file not found")
    with open(path) as f:
        first = next((ln for ln in f if ln.strip() and not ln.startswith("#")), "")
    if "," not in first:
        return read_tum(path)
    df = read_csv_strings(
        path, 8, what="EuRoC ground truth CSV (#timestamp, p_x, p_y, p_z, q_w, q_x, q_y, q_z)"
    )
    cols = df.columns
    t = to_int(path, df, cols[0])
    v = np.column_stack([to_float(path, df, c) for c in cols[1:8]])
    return PoseTable(t, v[:, :3], v[:, [4, 5, 6, 3]])


def read_groundtruth_biases(path: Path) -> ImuTable | None:
    """The IMU bias columns (b_w, b_a: columns 11-16) of a EuRoC ground-truth CSV, or None (TUM, fewer columns).

    Returned as an ImuTable: ``gyro`` = gyro bias [rad/s], ``acc`` = accelerometer bias [m/s^2]."""
    path = Path(path)
    with open(path) as f:
        first = next((ln for ln in f if ln.strip() and not ln.startswith("#")), "")
    if first.count(",") < 16:
        return None
    df = read_csv_strings(path, 17, what="EuRoC ground truth CSV with bias columns (b_w, b_a)")
    cols = df.columns
    t = to_int(path, df, cols[0])
    b = np.column_stack([to_float(path, df, c) for c in cols[11:17]])
    ok = np.isfinite(b).all(axis=1)
    o = np.argsort(t[ok], kind="stable")
    t, b = t[ok][o], b[ok][o]
    keep = np.r_[True, np.diff(t) > 0]
    return ImuTable(t[keep], b[keep, :3], b[keep, 3:])


def groundtruth_in_imu_frame(gt: PoseTable, T_B_imu: np.ndarray) -> PoseTable:
    """Body-frame poses T_W_B -> IMU-frame poses T_W_imu = T_W_B T_B_imu (the recording's poses are the IMU's)."""

    R = quat_to_rot(gt.q_xyzw)
    p = gt.p + R @ T_B_imu[:3, 3]
    return PoseTable(gt.t_ns, p, rot_to_quat(R @ T_B_imu[:3, :3]))


def read_image(path: Path) -> tuple[np.ndarray | None, bytes]:
    """A PNG as stored (mono8 stays bit-identical); returns (image or None when undecodable, file bytes)."""
    import cv2

    data = path.read_bytes()
    img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
    return img, data


# ---------------------------------------------------------------------------------------------------------------
# ASL folder
# ---------------------------------------------------------------------------------------------------------------
def _write_image_file(
    writer: RecordingWriter, topic: str, cam: str, t: int, file: Path, drops: Drops, digest
) -> None:
    if not file.is_file():
        drops.add(topic, "image listed in data.csv but missing on disk", 1, file.name)
        return
    img, data = read_image(file)
    digest.update(file.name.encode() + hashlib.sha256(data).digest())
    if img is None:
        drops.add(topic, "undecodable image file", 1, file.name)
        return
    if img.ndim == 3:
        import cv2

        img = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY if img.shape[2] == 3 else cv2.COLOR_BGRA2GRAY)
        drops.note(f"{topic}: colour images converted to mono8")
    if img.dtype != np.uint8:
        drops.add(topic, f"image is {img.dtype}, not 8-bit mono", 1, file.name)
        return
    writer.write_image(topic, t, img, frame_id=cam)


def _euroc_imu(mav0: Path, drops: Drops, files: list[Path]) -> tuple[dict, np.ndarray, ImuTable]:
    """imu0: its calibration, T_BS, and its samples (finite, in time order, no duplicates); files read appended."""
    imu_dir = mav0 / "imu0"
    imu_cal, T_B_imu = imu_calibration(imu_dir / "sensor.yaml")
    files += [imu_dir / "sensor.yaml", imu_dir / "data.csv"]
    imu = read_imu_csv(imu_dir / "data.csv")
    keep = np.isfinite(imu.gyro).all(1) & np.isfinite(imu.acc).all(1)
    drops.add(TOPIC_IMU, "non-finite IMU value", int((~keep).sum()))
    idx = np.flatnonzero(keep)
    imu = ImuTable(imu.t_ns[idx], imu.gyro[idx], imu.acc[idx])
    o = order_and_dedup(imu.t_ns, None, TOPIC_IMU, drops, imu_dir / "data.csv")
    imu = ImuTable(imu.t_ns[o], imu.gyro[o], imu.acc[o])
    return imu_cal, T_B_imu, imu


def _euroc_cameras(
    mav0: Path, T_B_imu: np.ndarray, drops: Drops, files: list[Path]
) -> tuple[dict, dict[str, tuple[np.ndarray, list[str]]]]:
    """cam0 (required) and cam1: calibrations and image lists (stamps, file names) in time order."""
    cameras, cam_lists = {}, {}
    for cam in ("cam0", "cam1"):
        d = mav0 / cam
        if not d.is_dir():
            if cam == "cam0":
                raise InputError(f"{d}: missing camera folder; a EuRoC ASL folder needs mav0/cam0")
            continue
        cal = camera_calibration(d / "sensor.yaml", T_B_imu)
        files += [d / "sensor.yaml", d / "data.csv"]
        t, names = read_image_list(d / "data.csv")
        o = order_and_dedup(t, None, CAM_TOPICS[cam], drops)
        cam_lists[cam] = (t[o], [names[i] for i in o])
        first = next((d / "data" / n for n in cam_lists[cam][1] if (d / "data" / n).is_file()), None)
        img = read_image(first)[0] if first is not None else None
        if img is not None:
            cal.check_image_size(
                (img.shape[1], img.shape[0]), f"in {d / 'data'}", str(d / "sensor.yaml"), "resolution"
            )
        cameras[cam] = cal.model_dump(exclude_none=True)
    return cameras, cam_lists


def _euroc_groundtruth(
    mav0: Path, groundtruth: Path | None, T_B_imu: np.ndarray, drops: Drops, files: list[Path]
) -> tuple[PoseTable | None, Path | None]:
    """The ground truth (``groundtruth`` or state_groundtruth_estimate0) in imu0's frame, and its file."""
    gt, gt_file = None, None
    if groundtruth is not None:
        gt_file = Path(groundtruth)
    elif (mav0 / "state_groundtruth_estimate0" / "data.csv").is_file():
        gt_file = mav0 / "state_groundtruth_estimate0" / "data.csv"
    else:
        drops.note("no ground truth (state_groundtruth_estimate0/data.csv absent; pass --groundtruth FILE)")
    if gt_file is not None:
        gt = read_groundtruth(gt_file)
        q, ok = normalise_quaternions(gt.q_xyzw, TOPIC_GT_POSE, drops)
        ok &= np.isfinite(gt.p).all(1)
        gt = PoseTable(gt.t_ns[ok], gt.p[ok], q[ok])
        o = order_and_dedup(gt.t_ns, None, TOPIC_GT_POSE, drops, gt_file)
        gt = PoseTable(gt.t_ns[o], gt.p[o], gt.q_xyzw[o])
        if not np.allclose(
            T_B_imu, np.eye(4)
        ):  # EuRoC's ground truth is the body frame B: express it in imu0's
            gt = groundtruth_in_imu_frame(gt, T_B_imu)
            drops.note("ground truth moved from the body frame to imu0's (imu0/sensor.yaml T_BS)")
        files.append(gt_file)
    return gt, gt_file


def convert_folder(path: Path, output: str | Path, groundtruth: Path | None = None) -> str:
    mav0 = find_mav0(path)
    sequence = (mav0.parent if mav0.name == "mav0" else mav0).name
    drops = Drops()
    files: list[Path] = []

    imu_cal, T_B_imu, imu = _euroc_imu(mav0, drops, files)
    cameras, cam_lists = _euroc_cameras(mav0, T_B_imu, drops, files)
    gt, gt_file = _euroc_groundtruth(mav0, groundtruth, T_B_imu, drops, files)
    gt_bias = read_groundtruth_biases(gt_file) if gt_file is not None else None

    hasher = Hasher(files)
    # one time-ordered event list (kind, row); images are read one at a time when their turn comes
    streams = [(imu.t_ns, 0)] + [
        (cam_lists[c][0], 1 + i) for i, c in enumerate(("cam0", "cam1")) if c in cam_lists
    ]
    if gt is not None:
        streams.append((gt.t_ns, 3))
    t_all = np.concatenate([s[0] for s in streams])
    kind = np.concatenate([np.full(len(s[0]), s[1], np.int8) for s in streams])
    row = np.concatenate([np.arange(len(s[0])) for s in streams])
    order = np.lexsort([kind, t_all])
    digests = {c: hashlib.sha256() for c in cam_lists}

    calibration = {
        "imu": imu_cal,
        "cameras": cameras,
        "groundtruth": {"lever_arm": [0.0, 0.0, 0.0], "frame": "body"},
    }
    with RecordingWriter(output) as w, progress(f"EuRoC {sequence}", len(order)) as advance:
        for k, r in zip(kind[order].tolist(), row[order].tolist(), strict=True):
            if k == 0:
                w.write_imu(int(imu.t_ns[r]), imu.gyro[r], imu.acc[r])
            elif k == 3:
                w.write_pose(int(gt.t_ns[r]), gt.p[r], gt.q_xyzw[r], topic=TOPIC_GT_POSE)
            else:
                cam = "cam0" if k == 1 else "cam1"
                t, names = cam_lists[cam]
                _write_image_file(
                    w, CAM_TOPICS[cam], cam, int(t[r]), mav0 / cam / "data" / names[r], drops, digests[cam]
                )
            advance(1)
        file_hashes = hasher.result() + [
            {
                "path": str(mav0 / c / "data"),
                "sha256": h.hexdigest(),
                "note": "sha256 over (file name, sha256 of file) of the images read",
            }
            for c, h in digests.items()
        ]
        if gt_bias is not None:
            w.write_imu_batch(gt_bias.t_ns, gt_bias.gyro, gt_bias.acc, topic=TOPIC_GT_IMU_BIAS)
        w.set_metadata(META_CALIBRATION, calibration)
        w.set_metadata(META_SOURCE, source_metadata("euroc", sequence, file_hashes, drops, format="asl"))
        counts = dict(w.counts)
    drops.note("calibration from " + ", ".join(f"{s}/sensor.yaml" for s in ["imu0", *cameras]))
    return summary(output, counts, drops, f"EuRoC ASL folder {sequence}")


# ---------------------------------------------------------------------------------------------------------------
# ROS1 bag
# ---------------------------------------------------------------------------------------------------------------
def header_time(raw, bag_t: int) -> int:
    t = ros1_header_stamp(raw)
    return t if t > 0 else int(bag_t)


# float64 values after the header of the pass-through types made of a header and doubles only
STAMPED_DOUBLES = {msgs.IMU: 37, msgs.POINT_STAMPED: 3}


def passthrough(out_topic: str, msgtype: str, check: StampCheck):
    """Handler writing a ROS1 message as CDR (`ros1_wire`): Image (mono8; the pixels go from the bag's chunk into
    the recording's chunk with no copy between) or a type of `STAMPED_DOUBLES`."""
    if msgtype == msgs.IMAGE:

        def handle(writer: RecordingWriter, conn, bag_t: int, raw) -> None:
            enc, head, pixels = ros1_wire.image_cdr(raw)
            if enc not in ("mono8", "8UC1"):
                raise Drop(f"image encoding {enc!r}, expected mono8")
            t = header_time(raw, bag_t)
            check(out_topic, t)
            writer.write_raw(out_topic, t, msgtype, (head, pixels))

        return handle
    n = STAMPED_DOUBLES[msgtype]

    def handle_doubles(writer: RecordingWriter, conn, bag_t: int, raw) -> None:
        cdr = ros1_wire.stamped_doubles_cdr(raw, n)
        t = header_time(raw, bag_t)
        check(out_topic, t)
        writer.write_raw(out_topic, t, msgtype, cdr)

    return handle_doubles


class ViconPoses:
    """Route of the Vicon topic (TransformStamped of the Vicon marker frame): the body pose ``T_W_V T_V_B`` per
    message. The messages are decoded as they stream by; the pose arithmetic runs over all of them at the end
    (`write`, one batch: per message it cost more than the rest of the conversion of that message), with the
    arithmetic of `_quat_to_rot` / `_rot_to_quat` row by row, so the poses are the same to the bit. Holds 8 numbers
    per message (~23 MB for an hour at 100 Hz)."""

    def __init__(self, check: StampCheck) -> None:
        self._check = check
        self._t: list[int] = []
        self._rows: list[tuple[float, ...]] = []

    def __call__(self, writer: RecordingWriter, conn, bag_t: int, raw) -> None:
        row = ros1_wire.transform_stamped(raw)
        t = header_time(raw, bag_t)
        self._check(TOPIC_GT_POSE, t)
        self._t.append(t)
        self._rows.append(row)

    def write(self, writer: RecordingWriter) -> None:
        if not self._t:
            return
        x = np.array(self._rows, float)
        T_W_V = np.zeros((len(x), 4, 4))
        T_W_V[:, 3, 3] = 1.0
        T_W_V[:, :3, :3] = _quats_to_rots(x[:, 3:])
        T_W_V[:, :3, 3] = x[:, :3]
        T_W_B = T_W_V @ np.linalg.inv(EUROC_T_B_VICON)  # 4x4 products one by one, as T_W_V @ T_V_B
        writer.write_pose_batch(
            np.array(self._t, np.int64),
            T_W_B[:, :3, 3],
            _rots_to_quats(T_W_B[:, :3, :3]),
            topic=TOPIC_GT_POSE,
        )


def _unit_rows(q: np.ndarray) -> np.ndarray:
    """Rows divided by their norms, each norm by ``np.linalg.norm`` of the row (bit for bit the scalar path)."""
    return q / np.array([np.linalg.norm(r) for r in q])[:, None]


def _quats_to_rots(q: np.ndarray) -> np.ndarray:
    """`_quat_to_rot` over rows of (x, y, z, w)."""
    x, y, z, w = _unit_rows(q).T
    R = np.empty((len(q), 3, 3))
    R[:, 0, 0] = 1 - 2 * (y * y + z * z)
    R[:, 0, 1] = 2 * (x * y - z * w)
    R[:, 0, 2] = 2 * (x * z + y * w)
    R[:, 1, 0] = 2 * (x * y + z * w)
    R[:, 1, 1] = 1 - 2 * (x * x + z * z)
    R[:, 1, 2] = 2 * (y * z - x * w)
    R[:, 2, 0] = 2 * (x * z - y * w)
    R[:, 2, 1] = 2 * (y * z + x * w)
    R[:, 2, 2] = 1 - 2 * (x * x + y * y)
    return R


def _rots_to_quats(R: np.ndarray) -> np.ndarray:
    """`_rot_to_quat` over a stack of rotations (the same branch per row)."""
    tr = R[:, 0, 0] + R[:, 1, 1] + R[:, 2, 2]
    case = np.argmax(np.stack([tr, R[:, 0, 0], R[:, 1, 1], R[:, 2, 2]], axis=1), axis=1)
    q = np.empty((len(R), 4))
    k = case == 0
    w = 0.5 * np.sqrt(1 + tr[k])
    Rk = R[k]
    q[k, 0] = (Rk[:, 2, 1] - Rk[:, 1, 2]) / (4 * w)
    q[k, 1] = (Rk[:, 0, 2] - Rk[:, 2, 0]) / (4 * w)
    q[k, 2] = (Rk[:, 1, 0] - Rk[:, 0, 1]) / (4 * w)
    q[k, 3] = w
    for a in range(3):
        k = case == a + 1
        b, c = (a + 1) % 3, (a + 2) % 3
        Rk = R[k]
        s = 2 * np.sqrt(1 + Rk[:, a, a] - Rk[:, b, b] - Rk[:, c, c])
        q[k, a] = 0.25 * s
        q[k, b] = (Rk[:, b, a] + Rk[:, a, b]) / s
        q[k, c] = (Rk[:, c, a] + Rk[:, a, c]) / s
        q[k, 3] = (Rk[:, c, b] - Rk[:, b, c]) / s
    q = _unit_rows(q)
    return np.where(q[:, 3:4] < 0, -q, q)


def _quat_to_rot(q: np.ndarray) -> np.ndarray:
    x, y, z, w = q / np.linalg.norm(q)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


def _rot_to_quat(R: np.ndarray) -> np.ndarray:
    """Hamilton (x, y, z, w) with w >= 0 (Shepperd's method)."""
    tr = np.trace(R)
    i = int(np.argmax([tr, R[0, 0], R[1, 1], R[2, 2]]))
    if i == 0:
        w = 0.5 * np.sqrt(1 + tr)
        q = np.array(
            [(R[2, 1] - R[1, 2]) / (4 * w), (R[0, 2] - R[2, 0]) / (4 * w), (R[1, 0] - R[0, 1]) / (4 * w), w]
        )
    else:
        a = i - 1
        b, c = (a + 1) % 3, (a + 2) % 3
        s = 2 * np.sqrt(1 + R[a, a] - R[b, b] - R[c, c])
        q = np.empty(4)
        q[a] = 0.25 * s
        q[b] = (R[b, a] + R[a, b]) / s
        q[c] = (R[c, a] + R[a, c]) / s
        q[3] = (R[c, b] - R[b, c]) / s
    q /= np.linalg.norm(q)
    return -q if q[3] < 0 else q


def convert_bag(path: Path, output: str | Path, groundtruth: Path | None = None) -> str:
    drops = Drops()
    check = StampCheck(series=(TOPIC_IMU, TOPIC_GT_POSITION, TOPIC_GT_POSE))
    vicon = ViconPoses(check)
    imu_types = ("sensor_msgs/msg/Imu",)
    img_types = ("sensor_msgs/msg/Image",)
    routes = {
        BAG_IMU: BagRoute(imu_types, passthrough(TOPIC_IMU, msgs.IMU, check), TOPIC_IMU),
        BAG_LEICA: BagRoute(
            ("geometry_msgs/msg/PointStamped",),
            passthrough(TOPIC_GT_POSITION, msgs.POINT_STAMPED, check),
            TOPIC_GT_POSITION,
        ),
        BAG_VICON: BagRoute(("geometry_msgs/msg/TransformStamped",), vicon, TOPIC_GT_POSE),
    }
    for src, dst in BAG_CAMS.items():
        routes[src] = BagRoute(img_types, passthrough(dst, msgs.IMAGE, check), dst)
    gt = None
    files = [path]
    if groundtruth is not None:
        gt = read_groundtruth(Path(groundtruth))
        q, ok = normalise_quaternions(gt.q_xyzw, TOPIC_GT_POSE, drops)
        gt = PoseTable(gt.t_ns[ok], gt.p[ok], q[ok])
        o = order_and_dedup(gt.t_ns, None, TOPIC_GT_POSE, drops, Path(groundtruth))
        gt = PoseTable(gt.t_ns[o], gt.p[o], gt.q_xyzw[o])
        routes.pop(BAG_VICON)
        routes.pop(BAG_LEICA)
        files.append(Path(groundtruth))
    gt_bias = read_groundtruth_biases(Path(groundtruth)) if groundtruth is not None else None
    hasher = Hasher(files)
    with RecordingWriter(output) as w:
        stream_bag(path, w, routes, drops, f"EuRoC {path.name}")
        vicon.write(w)
        if gt is not None:
            w.write_pose_batch(gt.t_ns, gt.p, gt.q_xyzw, topic=TOPIC_GT_POSE)
        if gt_bias is not None:
            w.write_imu_batch(gt_bias.t_ns, gt_bias.gyro, gt_bias.acc, topic=TOPIC_GT_IMU_BIAS)
        check.report(drops, path)
        counts = dict(w.counts)
        if TOPIC_GT_POSITION in counts:
            gt_meta = {"lever_arm": list(EUROC_LEICA_LEVER_ARM), "frame": "prism"}
        else:
            gt_meta = {"lever_arm": [0.0, 0.0, 0.0], "frame": "body"}
        if TOPIC_IMU not in counts:
            raise InputError(f"{path}: no IMU messages on {BAG_IMU}; not a EuRoC bag?")
        w.set_metadata(
            META_CALIBRATION, {"imu": dict(EUROC_IMU), "cameras": EUROC_CAMERAS, "groundtruth": gt_meta}
        )
        drops.note("calibration: EuRoC sensor.yaml defaults (bags carry none)")
        w.set_metadata(
            META_SOURCE, source_metadata("euroc", path.stem, hasher.result(), drops, format="rosbag1")
        )
    return summary(output, counts, drops, f"EuRoC ROS1 bag {path.name}")


def convert_euroc(path: str | Path, output: str | Path, groundtruth: str | Path | None = None) -> str:
    """Convert a EuRoC ASL folder or ROS1 bag into one recording; returns a human summary."""
    path = Path(path)
    gt = Path(groundtruth) if groundtruth is not None else None
    if path.is_file():
        if path.suffix != ".bag":
            raise InputError(f"{path}: not a ROS1 .bag; give a .bag file or an ASL folder containing mav0/")
        return convert_bag(path, output, gt)
    return convert_folder(path, output, gt)
