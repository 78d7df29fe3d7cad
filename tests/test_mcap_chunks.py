"""The pipelined chunk writer writes the plain mcap Writer's file, byte for byte."""

from __future__ import annotations

import io

import mcap.writer
import numpy as np
import zstandard
from mcap.reader import make_reader
from mcap.writer import CompressionType, Writer

from uwbcal.convert.mcap_chunks import ZSTD_LEVEL, PipelinedWriter


class _Level:
    """The zstandard module of mcap.writer at our level (mcap compresses at 3)."""

    @staticmethod
    def compress(data: bytes) -> bytes:
        return zstandard.ZstdCompressor(level=ZSTD_LEVEL).compress(data)


def _write(w: Writer) -> bytes:
    w.start(profile="ros2", library="test")
    sid = w.register_schema("a/msg/B", "ros2msg", b"float64 x")
    cids = [w.register_channel(f"/t{i}", "cdr", sid) for i in range(3)]
    rng = np.random.default_rng(0)
    for k in range(400):
        size = int(rng.integers(1, 3000)) if k != 100 else 3 << 20  # one outgrows the chunk buffer
        w.add_message(
            cids[k % 3], log_time=1000 + k, data=rng.bytes(size // 2) * 2, publish_time=k, sequence=k
        )
        if k == 250:
            w.add_metadata("mid", {"k": str(k)})
    w.add_metadata("end", {"json": "{}"})
    w.finish()


def test_pipelined_writer_writes_the_plain_writers_file(monkeypatch):
    plain, ours = io.BytesIO(), io.BytesIO()
    monkeypatch.setattr(mcap.writer, "zstandard", _Level)
    _write(Writer(plain, chunk_size=8192, compression=CompressionType.ZSTD))
    _write(PipelinedWriter(ours, chunk_size=8192))
    assert ours.getvalue() == plain.getvalue()
    reader = make_reader(io.BytesIO(ours.getvalue()))
    summary = reader.get_summary()
    assert summary.statistics.message_count == 400 and summary.statistics.chunk_count > 50
    assert [m.log_time for _, _, m in reader.iter_messages(log_time_order=True)] == list(range(1000, 1400))


def test_message_in_pieces_is_the_joined_message():
    """A payload given as a tuple of buffers (views included) writes the file its joined bytes write."""
    rng = np.random.default_rng(1)
    payloads = [
        (rng.bytes(int(rng.integers(0, 900))), rng.bytes(int(rng.integers(0, 5000)))) for _ in range(60)
    ]
    files = []
    for pieces in (True, False):
        out = io.BytesIO()
        w = PipelinedWriter(out, chunk_size=4096)
        w.start()
        cid = w.register_channel("/t", "cdr", w.register_schema("a/msg/B", "ros2msg", b""))
        for k, (a, b) in enumerate(payloads):
            data = (a, memoryview(bytearray(b))) if pieces else a + b
            w.add_message(cid, log_time=k, data=data, publish_time=k)
        w.finish()
        files.append(out.getvalue())
    assert files[0] == files[1]


def test_abort_ends_the_worker():
    w = PipelinedWriter(io.BytesIO(), chunk_size=100)
    w.start()
    sid = w.register_schema("a/msg/B", "ros2msg", b"")
    cid = w.register_channel("/t", "cdr", sid)
    for k in range(20):
        w.add_message(cid, log_time=k, data=b"x" * 64, publish_time=k)
    w.abort()
    assert w._pool._shutdown
