"""The normalised recording: round trips, an independent ROS 2 decoder, streaming, truncation, atomicity."""

import warnings

import numpy as np
import pytest
from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory

from convert.errors import InputError
from convert.recording import (
    META_CALIBRATION,
    TOPIC_CAM0,
    TOPIC_FEATURES,
    TOPIC_GT_POSE,
    TOPIC_GT_POSITION,
    TOPIC_IMU,
    TOPIC_ODOM,
    TOPIC_RANGE,
    RecordingReader,
    RecordingWriter,
)

T0 = 1_403_636_580_838_555_648


@pytest.fixture
def sample(tmp_path):
    rng = np.random.default_rng(0)
    n = 400
    t = T0 + np.arange(n, dtype=np.int64) * 5_000_000
    data = {
        "t": t,
        "gyro": rng.normal(size=(n, 3)),
        "acc": rng.normal(size=(n, 3)),
        "p": rng.normal(size=(n, 3)),
        "q": rng.normal(size=(n, 4)),
        "rt": t[::10] + 1234,
        "anchor": np.arange(n // 10) % 4 + 100,
        "dist": rng.uniform(0, 30, n // 10),
        "img": rng.integers(0, 255, size=(48, 64), dtype=np.uint8),
        "ids": np.array([3, 7, 4_000_000_000], dtype=np.uint32),
        "uv": rng.uniform(0, 700, size=(3, 2)),
        "cov": np.diag(np.arange(1.0, 7.0)),
    }
    data["q"] /= np.linalg.norm(data["q"], axis=1, keepdims=True)
    path = tmp_path / "rec.mcap"
    with RecordingWriter(path) as w:
        # written per topic in batches: the reader must still yield in time order
        w.write_pose_batch(t, data["p"], data["q"])
        w.write_imu_batch(t, data["gyro"], data["acc"])
        w.write_range_batch(data["rt"], 7, 1, data["anchor"], data["dist"])
        w.write_image(TOPIC_CAM0, int(t[5]), data["img"])
        w.write_features(int(t[5]), data["ids"], data["uv"])
        w.write_position_batch(t[:3], data["p"][:3])
        w.write_odometry(int(t[9]), data["p"][9], data["q"][9], data["cov"])
        w.set_metadata(META_CALIBRATION, {"imu": {"rate_hz": 200.0}})
    return path, data


def test_round_trip_every_type(sample):
    path, d = sample
    r = RecordingReader(path)
    imu = r.read_imu()
    np.testing.assert_array_equal(imu.t_ns, d["t"])
    np.testing.assert_array_equal(imu.gyro, d["gyro"])
    np.testing.assert_array_equal(imu.acc, d["acc"])
    poses = r.read_poses(TOPIC_GT_POSE)
    np.testing.assert_array_equal(poses.p, d["p"])
    np.testing.assert_array_equal(poses.q_xyzw, d["q"])
    rng = r.read_ranges()
    np.testing.assert_array_equal(rng.t_ns, d["rt"])
    np.testing.assert_array_equal(rng.anchor, d["anchor"])
    np.testing.assert_array_equal(rng.distance, d["dist"])
    assert set(rng.tag) == {7} and set(rng.antenna) == {1}
    ((t_img, img),) = list(r.iter_images(TOPIC_CAM0))
    assert t_img == d["t"][5]
    np.testing.assert_array_equal(img, d["img"])
    ((t_f, ids, uv),) = list(r.iter_features(TOPIC_FEATURES))
    np.testing.assert_array_equal(ids, d["ids"])
    np.testing.assert_array_equal(uv, d["uv"])
    np.testing.assert_array_equal(r.read_positions(TOPIC_GT_POSITION).p, d["p"][:3])
    odo = r.read_odometry(TOPIC_ODOM)
    np.testing.assert_array_equal(odo.cov[0], d["cov"])
    np.testing.assert_array_equal(odo.q_xyzw[0], d["q"][9])
    assert r.calibration == {"imu": {"rate_hz": 200.0}}
    info = r.topics()
    assert info[TOPIC_IMU].count == 400 and info[TOPIC_IMU].start_ns == d["t"][0]
    assert info[TOPIC_IMU].end_ns == d["t"][-1]
    assert info[TOPIC_IMU].rate_hz == pytest.approx(200.0)


def test_independent_ros2_decoder_reads_our_schemas(sample):
    """mcap_ros2 parses the ros2msg schema text itself: proves the schemas describe the bytes honestly."""
    path, d = sample
    seen = {}
    with open(path, "rb") as f:
        for _, channel, message, msg in make_reader(
            f, decoder_factories=[DecoderFactory()]
        ).iter_decoded_messages():
            seen.setdefault(channel.topic, []).append((message.log_time, msg))
    t, m = seen[TOPIC_IMU][17]
    assert t == d["t"][17] and m.header.stamp.sec * 10**9 + m.header.stamp.nanosec == d["t"][17]
    assert [m.angular_velocity.x, m.angular_velocity.y, m.angular_velocity.z] == list(d["gyro"][17])
    assert m.linear_acceleration.z == d["acc"][17, 2]
    _, m = seen[TOPIC_RANGE][3]
    assert (m.tag_id, m.antenna, m.anchor_id, m.distance) == (7, 1, d["anchor"][3], d["dist"][3])
    _, m = seen[TOPIC_FEATURES][0]
    assert list(m.ids) == list(d["ids"]) and list(m.v) == list(d["uv"][:, 1])
    _, m = seen[TOPIC_CAM0][0]
    assert m.encoding == "mono8" and bytes(m.data) == d["img"].tobytes()
    _, m = seen[TOPIC_ODOM][0]
    assert list(m.pose.covariance) == list(d["cov"].reshape(-1))
    _, m = seen[TOPIC_GT_POSE][2]
    assert m.pose.orientation.w == d["q"][2, 3]


def test_streaming_in_time_order_with_filters(sample):
    path, d = sample
    r = RecordingReader(path)
    stamps = [t for _, t, _ in r.messages()]
    assert stamps == sorted(stamps)
    sub = list(r.messages([TOPIC_IMU], int(d["t"][10]), int(d["t"][20])))
    assert [t for _, t, _ in sub] == list(d["t"][10:20])
    assert {topic for topic, _, _ in r.messages([TOPIC_RANGE, TOPIC_CAM0])} == {TOPIC_RANGE, TOPIC_CAM0}


def test_truncated_file_recovers_intact_chunks(tmp_path):
    path = tmp_path / "big.mcap"
    n = 20000
    t = T0 + np.arange(n, dtype=np.int64) * 5_000_000
    with RecordingWriter(path, chunk_size=64 * 1024) as w:
        w.write_imu_batch(t, np.zeros((n, 3)), np.ones((n, 3)))
    data = path.read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: len(data) // 2])
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        r = RecordingReader(cut)
    assert r.truncated and any("truncated" in str(c.message) for c in caught)
    imu = r.read_imu()
    assert 0 < len(imu.t_ns) < n
    np.testing.assert_array_equal(imu.t_ns, t[: len(imu.t_ns)])
    assert "recovered" in r.warnings[0]


def test_garbage_and_missing_files_are_input_errors(tmp_path):
    bad = tmp_path / "bad.mcap"
    bad.write_bytes(b"this is not an mcap file at all" * 10)
    with pytest.raises(InputError, match="bad.mcap: not an MCAP"):
        RecordingReader(bad)
    with pytest.raises(InputError, match="not found"):
        RecordingReader(tmp_path / "missing.mcap")


def test_writer_is_atomic(tmp_path):
    path = tmp_path / "out.mcap"
    with pytest.raises(RuntimeError), RecordingWriter(path) as w:
        w.write_imu(T0, [0, 0, 0], [0, 0, 9.81])
        raise RuntimeError("stage failed")
    assert not path.exists()
    assert list(tmp_path.iterdir()) == []


def test_missing_topic_names_the_file(sample):
    path, _ = sample
    with pytest.raises(InputError, match="no '/nope' topic"):
        RecordingReader(path).read_imu("/nope")


def test_merged_reader_interleaves_and_delegates(sample, tmp_path):
    from convert.recording import MergedReader

    path, d = sample
    extra = tmp_path / "features.mcap"
    with RecordingWriter(extra) as w:
        for i in (1, 50, 300):
            w.write_features(int(d["t"][i]) + 1, [i], [[1.0, 2.0]], topic="/cam0/features2")
    m = MergedReader(RecordingReader(path), RecordingReader(extra))
    stamps = [t for _, t, _ in m.messages(["/imu", "/cam0/features2"])]
    assert stamps == sorted(stamps) and len(stamps) == 403
    assert [int(i[0]) for _, i, _ in m.iter_features("/cam0/features2")] == [1, 50, 300]
    np.testing.assert_array_equal(m.read_imu().gyro, d["gyro"])
    assert m.calibration == {"imu": {"rate_hz": 200.0}}
