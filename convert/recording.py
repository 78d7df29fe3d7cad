"""The normalised recording: one MCAP file, ros2msg schemas, CDR messages, zstd chunks.

`RecordingWriter` is the only writer and `RecordingReader` the only reader of recordings. The hot fixed-layout
types (Imu, UwbRange, PoseStamped, PointStamped, Odometry) are packed and unpacked as numpy columns; the
others go through the rosbags typestore. The reader streams through the MCAP chunk and message indexes (time
order, topic and time-range filters) without loading the file, and recovers what it can from a truncated file
(up to the last intact chunk).
"""

from __future__ import annotations

import heapq
import json
import os
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from mcap.reader import make_reader

from uwbcal.convert import msgs
from uwbcal.convert.mcap_chunks import PipelinedWriter
from uwbcal.convert.mcap_index import (
    MCAP_MAGIC,
    OP_HEADER,
    REC_HEAD,
    U32,
    McapIndex,
    parse_meta,
)
from uwbcal.pipeline.core.atomic import discard, finish, prepare_output_file, temp_path
from uwbcal.pipeline.core.errors import InputError
from uwbcal.pipeline.core.topics import (  # noqa: F401  (re-exported: the recording format names its topics)
    TOPIC_CAM0,
    TOPIC_CAM1,
    TOPIC_FEATURES,
    TOPIC_GT_IMU_BIAS,
    TOPIC_GT_POSE,
    TOPIC_GT_POSITION,
    TOPIC_IMU,
    TOPIC_ODOM,
    TOPIC_RANGE,
    TOPIC_VIO,
)

META_CALIBRATION = "uwbcal.calibration"
META_SOURCE = "uwbcal.source"
META_TRUTH = "uwbcal.truth"
META_TOPICS = "uwbcal.topics"  # per-topic time spans, written by RecordingWriter (saves a scan)

# What each topic must carry (checked by `info`, before any stage, and by every column reader).
TOPIC_SCHEMAS = {
    TOPIC_IMU: msgs.IMU,
    TOPIC_CAM0: msgs.IMAGE,
    TOPIC_CAM1: msgs.IMAGE,
    TOPIC_FEATURES: msgs.FEATURE_TRACKS,
    TOPIC_RANGE: msgs.UWB_RANGE,
    TOPIC_GT_POSE: msgs.POSE_STAMPED,
    TOPIC_GT_POSITION: msgs.POINT_STAMPED,
    TOPIC_GT_IMU_BIAS: msgs.IMU,
    TOPIC_ODOM: msgs.ODOMETRY,
    TOPIC_VIO: msgs.ODOMETRY,
}


def written_by_uwbcal(path: str | os.PathLike) -> bool:
    """The MCAP header names uwbcal as the writing library (it survives truncation, unlike the metadata)."""
    try:
        with open(path, "rb") as f:
            head = f.read(len(MCAP_MAGIC) + 9 + 4 + 64)
    except OSError:
        return False
    if not head.startswith(MCAP_MAGIC) or len(head) < len(MCAP_MAGIC) + 13:
        return False
    op, _n = REC_HEAD.unpack_from(head, len(MCAP_MAGIC))
    if op != OP_HEADER:
        return False
    pos = len(MCAP_MAGIC) + 9
    (plen,) = U32.unpack_from(head, pos)
    pos += 4 + plen
    if pos + 4 > len(head):
        return False
    (llen,) = U32.unpack_from(head, pos)
    return head[pos + 4 : pos + 4 + llen] == b"uwbcal"


def schema_mismatches(topics: dict[str, TopicInfo]) -> dict[str, str]:
    """topic -> problem, for the known topics whose schema is not the one they must carry."""
    return {
        t: f"topic '{t}' carries {info.msgtype}, expected {TOPIC_SCHEMAS[t]}"
        for t, info in topics.items()
        if t in TOPIC_SCHEMAS and info.msgtype != TOPIC_SCHEMAS[t]
    }


_CHUNK_SIZE = 4 * 1024 * 1024


def _stamp_ns(header) -> int:
    return int(header.stamp.sec) * 1_000_000_000 + int(header.stamp.nanosec)


def _col(x, n: int, dtype, width: int | None = None, what: str = "") -> np.ndarray:
    a = np.asarray(x, dtype)
    shape = (n,) if width is None else (n, width)
    if a.shape != shape:
        try:
            a = np.broadcast_to(a, shape)
        except ValueError:
            raise ValueError(f"{what}: expected shape {shape}, got {a.shape}") from None
    return a


# ---------------------------------------------------------------------------------------------------------------
# writer
# ---------------------------------------------------------------------------------------------------------------
class RecordingWriter:
    """Writes a recording atomically: to a temporary sibling that replaces ``path`` on a clean close.

    Messages may be written in any order across topics (e.g. one batch per topic); readers iterate in time
    order through the index. log_time = publish_time = header.stamp = ``t_ns``.
    """

    def __init__(self, path: str | os.PathLike, *, chunk_size: int = _CHUNK_SIZE) -> None:
        self.path = prepare_output_file(path)
        self._tmp = temp_path(self.path)
        self._file = open(self._tmp, "xb")  # noqa: SIM115 (closed in close/abort)
        self._writer = PipelinedWriter(self._file, chunk_size=chunk_size)
        self._writer.start(profile="ros2", library="uwbcal")
        self._schemas: dict[str, int] = {}
        self._channels: dict[str, tuple[int, str]] = {}
        self._seq: dict[str, int] = {}
        self._metadata: dict[str, dict] = {}
        self._closed = False
        self.counts: dict[str, int] = {}
        self._spans: dict[str, list[int]] = {}

    # -- low level -----------------------------------------------------------------------------------------------
    def _channel(self, topic: str, msgtype: str) -> int:
        known = self._channels.get(topic)
        if known is not None:
            if known[1] != msgtype:
                raise ValueError(f"{topic}: already written as {known[1]}, not {msgtype}")
            return known[0]
        sid = self._schemas.get(msgtype)
        if sid is None:
            sid = self._writer.register_schema(msgtype, "ros2msg", msgs.schema_text(msgtype).encode())
            self._schemas[msgtype] = sid
        cid = self._writer.register_channel(topic, "cdr", sid)
        self._channels[topic] = (cid, msgtype)
        self._seq[topic] = 0
        return cid

    def _span(self, topic: str, lo: int, hi: int, n: int) -> None:
        self.counts[topic] = self.counts.get(topic, 0) + n
        span = self._spans.get(topic)
        if span is None:
            self._spans[topic] = [lo, hi]
        else:
            span[0] = min(span[0], lo)
            span[1] = max(span[1], hi)

    def write_raw(self, topic: str, t_ns: int, msgtype: str, cdr: bytes | memoryview | tuple) -> None:
        """Write an already CDR-encoded message (fast pass-through for converters); ``cdr`` may be a tuple of
        byte buffers, the message in pieces (e.g. an image's head and a view of its pixels)."""
        cid = self._channel(topic, msgtype)
        seq = self._seq[topic]
        self._seq[topic] = seq + 1
        t_ns = int(t_ns)
        # the buffers as they are: the chunk builder copies them in (no bytes() copy of every image first)
        self._writer.add_message(cid, log_time=t_ns, data=cdr, publish_time=t_ns, sequence=seq)
        self._span(topic, t_ns, t_ns, 1)

    def _write_rows(self, topic: str, msgtype: str, t_ns: np.ndarray, rows: np.ndarray | list[bytes]) -> None:
        """Write packed messages (``[N, size]`` uint8 rows, or a list of payloads) in the given order."""
        if len(t_ns) == 0:
            return
        cid = self._channel(topic, msgtype)
        seq = self._seq[topic]
        add = self._writer.add_message
        for i, t in enumerate(t_ns.tolist()):
            data = rows[i] if isinstance(rows, list) else rows[i].tobytes()
            add(cid, log_time=t, data=data, publish_time=t, sequence=seq + i)
        self._seq[topic] = seq + len(t_ns)
        self._span(topic, int(t_ns.min()), int(t_ns.max()), len(t_ns))

    def write(self, topic: str, t_ns: int, msg: Any) -> None:
        """Write a rosbags message object (any type registered in `msgs.typestore()`)."""
        ts = msgs.typestore()
        self.write_raw(topic, t_ns, msg.__msgtype__, ts.serialize_cdr(msg, msg.__msgtype__))

    # -- typed helpers -------------------------------------------------------------------------------------------
    def write_imu(self, t_ns: int, gyro, acc, topic: str = TOPIC_IMU, frame_id: str = "imu") -> None:
        t_ns = int(t_ns)
        sec, nsec = divmod(t_ns, 1_000_000_000)
        f = (*msgs.IMU_ORIENTATION, *map(float, gyro), *(0.0,) * 9, *map(float, acc), *(0.0,) * 9)
        self.write_raw(topic, t_ns, msgs.IMU, msgs.imu_layout(frame_id).pack_one(sec=sec, nsec=nsec, f=f))

    def write_imu_batch(self, t_ns, gyro, acc, topic: str = TOPIC_IMU, frame_id: str = "imu") -> None:
        t = np.asarray(t_ns, np.int64).reshape(-1)
        n = len(t)
        f = msgs.imu_block(_col(gyro, n, float, 3, "gyro"), _col(acc, n, float, 3, "acc"))
        sec, nsec = msgs.sec_nsec(t)
        self._write_rows(topic, msgs.IMU, t, msgs.imu_layout(frame_id).pack_many(n, sec=sec, nsec=nsec, f=f))

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
                header=_header_msg(t_ns, frame_id),
                height=h,
                width=w,
                encoding="mono8",
                is_bigendian=0,
                step=w,
                data=img.reshape(-1),
            ),
        )

    def write_features(self, t_ns: int, ids, uv, topic: str = TOPIC_FEATURES, frame_id: str = "cam0") -> None:
        """One frame of feature tracks: ids [N] and raw (distorted) pixel coordinates uv [N,2]."""
        _, T = _types()
        uv = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
        ids = np.asarray(ids, dtype=np.uint32).reshape(-1)
        if len(ids) != len(uv):
            raise ValueError(f"{topic}: {len(ids)} ids but {len(uv)} pixel coordinates")
        self.write(
            topic,
            t_ns,
            T[msgs.FEATURE_TRACKS](
                header=_header_msg(t_ns, frame_id),
                ids=ids,
                u=np.ascontiguousarray(uv[:, 0]),
                v=np.ascontiguousarray(uv[:, 1]),
            ),
        )

    def write_range(
        self, t_ns: int, tag: int, antenna: int, anchor: int, distance: float, topic: str = TOPIC_RANGE
    ) -> None:
        t_ns = int(t_ns)
        sec, nsec = divmod(t_ns, 1_000_000_000)
        data = msgs.range_layout(f"tag{int(tag)}").pack_one(
            sec=sec, nsec=nsec, tag=int(tag), antenna=int(antenna), anchor=int(anchor), d=float(distance)
        )
        self.write_raw(topic, t_ns, msgs.UWB_RANGE, data)

    def write_range_batch(self, t_ns, tag, antenna, anchor, distance, topic: str = TOPIC_RANGE) -> None:
        """Ranges as columns; ``tag``, ``antenna``, ``anchor`` may be scalars."""
        t = np.asarray(t_ns, np.int64).reshape(-1)
        n = len(t)
        tag = _col(tag, n, np.int64, what="tag")
        antenna = _col(antenna, n, np.int64, what="antenna")
        anchor = _col(anchor, n, np.int64, what="anchor")
        dist = _col(distance, n, float, what="distance")
        for name, v, hi in (
            ("tag", tag, 2**32 - 1),
            ("antenna", antenna, 255),
            ("anchor", anchor, 2**32 - 1),
        ):
            if n and (
                v.min() < 0 or v.max() > hi
            ):  # the message fields are uint32/uint8: never wrap silently
                raise ValueError(f"{topic}: {name} id {int(v[(v < 0) | (v > hi)][0])} outside 0..{hi}")
        tags = np.unique(tag).tolist()
        sec, nsec = msgs.sec_nsec(t)
        payloads: list[bytes] = [b""] * n
        for tg in tags:  # the frame id names the tag: one layout per tag; rows keep their order
            idx = np.flatnonzero(tag == tg)
            rows = msgs.range_layout(f"tag{tg}").pack_many(
                len(idx),
                sec=sec[idx],
                nsec=nsec[idx],
                tag=tg,
                antenna=antenna[idx],
                anchor=anchor[idx],
                d=dist[idx],
            )
            if len(tags) == 1:
                self._write_rows(topic, msgs.UWB_RANGE, t, rows)
                return
            for i, row in zip(idx.tolist(), rows, strict=True):
                payloads[i] = row.tobytes()
        self._write_rows(topic, msgs.UWB_RANGE, t, payloads)

    def write_pose(self, t_ns: int, p, q_xyzw, topic: str = TOPIC_GT_POSE, frame_id: str = "world") -> None:
        t_ns = int(t_ns)
        sec, nsec = divmod(t_ns, 1_000_000_000)
        f = (*map(float, p), *map(float, q_xyzw))
        self.write_raw(
            topic, t_ns, msgs.POSE_STAMPED, msgs.pose_layout(frame_id).pack_one(sec=sec, nsec=nsec, f=f)
        )

    def write_pose_batch(self, t_ns, p, q_xyzw, topic: str = TOPIC_GT_POSE, frame_id: str = "world") -> None:
        t = np.asarray(t_ns, np.int64).reshape(-1)
        n = len(t)
        f = np.concatenate([_col(p, n, float, 3, "p"), _col(q_xyzw, n, float, 4, "q_xyzw")], axis=1)
        sec, nsec = msgs.sec_nsec(t)
        self._write_rows(
            topic, msgs.POSE_STAMPED, t, msgs.pose_layout(frame_id).pack_many(n, sec=sec, nsec=nsec, f=f)
        )

    def write_position(self, t_ns: int, p, topic: str = TOPIC_GT_POSITION, frame_id: str = "world") -> None:
        t_ns = int(t_ns)
        sec, nsec = divmod(t_ns, 1_000_000_000)
        data = msgs.point_layout(frame_id).pack_one(sec=sec, nsec=nsec, f=tuple(map(float, p)))
        self.write_raw(topic, t_ns, msgs.POINT_STAMPED, data)

    def write_position_batch(self, t_ns, p, topic: str = TOPIC_GT_POSITION, frame_id: str = "world") -> None:
        t = np.asarray(t_ns, np.int64).reshape(-1)
        n = len(t)
        sec, nsec = msgs.sec_nsec(t)
        rows = msgs.point_layout(frame_id).pack_many(n, sec=sec, nsec=nsec, f=_col(p, n, float, 3, "p"))
        self._write_rows(topic, msgs.POINT_STAMPED, t, rows)

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
        """Odometry with a 6x6 pose covariance in ROS order (x, y, z, rx, ry, rz); twist optional."""
        self.write_odometry_batch(
            [t_ns],
            np.reshape(p, (1, 3)),
            np.reshape(q_xyzw, (1, 4)),
            cov6,
            topic,
            v=None if v is None else np.reshape(v, (1, 3)),
            w=None if w is None else np.reshape(w, (1, 3)),
            frame_id=frame_id,
            child_frame_id=child_frame_id,
        )

    def write_odometry_batch(
        self,
        t_ns,
        p,
        q_xyzw,
        cov6=None,
        topic: str = TOPIC_ODOM,
        v=None,
        w=None,
        frame_id: str = "world",
        child_frame_id: str = "body",
    ) -> None:
        """Odometry columns; ``cov6`` is one 6x6 for all or ``[N,6,6]``; ``v``, ``w`` twist ``[N,3]``."""
        t = np.asarray(t_ns, np.int64).reshape(-1)
        n = len(t)
        f = np.zeros((n, 85))
        f[:, 0:3] = _col(p, n, float, 3, "p")
        f[:, 3:7] = _col(q_xyzw, n, float, 4, "q_xyzw")
        if cov6 is not None:
            f[:, 7:43] = np.broadcast_to(np.asarray(cov6, float), (n, 6, 6)).reshape(n, 36)
        if v is not None:
            f[:, 43:46] = _col(v, n, float, 3, "v")
        if w is not None:
            f[:, 46:49] = _col(w, n, float, 3, "w")
        sec, nsec = msgs.sec_nsec(t)
        rows = msgs.odom_layout(frame_id, child_frame_id).pack_many(n, sec=sec, nsec=nsec, f=f)
        self._write_rows(topic, msgs.ODOMETRY, t, rows)

    def set_metadata(self, name: str, data: dict) -> None:
        """Store ``data`` as the MCAP metadata record ``name`` (``{"json": ...}``); the last call wins."""
        json.dumps(data, default=json_default)  # fail here, not at close
        self._metadata[name] = data

    # -- lifecycle -----------------------------------------------------------------------------------------------
    def close(self) -> None:
        if self._closed:
            return
        try:
            self._metadata[META_TOPICS] = {
                k: {"start_ns": v[0], "end_ns": v[1]} for k, v in self._spans.items()
            }
            for name, data in self._metadata.items():
                self._writer.add_metadata(name, {"json": json.dumps(data, default=json_default)})
            self._writer.finish()
            self._file.close()
        except BaseException:
            self.abort()
            raise
        self._closed = True
        try:
            finish(self._tmp, self.path)
        except BaseException:
            discard(self._tmp)
            raise

    def abort(self) -> None:
        """Drop the temporary file; ``path`` is left as it was."""
        if self._closed:
            return
        self._closed = True
        try:
            self._writer.abort()
            self._file.close()
        finally:
            discard(self._tmp)

    def __enter__(self) -> RecordingWriter:
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is None:
            self.close()
        else:
            self.abort()


def _types():
    ts = msgs.typestore()
    return ts, ts.types


def _header_msg(t_ns: int, frame_id: str):
    _, T = _types()
    sec, nsec = divmod(int(t_ns), 1_000_000_000)
    return T["std_msgs/msg/Header"](
        stamp=T["builtin_interfaces/msg/Time"](sec=sec, nanosec=nsec), frame_id=frame_id
    )


def json_default(o: Any) -> Any:
    """``json.dumps(default=...)`` for numpy arrays/scalars and paths (metadata, run-directory JSON)."""
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

    def __len__(self) -> int:
        return len(self.t_ns)


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

    def __len__(self) -> int:
        return len(self.t_ns)


@dataclass
class PositionData:
    t_ns: np.ndarray
    p: np.ndarray

    def __len__(self) -> int:
        return len(self.t_ns)


@dataclass
class OdometryData:
    t_ns: np.ndarray
    p: np.ndarray
    q_xyzw: np.ndarray
    cov: np.ndarray

    def __len__(self) -> int:
        return len(self.t_ns)


class RecordingReader(McapIndex):
    """Streaming reader of a recording: uwbcal's topics, metadata and typed columns over the file's chunk index
    (`McapIndex`). Raises `InputError` for anything that is not an MCAP recording."""

    def __init__(self, path: str | os.PathLike) -> None:
        super().__init__(path)
        self._topics: dict[str, TopicInfo] | None = None
        self.range_shift_ns = (
            0  # added to every range stamp read (a range-to-pose clock offset the run estimated)
        )

    # -- summary and metadata ------------------------------------------------------------------------------------
    def topics(self) -> dict[str, TopicInfo]:
        """topic -> TopicInfo(msgtype, count, start_ns, end_ns)."""
        if self._topics is not None:
            return dict(self._topics)
        known = {} if self.truncated else (self.metadata(META_TOPICS) or {})
        counts = self._counts
        if counts is None or any(ch[0] not in known for ch in self._channels.values()):
            counts, spans = self._index_stats()
        else:
            spans = {}
        out: dict[str, TopicInfo] = {}
        for cid, (topic, sid) in sorted(self._channels.items()):
            n = counts.get(cid, 0)
            if topic in known:
                start, end = int(known[topic]["start_ns"]), int(known[topic]["end_ns"])
            elif cid in spans:
                start, end = spans[cid]
            else:
                continue  # a channel without messages
            if n == 0:
                continue
            prev = out.get(topic)
            if prev is not None:  # several channels with one topic
                n, start, end = n + prev.count, min(start, prev.start_ns), max(end, prev.end_ns)
            out[topic] = TopicInfo(topic, self._schemas.get(sid, "?"), n, start, end)
        self._topics = out
        return dict(out)

    def metadata(self, name: str) -> dict | None:
        if self._metadata is None:
            self._metadata = {}
            try:
                with open(self.path, "rb") as f:
                    for m in make_reader(f).iter_metadata():
                        self._metadata[m.name] = parse_meta(m.metadata)
            except Exception as exc:  # noqa: BLE001
                raise InputError(f"{self.path}: unreadable metadata ({exc}); the file is corrupt") from None
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
        """Yield ``(topic, t_ns, msg)`` in time order (``end_ns`` exclusive), msg decoded by rosbags.
        ``raw`` yields the CDR bytes instead; ``file_order`` yields in the order of writing."""
        ts = msgs.typestore()
        names = {cid: (topic, self._schemas.get(sid, "?")) for cid, (topic, sid) in self._channels.items()}
        for rows in self._blocks(self._cids(topics), start_ns, end_ns, file_order):
            for c, t, data in zip(rows.cid.tolist(), rows.t.tolist(), rows.payloads(), strict=True):
                topic, typ = names[c]
                payload = bytes(data)
                yield topic, t, (payload if raw else ts.deserialize_cdr(payload, typ))

    def _need(self, topic: str) -> None:
        if topic not in self.topics():
            have = ", ".join(sorted(self.topics())) or "none"
            raise InputError(f"{self.path}: no '{topic}' topic (topics: {have})")
        self.check_schemas([topic])

    def check_schemas(self, topics: Iterable[str] | None = None) -> None:
        """Refuse a known topic carrying the wrong message type (InputError naming the file and topic)."""
        have = self.topics()
        bad = schema_mismatches({t: have[t] for t in (have if topics is None else topics) if t in have})
        if bad:
            raise InputError(
                f"{self.path}: {next(iter(bad.values()))}; the recording was not written by 'uwbcal convert' "
                "for this topic — re-convert it"
            )

    # -- column readers ------------------------------------------------------------------------------------------
    # Rows are in time order; ``file_order=True`` gives them in the order they were written (diagnostics).
    def _raw(
        self,
        topic: str,
        start_ns: int | None = None,
        end_ns: int | None = None,
        file_order: bool = False,
        prefix: int | None = None,
    ) -> msgs.CdrColumns:
        """The CDR payloads of one topic as columns; ``prefix`` keeps only the first bytes of each."""
        self._need(topic)
        blocks = list(self._blocks(self._cids(topic), start_ns, end_ns, file_order))
        lengths = np.concatenate([b.length for b in blocks]) if blocks else np.zeros(0, np.int64)
        if prefix is not None:
            lengths = np.minimum(lengths, prefix)
            data = b"".join(d[:prefix] for b in blocks for d in b.payloads())
        else:
            data = b"".join(d for b in blocks for d in b.payloads())
        return msgs.CdrColumns(data, lengths, f"{self.path}: {topic}")

    def header_stamps(self, topic: str) -> np.ndarray:
        """Header stamps of a topic in the order they were written (to diagnose stamp order)."""
        return self._raw(topic, file_order=True, prefix=12).stamp_ns()

    def read_imu(
        self,
        topic: str = TOPIC_IMU,
        start_ns: int | None = None,
        end_ns: int | None = None,
        *,
        file_order: bool = False,
    ) -> ImuData:
        c = self._raw(topic, start_ns, end_ns, file_order)
        d = c.f64(c.align(c.after_header(), 8), 37)  # quat 4, cov 9, gyro 3, cov 9, acc 3, cov 9
        return ImuData(c.stamp_ns(), d[:, 13:16].copy(), d[:, 25:28].copy())

    def read_ranges(
        self,
        topic: str = TOPIC_RANGE,
        start_ns: int | None = None,
        end_ns: int | None = None,
        *,
        file_order: bool = False,
    ) -> RangeData:
        """The ranges, stamps shifted by ``range_shift_ns`` (``start_ns``/``end_ns`` on the shifted stamps)."""
        sh = self.range_shift_ns
        c = self._raw(
            topic,
            None if start_ns is None else start_ns - sh,
            None if end_ns is None else end_ns - sh,
            file_order,
        )
        o = c.align(c.after_header(), 4)
        o_anchor = c.align(o + 5, 4)
        return RangeData(
            c.stamp_ns() + sh,
            c.u32(o).astype(np.int64),
            c.u8(o + 4).astype(np.int64),
            c.u32(o_anchor).astype(np.int64),
            c.f64(c.align(o_anchor + 4, 8), 1)[:, 0],
        )

    def read_poses(
        self,
        topic: str = TOPIC_GT_POSE,
        start_ns: int | None = None,
        end_ns: int | None = None,
        *,
        file_order: bool = False,
    ) -> PoseData:
        c = self._raw(topic, start_ns, end_ns, file_order)
        d = c.f64(c.align(c.after_header(), 8), 7)
        return PoseData(c.stamp_ns(), d[:, 0:3].copy(), d[:, 3:7].copy())

    def read_positions(
        self,
        topic: str = TOPIC_GT_POSITION,
        start_ns: int | None = None,
        end_ns: int | None = None,
        *,
        file_order: bool = False,
    ) -> PositionData:
        c = self._raw(topic, start_ns, end_ns, file_order)
        return PositionData(c.stamp_ns(), c.f64(c.align(c.after_header(), 8), 3))

    def read_odometry(
        self,
        topic: str = TOPIC_ODOM,
        start_ns: int | None = None,
        end_ns: int | None = None,
        *,
        file_order: bool = False,
    ) -> OdometryData:
        c = self._raw(topic, start_ns, end_ns, file_order)
        d = c.f64(c.align(c.after_string(c.after_header()), 8), 7 + 36)
        return OdometryData(
            c.stamp_ns(), d[:, 0:3].copy(), d[:, 3:7].copy(), d[:, 7:43].reshape(c.n, 6, 6).copy()
        )

    def iter_features(
        self, topic: str = TOPIC_FEATURES, start_ns: int | None = None, end_ns: int | None = None
    ) -> Iterator[tuple[int, np.ndarray, np.ndarray]]:
        """(t_ns, track ids int64 [N], raw distorted pixel coordinates uv [N,2]) per frame."""
        self._need(topic)
        for _, _, m in self.messages([topic], start_ns, end_ns):
            uv = np.stack([np.asarray(m.u, float), np.asarray(m.v, float)], axis=1)
            yield _stamp_ns(m.header), np.asarray(m.ids, np.int64), uv

    def iter_images(
        self, topic: str = TOPIC_CAM0, start_ns: int | None = None, end_ns: int | None = None
    ) -> Iterator[tuple[int, np.ndarray]]:
        """(t_ns, mono8 image [H,W] uint8) per frame."""
        self._need(topic)
        for _, _, m in self.messages([topic], start_ns, end_ns):
            if m.encoding not in ("mono8", "8UC1"):
                raise InputError(
                    f"{self.path}: {topic} @ {_stamp_ns(m.header)}: encoding {m.encoding!r}, expected mono8"
                )
            img = np.asarray(m.data, np.uint8).reshape(m.height, m.step)[:, : m.width]
            yield _stamp_ns(m.header), img


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

    @property
    def warnings(self) -> list[str]:
        return [w for r in self.readers for w in r.warnings]

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
