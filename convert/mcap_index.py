"""The read side of an MCAP file: its chunk index and message rows (`McapIndex`, the base of `RecordingReader`).

Reads through the chunk and message indexes (vectorised, no per-message heap); a file without a summary
(truncated, or killed while being written) is scanned up to the last intact chunk, with a warning; damaged chunks
are skipped and named.
"""

from __future__ import annotations

import io
import json
import os
import struct
import zlib
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import zstandard
from mcap.data_stream import ReadDataStream
from mcap.exceptions import McapError
from mcap.reader import make_reader
from mcap.records import Channel as McapChannel
from mcap.records import Metadata as McapMetadata
from mcap.records import Schema as McapSchema

from uwbcal.pipeline.core.errors import InputError

MCAP_MAGIC = b"\x89MCAP0\r\n"
OP_SCHEMA, OP_CHANNEL, OP_MESSAGE, OP_CHUNK, OP_MESSAGE_INDEX = 0x03, 0x04, 0x05, 0x06, 0x07
OP_METADATA, OP_DATA_END, OP_FOOTER, OP_HEADER = 0x0C, 0x0F, 0x02, 0x01
REC_HEAD = struct.Struct("<BQ")
U16, U32, U64 = struct.Struct("<H"), struct.Struct("<I"), struct.Struct("<Q")


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
        op, n = REC_HEAD.unpack_from(buf, pos)
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
            c = U16.unpack_from(buf, off)[0]
            if cids is None or c in cids:
                t.append(U64.unpack_from(buf, off + 6)[0])
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


class McapIndex:
    """An MCAP file's schemas, channels and chunks, and its message rows by channel and time window."""

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
                    crc=U32.unpack(crc)[0] if len(crc) == 4 else 0,
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
                op, n = REC_HEAD.unpack(head)
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
                        c, t = U16.unpack_from(content, 0)[0], U64.unpack_from(content, 6)[0]
                        loose.append((c, t, content[22:]))
                        counts[c] = counts.get(c, 0) + 1
                    elif op == OP_METADATA:
                        m = McapMetadata.read(ReadDataStream(io.BytesIO(content)))
                        meta[m.name] = parse_meta(m.metadata)
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
        (clen,) = U32.unpack_from(content, 28)
        compression = content[32 : 32 + clen].decode()
        (rlen,) = U64.unpack_from(content, 32 + clen)
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


def parse_meta(d: dict[str, str]) -> dict:
    if "json" in d:
        try:
            return json.loads(d["json"])
        except json.JSONDecodeError:
            return dict(d)
    return dict(d)
