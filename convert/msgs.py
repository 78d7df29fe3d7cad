"""Message types of the normalised recording: standard ROS 2 types plus two uwbcal_msgs types.

`typestore()` has every type (rosbags, for any message); `schema_text` gives the ros2msg schema for MCAP.
The hot fixed-layout types (Imu, UwbRange, PoseStamped, PointStamped, Odometry) also have explicit
little-endian CDR layouts: `Layout` packs one message with `struct` or many with numpy, and `CdrColumns`
decodes columns of many messages at once; the round-trip and independent-decoder tests keep both honest.
"""

from __future__ import annotations

import struct
from functools import cache
from typing import Any

import numpy as np
from rosbags.typesys import Stores, get_types_from_msg, get_typestore
from rosbags.typesys.store import Typestore

from uwbcal.pipeline.core.errors import InputError

UWB_RANGE = "uwbcal_msgs/msg/UwbRange"
FEATURE_TRACKS = "uwbcal_msgs/msg/FeatureTracks"
IMU = "sensor_msgs/msg/Imu"
IMAGE = "sensor_msgs/msg/Image"
POSE_STAMPED = "geometry_msgs/msg/PoseStamped"
POINT_STAMPED = "geometry_msgs/msg/PointStamped"
ODOMETRY = "nav_msgs/msg/Odometry"

UWB_RANGE_MSG = """\
# One UWB two-way range between a tag antenna on the robot and a fixed anchor.
std_msgs/Header header
uint32 tag_id
uint8 antenna
uint32 anchor_id
float64 distance
"""

FEATURE_TRACKS_MSG = """\
# Feature tracks of one camera frame: persistent track ids and raw (distorted) pixel coordinates.
std_msgs/Header header
uint32[] ids
float64[] u
float64[] v
"""


@cache
def typestore() -> Typestore:
    store = get_typestore(Stores.ROS2_HUMBLE)
    types = {}
    types.update(get_types_from_msg(UWB_RANGE_MSG, UWB_RANGE))
    types.update(get_types_from_msg(FEATURE_TRACKS_MSG, FEATURE_TRACKS))
    store.register(types)
    return store


@cache
def schema_text(msgtype: str) -> str:
    """The ros2msg schema (main definition followed by every dependency) for MCAP."""
    text, _ = typestore().generate_msgdef(msgtype, ros_version=2)
    # dependencies named as the fields name them ("std_msgs/Header header" ... "MSG: std_msgs/Header"), as
    # rosbag2's MCAP storage writes them: rerun's MCAP importer resolves a field only against that exact name
    # (with "MSG: std_msgs/msg/Header" it keeps the channel as raw bytes); Foxglove and mcap_ros2 read both.
    return text


_CDR_LE = b"\x00\x01\x00\x00"  # CDR encapsulation header, little endian


_KINDS = {"i4": ("<i4", "i", 4), "u4": ("<u4", "I", 4), "u1": ("u1", "B", 1), "f8": ("<f8", "d", 8)}


class Layout:
    """Little-endian CDR layout of a message whose only strings are constants.

    ``fields``: ``(name, kind, count)`` with kind in i4/u4/u1/f8, or ``(name, "str", text)`` for a constant
    string. Packs one message with `struct` or many at once into an ``[N, size]`` uint8 array with numpy.
    """

    def __init__(self, fields: list[tuple[str, str, Any]]) -> None:
        names, formats, offsets = ["enc"], ["S4"], [0]
        fmt = ["<4s"]
        self.consts: dict[str, Any] = {"enc": _CDR_LE}
        self.slots: list[tuple[str, int]] = []  # struct argument slots: (name, count); count 0 = constant
        self.slots.append(("enc", 0))
        off = 4
        for name, kind, arg in fields:
            if kind == "str":
                text = arg.encode() + b"\x00"
                off = self._pad(off, 4, fmt)
                names += [name + "_len", name]
                formats += ["<u4", f"S{len(text)}"]
                offsets += [off, off + 4]
                fmt += ["I", f"{len(text)}s"]
                self.consts[name + "_len"] = len(text)
                self.consts[name] = text
                self.slots += [(name + "_len", 0), (name, 0)]
                off += 4 + len(text)
                continue
            npt, st, size = _KINDS[kind]
            off = self._pad(off, size, fmt)
            names.append(name)
            formats.append(np.dtype((npt, (arg,))) if arg > 1 else np.dtype(npt))
            offsets.append(off)
            fmt.append(f"{arg}{st}")
            self.slots.append((name, arg))
            off += size * arg
        self.size = off
        self.dtype = np.dtype({"names": names, "formats": formats, "offsets": offsets, "itemsize": off})
        self.struct = struct.Struct("".join(fmt))

    @staticmethod
    def _pad(off: int, align: int, fmt: list[str]) -> int:
        pad = (-(off - 4)) % align
        if pad:
            fmt.append(f"{pad}x")
        return off + pad

    def pack_one(self, **values: Any) -> bytes:
        args: list[Any] = []
        for name, count in self.slots:
            if count == 0:
                args.append(self.consts[name])
            elif count == 1:
                args.append(values[name])
            else:
                args.extend(values[name])
        return self.struct.pack(*args)

    def pack_many(self, n: int, **values: Any) -> np.ndarray:
        arr = np.zeros(n, self.dtype)
        for name, v in self.consts.items():
            arr[name] = v
        for name, count in self.slots:
            if count:
                arr[name] = values[name]
        return arr.view(np.uint8).reshape(n, self.size)


def _header_fields(frame_id: str) -> list[tuple[str, str, Any]]:
    return [("sec", "i4", 1), ("nsec", "u4", 1), ("frame", "str", frame_id)]


@cache
def imu_layout(frame_id: str) -> Layout:
    return Layout([*_header_fields(frame_id), ("f", "f8", 37)])  # quat 4, cov 9, gyro 3, cov 9, acc 3, cov 9


@cache
def range_layout(frame_id: str) -> Layout:
    return Layout(
        [
            *_header_fields(frame_id),
            ("tag", "u4", 1),
            ("antenna", "u1", 1),
            ("anchor", "u4", 1),
            ("d", "f8", 1),
        ]
    )


@cache
def pose_layout(frame_id: str) -> Layout:
    return Layout([*_header_fields(frame_id), ("f", "f8", 7)])


@cache
def point_layout(frame_id: str) -> Layout:
    return Layout([*_header_fields(frame_id), ("f", "f8", 3)])


@cache
def odom_layout(frame_id: str, child_frame_id: str) -> Layout:
    # pose 7, pose covariance 36, twist 6, twist covariance 36
    return Layout([*_header_fields(frame_id), ("child", "str", child_frame_id), ("f", "f8", 85)])


def sec_nsec(t_ns) -> tuple[np.ndarray, np.ndarray]:
    t = np.asarray(t_ns, np.int64)
    return t // 1_000_000_000, t % 1_000_000_000


IMU_ORIENTATION = (0.0, 0.0, 0.0, 1.0, -1.0) + (0.0,) * 8  # orientation unknown: covariance[0] = -1 (REP 145)


def imu_block(gyro: np.ndarray, acc: np.ndarray) -> np.ndarray:
    n = len(gyro)
    f = np.zeros((n, 37))
    f[:, 0:13] = IMU_ORIENTATION
    f[:, 13:16] = gyro
    f[:, 25:28] = acc
    return f


# ---------------------------------------------------------------------------------------------------------------
# vectorised CDR decoding of the fixed-layout types (column readers)
# ---------------------------------------------------------------------------------------------------------------
class CdrColumns:
    """Byte offsets into many little-endian CDR messages at once (alignment is relative to byte 4)."""

    def __init__(self, data: bytes, lengths: np.ndarray, where: str) -> None:
        self.buf = np.frombuffer(data, np.uint8)
        self.n = len(lengths)
        self.lengths = np.asarray(lengths, np.int64)
        self.start = np.cumsum(self.lengths) - self.lengths
        self._where = where
        # all messages of one length (one frame id): a regular [N, L] array, sliced without fancy indexing
        same = self.n > 0 and bool(np.all(self.lengths == self.lengths[0]))
        self._grid = self.buf.reshape(self.n, int(self.lengths[0])) if same else None
        if self.n and np.any(self.lengths < 12):
            raise InputError(f"{self._where}: message shorter than a CDR header; the file is corrupt")
        if self.n and np.any(self.buf[self.start + 1] != 1):
            raise InputError(f"{self._where}: only little-endian CDR is supported")

    def _take(self, off: np.ndarray, nbytes: int) -> np.ndarray:
        if self.n and np.any(off + nbytes > self.lengths):
            raise InputError(f"{self._where}: message shorter than its type's layout; the file is corrupt")
        if self._grid is not None and self.n and off.min() == off.max():
            o = int(off[0])
            return self._grid[:, o : o + nbytes]
        out = np.empty((self.n, nbytes), np.uint8)
        pos = (self.start + off)[:, None]
        ar = np.arange(nbytes)[None, :]
        for i in range(0, self.n, 8192):  # bounded index arrays
            out[i : i + 8192] = self.buf[pos[i : i + 8192] + ar]
        return out

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
