"""`uwbcal convert bag`: ROS 1, ROS 2 .db3 and ROS 2 .mcap bags written here with rosbags' writers, each UWB
message type (and both Nooploop schema versions), decoded back value for value; every message accounted for."""

from __future__ import annotations

import sqlite3
from pathlib import Path

import numpy as np
import pytest
from rosbags.typesys import Stores, get_types_from_msg, get_typestore
from typer.testing import CliRunner

from uwbcal.cli import app
from uwbcal.convert import uwb_msgs
from uwbcal.convert.bag import bag_info, convert_bag, detect_topics
from uwbcal.convert.recording import RecordingReader
from uwbcal.pipeline.core.errors import InputError

FORMATS = ("ros1", "db3", "mcap")
T0 = 1_700_000_000_000_000_000
N = 6  # messages per topic


def _store(ros1: bool, variant: str, msgtype: str):
    """A type store with ``msgtype`` registered from the shipped definitions of ``variant``."""
    store = get_typestore(Stores.ROS1_NOETIC if ros1 else Stores.ROS2_HUMBLE)
    types: dict = {}
    for name, text in uwb_msgs._definitions_for(variant, msgtype).items():
        types.update(get_types_from_msg(text, name))
    store.register(types)
    return store


def _header(T, t_ns: int, frame: str = "uwb"):
    H = T["std_msgs/msg/Header"]
    seq = {"seq": 0} if "seq" in H.__dataclass_fields__ else {}  # ROS 1
    return H(
        **seq, stamp=T["builtin_interfaces/msg/Time"](sec=t_ns // 10**9, nanosec=t_ns % 10**9), frame_id=frame
    )


def _point(T, x=0.0, y=0.0, z=0.0):
    return T["geometry_msgs/msg/Point"](x=x, y=y, z=z)


def make_uwb(kind: str, T, i: int, t_ns: int):
    """One message of each UWB kind and the ranges (tag, antenna, anchor, distance) it must give."""
    d = 1.0 + 0.25 * i + 1e-3 * np.float32(0.5)
    if kind == "uwb_driver":
        m = T["uwb_driver/msg/UwbRange"](
            header=_header(T, t_ns), msgId=i, requester_id=200, responder_id=100 + i % 3,
            requester_idx=0, responder_idx=0, range_status=0, antenna=i % 2, stopwatch_time=0,
            distance=np.float32(d), coarse_range=0.0, filtered_range=0.0, distance_err=0.0,
            coarse_range_err=0.0, filtered_range_err=0.0, distance_dot=0.0, distance_dot_err=0.0,
            range_meas_type=0, requester_LED_flag=0, responder_LED_flag=0, noise=0, vPeak=0,
            coarse_tof_in_bins=0, uwb_time=0, requester_location=_point(T), responder_location=_point(T),
            rqst_antenna_offset=_point(T), rspd_antenna_offset=_point(T),
        )  # fmt: skip
        return m, [(t_ns, 200, i % 2, 100 + i % 3, float(np.float32(d)))]
    if kind.startswith("nodeframe"):
        frame3 = kind.startswith("nodeframe3")
        legacy = kind.endswith("legacy")
        pkg = "nlink_parser"
        name = f"{pkg}/msg/LinktrackNodeframe{3 if frame3 else 2}"
        node_t = T[f"{pkg}/msg/LinktrackNode2"]
        ds = [np.float32(d + k) for k in range(3)]
        if legacy:
            nodes = [node_t(role=1, id=k, dis=x, fpRssi=-80.0, rxRssi=-78.0) for k, x in enumerate(ds)]
        else:
            nodes = [node_t(role=1, id=k, dis=x, fp_rssi=-80.0, rx_rssi=-78.0) for k, x in enumerate(ds)]
        if i == N - 1:
            nodes = []  # a frame without ranges: dropped with a reason
        f = np.zeros(3, np.float32)
        if frame3:
            kw = {"localTime": i, "systemTime": i} if legacy else {"local_time": i, "system_time": i}
            m = T[name](role=2, id=7, voltage=5.0, **kw, **({"node": nodes} if legacy else {"nodes": nodes}))
            has_stamp = False
        elif legacy:
            m = T[name](role=2, id=7, localTime=i, systemTime=i, voltage=5.0, pos=f, eop=f, vel=f, angle=f,
                        q=np.zeros(4, np.float32), imuGyro=f, imuAcc=f, node=nodes)  # fmt: skip
            has_stamp = False
        else:
            m = T[name](header=_header(T, t_ns), unix_timestamp=0, role=2, id=7, local_time=i, system_time=i,
                        voltage=5.0, pos_3d=f, eop_3d=f, vel_3d=f, angle_3d=f,
                        quaternion=np.zeros(4, np.float32), imu_gyro_3d=f, imu_acc_3d=f, nodes=nodes)  # fmt: skip
            has_stamp = True
        t_exp = t_ns if has_stamp else t_ns + 5_000_000  # stamp-less frames take the bag time (t + 5 ms)
        return m, [(t_exp, 7, 0, k, float(x)) for k, x in enumerate(ds)] if nodes else []
    if kind == "twr":
        anchor_first = i % 2 == 0
        m = T["uwb_msgs/msg/TwoWayRangeStamped"](
            header=_header(T, t_ns), range_raw=d, range_corr=d - 0.1, rr=0.01,
            uwb_id1=10 + i if anchor_first else 3, uwb_id2=3 if anchor_first else 10 + i,
            type_id1=ord("A") if anchor_first else ord("T"), type_id2=ord("T") if anchor_first else ord("A"),
            los=True,
        )  # fmt: skip
        return m, [(t_ns, 3, 0, 10 + i, d)]
    if kind == "range":
        m = T["sensor_msgs/msg/Range"](
            header=_header(T, t_ns, f"anchor_{40 + i}"), radiation_type=2, field_of_view=0.0,
            min_range=0.1, max_range=100.0, range=np.float32(d),
        )  # fmt: skip
        return m, [(t_ns, 0, 0, 40 + i, float(np.float32(d)))]
    raise ValueError(kind)


KINDS = {
    "uwb_driver": ("uwb_driver/msg/UwbRange", "current"),
    "nodeframe2": ("nlink_parser/msg/LinktrackNodeframe2", "current"),
    "nodeframe2-legacy": ("nlink_parser/msg/LinktrackNodeframe2", "legacy"),
    "nodeframe3": ("nlink_parser/msg/LinktrackNodeframe3", "current"),
    "nodeframe3-legacy": ("nlink_parser/msg/LinktrackNodeframe3", "legacy"),
    "twr": ("uwb_msgs/msg/TwoWayRangeStamped", "current"),
    "range": ("sensor_msgs/msg/Range", "current"),
}


def write_bag(fmt: str, path: Path, kind: str, *, strip_uwb_definition: bool = False) -> tuple[Path, list]:
    """A bag with /imu, /uwb/<kind> and an unmapped /chatter; returns its path and the expected ranges."""
    msgtype, variant = KINDS[kind]
    ros1 = fmt == "ros1"
    store = _store(ros1, variant, msgtype)
    T = store.types
    expected = []
    msgs = []
    for i in range(N):
        t = T0 + i * 100_000_000
        imu = T["sensor_msgs/msg/Imu"](
            header=_header(T, t, "imu"), orientation=T["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0),
            orientation_covariance=np.zeros(9), angular_velocity=T["geometry_msgs/msg/Vector3"](x=0.1 * i, y=0.2, z=0.3),
            angular_velocity_covariance=np.zeros(9),
            linear_acceleration=T["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=9.81 + i),
            linear_acceleration_covariance=np.zeros(9),
        )  # fmt: skip
        msgs.append(("/imu", "sensor_msgs/msg/Imu", t, imu))
        m, exp = make_uwb(kind, T, i, t)
        msgs.append((f"/uwb/{kind}", msgtype, t + 5_000_000, m))
        expected += exp
        msgs.append(("/chatter", "std_msgs/msg/String", t, T["std_msgs/msg/String"](data=f"hello {i}")))
    if ros1:
        from rosbags.rosbag1 import Writer

        bag = path.with_suffix(".bag")
        with Writer(bag) as w:
            conns = {}
            for topic, ty, t, m in msgs:
                if topic not in conns:
                    conns[topic] = w.add_connection(topic, ty, typestore=store)
                w.write(conns[topic], t, store.serialize_ros1(m, ty))
        return bag, expected
    from rosbags.rosbag2 import StoragePlugin, Writer

    plugin = StoragePlugin.MCAP if fmt == "mcap" else StoragePlugin.SQLITE3
    with Writer(path, version=9, storage_plugin=plugin) as w:
        conns = {}
        for topic, ty, t, m in msgs:
            if topic not in conns:
                conns[topic] = w.add_connection(topic, ty, typestore=store)
            w.write(conns[topic], t, store.serialize_cdr(m, ty))
    if strip_uwb_definition:  # an older .db3: no message definition for the custom type
        db = next(path.glob("*.db3"))
        with sqlite3.connect(db) as con:
            con.execute("DELETE FROM message_definitions WHERE topic_type = ?", (msgtype,))
    return path, expected


def read_back(out: Path):
    r = RecordingReader(out)
    rng = r.read_ranges("/uwb/range")
    got = sorted(
        zip(
            rng.t_ns.tolist(), rng.tag.tolist(), rng.antenna.tolist(), rng.anchor.tolist(),
            rng.distance.tolist(), strict=True,
        )
    )  # fmt: skip
    return r, got


@pytest.mark.parametrize("fmt", FORMATS)
@pytest.mark.parametrize("kind", list(KINDS))
def test_round_trip_every_uwb_type(tmp_path, fmt, kind):
    bag, expected = write_bag(fmt, tmp_path / f"in_{fmt}", kind)
    out = tmp_path / "rec.mcap"
    convert_bag(bag, out, uwb=[f"/uwb/{kind}"] if kind == "range" else None)
    r, got = read_back(out)
    assert got == sorted(expected)  # value for value (float32 sources compared at their float32 value)
    imu = r.read_imu("/imu")
    assert imu.t_ns.tolist() == [T0 + i * 100_000_000 for i in range(N)]
    np.testing.assert_array_equal(imu.gyro[:, 0], 0.1 * np.arange(N))
    np.testing.assert_array_equal(imu.acc[:, 2], 9.81 + np.arange(N))
    src = r.source
    msgs = src["messages"]
    # every message accounted for: converted or dropped with a reason and count
    for topic, acc in msgs.items():
        assert acc["converted"] + acc["dropped"] == acc["count"] == N, (topic, acc)
    dropped = {(d["topic"], d["reason"]): d["count"] for d in src["dropped"]}
    assert dropped[("/chatter", "topic not mapped (type std_msgs/msg/String)")] == N
    if kind.startswith("nodeframe"):
        assert dropped[(f"/uwb/{kind}", "frame without ranges (no nodes)")] == 1
    assert sum(dropped.values()) == sum(a["dropped"] for a in msgs.values())
    assert src["format"] == {"ros1": "rosbag1", "db3": "rosbag2-sqlite3", "mcap": "rosbag2-mcap"}[fmt]


@pytest.mark.parametrize(
    "kind", ["nodeframe2", "nodeframe2-legacy", "nodeframe3-legacy", "twr", "uwb_driver"]
)
def test_db3_without_definitions_uses_the_shipped_ones(tmp_path, kind):
    bag, expected = write_bag("db3", tmp_path / "old", kind, strip_uwb_definition=True)
    out = tmp_path / "rec.mcap"
    convert_bag(bag, out)
    _, got = read_back(out)
    assert got == sorted(expected)
    assert "shipped one used" in bag_info(bag)


def test_unknown_topics_reported_by_info(tmp_path):
    bag, _ = write_bag("ros1", tmp_path / "b", "twr")
    text = bag_info(bag)
    assert "/chatter" in text and "not mapped: /chatter" in text
    assert "/uwb/twr" in text and "uwb" in text
    out = tmp_path / "rec.mcap"
    res = CliRunner().invoke(app, ["convert", "bag", str(bag), "-o", str(out)])
    assert res.exit_code == 0, res.output
    res = CliRunner().invoke(app, ["info", str(out)])
    assert res.exit_code == 0, res.output
    assert "bag /chatter (std_msgs/msg/String): 6 -> not mapped, 0 converted, 6 dropped" in res.output
    res = CliRunner().invoke(app, ["info", str(bag)])
    assert res.exit_code == 0 and "not mapped: /chatter" in res.output


def test_bad_bag_exits_2_with_one_line(tmp_path):
    bad = tmp_path / "broken.bag"
    bad.write_bytes(b"#ROSBAG V2.0\n" + b"\x00garbage" * 10)
    res = CliRunner().invoke(app, ["convert", "bag", str(bad), "-o", str(tmp_path / "x.mcap")])
    assert res.exit_code == 2
    lines = res.output.strip().splitlines()
    assert len(lines) == 1 and str(bad) in lines[0] and "unreadable ROS bag" in lines[0]
    bad2 = tmp_path / "broken.db3"
    bad2.write_bytes(b"not sqlite" * 20)
    res = CliRunner().invoke(app, ["convert", "bag", str(bad2), "-o", str(tmp_path / "y.mcap")])
    assert res.exit_code == 2 and len(res.output.strip().splitlines()) == 1


def test_given_topic_must_exist(tmp_path):
    bag, _ = write_bag("mcap", tmp_path / "m", "range")
    res = CliRunner().invoke(
        app, ["convert", "bag", str(bag), "--imu", "/nope", "-o", str(tmp_path / "x.mcap")]
    )
    assert res.exit_code == 2 and "--imu /nope: no such topic" in res.output


def test_detect_topics_by_type_and_name():
    topics = {
        "/imu0": ("sensor_msgs/msg/Imu", 100),
        "/right/image_raw": ("sensor_msgs/msg/Image", 10),
        "/left/image_raw": ("sensor_msgs/msg/Image", 10),
        "/vicon/body": ("geometry_msgs/msg/TransformStamped", 50),
        "/odom": ("nav_msgs/msg/Odometry", 50),
        "/sonar": ("sensor_msgs/msg/Range", 50),
        "/nlink_linktrack_nodeframe2": ("nlink_parser/msg/LinktrackNodeframe2", 50),
    }
    m = detect_topics(topics)
    assert (m.imu, m.cam0, m.cam1) == ("/imu0", "/left/image_raw", "/right/image_raw")
    assert m.groundtruth == "/vicon/body" and m.odometry == "/odom"
    assert m.uwb == ["/nlink_linktrack_nodeframe2"]  # a Range topic without 'uwb' in its name is not taken


@pytest.mark.parametrize("fmt", ["ros1", "mcap"])
def test_images_odometry_groundtruth(tmp_path, fmt):
    ros1 = fmt == "ros1"
    store = get_typestore(Stores.ROS1_NOETIC if ros1 else Stores.ROS2_HUMBLE)
    T = store.types
    rng = np.random.default_rng(0)
    gray = rng.integers(0, 255, (4, 5), dtype=np.uint8)
    rgb = rng.integers(0, 255, (4, 5, 3), dtype=np.uint8)
    cov = np.diag([1.0, 2.0, 3.0, 4.0, 5.0, 6.0]).reshape(-1)
    q = T["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=np.sin(0.25), w=np.cos(0.25))
    pose = T["geometry_msgs/msg/Pose"](position=_point(T, 1.0, 2.0, 3.0), orientation=q)
    msgs = [
        ("/cam0/image_raw", "sensor_msgs/msg/Image", T["sensor_msgs/msg/Image"](
            header=_header(T, T0, "cam0"), height=4, width=5, encoding="mono8", is_bigendian=0, step=5,
            data=gray.reshape(-1))),
        ("/cam1/image_raw", "sensor_msgs/msg/Image", T["sensor_msgs/msg/Image"](
            header=_header(T, T0, "cam1"), height=4, width=5, encoding="rgb8", is_bigendian=0, step=15,
            data=rgb.reshape(-1))),
        ("/odom", "nav_msgs/msg/Odometry", T["nav_msgs/msg/Odometry"](
            header=_header(T, T0, "odom"), child_frame_id="base",
            pose=T["geometry_msgs/msg/PoseWithCovariance"](pose=pose, covariance=cov),
            twist=T["geometry_msgs/msg/TwistWithCovariance"](
                twist=T["geometry_msgs/msg/Twist"](
                    linear=T["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0),
                    angular=T["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0)),
                covariance=np.zeros(36)))),
        ("/vicon/body", "geometry_msgs/msg/PoseStamped", T["geometry_msgs/msg/PoseStamped"](
            header=_header(T, T0, "world"), pose=pose)),
    ]  # fmt: skip
    if ros1:
        from rosbags.rosbag1 import Writer

        bag = tmp_path / "b.bag"
        with Writer(bag) as w:
            for topic, ty, m in msgs:
                w.write(w.add_connection(topic, ty, typestore=store), T0, store.serialize_ros1(m, ty))
    else:
        from rosbags.rosbag2 import StoragePlugin, Writer

        bag = tmp_path / "b"
        with Writer(bag, version=9, storage_plugin=StoragePlugin.MCAP) as w:
            for topic, ty, m in msgs:
                w.write(w.add_connection(topic, ty, typestore=store), T0, store.serialize_cdr(m, ty))
    out = tmp_path / "rec.mcap"
    convert_bag(bag, out)
    r = RecordingReader(out)
    imgs = {topic: next(iter(r.iter_images(topic)))[1] for topic in ("/cam0/image_raw", "/cam1/image_raw")}
    np.testing.assert_array_equal(imgs["/cam0/image_raw"], gray)
    import cv2

    np.testing.assert_array_equal(imgs["/cam1/image_raw"], cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY))
    od = r.read_odometry("/odometry")
    np.testing.assert_array_equal(od.p[0], [1.0, 2.0, 3.0])
    np.testing.assert_allclose(od.q_xyzw[0], [0.0, 0.0, np.sin(0.25), np.cos(0.25)], atol=1e-15)
    np.testing.assert_array_equal(od.cov[0], cov.reshape(6, 6))
    gt = r.read_poses("/groundtruth/pose")
    np.testing.assert_array_equal(gt.p[0], [1.0, 2.0, 3.0])
    assert r.source["topic_map"]["/vicon/body"] == "groundtruth"


def test_trim_and_anchor_truth(tmp_path):
    """--start/--end keep the messages in the span (the rest counted as dropped); --anchors-truth is the
    recording's anchor truth in the ground truth's frame."""
    bag, _ = write_bag("mcap", tmp_path / "in", "range")
    csv = tmp_path / "anchors.csv"
    csv.write_text("anchor,x,y,z\n10,1.0,2.0,3.0\n11,-1.0,0.5,2.0\n")
    out = tmp_path / "rec.mcap"
    convert_bag(bag, out, uwb=["/uwb/range"], anchors_truth=csv, start_s=0.25, end_s=0.65)
    r = RecordingReader(out)
    t = r.read_imu("/imu").t_ns
    assert t.tolist() == [T0 + i * 100_000_000 for i in (3, 4, 5)]
    acc = r.source["messages"]["/imu"]
    assert acc["converted"] == 3 and acc["dropped"] == N - 3
    truth = r.truth
    assert truth["kind"] == "surveyed" and truth["anchors_frame"] == "world"
    assert truth["anchors"]["10"]["position"] == [1.0, 2.0, 3.0]
    with pytest.raises(InputError, match="--end"):
        convert_bag(bag, tmp_path / "bad.mcap", start_s=0.5, end_s=0.2)
