"""Truncated ROS bags read up to their last intact chunk, through rosbags' own readers.

A bag whose writer was killed, or a copy cut short, has no index (ROS 1: the connection and chunk-info records at
the end; ROS 2 MCAP: the summary and footer), and rosbags refuses it. `prepare` swaps the opening step of the
reader inside an `AnyReader` for a sequential scan of the data records: ROS 1 chunks (each decompressed, its
connection and message records indexed as rosbags indexes them), MCAP records up to the last complete one (then
rosbags' own scan of an unindexed MCAP). Everything after the last intact record is lost; `Recovery` says how
much was kept. A ROS 2 bag in sqlite3 storage has no such structure to scan and is not recovered.
"""

from __future__ import annotations

import struct
from collections import defaultdict
from dataclasses import dataclass
from io import BytesIO
from pathlib import Path
from typing import Any, BinaryIO

from uwbcal.convert.mcap_index import MCAP_MAGIC, OP_CHUNK, OP_DATA_END, OP_FOOTER, OP_HEADER, REC_HEAD, U64


@dataclass
class Recovery:
    """What a recovering open kept of a truncated bag."""

    path: Path
    size: int = 0  # bytes in the file
    intact: int = 0  # bytes up to the end of the last intact record
    chunks: int = 0
    messages: int = 0

    def note(self) -> str:
        return (
            f"{self.path}: truncated bag (no index): recovered {self.messages} messages in {self.chunks} "
            f"intact chunk(s), {self.intact} of {self.size} bytes; the rest of the recording is lost"
        )


def prepare(any_reader: Any, fmt: str) -> Recovery | None:
    """Make the (unopened) ``any_reader`` open its bag by scanning (None: the format cannot be recovered)."""
    inner = any_reader.readers[0]
    rec = Recovery(Path(inner.path))
    if fmt == "rosbag1":
        inner.open = lambda: _open_ros1(inner, rec)
    elif fmt == "rosbag2-mcap" and inner.path.is_dir():  # a bag folder: its storage plugin opened per file
        storage = inner.storage
        storage.STORAGE_PLUGINS = {**type(storage).STORAGE_PLUGINS, "mcap": lambda p: _mcap_storage(p, rec)}
    elif fmt == "rosbag2-mcap":
        inner.storage = _mcap_storage(inner.storage.path, rec)
    else:
        return None
    return rec


# -- ROS 1 -----------------------------------------------------------------------------------------------------
def open_ros1(reader: Any) -> Recovery | None:
    """Open rosbags' (unopened) rosbag1 ``reader`` by scanning its chunks; None when nothing could be kept (the
    reader then closed)."""
    rec = Recovery(Path(reader.path))
    try:
        _open_ros1(reader, rec)
    except Exception:  # noqa: BLE001 - rosbags raises many kinds for a bad file
        rec.messages = 0
    if rec.messages:
        return rec
    if reader.bio is not None:
        reader.bio.close()
        reader.bio = None
    return None


def _open_ros1(reader: Any, rec: Recovery) -> None:
    """rosbags' rosbag1 `Reader.open`, with the index rebuilt from the intact chunks."""
    from rosbags.rosbag1.reader import Chunk, ChunkInfo, Header, ReaderError, RecordType, decompressors

    reader.bio = bio = reader.path.open("rb")
    rec.size = reader.path.stat().st_size
    if not bio.readline().startswith(b"#ROSBAG V2.0"):
        raise ReaderError("File magic is invalid.")
    Header.read(bio, RecordType.BAGHEADER)
    bio.seek(_u32(bio), 1)
    conns: dict[int, Any] = {}
    indexes: dict[int, list] = defaultdict(list)
    for pos, header, body in _records(bio, rec.size):
        op = header.get_uint8("op")
        if op == RecordType.CHUNK:
            decompress = decompressors.get(header.get_string("compression"))
            found = _ros1_chunk(reader, decompress, body, pos, conns)
            if found is None:
                break
            counts: dict[int, int] = defaultdict(int)
            for cid, entry in found:
                indexes[cid].append(entry)
                counts[cid] += 1
            if found:
                times = [e.time for _, e in found]
                reader.chunk_infos.append(ChunkInfo(pos, min(times), max(times) + 1, dict(counts)))
            reader.chunks[pos] = Chunk(len(body), bio.tell() - len(body), decompress)
            rec.chunks += 1
        elif op == RecordType.CONNECTION:
            _ros1_connection(reader, header, conns, bio, pos)
        rec.intact = bio.tell()
    reader.indexes = {c: sorted(indexes[c]) for c in conns}
    reader.connections = [c._replace(msgcount=len(reader.indexes[i])) for i, c in conns.items()]
    rec.messages = sum(len(v) for v in reader.indexes.values())


def _u32(bio: BinaryIO) -> int:
    return struct.unpack("<I", bio.read(4))[0]


def _records(bio: BinaryIO, end: int):
    """(offset, header, body) of each complete record from the stream's position up to ``end``."""
    from rosbags.rosbag1.reader import Header, ReaderError

    while bio.tell() < end:
        pos = bio.tell()
        try:
            header = Header.read(bio)
            header.get_uint8("op")
            size = _u32(bio)
        except (ReaderError, struct.error):
            return
        body = bio.read(size)
        if len(body) != size:
            return
        yield pos, header, body


def _ros1_chunk(reader: Any, decompress, data: bytes, pos: int, conns: dict) -> list | None:
    """(connection id, index entry) of each message in one chunk record (None: it does not decompress, or its
    records do not parse to its end)."""
    from rosbags.rosbag1.reader import IndexData, RecordType

    try:
        raw = decompress(data)
    except Exception:  # noqa: BLE001 (a damaged chunk: the recording ends before it)
        return None
    chunk, found = BytesIO(raw), []
    for offset, header, _ in _records(chunk, len(raw)):
        op = header.get_uint8("op")
        if op == RecordType.CONNECTION:
            _ros1_connection(reader, header, conns, chunk, offset)
        elif op == RecordType.MSGDATA:
            found.append((header.get_uint32("conn"), IndexData(header.get_time("time"), pos, offset)))
    return found if chunk.tell() == len(raw) else None


def _ros1_connection(reader: Any, header: Any, conns: dict, src: BinaryIO, offset: int) -> None:
    """The connection record at ``offset`` of ``src``, parsed by rosbags' own `read_connection`."""
    cid = header.get_uint32("conn")
    if cid in conns:
        return
    end = src.tell()
    src.seek(offset)
    bio, reader.bio = reader.bio, BytesIO(src.read(end - offset))
    try:
        conns[cid] = reader.read_connection()
    finally:
        reader.bio = bio


# -- ROS 2, MCAP storage -----------------------------------------------------------------------------------------
def _mcap_storage(path: Path, rec: Recovery) -> Any:
    """rosbags' MCAP storage, opened on the records before the truncation (read by its own unindexed scan)."""
    from rosbags.rosbag2.storage_mcap import McapReader

    storage = McapReader(Path(path))
    storage.open = lambda: _open_mcap(storage, rec)
    storage.messages = storage.messages_scan  # in file order, as written (no index to merge by time)
    return storage


def _open_mcap(storage: Any, rec: Recovery) -> None:
    from rosbags.rosbag2.errors import ReaderError

    storage.bio = bio = storage.path.open("rb")
    rec.path, rec.size = storage.path, storage.path.stat().st_size
    if bio.read(8) != MCAP_MAGIC or bio.read(1) != bytes([OP_HEADER]):
        raise ReaderError("File magic is invalid.")
    bio.seek(U64.unpack(bio.read(8))[0], 1)
    storage.data_start = end = bio.tell()
    while len(head := bio.read(REC_HEAD.size)) == REC_HEAD.size:
        op, size = REC_HEAD.unpack(head)
        if op in (OP_DATA_END, OP_FOOTER) or bio.tell() + size > rec.size:
            break
        bio.seek(size, 1)
        end = bio.tell()
        rec.chunks += op == OP_CHUNK
    storage.data_end = rec.intact = end
    storage.meta_scan()
    stats = storage.statistics
    storage.connections = [
        c._replace(msgcount=stats.channel_message_counts.get(c.id, 0)) for c in storage.connections
    ]
    n = stats.message_count
    storage.metadata = storage.metadata._replace(
        duration=stats.end_time - stats.start_time + 1 if n else 0,
        start_time=stats.start_time if n else 2**63 - 1,
        end_time=stats.end_time + 1 if n else 0,
        message_count=n,
    )
    rec.messages = n
