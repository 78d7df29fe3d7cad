"""NTU-VIRAL -> recording: ROS1 bag or a sequence folder of CSVs.

Bag: /imu/imu -> /imu, /left/image_raw -> /cam0/image_raw, /right/image_raw -> /cam1/image_raw (CDR pass-through),
/uwb_endorange_info (uwb_driver/UwbRange) -> /uwb/range, /leica/pose/relative (prism) -> /groundtruth/position.
Folder: uwb_ranges.csv -> /uwb/range, slict_odometry.csv -> /odometry (with a configured pose covariance),
leica_prism.csv -> /groundtruth/position. Antenna lever arms and the ranging-bias prior come from
uwb_antennas.yaml (folder, its parent, or ``antennas``). Anchor truth: ``published_anchors.csv`` (``site,anchor,x,y,z``;
folder, its parent, or ``anchors_truth``), the rows of the sequence's site -> ``uwbcal.truth`` (kind "published",
frame "odometry" = SLICT for a folder; "slict" for a bag, whose recording has no SLICT poses).
"""

from __future__ import annotations

from functools import cache
from pathlib import Path

import numpy as np

from uwbcal.convert import msgs
from uwbcal.convert.anchor_truth import find_published_anchors, read_anchor_truth, truth_note, truth_record
from uwbcal.convert.euroc import header_time, passthrough
from uwbcal.convert.recording import (
    META_CALIBRATION,
    META_SOURCE,
    META_TRUTH,
    TOPIC_CAM0,
    TOPIC_CAM1,
    TOPIC_GT_POSITION,
    TOPIC_IMU,
    TOPIC_ODOM,
    TOPIC_RANGE,
    RecordingWriter,
)
from uwbcal.convert.sources import (
    MAX_RANGE_M,
    BagRoute,
    Drop,
    Drops,
    Hasher,
    StampCheck,
    anchors_note,
    clean_ranges,
    default_tags,
    normalise_quaternions,
    order_and_dedup,
    parse_antennas,
    pose_covariance,
    read_csv_strings,
    read_ranges_csv,
    source_metadata,
    stream_bag,
    summary,
    to_float,
    to_int,
    uwb_calibration,
    write_ranges,
)
from uwbcal.pipeline.core.errors import InputError
from uwbcal.pipeline.core.progress import progress

UWB_RANGE_ROS1 = "uwb_driver/msg/UwbRange"
# ntu-aris/uwb_driver msg/UwbRange.msg (ROS1 md5 1065ab177c929b8c39cb8fde961d3e9e)
UWB_RANGE_MSG = """\
Header  header
uint16  msgId
uint8   requester_id
uint8   responder_id
int8    requester_idx
int8    responder_idx
uint8   range_status
uint8   antenna
uint16  stopwatch_time
float32 distance
float32 coarse_range
float32 filtered_range
float32 distance_err
float32 coarse_range_err
float32 filtered_range_err
float32 distance_dot
float32 distance_dot_err
uint8   range_meas_type
uint16  requester_LED_flag
uint16  responder_LED_flag
uint16  noise
uint16  vPeak
int32   coarse_tof_in_bins
uint32  uwb_time
geometry_msgs/Point requester_location
geometry_msgs/Point responder_location
geometry_msgs/Point rqst_antenna_offset
geometry_msgs/Point rspd_antenna_offset
"""

# viral_eval/trans_B2prism.csv: the Leica prism in the body (IMU) frame.
PRISM_LEVER_ARM = [-0.293656, -0.012288, -0.273095]
# VINS-Fusion config/ntuviral: acc_n, gyr_n, acc_w, gyr_w (used as continuous-time densities); VN100 at 385 Hz.
NTU_IMU = {
    "gyroscope_noise_density": 5.0e-3,
    "gyroscope_random_walk": 3.0e-6,
    "accelerometer_noise_density": 6.0e-2,
    "accelerometer_random_walk": 8.0e-5,
    "rate_hz": 385.0,
}
# camLeft.yaml / camRight.yaml; T_imu_cam = body_T_cam1 (left) and body_T_cam0 (right) of the VINS config.
NTU_CAMERAS = {
    "cam0": {
        "intrinsics": [
            4.250258563372763e02,
            4.267976260903337e02,
            3.860151866550880e02,
            2.419130336743440e02,
        ],
        "distortion_model": "radtan",
        "distortion": [-0.288105327549552, 0.074578284234601, 7.784489598138802e-04, -2.277853975035461e-04],
        "resolution": [752, 480],
        "rate_hz": 10.0,
        "topic": "/left/image_raw",
        "T_imu_cam": [
            [0.02183084, -0.01312053, 0.99967558, 0.00552943],
            [0.99975965, 0.00230088, -0.02180248, -0.12431302],
            [-0.00201407, 0.99991127, 0.01316761, 0.01614686],
            [0.0, 0.0, 0.0, 1.0],
        ],
    },
    "cam1": {
        "intrinsics": [
            4.313364265799752e02,
            4.327527965378035e02,
            3.548956286992647e02,
            2.325508916495161e02,
        ],
        "distortion_model": "radtan",
        "distortion": [-0.300267420221178, 0.090544063693053, 3.330220891093334e-05, 8.989607188457415e-05],
        "resolution": [752, 480],
        "rate_hz": 10.0,
        "topic": "/right/image_raw",
        "T_imu_cam": [
            [-0.01916508, -0.01496218, 0.99970437, 0.00519443],
            [0.99974371, 0.01176483, 0.01934191, 0.1347802],
            [-0.01205075, 0.99981884, 0.01473287, 0.01465067],
            [0.0, 0.0, 0.0, 1.0],
        ],
    },
}

# UWB model priors of an NTU-VIRAL recording (uwbcal.calibration.uwb):
# - sigma_range: the Humatics P440 ranges scatter by 0.2-0.3 m (robust sigma of the post-fit residuals of every
#   anchor of eee_01/nya_01, with per-antenna offsets of +-0.15 m), far above the 0.1 m generic default;
# - gamma: uwb_antennas.yaml gives the ranging bias the dataset's tools lock (anchor_estimator: measured + bias,
#   no scale), so it is a calibrated value, not a guess: a 1 cm prior sigma. A loose prior lets gamma trade off
#   against the anchor's distance (the flights circle the anchors at ~1.5 m height) by decimetres;
# - beta: time-of-flight ranging has no scale error beyond the radios' clock tolerance (tens of ppm).
NTU_SIGMA_RANGE = 0.2
NTU_GAMMA_SIGMA = 0.01
NTU_BETA_SIGMA = 0.001
# The CSV folder's poses are SLICT, a lidar SLAM whose frame is the frame the anchors are published in: its error
# is bounded, not a drift: 3 cm RMS against the Leica prism after SE(3) alignment (eee_01 3.1 cm, nya_01 2.5 cm,
# with the prism lever arm; 25 cm without it), autocorrelation 0.7-0.85 at 1 s, 0.4-0.7 at 5 s, 0.1-0.5 at 10 s.
# The odometry messages carry 3 cm / 0.5 deg (convert_folder), the error model a 5 s correlation time.
NTU_ODOMETRY = {"error_model": "bounded", "correlation_time_s": 5.0, "source": "SLICT lidar SLAM"}

BAG_IMU = "/imu/imu"
BAG_CAMS = {"/left/image_raw": TOPIC_CAM0, "/right/image_raw": TOPIC_CAM1}
BAG_UWB = "/uwb_endorange_info"
BAG_LEICA = "/leica/pose/relative"

SLICT_COLUMNS = (
    "field.header.stamp",
    "field.pose.pose.position.x",
    "field.pose.pose.position.y",
    "field.pose.pose.position.z",
    "field.pose.pose.orientation.x",
    "field.pose.pose.orientation.y",
    "field.pose.pose.orientation.z",
    "field.pose.pose.orientation.w",
)
LEICA_COLUMNS = (
    "field.header.stamp",
    "field.pose.position.x",
    "field.pose.position.y",
    "field.pose.position.z",
)


@cache
def ros1_typestore():
    """ROS1 Noetic types plus uwb_driver/UwbRange."""
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    ts = get_typestore(Stores.ROS1_NOETIC)
    ts.register(get_types_from_msg(UWB_RANGE_MSG, UWB_RANGE_ROS1))
    return ts


def find_antennas(path: Path, antennas: Path | None) -> Path | None:
    if antennas is not None:
        if not Path(antennas).is_file():
            raise InputError(f"{antennas}: antenna yaml not found")
        return Path(antennas)
    base = path if path.is_dir() else path.parent
    for cand in (base / "uwb_antennas.yaml", base.parent / "uwb_antennas.yaml"):
        if cand.is_file():
            return cand
    return None


def uwb_section(antenna_file: Path | None, tag: np.ndarray, antenna: np.ndarray, drops: Drops) -> dict:
    if antenna_file is None:
        drops.note("no uwb_antennas.yaml: zero antenna lever arms, gamma prior mean 0")
        return uwb_calibration(
            default_tags(tag, antenna),
            {},
            gamma_sigma=0.5,
            sigma_range=NTU_SIGMA_RANGE,
            beta_sigma=NTU_BETA_SIGMA,
        )
    tags, bias = parse_antennas(antenna_file)
    for t in np.unique(tag).tolist():
        n = len(tags.get(str(t), {}).get("antennas", []))
        if str(t) not in tags:
            drops.note(f"tag {t} has ranges but no antenna_offset in {antenna_file}")
        elif len(antenna) and int(antenna[tag == t].max()) >= n:
            drops.note(
                f"tag {t}: antenna index {int(antenna[tag == t].max())} but only {n} antennas in "
                f"{antenna_file}"
            )
    if not bias:
        drops.note(f"{antenna_file}: no ranging_bias; gamma prior 0 +- 0.5 m")
        return uwb_calibration(
            tags, bias, gamma_sigma=0.5, sigma_range=NTU_SIGMA_RANGE, beta_sigma=NTU_BETA_SIGMA
        )
    return uwb_calibration(
        tags, bias, gamma_sigma=NTU_GAMMA_SIGMA, sigma_range=NTU_SIGMA_RANGE, beta_sigma=NTU_BETA_SIGMA
    )


def _calibration(uwb: dict, odometry: dict | None = None) -> dict:
    cams = {k: {kk: vv for kk, vv in v.items() if kk != "topic"} for k, v in NTU_CAMERAS.items()}
    out = {
        "imu": dict(NTU_IMU),
        "cameras": cams,
        "uwb": uwb,
        "groundtruth": {"lever_arm": list(PRISM_LEVER_ARM), "frame": "prism"},
    }
    if odometry is not None:
        out["odometry"] = dict(odometry)
    return out


def published_truth(
    path: Path, anchors_truth: Path | None, ranged: np.ndarray, drops: Drops, frame: str
) -> tuple[dict | None, Path | None]:
    """``uwbcal.truth`` from the published anchors of the sequence's site (``eee_01`` -> ``eee``): the file given,
    else ``published_anchors.csv`` beside the data (a found file without the site is noted, not an error)."""
    site = (path.stem if path.is_file() else path.name).split("_")[0] or None
    given = anchors_truth is not None
    file = Path(anchors_truth) if given else find_published_anchors(path)
    if file is None:
        return None, None
    try:
        anchors = read_anchor_truth(file, site=site)
    except InputError as exc:
        if given:
            raise
        drops.note(f"no anchor truth: {exc}")
        return None, None
    drops.note(truth_note(anchors, ranged, file))
    return truth_record(anchors, "published", file, frame=frame), file


# ---------------------------------------------------------------------------------------------------------------
# sequence folder (CSVs)
# ---------------------------------------------------------------------------------------------------------------
def read_odometry_csv(path: Path):
    df = read_csv_strings(path, SLICT_COLUMNS, what="SLICT odometry CSV")
    t = to_int(path, df, SLICT_COLUMNS[0])
    v = np.column_stack([to_float(path, df, c) for c in SLICT_COLUMNS[1:]])
    return t, v[:, :3], v[:, 3:]


def read_leica_csv(path: Path):
    df = read_csv_strings(path, LEICA_COLUMNS, what="Leica prism CSV")
    t = to_int(path, df, LEICA_COLUMNS[0])
    return t, np.column_stack([to_float(path, df, c) for c in LEICA_COLUMNS[1:]])


def _slict_odometry(
    path: Path, drops: Drops, files: list[Path]
) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """slict_odometry.csv's usable poses (stamps, positions, quaternions) in time order, or None without it."""
    odom = None
    odom_file = path / "slict_odometry.csv"
    if odom_file.is_file():
        t, p, q = read_odometry_csv(odom_file)
        q, ok = normalise_quaternions(q, TOPIC_ODOM, drops)
        ok &= np.isfinite(p).all(1)
        drops.add(TOPIC_ODOM, "non-finite position", int((~np.isfinite(p).all(1)).sum()))
        idx = np.flatnonzero(ok)
        o = idx[order_and_dedup(t[idx], None, TOPIC_ODOM, drops, odom_file)]
        odom = (t[o], p[o], q[o])
        files.append(odom_file)
    else:
        drops.note("no slict_odometry.csv: no /odometry")
    return odom


def _leica_positions(path: Path, drops: Drops, files: list[Path]) -> tuple[np.ndarray, np.ndarray] | None:
    """leica_prism.csv's finite positions (stamps, positions) in time order, or None without it."""
    gt = None
    leica_file = path / "leica_prism.csv"
    if leica_file.is_file():
        t, p = read_leica_csv(leica_file)
        ok = np.isfinite(p).all(1)
        drops.add(TOPIC_GT_POSITION, "non-finite position", int((~ok).sum()))
        idx = np.flatnonzero(ok)
        o = idx[order_and_dedup(t[idx], None, TOPIC_GT_POSITION, drops, leica_file)]
        gt = (t[o], p[o])
        files.append(leica_file)
    return gt


def convert_folder(
    path: Path,
    output: str | Path,
    antennas: Path | None = None,
    *,
    anchors_truth: Path | None = None,
    sigma_pos: float = 0.03,
    sigma_rot_deg: float = 0.5,
    max_range: float = MAX_RANGE_M,
) -> str:
    ranges_file = path / "uwb_ranges.csv"
    if not ranges_file.is_file():
        have = ", ".join(sorted(p.name for p in path.iterdir())) or "empty folder"
        raise InputError(
            f"{path}: no uwb_ranges.csv (found: {have}); expected an NTU-VIRAL sequence folder "
            "with uwb_ranges.csv, slict_odometry.csv, leica_prism.csv"
        )
    drops = Drops()
    files = [ranges_file]
    raw_ranges, unit = read_ranges_csv(ranges_file)
    n_rows = len(raw_ranges)
    ranges = clean_ranges(raw_ranges, TOPIC_RANGE, drops, max_range)
    drops.note(f"{ranges_file.name}: {n_rows} rows, stamps in {unit}; " + anchors_note(ranges))

    odom = _slict_odometry(path, drops, files)
    gt = _leica_positions(path, drops, files)
    antenna_file = find_antennas(path, antennas)
    if antenna_file is not None:
        files.append(antenna_file)
    uwb = uwb_section(antenna_file, ranges.tag, ranges.antenna, drops)
    # SLICT poses are in the frame the anchors are published in; without them the run's frame is the VIO's
    truth, truth_file = published_truth(
        path, anchors_truth, ranges.anchor, drops, "odometry" if odom is not None else "slict"
    )
    if truth_file is not None:
        files.append(truth_file)
    hasher = Hasher(files)
    cov = pose_covariance(sigma_pos, sigma_rot_deg)
    total = len(ranges) + (len(odom[0]) if odom else 0) + (len(gt[0]) if gt else 0)
    with RecordingWriter(output) as w, progress(f"NTU-VIRAL {path.name}", total) as advance:
        write_ranges(w, ranges, TOPIC_RANGE)
        advance(len(ranges))
        if odom is not None:
            w.write_odometry_batch(*odom, cov6=cov, topic=TOPIC_ODOM)
            advance(len(odom[0]))
        if gt is not None:
            w.write_position_batch(*gt, topic=TOPIC_GT_POSITION)
            advance(len(gt[0]))
        w.set_metadata(META_CALIBRATION, _calibration(uwb, NTU_ODOMETRY if odom is not None else None))
        if truth is not None:
            w.set_metadata(META_TRUTH, truth)
        w.set_metadata(
            META_SOURCE,
            source_metadata(
                "ntu_viral",
                path.name,
                hasher.result(),
                drops,
                format="csv",
                range_rows=n_rows,
                odometry_covariance={
                    "sigma_pos_m": sigma_pos,
                    "sigma_rot_deg": sigma_rot_deg,
                    "order": "x y z rot_x rot_y rot_z",
                },
            ),
        )
        counts = dict(w.counts)
    return summary(output, counts, drops, f"NTU-VIRAL folder {path.name}")


# ---------------------------------------------------------------------------------------------------------------
# ROS1 bag
# ---------------------------------------------------------------------------------------------------------------
class RangeHandler:
    """/uwb_endorange_info -> /uwb/range with the same validity rules as the CSV path (streamed)."""

    def __init__(self, check: StampCheck, max_range: float) -> None:
        self.ts = ros1_typestore()
        self.check = check
        self.max_range = max_range
        self.last: dict[tuple[int, int, int], int] = {}
        self.tags: list[int] = []
        self.antennas: list[int] = []
        self.anchors: dict[int, int] = {}

    def __call__(self, writer: RecordingWriter, conn, bag_t: int, raw) -> None:
        m = self.ts.deserialize_ros1(raw, UWB_RANGE_ROS1)
        t = header_time(raw, bag_t)
        d = float(m.distance)
        if not np.isfinite(d):
            raise Drop("distance NaN/inf")
        if d < 0:
            raise Drop("negative distance")
        if d > self.max_range:
            raise Drop(f"absurd distance > {self.max_range:g} m")
        key = (int(m.requester_id), int(m.antenna), int(m.responder_id))
        if self.last.get(key) == t:
            raise Drop("duplicate stamp (kept the first)")
        self.last[key] = t
        self.check(TOPIC_RANGE, t)
        self.tags.append(key[0])
        self.antennas.append(key[1])
        self.anchors[key[2]] = self.anchors.get(key[2], 0) + 1
        writer.write_range(t, key[0], key[1], key[2], d, topic=TOPIC_RANGE)


def leica_handler(check: StampCheck):
    ts = ros1_typestore()

    def handle(writer: RecordingWriter, conn, bag_t: int, raw) -> None:
        m = ts.deserialize_ros1(raw, "geometry_msgs/msg/PoseStamped")
        t = header_time(raw, bag_t)
        p = m.pose.position
        if not np.isfinite([p.x, p.y, p.z]).all():
            raise Drop("non-finite position")
        check(TOPIC_GT_POSITION, t)
        writer.write_position(t, (p.x, p.y, p.z), topic=TOPIC_GT_POSITION)

    return handle


def convert_bag(
    path: Path,
    output: str | Path,
    antennas: Path | None = None,
    *,
    anchors_truth: Path | None = None,
    max_range: float = MAX_RANGE_M,
) -> str:
    drops = Drops()
    check = StampCheck(series=(TOPIC_IMU, TOPIC_GT_POSITION))
    ranges = RangeHandler(check, max_range)
    routes = {
        BAG_IMU: BagRoute(("sensor_msgs/msg/Imu",), passthrough(TOPIC_IMU, msgs.IMU, check), TOPIC_IMU),
        BAG_UWB: BagRoute((UWB_RANGE_ROS1,), ranges, TOPIC_RANGE),
        BAG_LEICA: BagRoute(("geometry_msgs/msg/PoseStamped",), leica_handler(check), TOPIC_GT_POSITION),
    }
    for src, dst in BAG_CAMS.items():
        routes[src] = BagRoute(("sensor_msgs/msg/Image",), passthrough(dst, msgs.IMAGE, check), dst)
    antenna_file = find_antennas(path, antennas)
    hasher = Hasher([path] + ([antenna_file] if antenna_file else []))
    with RecordingWriter(output) as w:
        stream_bag(path, w, routes, drops, f"NTU-VIRAL {path.name}")
        check.report(drops, path)
        counts = dict(w.counts)
        if not counts:
            raise InputError(f"{path}: none of the NTU-VIRAL topics ({', '.join(routes)}) has messages")
        if ranges.anchors:
            drops.note("anchors " + ", ".join(f"{a} ({c})" for a, c in sorted(ranges.anchors.items())))
        uwb = uwb_section(antenna_file, np.asarray(ranges.tags, int), np.asarray(ranges.antennas, int), drops)
        w.set_metadata(META_CALIBRATION, _calibration(uwb))
        truth, _ = published_truth(path, anchors_truth, np.asarray(list(ranges.anchors), int), drops, "slict")
        if truth is not None:
            w.set_metadata(META_TRUTH, truth)
        w.set_metadata(
            META_SOURCE, source_metadata("ntu_viral", path.stem, hasher.result(), drops, format="rosbag1")
        )
    return summary(output, counts, drops, f"NTU-VIRAL ROS1 bag {path.name}")


def convert_ntu_viral(
    path: str | Path,
    output: str | Path,
    antennas: str | Path | None = None,
    anchors_truth: str | Path | None = None,
) -> str:
    """Convert an NTU-VIRAL ROS1 bag or sequence folder of CSVs; returns a human summary. Anchor truth:
    ``anchors_truth`` (``[site,]anchor,x,y,z``) or ``published_anchors.csv`` beside the data -> ``uwbcal.truth``."""
    path = Path(path)
    ant = Path(antennas) if antennas is not None else None
    truth = Path(anchors_truth) if anchors_truth is not None else None
    if not path.exists():
        raise InputError(f"{path}: not found")
    if path.is_file():
        if path.suffix != ".bag":
            raise InputError(f"{path}: not a ROS1 .bag; give a .bag or a sequence folder with uwb_ranges.csv")
        return convert_bag(path, output, ant, anchors_truth=truth)
    return convert_folder(path, output, ant, anchors_truth=truth)
