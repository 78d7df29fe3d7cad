"""The normalised recording: one MCAP file, ros2msg schemas, CDR messages, zstd chunks (DESIGN §3).

`RecordingWriter` is the only writer and `RecordingReader` the only reader of recordings. The reader streams
through the MCAP index (time order, topic and time-range filters) without loading the file, offers column
readers for the stages, and recovers what it can from a truncated file (up to the last intact chunk).
"""

from __future__ import annotations

import heapq
import json
import os
import warnings
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from mcap.exceptions import McapError
from mcap.reader import make_reader
from mcap.records import Channel, Message, Schema
from mcap.stream_reader import StreamReader
from mcap.writer import CompressionType, Writer

from . import msgs
from .errors import InputError

TOPIC_IMU = "/imu"
TOPIC_CAM0 = "/cam0/image_raw"
TOPIC_CAM1 = "/cam1/image_raw"
TOPIC_FEATURES = "/cam0/features"
TOPIC_RANGE = "/uwb/range"
TOPIC_GT_POSE = "/groundtruth/pose"
TOPIC_GT_POSITION = "/groundtruth/position"
TOPIC_ODOM = "/odometry"
TOPIC_VIO = "/vio/odometry"

META_CALIBRATION = "uwbcal.calibration"
META_SOURCE = "uwbcal.source"
META_TRUTH = "uwbcal.truth"
META_TOPICS = "uwbcal.topics"  # per-topic time spans, written by RecordingWriter (saves a scan)

MCAP_MAGIC = b"\x89MCAP0\r\n"
_CHUNK_SIZE = 4 * 1024 * 1024


# ---------------------------------------------------------------------------------------------------------------
# message construction
# ---------------------------------------------------------------------------------------------------------------
def _types():
    ts = msgs.typestore()
    return ts, ts.types


def _stamp(t_ns: int, frame_id: str):
    ts, T = _types()
    t_ns = int(t_ns)
    return T["std_msgs/msg/Header"](
        stamp=T["builtin_interfaces/msg/Time"](sec=t_ns // 1_000_000_000, nanosec=t_ns % 1_000_000_000),
        frame_id=frame_id,
    )


def _vec3(v):
    _, T = _types()
    return T["geometry_msgs/msg/Vector3"](x=float(v[0]), y=float(v[1]), z=float(v[2]))


def _point(v):
    _, T = _types()
    return T["geometry_msgs/msg/Point"](x=float(v[0]), y=float(v[1]), z=float(v[2]))


def _quat(q):
    _, T = _types()
    return T["geometry_msgs/msg/Quaternion"](x=float(q[0]), y=float(q[1]), z=float(q[2]), w=float(q[3]))


def _stamp_ns(header) -> int:
    return int(header.stamp.sec) * 1_000_000_000 + int(header.stamp.nanosec)


# ---------------------------------------------------------------------------------------------------------------
# writer
# ---------------------------------------------------------------------------------------------------------------
class RecordingWriter:
    """Writes a recording atomically: to a temporary sibling that replaces ``path`` on a clean close."""

    def __init__(self, path: str | os.PathLike, *, chunk_size: int = _CHUNK_SIZE) -> None:
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._tmp = self.path.with_name(f".{self.path.name}.{os.getpid()}.part")
        self._file = open(self._tmp, "wb")  # noqa: SIM115 (closed in close/abort)
        self._writer = Writer(self._file, chunk_size=chunk_size, compression=CompressionType.ZSTD)
        self._writer.start(profile="ros2", library="uwbcal")
        self._schemas: dict[str, int] = {}
        self._channels: dict[str, int] = {}
        self._seq: dict[str, int] = {}
        self._metadata: dict[str, dict] = {}
        self._closed = False
        self.counts: dict[str, int] = {}
        self._spans: dict[str, list[int]] = {}

    # -- low level -----------------------------------------------------------------------------------------------
    def _channel(self, topic: str, msgtype: str) -> int:
        cid = self._channels.get(topic)
        if cid is not None:
            return cid
        sid = self._schemas.get(msgtype)
        if sid is None:
            sid = self._writer.register_schema(msgtype, "ros2msg", msgs.schema_text(msgtype).encode())
            self._schemas[msgtype] = sid
        cid = self._writer.register_channel(topic, "cdr", sid)
        self._channels[topic] = cid
        self._seq[topic] = 0
        return cid

    def write_raw(self, topic: str, t_ns: int, msgtype: str, cdr: bytes | memoryview) -> None:
        """Write an already CDR-encoded message (fast pass-through for converters)."""
        cid = self._channel(topic, msgtype)
        seq = self._seq[topic]
        self._seq[topic] = seq + 1
        t_ns = int(t_ns)
        self._writer.add_message(cid, log_time=t_ns, data=bytes(cdr), publish_time=t_ns, sequence=seq)
        self.counts[topic] = self.counts.get(topic, 0) + 1
        span = self._spans.get(topic)
        if span is None:
            self._spans[topic] = [t_ns, t_ns]
        else:
            span[0] = min(span[0], t_ns)
            span[1] = max(span[1], t_ns)

    def write(self, topic: str, t_ns: int, msg: Any) -> None:
        ts = msgs.typestore()
        self.write_raw(topic, t_ns, msg.__msgtype__, ts.serialize_cdr(msg, msg.__msgtype__))

    # -- typed helpers -------------------------------------------------------------------------------------------
    def write_imu(self, t_ns: int, gyro, acc, topic: str = TOPIC_IMU, frame_id: str = "imu") -> None:
        _, T = _types()
        z9 = np.zeros(9)
        self.write(
            topic,
            t_ns,
            T[msgs.IMU](
                header=_stamp(t_ns, frame_id),
                orientation=_quat((0, 0, 0, 1)),
                orientation_covariance=np.r_[-1.0, z9[1:]],
                angular_velocity=_vec3(gyro),
                angular_velocity_covariance=z9,
                linear_acceleration=_vec3(acc),
                linear_acceleration_covariance=z9,
            ),
        )

    def write_imu_batch(self, t_ns, gyro, acc, topic: str = TOPIC_IMU) -> None:
        for t, g, a in zip(np.asarray(t_ns), np.asarray(gyro), np.asarray(acc), strict=True):
            self.write_imu(int(t), g, a, topic)

    def write_image(self, topic: str, t_ns: int, img: np.ndarray, frame_id: str = "cam0") -> None:
        _, T = _types()
        img = np.ascontiguousarray(img)
        if img.dtype != np.uint8 or img.ndim != 2:
            raise ValueError(f"{topic}: expected a mono8 HxW uint8 image, got {img.dtype} {img.shape}")
        h, w = img.shape
        self.write(
            topic,
            t_ns,
            T[msgs.IMAGE](
                header=_stamp(t_ns, frame_id),
                height=h,
                width=w,
                encoding="mono8",
                is_bigendian=0,
                step=w,
                data=img.reshape(-1),
            ),
        )

    def write_features(self, t_ns: int, ids, uv, topic: str = TOPIC_FEATURES, frame_id: str = "cam0") -> None:
        _, T = _types()
        uv = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
        self.write(
            topic,
            t_ns,
            T[msgs.FEATURE_TRACKS](
                header=_stamp(t_ns, frame_id),
                ids=np.asarray(ids, dtype=np.uint32),
                u=np.ascontiguousarray(uv[:, 0]),
                v=np.ascontiguousarray(uv[:, 1]),
            ),
        )

    def write_range(
        self, t_ns: int, tag: int, antenna: int, anchor: int, distance: float, topic: str = TOPIC_RANGE
    ) -> None:
        _, T = _types()
        self.write(
            topic,
            t_ns,
            T[msgs.UWB_RANGE](
                header=_stamp(t_ns, f"tag{int(tag)}"),
                tag_id=int(tag),
                antenna=int(antenna),
                anchor_id=int(anchor),
                distance=float(distance),
            ),
        )

    def write_range_batch(self, t_ns, tag, antenna, anchor, distance, topic: str = TOPIC_RANGE) -> None:
        n = len(t_ns)
        tag, antenna, anchor = (np.broadcast_to(np.asarray(x), (n,)) for x in (tag, antenna, anchor))
        for row in zip(np.asarray(t_ns), tag, antenna, anchor, np.asarray(distance), strict=True):
            self.write_range(*row, topic=topic)

    def write_pose(self, t_ns: int, p, q_xyzw, topic: str = TOPIC_GT_POSE, frame_id: str = "world") -> None:
        _, T = _types()
        pose = T["geometry_msgs/msg/Pose"](position=_point(p), orientation=_quat(q_xyzw))
        self.write(topic, t_ns, T[msgs.POSE_STAMPED](header=_stamp(t_ns, frame_id), pose=pose))

    def write_pose_batch(self, t_ns, p, q_xyzw, topic: str = TOPIC_GT_POSE) -> None:
        for t, pp, qq in zip(np.asarray(t_ns), np.asarray(p), np.asarray(q_xyzw), strict=True):
            self.write_pose(int(t), pp, qq, topic)

    def write_position(self, t_ns: int, p, topic: str = TOPIC_GT_POSITION, frame_id: str = "world") -> None:
        _, T = _types()
        self.write(topic, t_ns, T[msgs.POINT_STAMPED](header=_stamp(t_ns, frame_id), point=_point(p)))

    def write_position_batch(self, t_ns, p, topic: str = TOPIC_GT_POSITION) -> None:
        for t, pp in zip(np.asarray(t_ns), np.asarray(p), strict=True):
            self.write_position(int(t), pp, topic)

    def write_odometry(
        self,
        t_ns: int,
        p,
        q_xyzw,
        cov6=None,
        topic: str = TOPIC_ODOM,
        v=None,
        w=None,
        frame_id: str = "world",
        child_frame_id: str = "body",
    ) -> None:
        _, T = _types()
        cov6 = np.zeros((6, 6)) if cov6 is None else np.asarray(cov6, float)
        pose = T["geometry_msgs/msg/PoseWithCovariance"](
            pose=T["geometry_msgs/msg/Pose"](position=_point(p), orientation=_quat(q_xyzw)),
            covariance=cov6.reshape(36),
        )
        twist = T["geometry_msgs/msg/TwistWithCovariance"](
            twist=T["geometry_msgs/msg/Twist"](
                linear=_vec3(np.zeros(3) if v is None else v), angular=_vec3(np.zeros(3) if w is None else w)
            ),
            covariance=np.zeros(36),
        )
        self.write(
            topic,
            t_ns,
            T[msgs.ODOMETRY](
                header=_stamp(t_ns, frame_id), child_frame_id=child_frame_id, pose=pose, twist=twist
            ),
        )

    def write_odometry_batch(self, t_ns, p, q_xyzw, cov6=None, topic: str = TOPIC_ODOM) -> None:
        n = len(t_ns)
        covs = np.zeros((n, 6, 6)) if cov6 is None else np.broadcast_to(np.asarray(cov6, float), (n, 6, 6))
        for t, pp, qq, cc in zip(np.asarray(t_ns), np.asarray(p), np.asarray(q_xyzw), covs, strict=True):
            self.write_odometry(int(t), pp, qq, cc, topic)

    def set_metadata(self, name: str, data: dict) -> None:
        self._metadata[name] = data

    # -- lifecycle -----------------------------------------------------------------------------------------------
    def close(self) -> None:
        if self._closed:
            return
        self._metadata[META_TOPICS] = {k: {"start_ns": v[0], "end_ns": v[1]} for k, v in self._spans.items()}
        for name, data in self._metadata.items():
            self._writer.add_metadata(name, {"json": json.dumps(data, default=_json_default)})
        self._writer.finish()
        self._file.close()
        self._closed = True
        os.replace(self._tmp, self.path)

    def abort(self) -> None:
        if self._closed:
            return
        self._closed = True
        try:
            self._file.close()
        finally:
            self._tmp.unlink(missing_ok=True)

    def __enter__(self) -> RecordingWriter:
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is None:
            self.close()
        else:
            self.abort()


def _json_default(o: Any) -> Any:
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, Path):
        return str(o)
    raise TypeError(f"not JSON serialisable: {type(o)}")


# ---------------------------------------------------------------------------------------------------------------
# reader
# ---------------------------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class TopicInfo:
    topic: str
    msgtype: str
    count: int
    start_ns: int
    end_ns: int

    @property
    def duration_s(self) -> float:
        return (self.end_ns - self.start_ns) * 1e-9

    @property
    def rate_hz(self) -> float:
        return (self.count - 1) / self.duration_s if self.count > 1 and self.duration_s > 0 else 0.0


@dataclass
class ImuData:
    t_ns: np.ndarray
    gyro: np.ndarray
    acc: np.ndarray


@dataclass
class RangeData:
    t_ns: np.ndarray
    tag: np.ndarray
    antenna: np.ndarray
    anchor: np.ndarray
    distance: np.ndarray

    def __len__(self) -> int:
        return len(self.t_ns)

    def select(self, mask: np.ndarray) -> RangeData:
        return RangeData(
            self.t_ns[mask], self.tag[mask], self.antenna[mask], self.anchor[mask], self.distance[mask]
        )


@dataclass
class PoseData:
    t_ns: np.ndarray
    p: np.ndarray
    q_xyzw: np.ndarray


@dataclass
class PositionData:
    t_ns: np.ndarray
    p: np.ndarray


@dataclass
class OdometryData:
    t_ns: np.ndarray
    p: np.ndarray
    q_xyzw: np.ndarray
    cov: np.ndarray


class RecordingReader:
    """Streaming reader of a recording. Raises `InputError` for anything that is not an MCAP recording."""

    def __init__(self, path: str | os.PathLike) -> None:
        self.path = Path(path)
        if not self.path.is_file():
            raise InputError(f"{self.path}: recording not found")
        with open(self.path, "rb") as f:
            head = f.read(len(MCAP_MAGIC))
        if head != MCAP_MAGIC:
            raise InputError(
                f"{self.path}: not an MCAP recording (bad magic); convert it with 'uwbcal convert'"
            )
        self.warnings: list[str] = []
        self._summary = None
        self._metadata: dict[str, dict] | None = None
        self._recovered: list[tuple[str, str, int, bytes]] | None = None
        try:
            with open(self.path, "rb") as f:
                self._summary = make_reader(f).get_summary()
        except (McapError, ValueError, EOFError, OSError, AssertionError):
            self._summary = None
        if self._summary is None:
            self._recover()

    # -- truncated files -----------------------------------------------------------------------------------------
    def _recover(self) -> None:
        """Read records up to the first broken one (no summary: truncated or still being written)."""
        schemas: dict[int, Schema] = {}
        channels: dict[int, Channel] = {}
        out: list[tuple[str, str, int, bytes]] = []
        meta: dict[str, dict] = {}
        broken = None
        with open(self.path, "rb") as f:
            try:
                for rec in StreamReader(f, skip_magic=False, emit_chunks=False).records:
                    if isinstance(rec, Schema):
                        schemas[rec.id] = rec
                    elif isinstance(rec, Channel):
                        channels[rec.id] = rec
                    elif isinstance(rec, Message):
                        ch = channels[rec.channel_id]
                        out.append((ch.topic, schemas[ch.schema_id].name, rec.log_time, bytes(rec.data)))
                    elif type(rec).__name__ == "Metadata":
                        meta[rec.name] = dict(rec.metadata)
            except Exception as exc:  # any decoding error ends the intact part
                broken = exc
        if not out and not channels:
            raise InputError(f"{self.path}: no readable MCAP records ({broken}); the file is corrupt")
        out.sort(key=lambda m: m[2])
        self._recovered = out
        self._metadata = {k: _parse_meta(v) for k, v in meta.items()}
        msg = (
            f"{self.path}: truncated or unfinished recording (no summary); recovered {len(out)} messages "
            f"from the intact chunks" + (f" (stopped at: {broken})" if broken else "")
        )
        self.warnings.append(msg)
        warnings.warn(msg, stacklevel=3)

    @property
    def truncated(self) -> bool:
        return self._recovered is not None

    # -- summary and metadata ------------------------------------------------------------------------------------
    def topics(self) -> dict[str, TopicInfo]:
        if self._recovered is not None:
            acc: dict[str, list] = {}
            for topic, typ, t, _ in self._recovered:
                a = acc.setdefault(topic, [typ, 0, t, t])
                a[1] += 1
                a[2] = min(a[2], t)
                a[3] = max(a[3], t)
            return {k: TopicInfo(k, v[0], v[1], v[2], v[3]) for k, v in acc.items()}
        s = self._summary
        stats = s.statistics
        counts = stats.channel_message_counts if stats else {}
        # per-channel time spans from the chunk indexes
        spans: dict[int, list[int]] = {}
        for ci in s.chunk_indexes:
            for cid in ci.message_index_offsets:
                sp = spans.setdefault(cid, [ci.message_start_time, ci.message_end_time])
                sp[0] = min(sp[0], ci.message_start_time)
                sp[1] = max(sp[1], ci.message_end_time)
        known = self.metadata(META_TOPICS) or {}
        out = {}
        for cid, ch in s.channels.items():
            start, end = spans.get(cid, [0, 0])
            if ch.topic in known:
                start, end = known[ch.topic]["start_ns"], known[ch.topic]["end_ns"]
            elif counts.get(cid, 0) > 0 and len(spans) > 1:
                # chunk spans are shared between channels; refine with the first/last message of the topic
                first = next(self.messages([ch.topic], raw=True), None)
                start = first[1] if first else start
                end = self._last_time(ch.topic, end)
            out[ch.topic] = TopicInfo(ch.topic, s.schemas[ch.schema_id].name, counts.get(cid, 0), start, end)
        return out

    def _last_time(self, topic: str, upper: int) -> int:
        s = self._summary
        cids = [cid for cid, ch in s.channels.items() if ch.topic == topic]
        cands = [ci for ci in s.chunk_indexes if any(c in ci.message_index_offsets for c in cids)]
        if not cands:
            return upper
        last_chunk = max(cands, key=lambda ci: ci.message_end_time)
        last = upper
        for _, t, _ in self.messages([topic], start_ns=last_chunk.message_start_time, raw=True):
            last = t
        return last

    def metadata(self, name: str) -> dict | None:
        if self._metadata is None:
            self._metadata = {}
            with open(self.path, "rb") as f:
                reader = make_reader(f)
                for m in reader.iter_metadata():
                    self._metadata[m.name] = _parse_meta(m.metadata)
        return self._metadata.get(name)

    @property
    def calibration(self) -> dict:
        return self.metadata(META_CALIBRATION) or {}

    @property
    def source(self) -> dict:
        return self.metadata(META_SOURCE) or {}

    @property
    def truth(self) -> dict | None:
        return self.metadata(META_TRUTH)

    def time_span(self) -> tuple[int, int]:
        tops = self.topics().values()
        if not tops:
            raise InputError(f"{self.path}: the recording has no messages")
        return min(t.start_ns for t in tops), max(t.end_ns for t in tops)

    # -- streaming -----------------------------------------------------------------------------------------------
    def messages(
        self,
        topics: Iterable[str] | None = None,
        start_ns: int | None = None,
        end_ns: int | None = None,
        *,
        raw: bool = False,
        file_order: bool = False,
    ) -> Iterator[tuple[str, int, Any]]:
        """Yield ``(topic, t_ns, msg)`` in time order; ``end_ns`` is exclusive. ``raw`` yields CDR bytes;
        ``file_order`` yields in the order of writing instead (to diagnose stamp order)."""
        topics = list(topics) if topics is not None else None
        ts = msgs.typestore()
        if self._recovered is not None:
            for topic, typ, t, data in self._recovered:
                if topics is not None and topic not in topics:
                    continue
                if (start_ns is not None and t < start_ns) or (end_ns is not None and t >= end_ns):
                    continue
                yield topic, t, (data if raw else ts.deserialize_cdr(data, typ))
            return
        with open(self.path, "rb") as f:
            reader = make_reader(f)
            try:
                for schema, channel, message in reader.iter_messages(
                    topics=topics, starting_at=start_ns, ending_before=end_ns, log_time_order=not file_order
                ):
                    data = message.data
                    yield (
                        channel.topic,
                        message.log_time,
                        (data if raw else ts.deserialize_cdr(data, schema.name)),
                    )
            except McapError as exc:
                raise InputError(f"{self.path}: corrupt chunk while reading ({exc})") from None

    def _need(self, topic: str) -> None:
        if topic not in self.topics():
            have = ", ".join(sorted(self.topics())) or "none"
            raise InputError(f"{self.path}: no '{topic}' topic (topics: {have})")

    # -- column readers ------------------------------------------------------------------------------------------
    def _raw(self, topic: str, start_ns: int | None = None, end_ns: int | None = None) -> _Cdr:
        self._need(topic)
        return _Cdr([bytes(d) for _, _, d in self.messages([topic], start_ns, end_ns, raw=True)])

    def header_stamps(self, topic: str) -> np.ndarray:
        """Header stamps of a topic in the order they were written (for diagnosing stamp order)."""
        self._need(topic)
        return _Cdr([bytes(d) for _, _, d in self.messages([topic], raw=True, file_order=True)]).stamp_ns()

    def read_imu(
        self, topic: str = TOPIC_IMU, start_ns: int | None = None, end_ns: int | None = None
    ) -> ImuData:
        c = self._raw(topic, start_ns, end_ns)
        d = c.f64(c.align(c.after_header(), 8), 37)  # quat 4, cov 9, gyro 3, cov 9, acc 3, cov 9
        return ImuData(c.stamp_ns(), d[:, 13:16].copy(), d[:, 25:28].copy())

    def read_ranges(
        self, topic: str = TOPIC_RANGE, start_ns: int | None = None, end_ns: int | None = None
    ) -> RangeData:
        c = self._raw(topic, start_ns, end_ns)
        o = c.align(c.after_header(), 4)
        tag = c.u32(o)
        antenna = c.u8(o + 4)
        anchor = c.u32(c.align(o + 5, 4))
        dist = c.f64(c.align(c.align(o + 5, 4) + 4, 8), 1)[:, 0]
        return RangeData(
            c.stamp_ns(), tag.astype(np.int64), antenna.astype(np.int64), anchor.astype(np.int64), dist
        )

    def read_poses(self, topic: str = TOPIC_GT_POSE) -> PoseData:
        c = self._raw(topic)
        d = c.f64(c.align(c.after_header(), 8), 7)
        return PoseData(c.stamp_ns(), d[:, 0:3].copy(), d[:, 3:7].copy())

    def read_positions(self, topic: str = TOPIC_GT_POSITION) -> PositionData:
        c = self._raw(topic)
        return PositionData(c.stamp_ns(), c.f64(c.align(c.after_header(), 8), 3))

    def read_odometry(self, topic: str = TOPIC_ODOM) -> OdometryData:
        c = self._raw(topic)
        d = c.f64(c.align(c.after_string(c.after_header()), 8), 7 + 36)
        return OdometryData(
            c.stamp_ns(), d[:, 0:3].copy(), d[:, 3:7].copy(), d[:, 7:43].reshape(c.n, 6, 6).copy()
        )

    def iter_features(
        self, topic: str = TOPIC_FEATURES, start_ns: int | None = None, end_ns: int | None = None
    ) -> Iterator[tuple[int, np.ndarray, np.ndarray]]:
        self._need(topic)
        for _, _, m in self.messages([topic], start_ns, end_ns):
            yield _stamp_ns(m.header), np.asarray(m.ids, np.int64), np.stack([m.u, m.v], axis=1).astype(float)

    def iter_images(
        self, topic: str = TOPIC_CAM0, start_ns: int | None = None, end_ns: int | None = None
    ) -> Iterator[tuple[int, np.ndarray]]:
        self._need(topic)
        for _, _, m in self.messages([topic], start_ns, end_ns):
            if m.encoding not in ("mono8", "8UC1"):
                raise InputError(
                    f"{self.path}: {topic} @ {_stamp_ns(m.header)}: encoding {m.encoding!r}, expected mono8"
                )
            img = np.asarray(m.data, np.uint8).reshape(m.height, m.step)[:, : m.width]
            yield _stamp_ns(m.header), img


# ---------------------------------------------------------------------------------------------------------------
# vectorised CDR decoding of the fixed-layout hot types (column readers); rosbags decodes everything else
# ---------------------------------------------------------------------------------------------------------------
class _Cdr:
    """Byte offsets into many little-endian CDR messages at once (alignment is relative to byte 4)."""

    def __init__(self, raws: list[bytes]) -> None:
        lens = np.fromiter((len(r) for r in raws), np.int64, len(raws))
        self.buf = np.frombuffer(b"".join(raws), np.uint8)
        self.start = np.concatenate([[0], np.cumsum(lens)[:-1]]).astype(np.int64)
        if len(raws) and bytes(self.buf[1:2]) != b"\x01":
            raise ValueError("only little-endian CDR is supported")
        self.n = len(raws)

    def _take(self, off: np.ndarray, nbytes: int) -> np.ndarray:
        idx = (self.start + off)[:, None] + np.arange(nbytes)[None, :]
        return self.buf[idx]

    def u32(self, off: np.ndarray) -> np.ndarray:
        return self._take(off, 4).copy().view("<u4").reshape(self.n)

    def u8(self, off: np.ndarray) -> np.ndarray:
        return self._take(off, 1).reshape(self.n)

    def f64(self, off: np.ndarray, k: int) -> np.ndarray:
        return self._take(off, 8 * k).copy().view("<f8").reshape(self.n, k)

    @staticmethod
    def align(off: np.ndarray, a: int) -> np.ndarray:
        return 4 + ((off - 4 + a - 1) // a) * a

    def stamp_ns(self) -> np.ndarray:
        sec = self._take(np.full(self.n, 4), 4).copy().view("<i4").reshape(self.n).astype(np.int64)
        nsec = self.u32(np.full(self.n, 8)).astype(np.int64)
        return sec * 1_000_000_000 + nsec

    def after_string(self, off: np.ndarray) -> np.ndarray:
        """Offset just past a CDR string whose uint32 length is at (4-aligned) ``off``."""
        off = self.align(off, 4)
        return off + 4 + self.u32(off).astype(np.int64)

    def after_header(self) -> np.ndarray:
        return self.after_string(np.full(self.n, 12, dtype=np.int64))


def _parse_meta(d: dict[str, str]) -> dict:
    if "json" in d:
        try:
            return json.loads(d["json"])
        except json.JSONDecodeError:
            return dict(d)
    return dict(d)


def merge_streams(*streams: Iterator[tuple[str, int, Any]]) -> Iterator[tuple[str, int, Any]]:
    """Merge several time-ordered message streams (e.g. a recording and a stage's output) into one."""
    return heapq.merge(*streams, key=lambda m: m[1])


class MergedReader:
    """Several recordings read as one (e.g. a recording plus a stage's output such as the front-end's tracks).

    Topic column readers go to the first recording that has the topic; metadata comes from the first one.
    """

    def __init__(self, *readers: RecordingReader) -> None:
        self.readers = readers
        self.path = readers[0].path
        self.warnings = [w for r in readers for w in r.warnings]

    def topics(self) -> dict[str, TopicInfo]:
        out: dict[str, TopicInfo] = {}
        for r in self.readers:
            for k, v in r.topics().items():
                out.setdefault(k, v)
        return out

    def _owner(self, topic: str) -> RecordingReader:
        for r in self.readers:
            if topic in r.topics():
                return r
        return self.readers[0]

    def messages(self, topics=None, start_ns=None, end_ns=None, *, raw=False, file_order=False):
        topics = list(topics) if topics is not None else None
        streams = []
        for r in self.readers:
            own = [t for t in (topics if topics is not None else r.topics()) if self._owner(t) is r]
            if own:
                streams.append(r.messages(own, start_ns, end_ns, raw=raw, file_order=file_order))
        return merge_streams(*streams)

    def metadata(self, name: str) -> dict | None:
        return self.readers[0].metadata(name)

    calibration = RecordingReader.calibration
    source = RecordingReader.source
    truth = RecordingReader.truth
    time_span = RecordingReader.time_span

    def __getattr__(self, name: str):
        # column readers: read_imu(topic=...), iter_features(topic=...), ... -> the reader owning the topic
        if not (name.startswith("read_") or name.startswith("iter_") or name == "header_stamps"):
            raise AttributeError(name)

        def call(*args, **kwargs):
            fn = getattr(RecordingReader, name)
            import inspect

            topic = args[0] if args else kwargs.get("topic")
            if topic is None:
                topic = inspect.signature(fn).parameters["topic"].default
            return getattr(self._owner(topic), name)(*args, **kwargs)

        return call
