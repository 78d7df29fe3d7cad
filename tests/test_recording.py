"""The normalised recording: round trips, an independent ROS 2 decoder, streaming, truncation, atomicity."""

import re
import warnings

import numpy as np
import pytest
from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory

from uwbcal.convert.recording import (
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
from uwbcal.pipeline.core.errors import InputError

from support import T0


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
    assert m.pose.orientation.w == d["q"][2, 3] and m.pose.position.y == d["p"][2, 1]
    _, m = seen[TOPIC_GT_POSITION][1]
    assert [m.point.x, m.point.y, m.point.z] == list(d["p"][1])
    with open(path, "rb") as f:
        schemas = {s.name: s for s in make_reader(f).get_summary().schemas.values()}
    assert set(schemas) == {
        "sensor_msgs/msg/Imu",
        "sensor_msgs/msg/Image",
        "geometry_msgs/msg/PoseStamped",
        "geometry_msgs/msg/PointStamped",
        "nav_msgs/msg/Odometry",
        "uwbcal_msgs/msg/UwbRange",
        "uwbcal_msgs/msg/FeatureTracks",
    }
    assert all(s.encoding == "ros2msg" for s in schemas.values())
    # dependencies named as the fields name them (rosbag2's form; rerun's importer resolves only that)
    text = schemas["uwbcal_msgs/msg/UwbRange"].data.decode()
    assert text.startswith("std_msgs/Header header\n") and "\nMSG: std_msgs/Header\n" in text


def test_rerun_mcap_importer_decodes_our_recording(sample, tmp_path):
    """`rerun recording.mcap` opens a recording with rerun's own MCAP importer: every channel decoded by
    reflection from our schemas, none kept as raw bytes."""
    import subprocess

    from uwbcal.pipeline.viz.runlog import _rerun_exe

    path, _ = sample
    out = tmp_path / "rec.rrd"
    res = subprocess.run(
        [*_rerun_exe(), "mcap", "convert", str(path), "-o", str(out)], capture_output=True, text=True
    )
    assert res.returncode == 0, res.stderr[-500:]
    from rerun.chunk import RrdReader

    r = RrdReader(out)
    cols = {}
    for st in r.recordings():
        for ch in r.stream(store=st).to_chunks():
            if not ch.is_static and not ch.entity_path.startswith("/__"):
                cols.setdefault(ch.entity_path, set()).update(ch.to_record_batch().schema.names)
    assert {TOPIC_IMU, TOPIC_RANGE, TOPIC_ODOM, TOPIC_GT_POSE} <= set(cols)
    raw = sorted(e for e, c in cols.items() if "McapMessage:data" in c)
    assert raw == [], raw
    assert "uwbcal_msgs.msg.UwbRange:message" in cols[TOPIC_RANGE]


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
    # reported once, as data (info, run, metrics.json), never as a raw Python warning
    assert r.truncated and not caught and "truncated" in r.warnings[0]
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
    from uwbcal.convert.recording import MergedReader

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


def _hdr(T, t, frame):
    return T["std_msgs/msg/Header"](
        stamp=T["builtin_interfaces/msg/Time"](sec=t // 10**9, nanosec=t % 10**9), frame_id=frame
    )


def test_hand_packed_layouts_are_byte_identical_to_rosbags():
    from uwbcal.convert import msgs

    ts = msgs.typestore()
    T = ts.types
    t = T0 + 123_456_789
    sec, nsec = divmod(t, 10**9)
    v3 = lambda v: T["geometry_msgs/msg/Vector3"](x=v[0], y=v[1], z=v[2])  # noqa: E731
    pt = lambda v: T["geometry_msgs/msg/Point"](x=v[0], y=v[1], z=v[2])  # noqa: E731
    qt = lambda q: T["geometry_msgs/msg/Quaternion"](x=q[0], y=q[1], z=q[2], w=q[3])  # noqa: E731
    g, a, p, q = [0.1, -2.0, 3.5], [4.0, 5.25, -9.81], [1.0, 2.0, 3.0], [0.5, 0.5, -0.5, 0.5]
    cov = np.arange(36.0)
    imu = T[msgs.IMU](
        header=_hdr(T, t, "imu"),
        orientation=qt([0.0, 0.0, 0.0, 1.0]),
        orientation_covariance=np.r_[-1.0, np.zeros(8)],
        angular_velocity=v3(g),
        angular_velocity_covariance=np.zeros(9),
        linear_acceleration=v3(a),
        linear_acceleration_covariance=np.zeros(9),
    )
    f = msgs.imu_block(np.array([g]), np.array([a]))
    assert msgs.imu_layout("imu").pack_many(1, sec=[sec], nsec=[nsec], f=f)[0].tobytes() == bytes(
        ts.serialize_cdr(imu, msgs.IMU)
    )
    assert msgs.imu_layout("imu").pack_one(sec=sec, nsec=nsec, f=f[0]) == bytes(
        ts.serialize_cdr(imu, msgs.IMU)
    )
    rng = T[msgs.UWB_RANGE](
        header=_hdr(T, t, "tag3"), tag_id=3, antenna=2, anchor_id=4_000_000_001, distance=7.5
    )
    packed = msgs.range_layout("tag3").pack_one(
        sec=sec, nsec=nsec, tag=3, antenna=2, anchor=4_000_000_001, d=7.5
    )
    assert packed == bytes(ts.serialize_cdr(rng, msgs.UWB_RANGE))
    pose = T[msgs.POSE_STAMPED](
        header=_hdr(T, t, "world"), pose=T["geometry_msgs/msg/Pose"](position=pt(p), orientation=qt(q))
    )
    assert msgs.pose_layout("world").pack_one(sec=sec, nsec=nsec, f=p + q) == bytes(
        ts.serialize_cdr(pose, msgs.POSE_STAMPED)
    )
    point = T[msgs.POINT_STAMPED](header=_hdr(T, t, "world"), point=pt(p))
    assert msgs.point_layout("world").pack_one(sec=sec, nsec=nsec, f=p) == bytes(
        ts.serialize_cdr(point, msgs.POINT_STAMPED)
    )
    odo = T[msgs.ODOMETRY](
        header=_hdr(T, t, "world"),
        child_frame_id="body",
        pose=T["geometry_msgs/msg/PoseWithCovariance"](
            pose=T["geometry_msgs/msg/Pose"](position=pt(p), orientation=qt(q)), covariance=cov
        ),
        twist=T["geometry_msgs/msg/TwistWithCovariance"](
            twist=T["geometry_msgs/msg/Twist"](linear=v3(a), angular=v3(g)), covariance=np.zeros(36)
        ),
    )
    fo = np.r_[p, q, cov, a, g, np.zeros(36)]
    assert msgs.odom_layout("world", "body").pack_one(sec=sec, nsec=nsec, f=fo) == bytes(
        ts.serialize_cdr(odo, msgs.ODOMETRY)
    )


def test_messages_are_decoded_by_rosbags(sample):
    path, d = sample
    r = RecordingReader(path)
    imu = [m for _, _, m in r.messages([TOPIC_IMU])]
    assert len(imu) == 400 and imu[7].angular_velocity.y == d["gyro"][7, 1]
    assert imu[7].orientation.w == 1.0 and imu[7].header.frame_id == "imu"
    ranges = [m for _, _, m in r.messages([TOPIC_RANGE])]
    assert [m.anchor_id for m in ranges] == list(d["anchor"]) and ranges[0].header.frame_id == "tag7"
    ((_, _, odo),) = r.messages([TOPIC_ODOM])
    np.testing.assert_array_equal(odo.pose.covariance, d["cov"].reshape(-1))
    assert odo.child_frame_id == "body"


def test_time_order_and_filters_match_the_mcap_reader(tmp_path):
    """Several topics written as whole batches into many small chunks: same order as mcap's own index merge."""
    path = tmp_path / "order.mcap"
    n = 3000
    t = T0 + np.arange(n, dtype=np.int64) * 5_000_000
    rng = np.random.default_rng(1)
    with RecordingWriter(path, chunk_size=16 * 1024) as w:
        w.write_range_batch(t[::7] + 1, rng.integers(0, 3, len(t[::7])), 0, 9, rng.uniform(1, 9, len(t[::7])))
        w.write_pose_batch(
            t[::2] + 2, rng.normal(size=(len(t[::2]), 3)), np.tile([0, 0, 0, 1.0], (len(t[::2]), 1))
        )
        w.write_imu_batch(t, rng.normal(size=(n, 3)), rng.normal(size=(n, 3)))
        for k in range(0, n, 100):
            w.write_features(int(t[k]) + 3, [k], [[1.0, 2.0]])
    r = RecordingReader(path)
    ours = [(topic, ts) for topic, ts, _ in r.messages(raw=True)]
    with open(path, "rb") as f:
        ref = [(c.topic, m.log_time) for _, c, m in make_reader(f).iter_messages(log_time_order=True)]
    assert ours == ref
    lo, hi = int(t[1000]), int(t[2000])
    sub = [(topic, ts) for topic, ts, _ in r.messages([TOPIC_IMU, TOPIC_RANGE], lo, hi, raw=True)]
    assert sub == [x for x in ref if x[0] in (TOPIC_IMU, TOPIC_RANGE) and lo <= x[1] < hi]
    imu = r.read_imu(start_ns=lo, end_ns=hi)
    np.testing.assert_array_equal(imu.t_ns, t[1000:2000])
    rr = r.read_ranges(start_ns=lo, end_ns=hi)
    np.testing.assert_array_equal(rr.t_ns, [x[1] for x in sub if x[0] == TOPIC_RANGE])
    assert [f[0] for f in r.iter_features(start_ns=lo, end_ns=hi)] == list(t[1000:2000:100] + 3)
    np.testing.assert_array_equal(r.header_stamps(TOPIC_RANGE), t[::7] + 1)  # mixed tags keep writing order
    assert {(m.tag_id, m.header.frame_id) for _, _, m in r.messages([TOPIC_RANGE])} == {
        (k, f"tag{k}") for k in range(3)
    }
    info = r.topics()
    assert info[TOPIC_RANGE].count == len(t[::7]) and info[TOPIC_RANGE].end_ns == t[::7][-1] + 1
    assert info["/cam0/features"].msgtype == "uwbcal_msgs/msg/FeatureTracks"


@pytest.mark.parametrize("fraction", [0.3, 0.75, 0.999])
def test_truncated_mixed_file_recovers_a_consistent_prefix(tmp_path, fraction):
    path = tmp_path / "mixed.mcap"
    n = 6000
    t = T0 + np.arange(n, dtype=np.int64) * 5_000_000
    g = np.random.default_rng(2).normal(size=(n, 3))
    with RecordingWriter(path, chunk_size=32 * 1024) as w:
        for k in range(0, n, 500):  # interleaved writing, as a converter does
            w.write_imu_batch(t[k : k + 500], g[k : k + 500], g[k : k + 500])
            w.write_range_batch(t[k : k + 500 : 10], 1, 0, 4, np.ones(50))
        w.set_metadata(META_CALIBRATION, {"imu": {"rate_hz": 200.0}})
    data = path.read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: int(len(data) * fraction)])
    r = RecordingReader(cut)
    assert re.search(r"cut\.mcap: truncated recording .* recovered \d+ messages", r.warnings[0])
    imu = r.read_imu()
    k = len(imu)
    assert 0 < k < n if fraction < 0.9 else k == n  # 0.999: only the summary is cut off
    np.testing.assert_array_equal(imu.t_ns, t[:k])
    np.testing.assert_array_equal(imu.gyro, g[:k])
    assert r.topics()[TOPIC_IMU].count == k and r.topics()[TOPIC_IMU].end_ns == t[k - 1]
    assert len(r.read_ranges()) > 0
    stamps = [ts for _, ts, _ in r.messages(raw=True)]
    assert stamps == sorted(stamps)


def test_cut_header_and_garbage_after_magic_are_input_errors(tmp_path, sample):
    path, _ = sample
    head = tmp_path / "head.mcap"
    head.write_bytes(path.read_bytes()[:20])
    with pytest.raises(InputError, match="head.mcap: no readable MCAP records"):
        RecordingReader(head)
    junk = tmp_path / "junk.mcap"
    junk.write_bytes(b"\x89MCAP0\r\n" + np.random.default_rng(3).bytes(5000))
    with pytest.raises(InputError, match="junk.mcap"):
        RecordingReader(junk)


def test_empty_recording_and_odometry_twist(tmp_path):
    empty = tmp_path / "empty.mcap"
    with RecordingWriter(empty):
        pass
    r = RecordingReader(empty)
    assert r.topics() == {} and list(r.messages()) == [] and r.calibration == {}
    path = tmp_path / "odo.mcap"
    covs = np.stack([np.diag(np.full(6, k + 1.0)) for k in range(5)])
    t = T0 + np.arange(5, dtype=np.int64) * 10**8
    with RecordingWriter(path) as w:
        w.write_odometry_batch(
            t, np.ones((5, 3)), np.tile([0, 0, 0, 1.0], (5, 1)), covs, topic="/vio/odometry"
        )
        w.write_odometry(int(t[-1]) + 1, [1, 2, 3], [0, 0, 0, 1], covs[0], v=[0.5, 0, 0], w=[0, 0, 0.1])
    r = RecordingReader(path)
    np.testing.assert_array_equal(r.read_odometry("/vio/odometry").cov, covs)
    ((_, _, m),) = r.messages([TOPIC_ODOM])
    assert (m.twist.twist.linear.x, m.twist.twist.angular.z) == (0.5, 0.1)


def test_equal_stamps_keep_writing_order_across_chunks(tmp_path):
    """IMU and feature frames share stamps and live in different, overlapping chunks: ties go in writing order."""
    path = tmp_path / "ties.mcap"
    n = 4000
    t = T0 + np.arange(n, dtype=np.int64) * 5_000_000
    with RecordingWriter(path, chunk_size=8 * 1024) as w:
        w.write_imu_batch(t[: n // 2], np.zeros((n // 2, 3)), np.zeros((n // 2, 3)))
        for k in range(0, n, 40):
            w.write_features(int(t[k]), np.arange(20), np.ones((20, 2)))
        w.write_imu_batch(t[n // 2 :], np.zeros((n // 2, 3)), np.zeros((n // 2, 3)))
    ours = [(topic, ts) for topic, ts, _ in RecordingReader(path).messages(raw=True)]
    with open(path, "rb") as f:
        ref = [(c.topic, m.log_time) for _, c, m in make_reader(f).iter_messages(log_time_order=True)]
    assert ours == ref
    first_half = [topic for topic, ts in ours if ts == t[40]]
    second_half = [topic for topic, ts in ours if ts == t[n // 2 + 40]]
    assert first_half == [TOPIC_IMU, TOPIC_FEATURES] and second_half == [TOPIC_FEATURES, TOPIC_IMU]
