"""Any ROS bag -> recording: ROS 1 ``.bag``, ROS 2 ``.db3`` or ``.mcap`` (file or bag folder), via rosbags' AnyReader.

Topics are given (``--imu``, ``--cam0``, ``--cam1``, ``--uwb`` ..., ``--odometry``, ``--groundtruth``) or found by
message type (`detect_topics`). Each mapped topic is decoded and written with the recording's typed writers:

| role | bag types | recording |
|---|---|---|
| imu | sensor_msgs/Imu | /imu |
| cam0, cam1 | sensor_msgs/Image (mono8, 8UC1, rgb8, bgr8, rgba8, bgra8, mono16), CompressedImage | /cam0/image_raw, /cam1/image_raw (mono8) |
| uwb | the types of `convert.uwb_msgs` | /uwb/range |
| odometry | nav_msgs/Odometry | /odometry (with its pose covariance) |
| groundtruth | PoseStamped, PoseWithCovarianceStamped, TransformStamped, Odometry / PointStamped | /groundtruth/pose / position |

Every message of the bag is accounted for in ``uwbcal.source``: ``messages`` per bag topic (type, count, converted,
dropped) and ``dropped`` with a reason and count (unmapped topics, undecodable messages, duplicate stamps, invalid
ranges). Calibration: ``--calibration`` YAML in the layout of ``uwbcal.calibration`` (imu, cameras, uwb,
groundtruth, odometry), ``--antennas`` the antenna yaml (lever arms, ranging bias) of `convert.sources`.
"""

from __future__ import annotations

import re
from collections import Counter
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from uwbcal.convert import uwb_msgs
from uwbcal.convert.anchor_truth import read_anchor_truth, truth_note, truth_record
from uwbcal.convert.bag_recovery import Recovery, prepare
from uwbcal.convert.calibration import Calibration, load_calibration_yaml, parse_calibration
from uwbcal.convert.recording import (
    META_CALIBRATION,
    META_SOURCE,
    META_TRUTH,
    TOPIC_CAM0,
    TOPIC_CAM1,
    TOPIC_GT_POSE,
    TOPIC_GT_POSITION,
    TOPIC_IMU,
    TOPIC_ODOM,
    TOPIC_RANGE,
    RangeData,
    RecordingReader,
    RecordingWriter,
    written_by_uwbcal,
)
from uwbcal.convert.sample_times import sample_times
from uwbcal.convert.sources import (
    MAX_RANGE_M,
    Drop,
    Drops,
    Hasher,
    StampCheck,
    anchors_note,
    clean_ranges,
    default_tags,
    id_problem,
    id_text,
    parse_antennas,
    shift_ranges,
    source_metadata,
    summary,
    time_offset_ns,
    uwb_calibration,
    write_ranges,
)
from uwbcal.pipeline.core.errors import InputError
from uwbcal.pipeline.core.progress import progress

IMU_TYPES = ("sensor_msgs/msg/Imu",)
IMAGE_TYPES = ("sensor_msgs/msg/Image", "sensor_msgs/msg/CompressedImage")
ODOM_TYPES = ("nav_msgs/msg/Odometry",)
GT_POSE_TYPES = (
    "geometry_msgs/msg/PoseStamped",
    "geometry_msgs/msg/PoseWithCovarianceStamped",
    "geometry_msgs/msg/TransformStamped",
    "nav_msgs/msg/Odometry",
)
GT_POSITION_TYPES = ("geometry_msgs/msg/PointStamped",)
GT_NAME_HINTS = ("groundtruth", "ground_truth", "gt", "vicon", "leica", "mocap", "optitrack", "qualisys")
ROLES = ("imu", "cam0", "cam1", "uwb", "odometry", "groundtruth")
# roles whose sensor samples at a fixed rate: their arrival stamps are put back to sample times (`sample_times`)
FIXED_RATE_ROLES = {"imu": TOPIC_IMU, "cam0": TOPIC_CAM0, "cam1": TOPIC_CAM1}


def norm_type(msgtype: str) -> str:
    """``pkg/Name`` (ROS 1) -> ``pkg/msg/Name``: one spelling for both bag versions."""
    return uwb_msgs.ros2_name(msgtype)


# ---------------------------------------------------------------------------------------------------------------
# opening
# ---------------------------------------------------------------------------------------------------------------
def bag_format(path: Path) -> str:
    """rosbag1, rosbag2-sqlite3 or rosbag2-mcap; InputError for anything else."""
    if not path.exists():
        raise InputError(f"{path}: not found")
    if path.is_dir():
        if not (path / "metadata.yaml").is_file():
            raise InputError(
                f"{path}: a folder without metadata.yaml is not a ROS 2 bag; give the bag folder"
            )
        files = sorted(p.suffix for p in path.iterdir())
        return "rosbag2-mcap" if ".mcap" in files else "rosbag2-sqlite3"
    kind = {".bag": "rosbag1", ".db3": "rosbag2-sqlite3", ".mcap": "rosbag2-mcap"}.get(path.suffix)
    if kind is None:
        raise InputError(f"{path}: not a ROS bag (.bag, .db3, .mcap or a ROS 2 bag folder)")
    if kind == "rosbag2-mcap" and _is_recording(path):
        raise InputError(f"{path}: already a uwbcal recording; use it directly (uwbcal info / uwbcal run)")
    return kind


def _is_recording(path: Path) -> bool:
    if written_by_uwbcal(path):  # also a truncated recording (its metadata, written last, is lost)
        return True
    try:
        return bool(RecordingReader(path).metadata(META_SOURCE))
    except Exception:  # noqa: BLE001 (anything unreadable is left to the bag reader's own error)
        return False


REPAIR = {  # what repairs a bag this reader cannot read, per format
    "rosbag1": "rosbag reindex",
    "rosbag2-mcap": "mcap recover",
    "rosbag2-sqlite3": "a truncated sqlite3 bag cannot be read up to its damage; try sqlite3's .recover",
}


def _bag_error(path: Path, exc: BaseException, fmt: str) -> InputError:
    text = " ".join(str(exc).split()) or type(exc).__name__
    return InputError(
        f"{path}: unreadable ROS bag ({text[:200]}); the file is truncated, corrupt or not a bag — "
        f"re-export or repair it ({REPAIR[fmt]})"
    )


class BagReader:
    """AnyReader opened on one bag, with a decoder per connection (see `decoder_for`)."""

    def __init__(self, path: str | Path) -> None:
        from rosbags.highlevel import AnyReader
        from rosbags.typesys import Stores, get_typestore

        self.path = Path(path)
        self.format = bag_format(self.path)
        self.recovery: Recovery | None = None  # a truncated bag: what was read of it
        store = get_typestore(Stores.ROS2_HUMBLE)
        try:
            self.reader = AnyReader([self.path], default_typestore=store)
            self.reader.open()
        except Exception as exc:  # noqa: BLE001 (rosbags raises many kinds for a bad file)
            self.reader = AnyReader([self.path], default_typestore=store)
            if not self._recover():
                raise _bag_error(self.path, exc, self.format) from None
        self.ros1 = not self.reader.is2
        self._decoders: dict[int, Callable[[bytes], Any] | str] = {}

    def _recover(self) -> bool:
        """Open the (fresh, unopened) reader by scanning the bag's records (`bag_recovery`): True when that
        kept a message."""
        self.recovery = prepare(self.reader, self.format)
        if self.recovery is None:
            return False
        try:
            self.reader.open()
        except Exception:  # noqa: BLE001
            return False
        return self.recovery.messages > 0

    def close(self) -> None:
        if self.reader.stack:
            self.reader.close()

    def __enter__(self) -> BagReader:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    @property
    def connections(self):
        return self.reader.connections

    def topics(self) -> dict[str, tuple[str, int]]:
        """bag topic -> (message type as pkg/msg/Name, message count)."""
        out: dict[str, tuple[str, int]] = {}
        for c in self.connections:
            t, n = out.get(c.topic, (norm_type(c.msgtype), 0))
            out[c.topic] = (t, n + c.msgcount)
        return out

    def decoder_for(self, conn, raw: bytes | memoryview) -> Callable[[bytes], Any] | str:
        """A function raw -> message object for ``conn``, or a string saying why the type cannot be decoded.

        ROS 1 bags and ROS 2 bags with definitions decode with the bag's own definitions; a ROS 2 bag without
        them with ROS 2 Humble's types, or for the UWB types the shipped variant that decodes ``raw`` exactly."""
        if conn.id in self._decoders:
            return self._decoders[conn.id]
        store = self.reader.typestore
        name = conn.msgtype
        dec: Callable[[bytes], Any] | str
        if self.ros1:
            dec = lambda b, s=store, n=name: s.deserialize_ros1(bytes(b), n)  # noqa: E731
        elif conn.msgdef.data and name in store.fielddefs:
            dec = lambda b, s=store, n=name: s.deserialize_cdr(bytes(b), n)  # noqa: E731
        else:
            dec = "no message definition in the bag and none shipped for this type"
            for variant in uwb_msgs.definition_variants(name) if uwb_msgs.is_uwb_type(name) else ["current"]:
                vs = uwb_msgs.variant_typestore(variant, name)
                if name in vs.fielddefs and uwb_msgs.decodes_exactly(vs, raw, name) is not None:
                    dec = lambda b, s=vs, n=name: s.deserialize_cdr(bytes(b), n)  # noqa: E731
                    break
            else:
                if uwb_msgs.is_uwb_type(name):
                    dec = "matches none of the shipped definitions of this type"
        self._decoders[conn.id] = dec
        return dec

    def span_ns(self, start_s: float | None, end_s: float | None) -> tuple[int | None, int | None]:
        """Bag-time bounds [start, stop) for the seconds ``start_s`` / ``end_s`` after the bag's start."""
        t0 = int(self.reader.start_time)
        lo = None if start_s is None else t0 + int(round(start_s * 1e9))
        hi = None if end_s is None else t0 + int(round(end_s * 1e9))
        if lo is not None and hi is not None and hi <= lo:
            raise InputError(f"{self.path}: --end {end_s:g} s is not after --start {start_s:g} s")
        return lo, hi

    def messages(self, connections, start: int | None = None, stop: int | None = None):
        try:
            yield from self.reader.messages(connections=connections, start=start, stop=stop)
        except Exception as exc:  # noqa: BLE001
            raise _bag_error(self.path, exc, self.format) from None


# ---------------------------------------------------------------------------------------------------------------
# topic map
# ---------------------------------------------------------------------------------------------------------------
@dataclass
class TopicMap:
    """Which bag topic plays which role; ``notes`` say how each was chosen."""

    imu: str | None = None
    cam0: str | None = None
    cam1: str | None = None
    uwb: list[str] = field(default_factory=list)
    odometry: str | None = None
    groundtruth: str | None = None
    notes: list[str] = field(default_factory=list)

    def roles(self) -> dict[str, str]:
        """bag topic -> role."""
        out = {t: r for r in ("imu", "cam0", "cam1", "odometry", "groundtruth") if (t := getattr(self, r))}
        out.update({t: "uwb" for t in self.uwb})
        return out


def _camera_rank(topic: str) -> tuple[int, str]:
    t = topic.lower()
    first = any(k in t for k in ("cam0", "left", "infra1"))
    second = any(k in t for k in ("cam1", "right", "infra2"))
    return (0 if first else 2 if second else 1, topic)


def _gt_named(topic: str) -> bool:
    """A ground-truth topic name: a token 'gt' or a word like groundtruth, vicon, leica in it."""
    low = topic.lower()
    return "gt" in re.split(r"[/_\-.]", low) or any(h in low for h in GT_NAME_HINTS if h != "gt")


def detect_topics(topics: dict[str, tuple[str, int]], given: dict[str, Any] | None = None) -> TopicMap:
    """Map bag topics to roles: given ones first (checked to exist with a usable type), the rest by type."""
    given = given or {}
    m = TopicMap()

    def check(role: str, topic: str, types: Sequence[str] | None) -> str:
        if topic not in topics:
            have = ", ".join(f"{t} ({ty})" for t, (ty, _) in sorted(topics.items())) or "no topics"
            raise InputError(f"--{role} {topic}: no such topic in the bag (found: {have})")
        ty = topics[topic][0]
        ok = uwb_msgs.is_uwb_type(ty) if types is None else ty in types
        if not ok:
            raise InputError(f"--{role} {topic}: type {ty} cannot be used as {role}")
        m.notes.append(f"{role}: {topic} ({ty}, given)")
        return topic

    by_type: dict[str, list[str]] = {}
    for t, (ty, _) in topics.items():
        by_type.setdefault(ty, []).append(t)

    def pick(role: str, types: Sequence[str], cands: list[str] | None = None) -> str | None:
        cands = cands if cands is not None else sorted(t for ty in types for t in by_type.get(ty, []))
        if not cands:
            return None
        best = max(cands, key=lambda t: (topics[t][1], t))
        if len(cands) > 1:
            m.notes.append(f"{role}: {best} (most messages of {', '.join(cands)}; choose with --{role})")
        else:
            m.notes.append(f"{role}: {best} ({topics[best][0]}, by type)")
        return best

    m.imu = check("imu", given["imu"], IMU_TYPES) if given.get("imu") else pick("imu", IMU_TYPES)
    cams = sorted((t for ty in IMAGE_TYPES for t in by_type.get(ty, [])), key=_camera_rank)
    for role in ("cam0", "cam1"):
        if given.get(role):
            setattr(m, role, check(role, given[role], IMAGE_TYPES))
    if not given.get("cam0") and not given.get("cam1"):
        for role, t in zip(("cam0", "cam1"), cams, strict=False):
            setattr(m, role, t)
            m.notes.append(f"{role}: {t} ({topics[t][0]}, by type and name)")
    if given.get("uwb"):
        m.uwb = [check("uwb", t, None) for t in given["uwb"]]
    else:
        for t in sorted(topics):
            ty = topics[t][0]
            if not uwb_msgs.is_uwb_type(ty):
                continue
            if uwb_msgs.base_name(ty) == "Range" and "uwb" not in t.lower():
                m.notes.append(
                    f"uwb: {t} (sensor_msgs/Range) not taken: name has no 'uwb'; give it with --uwb"
                )
                continue
            m.uwb.append(t)
            m.notes.append(f"uwb: {t} ({ty}, by type)")
    gt_hint = [t for t in topics if _gt_named(t)]
    if given.get("groundtruth"):
        m.groundtruth = check("groundtruth", given["groundtruth"], GT_POSE_TYPES + GT_POSITION_TYPES)
    else:
        cands = sorted(t for t in gt_hint if topics[t][0] in GT_POSE_TYPES + GT_POSITION_TYPES)
        m.groundtruth = pick("groundtruth", (), cands)
    if given.get("odometry"):
        m.odometry = check("odometry", given["odometry"], ODOM_TYPES)
    else:
        cands = sorted(t for t in by_type.get(ODOM_TYPES[0], []) if t != m.groundtruth)
        m.odometry = pick("odometry", ODOM_TYPES, cands)
    return m


# ---------------------------------------------------------------------------------------------------------------
# per-role writers (message object -> recording)
# ---------------------------------------------------------------------------------------------------------------
def _stamp(m: Any, bag_t: int) -> int:
    t = uwb_msgs.message_stamp(m)
    return t if t is not None else int(bag_t)


def _vec(v: Any) -> tuple[float, float, float]:
    return float(v.x), float(v.y), float(v.z)


def _quat(q: Any) -> tuple[float, float, float, float]:
    out = np.array([q.x, q.y, q.z, q.w], float)
    n = np.linalg.norm(out)
    if not np.isfinite(n) or abs(n - 1.0) > 1e-2:
        raise Drop(f"non-unit quaternion (|q| = {n:.4g})")
    return tuple((out / n).tolist())


def image_mono8(m: Any) -> np.ndarray:
    """sensor_msgs/Image or CompressedImage -> HxW uint8."""
    import cv2

    if hasattr(m, "format"):  # CompressedImage
        img = cv2.imdecode(np.asarray(m.data, np.uint8), cv2.IMREAD_GRAYSCALE)
        if img is None:
            raise Drop(f"compressed image ({m.format!r}) does not decode")
        return img
    h, w, enc, step = int(m.height), int(m.width), str(m.encoding), int(m.step)
    data = np.asarray(m.data, np.uint8)
    ch = {"mono8": 1, "8UC1": 1, "rgb8": 3, "bgr8": 3, "rgba8": 4, "bgra8": 4, "mono16": 2, "16UC1": 2}.get(
        enc
    )
    if ch is None:
        raise Drop(f"image encoding {enc!r} not supported")
    if step < w * ch or data.size < h * step:
        raise Drop(f"image data {data.size} bytes for {h}x{w} {enc} (step {step})")
    rows = data[: h * step].reshape(h, step)[:, : w * ch]
    if ch == 2:
        px = rows.copy().view(">u2" if m.is_bigendian else "<u2").reshape(h, w)
        return (px >> 8).astype(np.uint8)
    px = rows.reshape(h, w, ch)
    if ch == 1:
        return np.ascontiguousarray(px[:, :, 0])
    code = {"rgb8": cv2.COLOR_RGB2GRAY, "bgr8": cv2.COLOR_BGR2GRAY, "rgba8": cv2.COLOR_RGBA2GRAY}.get(
        enc, cv2.COLOR_BGRA2GRAY
    )
    return cv2.cvtColor(np.ascontiguousarray(px), code)


def _pose_of(m: Any) -> tuple[tuple, tuple]:
    if hasattr(m, "transform"):
        return _vec(m.transform.translation), _quat(m.transform.rotation)
    pose = m.pose.pose if hasattr(m.pose, "pose") else m.pose
    return _vec(pose.position), _quat(pose.orientation)


@dataclass
class RangeBuffer:
    """Ranges of every UWB topic, cleaned and written at the end (sorted, duplicates dropped)."""

    t: list[int] = field(default_factory=list)
    tag: list[int] = field(default_factory=list)
    antenna: list[int] = field(default_factory=list)
    anchor: list[int] = field(default_factory=list)
    d: list[float] = field(default_factory=list)

    def add(self, r: uwb_msgs.Ranges, bag_t: int) -> None:
        t = r.stamp_ns if r.stamp_ns is not None else int(bag_t)
        n = len(r.distance)
        self.t += [t] * n
        self.tag += r.tag
        self.antenna += r.antenna
        self.anchor += r.anchor
        self.d += r.distance

    def data(self) -> RangeData:
        return RangeData(
            np.asarray(self.t, np.int64),
            np.asarray(self.tag, np.int64),
            np.asarray(self.antenna, np.int64),
            np.asarray(self.anchor, np.int64),
            np.asarray(self.d, float),
        )


class Converter:
    """Writes one decoded message of a role; raises Drop to drop it with a reason."""

    def __init__(
        self, writer: RecordingWriter, check_size: Callable[[str, tuple[int, int], str], None]
    ) -> None:
        self.w = writer
        self.check_size = check_size  # (role, (width, height), topic): raises InputError for a mismatch
        self.ranges = RangeBuffer()
        # duplicates dropped, steps back counted per recording topic; a clock jump in a sensor's series refused
        self._once = StampCheck(series=(TOPIC_IMU, TOPIC_ODOM, TOPIC_GT_POSE, TOPIC_GT_POSITION))
        self.stamp_sources: dict[str, Counter] = {}
        self.zero_cov = 0
        self.image_sizes: dict[str, tuple[int, int]] = {}  # camera role -> (width, height) of its first image
        self.imu_span: list[int] = []  # count, first and last stamp of the IMU samples written
        # fixed-rate role -> (its sorted bag stamps, their sample times): `bag_sample_times`
        self.sample_times: dict[str, tuple[np.ndarray, np.ndarray]] = {}

    def _sample_time(self, role: str, t: int) -> int:
        """The sample time of a fixed-rate role's stamp ``t`` (``t`` itself when not re-stamped)."""
        raw, fixed = self.sample_times.get(role, (None, None))
        if raw is None:
            return t
        i = int(np.searchsorted(raw, t))
        return int(fixed[i]) if i < len(raw) and raw[i] == t else t

    def imu_rate_hz(self) -> float | None:
        n, t0, t1 = (self.imu_span + [0, 0, 0])[:3]
        return (n - 1) / ((t1 - t0) * 1e-9) if n > 1 and t1 > t0 else None

    def __call__(self, role: str, bag_topic: str, msgtype: str, m: Any, bag_t: int) -> None:
        if role == "uwb":
            try:
                r = uwb_msgs.decoder(msgtype)(m)
            except (uwb_msgs.Undecodable, AttributeError, TypeError, ValueError) as exc:
                raise Drop(str(exc)) from None
            if not r.distance:
                raise Drop("frame without ranges (no nodes)")
            src = "header" if r.stamp_ns is not None else "bag time"
            self.stamp_sources.setdefault(bag_topic, Counter())[src] += 1
            self.ranges.add(r, bag_t)
            return
        t = self._sample_time(role, _stamp(m, bag_t))
        if role == "imu":
            self._once(TOPIC_IMU, t)
            gyro, acc = _vec(m.angular_velocity), _vec(m.linear_acceleration)
            if not np.isfinite(gyro + acc).all():
                raise Drop("non-finite IMU sample")
            self.w.write_imu(t, gyro, acc, topic=TOPIC_IMU)
            span = self.imu_span
            self.imu_span = [span[0] + 1, span[1], t] if span else [1, t, t]
        elif role in ("cam0", "cam1"):
            topic = TOPIC_CAM0 if role == "cam0" else TOPIC_CAM1
            self._once(topic, t)
            img = image_mono8(m)
            size = (img.shape[1], img.shape[0])
            if role not in self.image_sizes:
                self.image_sizes[role] = size
                self.check_size(role, size, bag_topic)
            elif size != self.image_sizes[role]:  # the intrinsics hold for one image size
                w, h = self.image_sizes[role]
                raise Drop(f"image of {size[0]}x{size[1]}, not the {w}x{h} of the camera's first image")
            self.w.write_image(topic, t, img, frame_id=role)
        elif role == "odometry":
            self._once(TOPIC_ODOM, t)
            p, q = _pose_of(m)
            cov = np.asarray(m.pose.covariance, float).reshape(6, 6)
            self.zero_cov += int(not cov.any())
            self.w.write_odometry(t, p, q, cov6=cov, topic=TOPIC_ODOM)
        elif role == "groundtruth":
            if msgtype in GT_POSITION_TYPES:
                self._once(TOPIC_GT_POSITION, t)
                self.w.write_position(t, _vec(m.point), topic=TOPIC_GT_POSITION)
            else:
                self._once(TOPIC_GT_POSE, t)
                p, q = _pose_of(m)
                self.w.write_pose(t, p, q, topic=TOPIC_GT_POSE)


# ---------------------------------------------------------------------------------------------------------------
# calibration
# ---------------------------------------------------------------------------------------------------------------
def check_image_size(cal: Calibration, role: str, size: tuple[int, int], topic: str, source: str) -> None:
    """The first image of camera ``role`` against the calibration's resolution (intrinsics are per image size)."""
    c = cal.cameras.get(role)
    if c is not None:
        c.check_image_size(size, f"on {topic}", source, f"cameras.{role}.resolution")


def _final_calibration(data: dict, source: str, conv: Converter, counts: dict, drops: Drops) -> dict:
    """The recording's calibration: validated; a resolution or IMU rate left out taken from the data, the other
    defaults named in notes."""
    cal = parse_calibration(data, source)
    for role, size in conv.image_sizes.items():
        c = cal.cameras.get(role)
        if c is None:
            drops.note(f"no calibration for {role} (cameras.{role}): uwbcal run cannot use its images (VIO)")
        elif c.resolution is None:
            c.resolution = list(size)
            drops.note(f"cameras.{role}.resolution not given: {size[0]}x{size[1]}, the images' size")
    if cal.imu is not None and cal.imu.rate_hz is None and conv.imu_rate_hz() is not None:
        cal.imu.rate_hz = round(conv.imu_rate_hz(), 3)
        drops.note(f"imu.rate_hz not given: {cal.imu.rate_hz:g} Hz, from the IMU stamps")
    if cal.imu is None and TOPIC_IMU in counts and conv.image_sizes:
        drops.note("no imu calibration (imu: noise densities): uwbcal run cannot use the IMU (VIO)")
    for note in cal.defaults_used():
        drops.note(note)
    return cal.to_metadata()


def _uwb_section(r: RangeData, antennas: Path | None, given: dict | None, drops: Drops) -> dict:
    if given is not None and antennas is None:
        return given
    if antennas is None:
        drops.note("no --antennas: zero antenna lever arms, gamma prior 0 +- 0.3 m")
        return uwb_calibration(default_tags(r.tag, r.antenna), {})
    tags, bias = parse_antennas(antennas)
    for t in np.unique(r.tag).tolist():
        if str(t) not in tags:
            drops.note(f"tag {t} has ranges but no antenna_offset in {antennas}")
    out = uwb_calibration(tags, bias)
    if given:
        out = {**given, **out}
    return out


# ---------------------------------------------------------------------------------------------------------------
# conversion
# ---------------------------------------------------------------------------------------------------------------
def _surveyed_truth(path: str | Path | None) -> dict | None:
    """``--anchors-truth``: the surveyed anchors in the ground truth's (world) frame."""
    if path is None:
        return None
    return truth_record(read_anchor_truth(path), "surveyed", path, frame="world")


def _account_unread(
    accounts: dict, drops: Drops, start_s: float | None, end_s: float | None, truncated: bool
) -> None:
    """Messages of mapped topics the bag counts but the conversion did not read (outside ``--start``/``--end``,
    or lost to the truncation of the bag): counted as dropped."""
    reasons = (
        []
        if start_s is None and end_s is None
        else [f"outside --start {start_s or 0:g} s / --end {'end' if end_s is None else f'{end_s:g} s'}"]
    )
    reasons += ["lost after the truncation of the bag"] if truncated else []
    for t, acc in accounts.items():
        left = acc["count"] - acc["converted"] - acc["dropped"]
        if reasons and acc["role"] is not None and left > 0:
            acc["dropped"] += left
            drops.add(t, " or ".join(reasons), left)


@dataclass
class _BagRun:
    """One conversion's inputs and running accounts (what the steps of `convert_bag` share)."""

    path: Path
    antennas: Path | None
    cal: dict  # the given calibration as metadata
    cal_source: str
    roles: dict[str, str]  # topic -> role
    accounts: dict[str, dict]  # topic -> type, count, role, converted, dropped
    drops: Drops


def convert_bag(
    path: str | Path,
    output: str | Path,
    *,
    imu: str | None = None,
    cam0: str | None = None,
    cam1: str | None = None,
    uwb: Sequence[str] | None = None,
    odometry: str | None = None,
    groundtruth: str | None = None,
    antennas: str | Path | None = None,
    calibration: str | Path | None = None,
    anchors_truth: str | Path | None = None,
    start_s: float | None = None,
    end_s: float | None = None,
    max_range: float = MAX_RANGE_M,
    time_offset: float = 0.0,
) -> str:
    """Convert a ROS 1 / ROS 2 bag into one recording; returns a human summary. ``time_offset`` [s] is added to
    every range stamp (a known range-to-pose clock offset); ``anchors_truth``: a surveyed ``anchor,x,y,z`` CSV in
    the ground truth's frame (``uwbcal.truth``); ``start_s`` / ``end_s``: keep the messages from / before these
    seconds after the bag's start."""
    path = Path(path)
    time_offset_ns(time_offset)
    ant = Path(antennas) if antennas is not None else None
    if ant is not None and not ant.is_file():
        raise InputError(f"{ant}: antenna yaml not found")
    cal_source = str(calibration) if calibration is not None else f"{path}: calibration"
    given_cal = (
        load_calibration_yaml(calibration) if calibration is not None else parse_calibration({}, cal_source)
    )
    cal = given_cal.to_metadata()
    drops = Drops()
    truth = _surveyed_truth(anchors_truth)
    given = {"imu": imu, "cam0": cam0, "cam1": cam1, "uwb": list(uwb or []), "odometry": odometry}
    given["groundtruth"] = groundtruth
    with BagReader(path) as bag:
        topics = bag.topics()
        tmap = _mapped_topics(topics, given, path)
        roles = tmap.roles()
        run = _BagRun(path, ant, cal, cal_source, roles, _accounts(topics, roles, drops), drops)
        if bag.recovery is not None:
            drops.note(bag.recovery.note())
        use = [c for c in bag.connections if c.topic in roles]
        lo, hi = bag.span_ns(start_s, end_s)
        files = [path] if path.is_file() else sorted(p for p in path.iterdir() if p.is_file())
        hasher = Hasher(files + [Path(f) for f in (ant, calibration, anchors_truth) if f is not None])
        with RecordingWriter(output) as w:
            conv = Converter(
                w, lambda role, size, topic: check_image_size(given_cal, role, size, topic, cal_source)
            )
            conv.sample_times = bag_sample_times(bag, use, run, lo, hi)
            _convert_messages(bag, use, conv, run, lo, hi)
            _account_unread(run.accounts, drops, start_s, end_s, bag.recovery is not None)
            raw_ranges, ranges = _write_bag_ranges(w, conv, run, max_range, time_offset)
            counts = dict(w.counts)
            if not counts:
                raise InputError(f"{path}: nothing converted ({', '.join(roles)} had no usable message)")
            calib = _bag_calibration(run, conv, counts, raw_ranges, ranges, tmap.notes)
            w.set_metadata(META_CALIBRATION, calib)
            if truth is not None:
                drops.note(truth_note(truth["anchors"], ranges.anchor, Path(anchors_truth)))
                w.set_metadata(META_TRUTH, truth)
            w.set_metadata(META_SOURCE, _bag_source(run, bag.format, hasher, len(raw_ranges), len(ranges)))
    return summary(output, counts, drops, f"{bag.format} {path.name}")


def _mapped_topics(topics: dict[str, tuple[str, int]], given: dict[str, Any], path: Path) -> TopicMap:
    """The bag's topics mapped to roles; a bag without a topic of a known type refused with what it holds."""
    tmap = detect_topics(topics, given)
    if not tmap.roles():
        have = ", ".join(f"{t} ({ty})" for t, (ty, _) in sorted(topics.items())) or "no topics"
        raise InputError(f"{path}: no topic of a known type (found: {have}); name them with --imu/--uwb/...")
    return tmap


def _bag_source(run: _BagRun, fmt: str, hasher: Hasher, decoded: int, written: int) -> dict:
    """The recording's source record: the bag's format, topic map, message accounts and range counts."""
    return source_metadata(
        "bag",
        run.path.stem,
        hasher.result(),
        run.drops,
        format=fmt,
        topic_map={t: r for t, r in sorted(run.roles.items())},
        messages=run.accounts,
        ranges={"decoded": decoded, "written": written},
    )


def _accounts(topics: dict[str, tuple[str, int]], roles: dict[str, str], drops: Drops) -> dict[str, dict]:
    """Per topic: its type, message count, role and (so far) converted / dropped; unmapped topics dropped."""
    accounts = {
        t: {"type": ty, "count": n, "role": roles.get(t), "converted": 0, "dropped": 0}
        for t, (ty, n) in topics.items()
    }
    for t, (ty, n) in sorted(topics.items()):
        if t not in roles:
            drops.add(t, f"topic not mapped (type {ty})", n)
            accounts[t]["dropped"] = n
    return accounts


def bag_sample_times(
    bag: BagReader, use: list, run: _BagRun, start: int | None = None, stop: int | None = None
) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """A first pass over the fixed-rate topics (IMU, cameras): their stamps, and the sample times the one-way
    delay model gives them (`sample_times`); samples delivered late are noted in the summary. Per role: (sorted
    unique stamps, sample times). Messages that do not decode are left to the conversion pass to drop."""
    fixed = [c for c in use if run.roles[c.topic] in FIXED_RATE_ROLES]
    stamps: dict[str, list[int]] = {}
    for conn, bag_t, raw in bag.messages(fixed, start, stop):
        dec = bag.decoder_for(conn, raw)
        if isinstance(dec, str):
            continue
        try:
            t = _stamp(dec(raw), bag_t)
        except Exception:  # noqa: BLE001 (the conversion pass drops and counts it)
            continue
        stamps.setdefault(run.roles[conn.topic], []).append(t)
    out = {}
    origin = min((min(v) for v in stamps.values() if v), default=0)
    for role, ts in sorted(stamps.items()):
        raw = np.unique(np.asarray(ts, np.int64))
        res = sample_times(raw)
        note = res.note(FIXED_RATE_ROLES[role], origin)
        if note is not None:
            run.drops.note(note)
        out[role] = (raw, res.t_ns)
    return out


def _convert_messages(
    bag: BagReader,
    use: list,
    conv: Converter,
    run: _BagRun,
    start: int | None = None,
    stop: int | None = None,
) -> None:
    """Decode and convert every message of the connections ``use``; a message that does not decode or convert
    is dropped and counted (an `InputError` stops the conversion)."""
    drops = run.drops
    total = sum(c.msgcount for c in use)
    with progress(f"bag {run.path.name}", total) as advance:
        for conn, bag_t, raw in bag.messages(use, start, stop):
            acc = run.accounts[conn.topic]
            role = run.roles[conn.topic]
            advance(1)
            dec = bag.decoder_for(conn, raw)
            if isinstance(dec, str):
                acc["dropped"] += 1
                drops.add(conn.topic, f"undecodable: {norm_type(conn.msgtype)} {dec}", 1)
                continue
            try:
                m = dec(raw)
                conv(role, conn.topic, norm_type(conn.msgtype), m, bag_t)
            except Drop as exc:
                acc["dropped"] += 1
                drops.add(conn.topic, str(exc), 1, f"bag t={bag_t}")
                continue
            except InputError:
                raise
            except Exception as exc:  # noqa: BLE001 (a corrupt message: drop it, say which)
                acc["dropped"] += 1
                drops.add(conn.topic, f"undecodable message ({type(exc).__name__})", 1, f"bag t={bag_t}")
                continue
            acc["converted"] += 1


def _write_bag_ranges(
    w: RecordingWriter, conv: Converter, run: _BagRun, max_range: float, time_offset: float
) -> tuple[RangeData, RangeData]:
    """The decoded ranges (ids checked, shifted by ``time_offset``) and the cleaned ones, written."""
    drops = run.drops
    buf = conv.ranges  # ids checked as decoded (Python ints): one beyond int64 must not overflow first
    bad = id_problem({"tag": buf.tag, "antenna": buf.antenna, "anchor": buf.anchor})
    if bad is not None:
        name, i = bad
        value = int(getattr(buf, name)[i])
        raise InputError(f"{run.path}: UWB range at t={buf.t[i]} ns: {id_text(name, value)}")
    raw_ranges = shift_ranges(buf.data(), time_offset, drops)
    ranges = clean_ranges(raw_ranges, TOPIC_RANGE, drops, max_range) if len(raw_ranges) else raw_ranges
    write_ranges(w, ranges, TOPIC_RANGE)
    if len(ranges):
        drops.note(f"{len(raw_ranges)} ranges decoded; " + anchors_note(ranges))
    for t, c in conv.stamp_sources.items():
        drops.note(f"{t}: stamps from " + ", ".join(f"{k} ({v})" for k, v in sorted(c.items())))
    if conv.zero_cov:
        drops.note(f"{TOPIC_ODOM}: {conv.zero_cov} messages with an all-zero pose covariance")
    return raw_ranges, ranges


def _bag_calibration(
    run: _BagRun, conv: Converter, counts: dict, raw_ranges: RangeData, ranges: RangeData, notes: list[str]
) -> dict:
    """The recording's calibration metadata: the given one, its uwb section from the ranges and antennas, and
    what the conversion found (`_final_calibration`); the notes on what is missing."""
    cal, drops = run.cal, run.drops
    calib = {k: v for k, v in cal.items() if k != "uwb"}
    if len(raw_ranges) or cal.get("uwb") is not None:
        calib["uwb"] = _uwb_section(ranges, run.antennas, cal.get("uwb"), drops)
    if not cal and ({TOPIC_IMU, TOPIC_CAM0, TOPIC_CAM1} & set(counts)):
        drops.note("no --calibration: IMU noise, camera intrinsics and extrinsics unknown")
    conv._once.report(drops, run.path)
    for n in notes:
        drops.note("topic " + n)
    return _final_calibration(calib, run.cal_source, conv, counts, drops)


# ---------------------------------------------------------------------------------------------------------------
# info on a bag (before converting)
# ---------------------------------------------------------------------------------------------------------------
def bag_info(path: str | Path, given: dict[str, Any] | None = None) -> str:
    """What a bag holds, which role each topic would take, and what would not be mapped."""
    path = Path(path)
    with BagReader(path) as bag:
        topics = bag.topics()
        tmap = detect_topics(topics, given)
        roles = tmap.roles()
        defs = {c.topic: bool(c.msgdef.data) or bag.ros1 for c in bag.connections}
        span = (bag.reader.start_time, bag.reader.end_time) if topics else (0, 0)
    lines = [
        f"bag        {path} ({bag.format})",
        f"duration   {(span[1] - span[0]) * 1e-9:.3f} s",
        "",
        f"{'topic':<32} {'type':<44} {'count':>8}  maps to",
    ]
    for t, (ty, n) in sorted(topics.items()):
        role = roles.get(t)
        what = role if role else "not mapped"
        if not defs.get(t, True):
            what += " (no definition in the bag: shipped one used)" if role == "uwb" else ""
        lines.append(f"{t:<32} {ty:<44} {n:>8}  {what}")
    lines += ["", *(f"  {n}" for n in tmap.notes)]
    if bag.recovery is not None:
        lines.append(f"  {bag.recovery.note()}")
    unmapped = [t for t in topics if t not in roles]
    lines.append(f"not mapped: {', '.join(sorted(unmapped)) if unmapped else 'nothing'}")
    return "\n".join(lines)


def is_bag(path: str | Path) -> bool:
    """True for a path `bag_info` reads (a .bag, .db3, ROS 2 bag folder, or an .mcap that is not a recording)."""
    p = Path(path)
    if p.is_dir():
        return (p / "metadata.yaml").is_file()
    if p.suffix in (".bag", ".db3"):
        return True
    return p.suffix == ".mcap" and p.is_file() and not _is_recording(p)
