"""An ``mcap`` Writer whose chunks are compressed on worker threads while the next chunks are being built.

``mcap.writer.Writer`` compresses (zstd) and checksums each chunk in the calling thread when it is full. Here a
full chunk goes to a pool of ``IN_FLIGHT`` = 2 worker threads (zstd and zlib release the GIL); the oldest chunk
is written when ``IN_FLIGHT`` chunks are in flight and a new one is full, and all of them before anything else is
written (metadata, the summary at ``finish``). Converting a bag, the reading and re-encoding runs on one core
while the chunks are compressed on both: with one chunk in flight the second core carried the whole compression
and the source hash (`sources.Hasher`) and was the longer path; with two, a chunk is compressed on whichever
core is free. Messages go into the chunk with one packed header per message (`PipelinedWriter.add_message`).
The file is the one the plain Writer writes, byte for byte (same records in the same order).

Compression: zstd level ``ZSTD_LEVEL`` = 1 instead of mcap's 3: on camera images it keeps 96-99 % of the ratio at
~3.5x the speed (measured on EuRoC and synthetic frames). Negative levels compress ~2.1x faster again but keep
much less (EuRoC V1_01 frames: size 0.914 of the raw at level -1 against 0.790 at level 1); not used.

A chunk is built in a preallocated buffer (`_ChunkBuffer`) taken from a small pool and given back once the chunk
is written, so the pages of a chunk are reused rather than fresh ones faulted in for every chunk; the compressor
reads it in place and the compressed chunk goes to the file without being copied into a record first. A message
may come as several pieces (e.g. an image's CDR head and its pixels as a view of the source), copied once, into
the chunk.

The overrides use the mangled names of the Writer's private members (``_Writer__…``); `tests/test_mcap_chunks.py`
checks that the output is the plain Writer's.
"""

from __future__ import annotations

import struct
import zlib
from collections import deque
from concurrent.futures import Future, ThreadPoolExecutor
from io import RawIOBase

import zstandard
from mcap.data_stream import RecordBuilder
from mcap.opcode import Opcode
from mcap.records import ChunkIndex, MessageIndex
from mcap.writer import CompressionType, IndexType, Writer

ZSTD_LEVEL = 1
IN_FLIGHT = 2  # chunks compressed at once (one worker thread each)
# a Message record's opcode, length, channel, sequence, log and publish time (then the payload)
_MESSAGE_HEAD = struct.Struct("<BQHIQQ")
_MESSAGE_FIELDS = _MESSAGE_HEAD.size - 9


_CHUNK_HEAD = struct.Struct("<BQQQQII4s")  # opcode, length, start/end time, size, crc, "zstd"
_U64 = struct.Struct("<Q")
_PATCH_U64 = _U64.pack_into


def _nbytes(data) -> int:
    t = type(data)
    if t is bytes or t is bytearray:
        return len(data)
    return data.nbytes if t is memoryview else memoryview(data).nbytes


class _ChunkBuffer(RecordBuilder):
    """The chunk's RecordBuilder on a preallocated bytearray from ``pool`` (grown only for a chunk that outgrows
    it). `take` hands the filled buffer out and continues in a fresh one."""

    def __init__(self, capacity: int, pool: list[bytearray]) -> None:
        self._capacity = capacity
        self._pool = pool
        self._buf = self._new()
        self._pos = 0
        self._record_start_offset = 0

    def _new(self) -> bytearray:
        return self._pool.pop() if self._pool else bytearray(self._capacity)

    @property
    def count(self) -> int:
        return self._pos

    def reserve(self, end: int) -> bytearray:
        """The buffer, grown if it is shorter than ``end`` bytes (the content up to the count kept)."""
        if end > len(self._buf):
            grown = bytearray(max(end, 2 * len(self._buf)))
            grown[: self._pos] = memoryview(self._buf)[: self._pos]
            self._buf = grown
        return self._buf

    def write(self, data) -> None:
        end = self._pos + _nbytes(data)
        self.reserve(end)[self._pos : end] = data  # same length: a copy in place
        self._pos = end

    def start_record(self, opcode) -> None:
        self._record_start_offset = self._pos
        self.write(struct.pack("<BQ", opcode, 0))

    def finish_record(self) -> None:
        _PATCH_U64(self._buf, self._record_start_offset + 1, self._pos - self._record_start_offset - 9)

    def take(self) -> tuple[bytearray, int]:
        """The filled buffer and its size; the builder continues empty in another buffer."""
        out = (self._buf, self._pos)
        self._buf, self._pos = self._new(), 0
        return out

    def end(self) -> bytes:
        out = bytes(memoryview(self._buf)[: self._pos])
        self._pos = 0
        return out


def _compress(data, crc: bool) -> tuple[bytes, int]:
    # a compressor per chunk: ZstdCompressor objects must not be shared between threads
    return zstandard.ZstdCompressor(level=ZSTD_LEVEL).compress(data), (zlib.crc32(data) if crc else 0)


class _Positioned:
    """A binary output that counts the bytes written: ``tell`` without a system call (the Writer asks for the
    position of every chunk and index)."""

    def __init__(self, stream) -> None:
        self._stream = stream
        self._pos = stream.tell()

    def write(self, data) -> int:
        n = _nbytes(data)
        self._stream.write(data)
        self._pos += n
        return n

    def tell(self) -> int:
        return self._pos

    def flush(self) -> None:
        self._stream.flush()

    def close(self) -> None:
        self._stream.close()


class PipelinedWriter(Writer):
    """``mcap.writer.Writer`` (zstd chunks only) with the chunk compression overlapped with building the next
    chunks: up to ``in_flight`` chunks are compressed at once, on as many worker threads, and written in order.
    Call `finish` (or `abort`) to end the workers."""

    def __init__(
        self, output, *, chunk_size: int, enable_crcs: bool = True, in_flight: int = IN_FLIGHT
    ) -> None:
        if not isinstance(output, str | RawIOBase):
            output = _Positioned(output)
        super().__init__(
            output, chunk_size=chunk_size, compression=CompressionType.ZSTD, enable_crcs=enable_crcs
        )
        self._crcs = enable_crcs
        self._in_flight = max(1, in_flight)
        self._pool = ThreadPoolExecutor(self._in_flight, thread_name_prefix="mcap-chunk")
        self._pending: deque[tuple[Future, int, int, int, dict, bytearray]] = deque()
        self._buffers: list[bytearray] = []
        # room for the message that takes a chunk over its size without growing the buffer
        capacity = chunk_size + max(chunk_size // 4, 1 << 20)
        self._Writer__chunk_builder.record_writer = _ChunkBuffer(capacity, self._buffers)

    def add_message(self, channel_id: int, log_time: int, data, publish_time: int, sequence: int = 0) -> None:
        """``Writer.add_message`` into the chunk, the same bytes and indices with the header packed in place and
        one copy per payload piece instead of a Message object and six builder calls. ``data``: bytes, a byte buffer, or a tuple of them
        (the payload in pieces); copied into the chunk here, so a caller may reuse it."""
        builder = self._Writer__chunk_builder
        if builder is None:
            if isinstance(data, tuple):
                data = b"".join(data)
            super().add_message(channel_id, log_time, data, publish_time, sequence)
            return
        st = self._Writer__statistics
        st.message_start_time = log_time if st.message_count == 0 else min(log_time, st.message_start_time)
        st.message_end_time = max(log_time, st.message_end_time)
        st.channel_message_counts[channel_id] += 1
        st.message_count += 1
        if builder.num_messages == 0:
            builder.message_start_time = log_time
        else:
            builder.message_start_time = min(builder.message_start_time, log_time)
        builder.message_end_time = max(builder.message_end_time, log_time)
        index = builder.message_indices.get(channel_id)
        if index is None:
            index = builder.message_indices[channel_id] = MessageIndex(channel_id=channel_id, records=[])
        rw = builder.record_writer
        pos = rw._pos
        index.records.append((log_time, pos))
        builder.num_messages += 1
        if type(data) is tuple:
            parts, sizes = data, [_nbytes(p) for p in data]
        else:
            parts, sizes = (data,), (_nbytes(data),)
        size = sum(sizes)
        end = pos + _MESSAGE_HEAD.size + size
        buf = rw.reserve(end)
        _MESSAGE_HEAD.pack_into(
            buf, pos, Opcode.MESSAGE, _MESSAGE_FIELDS + size, channel_id, sequence, log_time, publish_time
        )
        pos += _MESSAGE_HEAD.size
        for p, n in zip(parts, sizes, strict=True):
            buf[pos : pos + n] = p  # same length: a copy in place
            pos += n
        rw._pos = end
        if end > self._Writer__chunk_size:
            self._Writer__finalize_chunk()

    # -- the overridden private step of Writer: hand the chunk to a worker, write the oldest ones --------------
    def _Writer__finalize_chunk(self) -> None:  # noqa: N802 (the name Writer calls)
        builder = self._Writer__chunk_builder
        if not builder or builder.num_messages == 0:
            return
        self._Writer__statistics.chunk_count += 1
        buf, size = builder.record_writer.take()
        job = self._pool.submit(_compress, memoryview(buf)[:size], self._crcs)
        pending = (job, size, builder.message_start_time, builder.message_end_time)
        indices = dict(builder.message_indices)  # reset() clears the builder's dict, not the indices
        builder.reset()
        while len(self._pending) >= self._in_flight:
            self._write_oldest()
        self._pending.append((*pending, indices, buf))

    def write_pending(self) -> None:
        """Write the chunks in flight, if any, in order."""
        while self._pending:
            self._write_oldest()

    def _write_oldest(self) -> None:
        """Write the oldest chunk in flight (what ``Writer.__finalize_chunk`` writes after compressing)."""
        job, size, t0, t1, indices, buf = self._pending.popleft()
        compressed, crc = job.result()
        self._buffers.append(buf)  # compressed: the buffer takes a next chunk
        rb = self._Writer__record_builder
        self._Writer__flush()
        stream = self._Writer__stream
        chunk_start = stream.tell()
        # the Chunk record as mcap.records.Chunk.write makes it, the compressed data written as it is
        head = _CHUNK_HEAD.pack(
            Opcode.CHUNK, _CHUNK_HEAD.size - 9 + 8 + len(compressed), t0, t1, size, crc, 4, b"zstd"
        ) + _U64.pack(len(compressed))
        if self._Writer__enable_data_crcs:
            self._Writer__data_section_crc = zlib.crc32(
                compressed, zlib.crc32(head, self._Writer__data_section_crc)
            )
        stream.write(head)
        stream.write(compressed)
        chunk_length = len(head) + len(compressed)
        chunk_index = ChunkIndex(
            message_start_time=t0,
            message_end_time=t1,
            chunk_start_offset=chunk_start,
            chunk_length=chunk_length,
            message_index_offsets={},
            message_index_length=0,
            compression="zstd",
            compressed_size=len(compressed),
            uncompressed_size=size,
        )
        index_start = chunk_start + chunk_length
        if self._Writer__index_types & IndexType.MESSAGE:
            for cid, index in indices.items():
                chunk_index.message_index_offsets[cid] = index_start + rb.count
                index.write(rb)
        chunk_index.message_index_length = rb.count
        self._Writer__flush()
        self._Writer__chunk_indices.append(chunk_index)

    # -- everything that writes records outside chunks writes the chunk in flight first ----------------------
    def add_metadata(self, name, data) -> None:
        self.write_pending()
        super().add_metadata(name, data)

    def add_attachment(self, *args, **kwargs) -> None:
        self.write_pending()
        super().add_attachment(*args, **kwargs)

    def flush(self) -> None:
        self._Writer__finalize_chunk()
        self.write_pending()
        super().flush()

    def finish(self) -> None:
        try:
            self._Writer__finalize_chunk()
            self.write_pending()
            super().finish()
        finally:
            self._pool.shutdown(wait=True)

    def abort(self) -> None:
        """Drop the chunks in flight and end the workers (the file is being discarded)."""
        self._pending.clear()
        self._pool.shutdown(wait=True, cancel_futures=True)
