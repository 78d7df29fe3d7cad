"""Inputs for the fault-injection suite (tests/test_faults.py), generated here, small: a few seconds of
simulated data, TUM/CSV/YAML/TOML texts, damaged copies of recordings and run directories."""

from __future__ import annotations

import os
import struct
from pathlib import Path

import numpy as np

from uwbcal.convert.recording import (
    META_CALIBRATION,
    META_SOURCE,
    META_TRUTH,
    TOPIC_RANGE,
    RecordingReader,
    RecordingWriter,
)

T0 = 1_700_000_000_000_000_000
ANCHORS = np.array([[4.0, 3.0, 1.0], [-3.5, 1.0, 2.5], [1.0, -3.5, 2.0]])


# -- tabular inputs ------------------------------------------------------------------------------------------------
def circle_poses(n: int = 200, rate: float = 10.0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A 3-D flight (stamps [s], positions, unit quaternions xyzw) that observes anchors from all sides."""
    t = np.arange(n) / rate
    a = 2 * np.pi * t / (n / rate) * 2
    p = np.column_stack([2.5 * np.cos(a), 2.0 * np.sin(a), 1.0 + 0.8 * np.sin(0.5 * a)])
    yaw = a + np.pi / 2
    q = np.column_stack([np.zeros(n), np.zeros(n), np.sin(yaw / 2), np.cos(yaw / 2)])
    return t, p, q


def tum_text(t=None, p=None, q=None) -> str:
    if t is None:
        t, p, q = circle_poses()
    return "".join(
        f"{ti:.6f} " + " ".join(f"{v:.6f}" for v in (*pi, *qi)) + "\n"
        for ti, pi, qi in zip(t, p, q, strict=True)
    )


def ranges_rows(anchor_ids=(0, 1, 2), noise: float = 0.05, seed: int = 0) -> list[list]:
    """[stamp_ns, tag, antenna, anchor, distance] at 10 Hz per anchor along `circle_poses`."""
    rng = np.random.default_rng(seed)
    t, p, _ = circle_poses()
    rows = []
    for i in range(len(t)):
        for k, a in enumerate(anchor_ids):
            d = np.linalg.norm(ANCHORS[k % len(ANCHORS)] - p[i]) + rng.normal(0, noise)
            rows.append([int(round(t[i] * 1e9)) + T0 + k * 1000, 1, 0, a, round(float(d), 4)])
    return rows


def csv_text(rows, header: str = "stamp,tag,antenna,anchor,distance") -> str:
    return header + "\n" + "".join(",".join(str(v) for v in r) + "\n" for r in rows)


def tum_for_ranges() -> str:
    """TUM stamps on the same clock as `ranges_rows` (ns offset T0), exact decimal seconds."""
    return tum_abs(*circle_poses())


def tum_abs(t, p, q) -> str:
    lines = []
    for ti, pi, qi in zip(t, p, q, strict=True):
        ns = T0 + int(round(ti * 1e9))
        lines.append(f"{ns // 10**9}.{ns % 10**9:09d} " + " ".join(f"{v:.6f}" for v in (*pi, *qi)))
    return "\n".join(lines) + "\n"


ANTENNA_YAML = "antenna_offset: [1, 1, 0.0, 0.0, 0.1]\nranging_bias: [1, 0.0]\n"


# -- recordings ----------------------------------------------------------------------------------------------------
def rewrite(
    src: Path,
    dst: Path,
    *,
    ranges=None,
    chunk_size: int | None = None,
    swap_schema: dict | None = None,
    calibration=None,
) -> Path:
    """Copy a recording message by message; ``ranges(RangeData) -> RangeData`` edits the ranges,
    ``chunk_size`` re-chunks, ``swap_schema = {topic: (msgtype, source_topic)}`` writes another topic's
    messages under ``topic`` (a wrong message type), ``calibration(dict) -> dict`` edits the calibration."""
    r = RecordingReader(src)
    topics = r.topics()
    kw = {"chunk_size": chunk_size} if chunk_size else {}
    swap_schema = swap_schema or {}
    with RecordingWriter(dst, **kw) as w:
        if (
            ranges is None and not swap_schema
        ):  # interleaved in time, as a converter writes (chunks mix topics)
            for topic, t, raw in r.messages(raw=True):
                w.write_raw(topic, t, topics[topic].msgtype, raw)
            topics = {}
        for topic, info in topics.items():
            if topic in swap_schema:
                continue
            if topic == TOPIC_RANGE and ranges is not None:
                d = ranges(r.read_ranges())
                w.write_range_batch(d.t_ns, d.tag, d.antenna, d.anchor, d.distance)
                continue
            for _, t, raw in r.messages([topic], raw=True):
                w.write_raw(topic, t, info.msgtype, raw)
        for topic, (msgtype, source) in swap_schema.items():
            for _, t, raw in r.messages([source], raw=True):
                w.write_raw(topic, t, msgtype, raw)
        for name in (META_CALIBRATION, META_SOURCE, META_TRUTH):
            m = r.metadata(name)
            if name == META_CALIBRATION and calibration is not None:
                m = calibration(m)
            if m is not None:
                w.set_metadata(name, m)
    return dst


def chunk_data_spans(path: Path) -> list[tuple[int, int]]:
    """(start, end) byte offsets of the compressed records of each chunk (for targeted bit rot)."""
    from mcap.reader import make_reader

    with open(path, "rb") as f:
        s = make_reader(f).get_summary()
    return [
        (
            ci.chunk_start_offset + ci.chunk_length - ci.compressed_size,
            ci.chunk_start_offset + ci.chunk_length,
        )
        for ci in sorted(s.chunk_indexes, key=lambda c: c.chunk_start_offset)
    ]


def flip_bytes(path: Path, dst: Path, n: int, lo: int, hi: int, seed: int = 0) -> Path:
    data = bytearray(path.read_bytes())
    rng = np.random.default_rng(seed)
    for k in rng.integers(lo, hi, size=n).tolist():
        data[k] ^= 0xFF
    dst.write_bytes(bytes(data))
    return dst


def truncate(path: Path, dst: Path, fraction: float) -> Path:
    data = path.read_bytes()
    dst.write_bytes(data[: int(len(data) * fraction)])
    return dst


def junk(n: int, seed: int = 0) -> bytes:
    """Reproducible garbage bytes."""
    return np.random.default_rng(seed + n).bytes(n)


def dead_pid() -> int:
    """A pid that is not running (probing upwards from a high number)."""
    pid = 4_000_000
    while True:
        try:
            os.kill(pid, 0)
        except ProcessLookupError:
            return pid
        except PermissionError:
            pass
        pid += 1


def fake_ros1_bag(path: Path, *, truncated: bool) -> Path:
    """A ROS1 bag header record followed by nothing (or by garbage): what a killed `rosbag record` leaves."""
    header = b"#ROSBAG V2.0\n"
    fields = b"".join(
        struct.pack("<I", len(f)) + f
        for f in (b"op=\x03", b"index_pos=" + struct.pack("<Q", 4117), b"conn_count=" + struct.pack("<I", 1))
    )
    rec = struct.pack("<I", len(fields)) + fields + struct.pack("<I", 10) + b" " * 10
    path.write_bytes(header + (rec[: len(rec) // 2] if truncated else rec + os.urandom(64)))
    return path


# -- ROS bags with many small chunks (a truncation keeps some of them) ---------------------------------------------
BAG_N = 60  # messages per topic, 10 Hz
BAG_TOPICS = ("/imu", "/uwb/range")


def bag_stamps(n: int = BAG_N) -> list[int]:
    return [T0 + i * 100_000_000 for i in range(n)]


def small_bag(
    fmt: str,
    path: Path,
    compression: str | None = None,
    imu_topic: str = "/imu",
    *,
    imu_stamp=None,
    frame=None,
    image_size=None,
) -> Path:
    """A ROS 1 ``.bag`` or a ROS 2 bag folder (``mcap`` / ``sqlite3``) with /imu (sensor_msgs/Imu; or
    ``imu_topic``) and /uwb/range (sensor_msgs/Range, anchor 40 + i % 3 in its frame id), ``BAG_N`` each, in
    chunks of a few messages. Returns the .bag file or the bag folder. Edits: ``imu_stamp(i, t)`` the header
    stamp of IMU sample i, ``frame(i)`` the frame id of range i, ``image_size(i)`` -> (width, height) adds a
    mono8 image on /cam0/image_raw at every other message."""
    from rosbags.typesys import Stores, get_typestore

    ros1 = fmt == "ros1"
    store = get_typestore(Stores.ROS1_NOETIC if ros1 else Stores.ROS2_HUMBLE)
    edits = {"imu_stamp": imu_stamp, "frame": frame, "image_size": image_size}
    msgs = [m for i, t in enumerate(bag_stamps()) for m in _bag_messages(store.types, i, t, ros1, **edits)]
    ser = store.serialize_ros1 if ros1 else store.serialize_cdr
    if ros1:
        from rosbags.rosbag1 import Writer

        w = Writer(path)
        if compression:
            w.set_compression(getattr(Writer.CompressionFormat, compression.upper()))
        w.chunk_threshold = 1500  # a chunk every few messages
        flush = lambda: None  # noqa: E731
    else:
        from rosbags.rosbag2 import StoragePlugin, Writer

        plugin = StoragePlugin.MCAP if fmt == "mcap" else StoragePlugin.SQLITE3
        w = Writer(path, version=9, storage_plugin=plugin)
        flush = lambda: getattr(w.storage, "close_chunk", lambda: None)()  # noqa: E731
    with w:
        conns: dict = {}
        for k, (topic, ty, t, m) in enumerate(msgs):
            topic = imu_topic if topic == "/imu" else topic
            if topic not in conns:
                conns[topic] = w.add_connection(topic, ty, typestore=store)
            w.write(conns[topic], t, ser(m, ty))
            if k % 8 == 7:
                flush()
    return path


def _bag_messages(T, i: int, t: int, ros1: bool, imu_stamp=None, frame=None, image_size=None) -> list[tuple]:
    seq = {"seq": i} if ros1 else {}
    stamp = T["builtin_interfaces/msg/Time"](sec=t // 10**9, nanosec=t % 10**9)
    ti = imu_stamp(i, t) if imu_stamp else t
    imu_stamp_msg = T["builtin_interfaces/msg/Time"](sec=ti // 10**9, nanosec=ti % 10**9)
    H = T["std_msgs/msg/Header"]
    vec = T["geometry_msgs/msg/Vector3"]
    imu = T["sensor_msgs/msg/Imu"](
        header=H(**seq, stamp=imu_stamp_msg, frame_id="imu"),
        orientation=T["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0),
        orientation_covariance=np.zeros(9), angular_velocity=vec(x=0.01 * i, y=0.0, z=0.0),
        angular_velocity_covariance=np.zeros(9), linear_acceleration=vec(x=0.0, y=0.0, z=9.81),
        linear_acceleration_covariance=np.zeros(9),
    )  # fmt: skip
    rng = T["sensor_msgs/msg/Range"](
        header=H(**seq, stamp=stamp, frame_id=frame(i) if frame else f"anchor_{40 + i % 3}"), radiation_type=2,
        field_of_view=0.0, min_range=0.1, max_range=100.0, range=np.float32(2.0 + 0.01 * i),
    )  # fmt: skip
    out = [("/imu", "sensor_msgs/msg/Imu", t, imu), ("/uwb/range", "sensor_msgs/msg/Range", t + 1000, rng)]
    if image_size is not None and i % 2 == 0:
        w, h = image_size(i)
        img = T["sensor_msgs/msg/Image"](
            header=H(**seq, stamp=stamp, frame_id="cam0"), height=h, width=w, encoding="mono8", is_bigendian=0,
            step=w, data=np.full(w * h, 100, np.uint8),
        )  # fmt: skip
        out.append(("/cam0/image_raw", "sensor_msgs/msg/Image", t + 2000, img))
    return out


def bag_storage(bag: Path) -> Path:
    """The file of a bag that holds its messages (the .bag, or the storage file inside a ROS 2 bag folder)."""
    return bag if bag.is_file() else next(p for p in sorted(bag.iterdir()) if p.suffix in (".mcap", ".db3"))


# -- a EuRoC ASL folder (IMU, cam0 with images of the calibration's size) -------------------------------------------
EUROC_IMU_YAML = (
    "sensor_type: imu\nrate_hz: 200\nT_BS:\n  cols: 4\n  rows: 4\n  data: [1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, "
    "0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0]\ngyroscope_noise_density: 1.7e-4\ngyroscope_random_walk: 1.9e-05\n"
    "accelerometer_noise_density: 2.0e-3\naccelerometer_random_walk: 3.0e-3\n"
)
EUROC_CAM_YAML = (
    "%YAML:1.0\nsensor_type: camera\nT_BS:\n  cols: 4\n  rows: 4\n  data: [0.0148655429818, -0.999880929698, "
    "0.00414029679422, -0.0216401454975, 0.999557249008, 0.0149672133247, 0.025715529948, -0.064676986768, "
    "-0.0257744366974, 0.00375618835797, 0.999660727178, 0.00981073058949, 0.0, 0.0, 0.0, 1.0]\nrate_hz: 20\n"
    "resolution: [752, 480]\ncamera_model: pinhole\nintrinsics: [458.654, 457.296, 367.215, 248.375]\n"
    "distortion_model: radial-tangential\ndistortion_coefficients: [-0.28340811, 0.07395907, 0.00019359, "
    "1.76187114e-05]\n"
)


def euroc_folder(
    root: Path, imu_yaml: str = EUROC_IMU_YAML, cam_yaml: str = EUROC_CAM_YAML, size=(752, 480)
) -> Path:
    """``root/mav0``: 0.5 s of a resting IMU at 200 Hz, 3 cam0 images of ``size`` (width, height)."""
    import cv2

    mav0 = root / "mav0"
    (mav0 / "imu0").mkdir(parents=True)
    (mav0 / "cam0" / "data").mkdir(parents=True)
    t0 = 1_403_636_579_758_555_392
    rows = "".join(f"{t0 + i * 5_000_000},0.0,0.0,0.0,0.0,0.0,9.81\n" for i in range(100))
    (mav0 / "imu0" / "data.csv").write_text("#timestamp [ns],w_x,w_y,w_z,a_x,a_y,a_z\n" + rows)
    (mav0 / "imu0" / "sensor.yaml").write_text(imu_yaml)
    lines = ["#timestamp [ns],filename"]
    for k in range(3):
        t = t0 + k * 50_000_000
        cv2.imwrite(str(mav0 / "cam0" / "data" / f"{t}.png"), np.full((size[1], size[0]), 90 + k, np.uint8))
        lines.append(f"{t},{t}.png")
    (mav0 / "cam0" / "data.csv").write_text("\n".join(lines) + "\n")
    (mav0 / "cam0" / "sensor.yaml").write_text(cam_yaml)
    return root
