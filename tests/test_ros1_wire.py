"""ros1_wire: ROS1 bag messages read as views and the pass-through ROS1 -> CDR, against rosbags' own reader and
ros1_to_cdr (byte for byte), and what damaged bags and messages do."""

from __future__ import annotations

import numpy as np
import pytest
from rosbags.rosbag1 import Reader, ReaderError, Writer
from rosbags.typesys import Stores, get_typestore

from uwbcal.benchmarks.convert_bag import write_euroc_bag
from uwbcal.convert import msgs
from uwbcal.convert.euroc import convert_euroc
from uwbcal.convert.recording import RecordingReader
from uwbcal.convert.ros1_wire import image_cdr, messages, stamped_doubles_cdr, transform_stamped
from uwbcal.pipeline.core.errors import InputError

TS1 = get_typestore(Stores.ROS1_NOETIC)
T = TS1.types


def _header(frame: str, k: int):
    stamp = T["builtin_interfaces/msg/Time"](sec=1_403_715_273 + k, nanosec=999_999_999 - k)
    return T["std_msgs/msg/Header"](seq=k, stamp=stamp, frame_id=frame)


def _vec(x, y, z):
    return T["geometry_msgs/msg/Vector3"](x=x, y=y, z=z)


def _ser(msg, name: str) -> memoryview:
    return memoryview(TS1.serialize_ros1(msg, name))


def _imu(frame: str, k: int) -> memoryview:
    m = T["sensor_msgs/msg/Imu"](
        header=_header(frame, k),
        orientation=T["geometry_msgs/msg/Quaternion"](x=0.1, y=0.2, z=0.3, w=0.9),
        orientation_covariance=np.arange(9.0),
        angular_velocity=_vec(0.1 * k, -0.2, 0.3),
        angular_velocity_covariance=np.arange(9.0) + 1,
        linear_acceleration=_vec(1.1, 1.2, 9.81),
        linear_acceleration_covariance=np.arange(9.0) + 2,
    )
    return _ser(m, "sensor_msgs/msg/Imu")


def _image(frame: str, encoding: str, k: int, h: int = 5, w: int = 7) -> memoryview:
    m = T["sensor_msgs/msg/Image"](
        header=_header(frame, k),
        height=h,
        width=w,
        encoding=encoding,
        is_bigendian=k % 2,
        step=w,
        data=(np.arange(h * w) * (k + 1)).astype(np.uint8),
    )
    return _ser(m, "sensor_msgs/msg/Image")


@pytest.mark.parametrize("frame_len", range(9))
def test_cdr_pieces_are_ros1_to_cdr(frame_len):
    """Every alignment case of the strings: the pieces joined are rosbags' ros1_to_cdr, byte for byte."""
    ts = msgs.typestore()
    frame = "abcdefghi"[:frame_len]
    for enc_len in range(9):
        enc = "mono8xyzw"[:enc_len]
        raw = _image(frame, enc, enc_len)
        got_enc, head, pixels = image_cdr(raw)
        assert got_enc == enc
        assert bytes(head) + bytes(pixels) == bytes(ts.ros1_to_cdr(raw, msgs.IMAGE))
        assert pixels.obj is raw.obj  # the pixels are not copied
    raw = _imu(frame, frame_len)
    assert bytes(stamped_doubles_cdr(raw, 37)) == bytes(ts.ros1_to_cdr(raw, msgs.IMU))
    point = T["geometry_msgs/msg/PointStamped"](
        header=_header(frame, 3), point=T["geometry_msgs/msg/Point"](x=1.5, y=-2.0, z=3.25)
    )
    raw = _ser(point, "geometry_msgs/msg/PointStamped")
    assert bytes(stamped_doubles_cdr(raw, 3)) == bytes(ts.ros1_to_cdr(raw, msgs.POINT_STAMPED))
    for child_len in range(5):
        tf = T["geometry_msgs/msg/TransformStamped"](
            header=_header(frame, 1),
            child_frame_id="child"[:child_len],
            transform=T["geometry_msgs/msg/Transform"](
                translation=_vec(0.1, 0.2, 0.3),
                rotation=T["geometry_msgs/msg/Quaternion"](x=0.4, y=0.5, z=0.6, w=0.7),
            ),
        )
        raw = _ser(tf, "geometry_msgs/msg/TransformStamped")
        d = TS1.deserialize_ros1(raw, "geometry_msgs/msg/TransformStamped").transform
        want = (d.translation.x, d.translation.y, d.translation.z)
        want += (d.rotation.x, d.rotation.y, d.rotation.z, d.rotation.w)
        assert transform_stamped(raw) == want


def test_malformed_messages_raise_value_error():
    img, imu = _image("cam0", "mono8", 1), _imu("imu4", 1)
    with pytest.raises(ValueError, match="pixel bytes"):
        image_cdr(img[:-1])
    with pytest.raises(ValueError, match="ends inside its fields"):
        image_cdr(img[:40])
    with pytest.raises(ValueError, match="37 float64"):
        stamped_doubles_cdr(imu[:-8], 37)
    with pytest.raises(ValueError, match="runs past"):
        stamped_doubles_cdr(imu[:18], 37)


@pytest.mark.parametrize("compression", [None, "BZ2", "LZ4"])
def test_messages_in_the_readers_order(tmp_path, compression):
    """Small chunks written out of time order (a later chunk holds earlier stamps, so the merge goes back to an
    earlier chunk), equal stamps on two connections, compressed or not: the same messages in the same order as
    ``Reader.messages``."""
    bag = tmp_path / "o.bag"
    rng = np.random.default_rng(3)
    w = Writer(bag)
    if compression:
        w.set_compression(getattr(Writer.CompressionFormat, compression))
    w.chunk_threshold = 2000
    with w:
        ci = w.add_connection("/imu0", "sensor_msgs/msg/Imu", typestore=TS1)
        cc = w.add_connection("/cam0/image_raw", "sensor_msgs/msg/Image", typestore=TS1)
        stamps = rng.permutation(np.repeat(np.arange(60), 2))
        for k, t in enumerate(stamps.tolist()):
            if k % 3:
                w.write(ci, 1000 + 10 * t, bytes(_imu("imu4", k)))
            else:
                w.write(cc, 1000 + 10 * t, bytes(_image("cam0", "mono8", k, 12, 20)))
    with Reader(bag) as r:
        want = [(c.id, t, bytes(raw)) for c, t, raw in r.messages()]
        assert len(r.chunks) > 5
    with Reader(bag) as r:
        got = [(c.id, t, bytes(raw)) for c, t, raw in messages(r, r.connections)]
        cam = r.connections[1].id
        one = [(c.id, t) for c, t, _ in messages(r, [r.connections[1]])]
    assert got == want
    assert one == [(c, t) for c, t, _ in want if c == cam]


def _first_record_pos(bag) -> int:
    """File position of the first indexed message record."""
    with Reader(bag) as r:
        first = min(r.indexes[c.id][0] for c in r.connections)
        return r.chunks[first.chunk_pos].datapos + first.offset


def test_damaged_chunk(tmp_path):
    """A message record whose header length runs past its chunk: the reader's error, and converting says
    which file is damaged and leaves no output."""
    bag = tmp_path / "d.bag"
    write_euroc_bag(bag, duration_s=0.2, width=16, height=12)
    data = bytearray(bag.read_bytes())
    pos = _first_record_pos(bag)
    data[pos : pos + 4] = (10**6).to_bytes(4, "little")
    bag.write_bytes(bytes(data))
    with Reader(bag) as r, pytest.raises(ReaderError):
        list(messages(r, r.connections))
    with pytest.raises(InputError, match=r"d.bag: corrupt ROS1 bag while reading"):
        convert_euroc(bag, tmp_path / "d.mcap")
    assert not (tmp_path / "d.mcap").exists()


def test_malformed_image_is_dropped_and_counted(tmp_path):
    """An image message shorter than its fields say is dropped with its reason; the rest converts."""
    bag = tmp_path / "m.bag"
    with Writer(bag) as w:
        ci = w.add_connection("/imu0", "sensor_msgs/msg/Imu", typestore=TS1)
        cc = w.add_connection("/cam0/image_raw", "sensor_msgs/msg/Image", typestore=TS1)
        for k in range(4):
            w.write(ci, 10 + k, bytes(_imu("imu4", k)))
        w.write(cc, 20, bytes(_image("cam0", "mono8", 1))[:-3])
        w.write(cc, 21, bytes(_image("cam0", "mono8", 2)))
    convert_euroc(bag, tmp_path / "m.mcap")
    rec = RecordingReader(tmp_path / "m.mcap")
    dropped = rec.metadata("uwbcal.source")["dropped"]
    assert [(d["topic"], d["reason"], d["count"]) for d in dropped] == [
        ("/cam0/image_raw", "undecodable message (ValueError)", 1)
    ]
    topics = rec.topics()
    assert topics["/cam0/image_raw"].count == 1 and topics["/imu"].count == 4
