"""ROS1 bag messages without copies, and ROS1 -> CDR of the pass-through message types as byte pieces.

`messages` yields the messages of an opened ``rosbags.rosbag1.Reader`` in the reader's own order (its per-connection
indices merged by time, as ``Reader.messages`` merges them), each as a memoryview into the chunk it was read with: an
uncompressed chunk is read into one reused buffer (no fresh bytes per chunk and per message). A message's view is
valid until the next message is taken; a handler that keeps data copies it. Damaged records raise
``rosbags.rosbag1.ReaderError`` as the reader does.

`transform_stamped` reads the 7 numbers of a ROS1 ``geometry_msgs/TransformStamped``. `image_cdr` /
`stamped_doubles_cdr` turn a ROS1 ``sensor_msgs/Image`` / a message of a header and doubles only
(``sensor_msgs/Imu``, ``geometry_msgs/PointStamped``) into the CDR that ``Typestore.ros1_to_cdr`` makes, the
pixels as a view of the input instead of a copy (`tests/test_ros1_wire.py` compares them byte for byte).
Malformed messages raise ValueError.
"""

from __future__ import annotations

import os
import struct
from collections.abc import Iterable, Iterator, Sequence

import numpy as np
from rosbags.rosbag1.reader import ReaderError, RecordType, decompressors

_U32 = struct.Struct("<I")
_II = struct.Struct("<II")
_7D = struct.Struct("<7d")
_CDR_LE = b"\x00\x01\x00\x00"  # CDR encapsulation header, little endian
_NO_COMPRESSION = decompressors["none"]


def _fields(header: bytes) -> dict[bytes, bytes]:
    """The name=value fields of a ROS1 record header."""
    out: dict[bytes, bytes] = {}
    pos, n = 0, len(header)
    while pos < n:
        if pos + 4 > n:
            raise ReaderError("Header field size could not be read.")
        (size,) = _U32.unpack_from(header, pos)
        pos += 4
        if pos + size > n:
            raise ReaderError("Declared field size is too large for header.")
        name, sep, value = header[pos : pos + size].partition(b"=")
        if not sep:
            raise ReaderError("Header field could not be parsed.")
        out[name] = value
        pos += size
    return out


def _u32_at(view: memoryview, pos: int, end: int) -> int:
    if pos + 4 > end:
        raise ReaderError(f"Got only {max(end - pos, 0)} of requested 4 bytes.")
    return _U32.unpack_from(view, pos)[0]


def _pread(fd: int, view: memoryview, offset: int) -> int:
    """Read into ``view`` from ``offset`` (one system call, no seek); the byte count read (short at EOF)."""
    got = 0
    while got < len(view):
        n = os.preadv(fd, [view[got:]], offset + got)
        if n == 0:
            break
        got += n
    return got


def _merged(indexes: Iterable[list]) -> Iterator[tuple[int, int, int]]:
    """(time, chunk position, offset) of the index entries in ``heapq.merge`` order (the reader's): by time, ties
    in the order of the indices, then of the entries (each index is sorted by time)."""
    entries = [np.array(idx, np.int64).reshape(-1, 3) for idx in indexes]
    if not entries:
        return iter(())
    e = np.concatenate(entries)
    e = e[np.argsort(e[:, 0], kind="stable")]
    return zip(*(e[:, k].tolist() for k in range(3)), strict=True)


def messages(reader, connections: Sequence) -> Iterator[tuple[object, int, memoryview]]:
    """(connection, bag time [ns], raw message view) of ``connections`` in the order of ``reader.messages``."""
    bio = reader.bio
    if bio is None:
        raise ReaderError("Rosbag is not open.")
    fd = bio.fileno()
    connmap = {c.id: c for c in reader.connections}
    buf = bytearray()
    view, size, current = memoryview(buf), 0, -1
    for time, chunk_pos, offset in _merged(reader.indexes[c.id] for c in connections):
        if chunk_pos != current:
            chunk = reader.chunks[chunk_pos]
            if chunk.decompressor is _NO_COMPRESSION:
                size = chunk.datasize
                if size > len(buf):  # a new, larger buffer (a view of the old one may still be held)
                    buf = bytearray(max(size, 2 * len(buf)))
                    view = memoryview(buf)
                got = _pread(fd, view[:size], chunk.datapos)
            else:
                bio.seek(chunk.datapos)
                data = bio.read(chunk.datasize)
                got = len(data)
                if got == chunk.datasize:
                    data = chunk.decompressor(data)
                view, size = memoryview(data), len(data)
            if got != chunk.datasize:
                raise ReaderError(f"Got only {got} of requested {chunk.datasize} bytes.")
            current = chunk_pos
        pos = offset
        while True:
            hlen = _u32_at(view, pos, size)
            if pos + 4 + hlen > size:
                raise ReaderError(f"Got only {size - pos - 4} of requested {hlen} bytes.")
            fields = _fields(bytes(view[pos + 4 : pos + 4 + hlen]))
            pos += 4 + hlen
            op = fields.get(b"op", b"")
            if len(op) != 1:
                raise ReaderError("Could not read uint8 field 'op'.")
            dlen = _u32_at(view, pos, size)
            pos += 4
            if op[0] != RecordType.CONNECTION:
                break
            pos += dlen
        if op[0] != RecordType.MSGDATA:
            raise ReaderError("Expected to find message data.")
        if pos + dlen > size:
            raise ReaderError(f"Got only {size - pos} of requested {dlen} bytes.")
        conn, stamp = fields.get(b"conn", b""), fields.get(b"time", b"")
        if len(conn) != 4 or len(stamp) != 8:
            raise ReaderError("Could not read the conn or time field of a message record.")
        sec, nsec = _II.unpack(stamp)
        if sec * 1_000_000_000 + nsec != time:
            raise ReaderError("Message time differs from its index entry.")
        yield connmap[_U32.unpack(conn)[0]], time, view[pos : pos + dlen]


# ---------------------------------------------------------------------------------------------------------------
# ROS1 -> CDR
# ---------------------------------------------------------------------------------------------------------------
def _align(out: bytearray, n: int) -> None:
    """Zero padding to an ``n``-byte boundary of the CDR body (after the 4-byte encapsulation header)."""
    out += bytes(-(len(out) - 4) % n)


def _header(raw: memoryview) -> tuple[bytearray, int]:
    """CDR of a leading std_msgs/Header (stamp, frame_id; ROS1's seq dropped) and the ROS1 offset after it."""
    (flen,) = _U32.unpack_from(raw, 12)
    end = 16 + flen
    if end > len(raw):
        raise ValueError(f"frame_id of {flen} bytes runs past the message ({len(raw)} bytes)")
    out = bytearray(_CDR_LE)
    out += raw[4:12]
    out += _U32.pack(flen + 1)
    out += raw[16:end]
    out += b"\x00"
    return out, end


def stamped_doubles_cdr(raw: memoryview, n: int) -> bytearray:
    """CDR of a ROS1 message made of a std_msgs/Header and ``n`` float64 (Imu: 37, PointStamped: 3)."""
    out, pos = _header(raw)
    if pos + 8 * n != len(raw):
        raise ValueError(f"message of {len(raw)} bytes, expected {pos + 8 * n} (header and {n} float64)")
    _align(out, 8)
    out += raw[pos:]
    return out


def image_cdr(raw: memoryview) -> tuple[str, bytearray, memoryview]:
    """ROS1 sensor_msgs/Image -> (encoding, CDR up to the pixels, the pixels as a view of ``raw``)."""
    out, pos = _header(raw)
    height_width = raw[pos : pos + 8]
    (elen,) = _U32.unpack_from(raw, pos + 8)
    pos += 12
    encoding = bytes(raw[pos : pos + elen])
    pos += elen
    if pos + 9 > len(raw):
        raise ValueError(f"image message of {len(raw)} bytes ends inside its fields")
    big_endian = raw[pos : pos + 1]
    step, dlen = _II.unpack_from(raw, pos + 1)
    pos += 9
    if pos + dlen != len(raw):
        raise ValueError(
            f"image message of {len(raw)} bytes, its fields and {dlen} pixel bytes take {pos + dlen}"
        )
    _align(out, 4)
    out += height_width
    out += _U32.pack(elen + 1)
    out += encoding
    out += b"\x00"
    out += big_endian
    _align(out, 4)
    out += _II.pack(step, dlen)
    return encoding.decode("ascii", "replace"), out, raw[pos:]


def transform_stamped(raw: memoryview) -> tuple[float, ...]:
    """ROS1 geometry_msgs/TransformStamped -> (translation x, y, z, rotation x, y, z, w)."""
    (flen,) = _U32.unpack_from(raw, 12)
    pos = 16 + flen
    (clen,) = _U32.unpack_from(raw, pos)  # child_frame_id
    pos += 4 + clen
    if pos + _7D.size != len(raw):
        raise ValueError(
            f"message of {len(raw)} bytes, expected {pos + _7D.size} (header, child frame, 7 float64)"
        )
    return _7D.unpack_from(raw, pos)
