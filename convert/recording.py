"""The normalised recording: one MCAP file, ros2msg schemas, CDR messages, zstd chunks.

`RecordingWriter` is the only writer and `RecordingReader` the only reader of recordings. The hot fixed-layout
types (Imu, UwbRange, PoseStamped, PointStamped, Odometry) are packed and unpacked as numpy columns; the
others go through the rosbags typestore. The reader streams through the MCAP chunk and message indexes (time
order, topic and time-range filters) without loading the file, and recovers what it can from a truncated file
(up to the last intact chunk).
"""

from __future__ import annotations

import heapq
import io
import json
import os
import struct
import zlib
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import zstandard
from mcap.data_stream import ReadDataStream
from mcap.exceptions import McapError
from mcap.reader import make_reader
from mcap.records import Channel as McapChannel
from mcap.records import Metadata as McapMetadata
from mcap.records import Schema as McapSchema

from uwbcal.convert import msgs
from uwbcal.convert.mcap_chunks import PipelinedWriter
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
    op, _n = _REC_HEAD.unpack_from(head, len(MCAP_MAGIC))
    if op != OP_HEADER:
        return False
    pos = len(MCAP_MAGIC) + 9
    (plen,) = _U32.unpack_from(head, pos)
    pos += 4 + plen
    if pos + 4 > len(head):
        return False
    (llen,) = _U32.unpack_from(head, pos)
    return head[pos + 4 : pos + 4 + llen] == b"uwbcal"


def schema_mismatches(topics: dict[str, TopicInfo]) -> dict[str, str]:
    """topic -> problem, for the known topics whose schema is not the one they must carry."""
    return {
        t: f"topic '{t}' carries {info.msgtype}, expected {TOPIC_SCHEMAS[t]}"
        for t, info in topics.items()
        if t in TOPIC_SCHEMAS and info.msgtype != TOPIC_SCHEMAS[t]
    }


MCAP_MAGIC = b"\x89MCAP0\r\n"
_CHUNK_SIZE = 4 * 1024 * 1024
OP_SCHEMA, OP_CHANNEL, OP_MESSAGE, OP_CHUNK, OP_MESSAGE_INDEX = 0x03, 0x04, 0x05, 0x06, 0x07
OP_METADATA, OP_DATA_END, OP_FOOTER, OP_HEADER = 0x0C, 0x0F, 0x02, 0x01
_REC_HEAD = struct.Struct("<BQ")
_U16, _U32, _U64 = struct.Struct("<H"), struct.Struct("<I"), struct.Struct("<Q")


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


class _Broken(Exception):
    """A record of the data section could not be read (truncated or corrupt file)."""


class _Damaged(Exception):
    """One chunk is damaged (CRC mismatch, undecodable): skipped and counted, the rest is read."""


@dataclass
class _Chunk:
    """Where one chunk's messages are. ``index``: channel id -> file offset of its message index record
    (None: no index, walk the records). ``loose``: messages stored outside any chunk, held in memory."""

    seq: int
    start_ns: int
    end_ns: int
    data_offset: int = 0
    compressed_size: int = 0
    uncompressed_size: int = 0
    compression: str = ""
    channels: set[int] | None = None
    index: dict[int, int] | None = None
    loose: _Rows | None = None
    crc: int = 0  # CRC32 of the uncompressed records (0: not stored)


@dataclass
class _Rows:
    """Message rows taken out of decompressed chunk buffers: buffer index, log time, channel, data slice."""

    bufs: list[bytes]
    bi: np.ndarray
    t: np.ndarray
    cid: np.ndarray
    start: np.ndarray
    length: np.ndarray
    pos: np.ndarray | None = None  # position in the file (chunk seq, offset): breaks ties between stamps

    def take(self, idx: np.ndarray) -> _Rows:
        pos = None if self.pos is None else self.pos[idx]
        return _Rows(
            self.bufs, self.bi[idx], self.t[idx], self.cid[idx], self.start[idx], self.length[idx], pos
        )

    @staticmethod
    def concat(rows: list[_Rows]) -> _Rows:
        bufs: list[bytes] = []
        parts = []
        for r in rows:
            pos = r.pos if r.pos is not None else np.full(len(r.t), -1, np.int64)
            parts.append((r.bi + len(bufs), r.t, r.cid, r.start, r.length, pos))
            bufs.extend(r.bufs)
        cols = [np.concatenate(c) for c in zip(*parts, strict=True)] if parts else [np.zeros(0, np.int64)] * 6
        rows_out = _Rows(bufs, *cols)
        used = np.unique(rows_out.bi)  # drop buffers nothing points to any more
        if len(used) < len(bufs):
            remap = np.full(len(bufs), -1, np.int64)
            remap[used] = np.arange(len(used))
            rows_out = _Rows([bufs[i] for i in used], remap[rows_out.bi], *cols[1:])
        return rows_out

    def payloads(self) -> Iterator[memoryview]:
        views = [memoryview(b) for b in self.bufs]
        for b, s, n in zip(self.bi.tolist(), self.start.tolist(), self.length.tolist(), strict=True):
            yield views[b][s : s + n]


def _decompress(raw: bytes, compression: str, size: int) -> bytes:
    if compression == "":
        return raw
    if compression == "zstd":
        return zstandard.ZstdDecompressor().decompress(raw, max_output_size=size)
    if compression == "lz4":
        import lz4.frame  # optional; only for files written by other tools

        return lz4.frame.decompress(raw)
    raise _Broken(f"unknown chunk compression {compression!r}")


def _walk_records(buf: bytes, pos: int = 0) -> Iterator[tuple[int, int, int]]:
    """(opcode, content offset, content length) of consecutive records; stops at a record cut short."""
    end = len(buf)
    while pos + 9 <= end:
        op, n = _REC_HEAD.unpack_from(buf, pos)
        if pos + 9 + n > end:
            raise _Broken(f"record at byte {pos} is cut short")
        yield op, pos + 9, n
        pos += 9 + n
    if pos != end:
        raise _Broken(f"record header at byte {pos} is cut short")


def _message_rows(buf: bytes, cids: set[int] | None) -> tuple[_Rows, list[tuple[int, bytes]]]:
    """Walk a chunk's records (no message index at hand): message rows plus any schema/channel records."""
    bi, t, cid, start, length, others = [], [], [], [], [], []
    for op, off, n in _walk_records(buf):
        if op == OP_MESSAGE:
            c = _U16.unpack_from(buf, off)[0]
            if cids is None or c in cids:
                t.append(_U64.unpack_from(buf, off + 6)[0])
                cid.append(c)
                start.append(off + 22)
                length.append(n - 22)
        elif op in (OP_SCHEMA, OP_CHANNEL):
            others.append((op, buf[off : off + n]))
    bi = np.zeros(len(t), np.int64)
    rows = _Rows(
        [buf],
        bi,
        np.array(t, np.int64),
        np.array(cid, np.int64),
        np.array(start, np.int64),
        np.array(length, np.int64),
    )
    return rows, others


class RecordingReader:
    """Streaming reader of a recording. Raises `InputError` for anything that is not an MCAP recording.

    Reads through the chunk and message indexes (vectorised, no per-message heap); a file without a summary
    (truncated, or killed while being written) is scanned up to the last intact chunk, with a warning.
    """

    def __init__(self, path: str | os.PathLike) -> None:
        self.path = Path(path)
        if not self.path.is_file():
            raise InputError(f"{self.path}: recording not found; check the path")
        self.size = self.path.stat().st_size
        with open(self.path, "rb") as f:
            head = f.read(len(MCAP_MAGIC))
        if head != MCAP_MAGIC:
            raise InputError(
                f"{self.path}: not an MCAP recording (bad magic bytes); convert the data with 'uwbcal convert'"
            )
        self._notes: list[str] = []
        self._damaged: dict[int, str] = {}  # chunk seq -> what is wrong
        self.truncated = False
        self._metadata: dict[str, dict] | None = None
        self._schemas: dict[int, str] = {}  # schema id -> msgtype
        self._channels: dict[int, tuple[str, int]] = {}  # channel id -> (topic, schema id)
        self._chunks: list[_Chunk] = []
        self._counts: dict[int, int] | None = None
        self._topics: dict[str, TopicInfo] | None = None
        summary = None
        try:
            with open(self.path, "rb") as f:
                summary = make_reader(f).get_summary()
        except Exception:  # noqa: BLE001 - any failure to read the summary means: scan the data section
            summary = None
        if summary is not None and (summary.chunk_indexes or not summary.channels):
            self._from_summary(summary)
        else:
            self._scan(damaged=summary is None)

    @property
    def warnings(self) -> list[str]:
        """Data-quality notes: truncation, damaged chunks skipped (one line each)."""
        out = list(self._notes)
        if self._damaged:
            first = next(iter(self._damaged.values()))
            out.append(
                f"{self.path}: {len(self._damaged)} damaged chunk(s) skipped "
                f"(e.g. {first}); their messages are missing — re-create or re-convert the recording"
            )
        return out

    def verify(self) -> list[str]:
        """Check every chunk's CRC (damaged chunks are skipped from then on); returns `warnings`."""
        with open(self.path, "rb") as f:
            for c in self._chunks:
                if c.loose is None and c.seq not in self._damaged:
                    self._chunk_buf(f, c)
        return self.warnings

    # -- opening -------------------------------------------------------------------------------------------------
    def _from_summary(self, s) -> None:
        self._schemas = {k: v.name for k, v in s.schemas.items()}
        self._channels = {k: (v.topic, v.schema_id) for k, v in s.channels.items()}
        if s.statistics is not None:
            self._counts = dict(s.statistics.channel_message_counts)
        f = open(self.path, "rb")  # noqa: SIM115
        for i, ci in enumerate(sorted(s.chunk_indexes, key=lambda c: c.chunk_start_offset)):
            idx = dict(ci.message_index_offsets) or None
            f.seek(ci.chunk_start_offset + 9 + 24)  # opcode, length, start, end, uncompressed size
            crc = f.read(4)
            self._chunks.append(
                _Chunk(
                    seq=i,
                    start_ns=ci.message_start_time,
                    end_ns=ci.message_end_time,
                    data_offset=ci.chunk_start_offset + ci.chunk_length - ci.compressed_size,
                    compressed_size=ci.compressed_size,
                    uncompressed_size=ci.uncompressed_size,
                    compression=ci.compression,
                    channels=set(idx) if idx else None,
                    index=idx,
                    crc=_U32.unpack(crc)[0] if len(crc) == 4 else 0,
                )
            )
        f.close()

    def _scan(self, damaged: bool) -> None:
        """Read the data section record by record: keep every intact chunk. ``damaged``: the summary is
        missing or unreadable (a truncated file, or one whose writer was killed)."""
        meta: dict[str, dict] = {}
        counts: dict[int, int] = {}
        loose: list[tuple[int, int, bytes]] = []
        broken: str | None = None
        pos = len(MCAP_MAGIC)
        finished = False
        with open(self.path, "rb") as f:
            f.seek(pos)
            while not finished:
                head = f.read(9)
                if len(head) == 0:
                    break
                if len(head) < 9:
                    broken = f"record header at byte {pos} is cut short"
                    break
                op, n = _REC_HEAD.unpack(head)
                if op == 0 or op > 0x0F:
                    broken = f"invalid record opcode {op:#x} at byte {pos}"
                    break
                if pos + 9 + n > self.size:
                    broken = f"record at byte {pos} ({n} bytes) runs past the end of the file"
                    break
                content = f.read(n)
                try:
                    if op == OP_CHUNK:
                        try:
                            chunk, n_msgs, others = self._scan_chunk(content, pos + 9, len(self._chunks))
                        except (_Damaged, zstandard.ZstdError) as exc:
                            seq = len(self._chunks) + len(self._damaged) + 1_000_000  # no _Chunk kept
                            self._damaged[seq] = f"chunk at byte {pos}: {exc}"
                            pos += 9 + n
                            continue
                        for sub_op, rec in others:
                            self._add_record(sub_op, rec)
                        if chunk is not None:
                            self._chunks.append(chunk)
                            for c, k in n_msgs.items():
                                counts[c] = counts.get(c, 0) + k
                    elif op in (OP_SCHEMA, OP_CHANNEL):
                        self._add_record(op, content)
                    elif op == OP_MESSAGE:
                        c, t = _U16.unpack_from(content, 0)[0], _U64.unpack_from(content, 6)[0]
                        loose.append((c, t, content[22:]))
                        counts[c] = counts.get(c, 0) + 1
                    elif op == OP_METADATA:
                        m = McapMetadata.read(ReadDataStream(io.BytesIO(content)))
                        meta[m.name] = _parse_meta(m.metadata)
                    elif op in (OP_DATA_END, OP_FOOTER):
                        finished = True
                except (_Broken, zstandard.ZstdError, struct.error, McapError, ValueError) as exc:
                    broken = f"record at byte {pos}: {exc}"
                    break
                pos += 9 + n
        if loose:
            self._chunks.append(self._loose_chunk(loose, len(self._chunks)))
        if not self._channels and not meta:
            raise InputError(
                f"{self.path}: no readable MCAP records ({broken or 'empty data section'}); the file is corrupt"
            )
        self._counts = counts
        self._metadata = meta
        if damaged or not finished or broken:
            self.truncated = True
            total = sum(counts.values())
            lost = (
                "data section complete, only the summary is lost"
                if finished and not broken
                else f"the last {self.size - pos} bytes are unreadable ({broken or 'end of file'})"
            )
            msg = (
                f"{self.path}: truncated recording (no summary/footer): recovered {total} messages from "
                f"{len(self._chunks)} intact chunks; {lost}. Re-create or re-convert it if data are missing"
            )
            self._notes.append(msg)

    def _add_record(self, op: int, content: bytes) -> None:
        stream = ReadDataStream(io.BytesIO(content))
        if op == OP_SCHEMA:
            s = McapSchema.read(stream)
            self._schemas[s.id] = s.name
        else:
            c = McapChannel.read(stream)
            self._channels[c.id] = (c.topic, c.schema_id)

    @staticmethod
    def _scan_chunk(content: bytes, offset: int, seq: int) -> tuple[_Chunk | None, dict[int, int], list]:
        t0, t1, usize, _crc = struct.unpack_from("<QQQI", content, 0)
        (clen,) = _U32.unpack_from(content, 28)
        compression = content[32 : 32 + clen].decode()
        (rlen,) = _U64.unpack_from(content, 32 + clen)
        rstart = 40 + clen
        raw = content[rstart : rstart + rlen]
        if len(raw) != rlen:
            raise _Broken("chunk records cut short")
        try:
            buf = _decompress(raw, compression, usize)
        except zstandard.ZstdError as exc:
            raise _Damaged(f"undecodable ({exc})") from None
        if len(buf) != usize:
            raise _Damaged(f"decompressed to {len(buf)} bytes, expected {usize}")
        if _crc and zlib.crc32(buf) != _crc:
            raise _Damaged("CRC mismatch")
        try:
            rows, others = _message_rows(buf, None)
        except _Broken as exc:
            raise _Damaged(str(exc)) from None
        if len(rows.t) == 0:
            return None, {}, others
        cids, n = np.unique(rows.cid, return_counts=True)
        chunk = _Chunk(
            seq=seq,
            start_ns=int(rows.t.min()),
            end_ns=int(rows.t.max()),
            data_offset=offset + rstart,
            compressed_size=rlen,
            uncompressed_size=usize,
            compression=compression,
            channels=set(cids.tolist()),
            crc=_crc,
        )
        return chunk, dict(zip(cids.tolist(), n.tolist(), strict=True)), others

    @staticmethod
    def _loose_chunk(loose: list[tuple[int, int, bytes]], seq: int) -> _Chunk:
        lens = np.array([len(d) for _, _, d in loose], np.int64)
        t = np.array([t for _, t, _ in loose], np.int64)
        cid = np.array([c for c, _, _ in loose], np.int64)
        rows = _Rows(
            [b"".join(d for _, _, d in loose)],
            np.zeros(len(t), np.int64),
            t,
            cid,
            np.cumsum(lens) - lens,
            lens,
        )
        return _Chunk(
            seq=seq, start_ns=int(t.min()), end_ns=int(t.max()), channels=set(cid.tolist()), loose=rows
        )

    # -- loading chunks ------------------------------------------------------------------------------------------
    def _chunk_buf(self, f, chunk: _Chunk) -> bytes | None:
        """The chunk's decompressed records, or None when it is damaged (then recorded in `warnings`)."""
        if chunk.seq in self._damaged:
            return None
        f.seek(chunk.data_offset)
        raw = f.read(chunk.compressed_size)
        problem = None
        if len(raw) != chunk.compressed_size:
            problem = "cut short"
        else:
            try:
                buf = _decompress(raw, chunk.compression, chunk.uncompressed_size)
            except (zstandard.ZstdError, _Broken, MemoryError) as exc:
                problem = f"undecodable ({exc})"
            else:
                if len(buf) != chunk.uncompressed_size:
                    problem = f"decompressed to {len(buf)} bytes, expected {chunk.uncompressed_size}"
                elif chunk.crc and zlib.crc32(buf) != chunk.crc:
                    problem = "CRC mismatch"
        if problem is not None:
            self._damaged[chunk.seq] = f"chunk at byte {chunk.data_offset}: {problem}"
            return None
        return buf

    def _load(self, f, chunk: _Chunk, cids: set[int] | None) -> _Rows:
        if chunk.loose is not None:
            rows = chunk.loose
            return rows if cids is None else rows.take(np.flatnonzero(np.isin(rows.cid, list(cids))))
        buf = self._chunk_buf(f, chunk)
        if buf is None:
            z = np.zeros(0, np.int64)
            return _Rows([b""], z, z, z, z, z)
        if chunk.index is not None:
            try:
                return self._indexed_rows(f, chunk, buf, cids)
            except (_Broken, struct.error, ValueError, IndexError):
                pass  # a damaged message index: the records themselves are intact (CRC), walk them
        try:
            return _message_rows(buf, cids)[0]
        except _Broken as exc:
            self._damaged[chunk.seq] = f"chunk at byte {chunk.data_offset}: {exc}"
            z = np.zeros(0, np.int64)
            return _Rows([b""], z, z, z, z, z)

    def _indexed_rows(self, f, chunk: _Chunk, buf: bytes, cids: set[int] | None) -> _Rows:
        parts = []
        nb = np.frombuffer(buf, np.uint8)
        for c, off in chunk.index.items():
            if cids is not None and c not in cids:
                continue
            f.seek(off)
            head = f.read(15)
            op, _n, _c, alen = struct.unpack("<BQHI", head)
            if op != OP_MESSAGE_INDEX:
                raise _Broken(f"bad message index at byte {off}")
            ent = np.frombuffer(f.read(alen), "<u8").reshape(-1, 2).astype(np.int64)
            offs = ent[:, 1]
            if len(offs) and (offs.min() < 0 or offs.max() + 9 > len(buf)):
                raise _Broken(f"message index at byte {off} points outside the chunk")
            reclen = nb[(offs + 1)[:, None] + np.arange(8)].copy().view("<u8").reshape(-1).astype(np.int64)
            if len(offs) and ((offs + 9 + reclen).max() > len(buf) or reclen.min() < 22):
                raise _Broken(f"message index at byte {off} disagrees with the chunk's records")
            parts.append((ent[:, 0], np.full(len(ent), c, np.int64), offs + 9 + 22, reclen - 22))
        if not parts:
            z = np.zeros(0, np.int64)
            return _Rows([buf], z, z, z, z, z)
        t, cid, start, length = (np.concatenate(p) for p in zip(*parts, strict=True))
        order = np.argsort(start, kind="stable")  # file order within the chunk
        return _Rows([buf], np.zeros(len(t), np.int64), t[order], cid[order], start[order], length[order])

    def _cids(self, topics: Iterable[str] | str | None) -> set[int] | None:
        if topics is None:
            return None
        if isinstance(topics, str):
            topics = [topics]
        want = set(topics)
        return {cid for cid, (topic, _) in self._channels.items() if topic in want}

    def _blocks(
        self, cids: set[int] | None, start_ns: int | None, end_ns: int | None, file_order: bool = False
    ) -> Iterator[_Rows]:
        """Message rows in time order (stable: file order among equal stamps), a block per loaded chunk."""
        chunks = [
            c
            for c in self._chunks
            if (cids is None or c.channels is None or cids & c.channels)
            and (end_ns is None or c.start_ns < end_ns)
            and (start_ns is None or c.end_ns >= start_ns)
        ]
        if cids is not None and not cids:
            return
        chunks.sort(key=(lambda c: c.seq) if file_order else (lambda c: (c.start_ns, c.seq)))

        def window(rows: _Rows) -> _Rows:
            keep = np.ones(len(rows.t), bool)
            if start_ns is not None:
                keep &= rows.t >= start_ns
            if end_ns is not None:
                keep &= rows.t < end_ns
            return rows if keep.all() else rows.take(np.flatnonzero(keep))

        with open(self.path, "rb") as f:
            if file_order:
                for c in chunks:
                    yield window(self._load(f, c, cids))
                return
            pending: _Rows | None = None
            for i, c in enumerate(chunks):
                rows = window(self._load(f, c, cids))
                rows.pos = c.seq * (1 << 40) + rows.start
                pending = rows if pending is None else _Rows.concat([pending, rows])
                horizon = chunks[i + 1].start_ns if i + 1 < len(chunks) else None
                order = np.lexsort((pending.pos, pending.t))  # equal stamps: in writing order
                if horizon is None:
                    yield pending.take(order)
                    pending = None
                    break
                ready = pending.t[order] < horizon
                k = int(np.count_nonzero(ready))
                if k:
                    yield pending.take(order[:k])
                    pending = _Rows.concat([pending.take(np.sort(order[k:]))])

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

    def _index_stats(self) -> tuple[dict[int, int], dict[int, tuple[int, int]]]:
        """Per channel message count and time span, from the message indexes (or the records, without)."""
        counts: dict[int, int] = {}
        spans: dict[int, tuple[int, int]] = {}

        def add(cid: int, t: np.ndarray) -> None:
            if len(t) == 0:
                return
            counts[cid] = counts.get(cid, 0) + len(t)
            lo, hi = spans.get(cid, (int(t.min()), int(t.max())))
            spans[cid] = (min(lo, int(t.min())), max(hi, int(t.max())))

        with open(self.path, "rb") as f:
            for c in self._chunks:
                if c.index is not None:
                    for cid, off in c.index.items():
                        f.seek(off)
                        _op, _n, _c, alen = struct.unpack("<BQHI", f.read(15))
                        add(cid, np.frombuffer(f.read(alen), "<u8").reshape(-1, 2)[:, 0].astype(np.int64))
                else:
                    rows = self._load(f, c, None)
                    for cid in np.unique(rows.cid).tolist():
                        add(cid, rows.t[rows.cid == cid])
        return counts, spans

    def metadata(self, name: str) -> dict | None:
        if self._metadata is None:
            self._metadata = {}
            try:
                with open(self.path, "rb") as f:
                    for m in make_reader(f).iter_metadata():
                        self._metadata[m.name] = _parse_meta(m.metadata)
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
        c = self._raw(topic, start_ns, end_ns, file_order)
        o = c.align(c.after_header(), 4)
        o_anchor = c.align(o + 5, 4)
        return RangeData(
            c.stamp_ns(),
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
