"""NTU-VIRAL converters: the real eee_01 CSV folder (every row accounted for) and synthetic ROS1 bags written from
the real CSV rows with the real uwb_driver/UwbRange definition, compared value by value."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest

from uwbcal.benchmarks.convert_bag import synthetic_image
from uwbcal.convert.ntu_viral import (
    PRISM_LEVER_ARM,
    UWB_RANGE_MSG,
    UWB_RANGE_ROS1,
    convert_ntu_viral,
    ros1_typestore,
)
from uwbcal.convert.recording import RecordingReader
from uwbcal.convert.sources import read_ranges_csv
from uwbcal.pipeline.core.errors import InputError


def _seq(data_dir: Path) -> Path:
    return data_dir / "ntu_viral" / "eee_01"


def test_embedded_msg_matches_meta(data_dir):
    text = (data_dir / "ntu_viral/meta/uwb_driver/msg/UwbRange.msg").read_text()
    fields = [ln.split("#")[0].split() for ln in text.splitlines() if ln.split("#")[0].strip()]
    assert fields == [ln.split() for ln in UWB_RANGE_MSG.splitlines()]
    assert ros1_typestore().generate_msgdef(UWB_RANGE_ROS1)[1] == "1065ab177c929b8c39cb8fde961d3e9e"


def test_eee01_folder_every_row_accounted(data_dir, eee_01):
    out, text = eee_01  # the session's one conversion (conftest)
    rec = RecordingReader(out)
    src = rec.source
    rows = len((_seq(data_dir) / "uwb_ranges.csv").read_text().strip().splitlines()) - 1
    dropped = sum(d["count"] for d in src["dropped"] if d["topic"] == "/uwb/range")
    r = rec.read_ranges()
    assert len(r) + dropped == rows == src["range_rows"] == 23436
    ref, unit = read_ranges_csv(_seq(data_dir) / "uwb_ranges.csv")
    assert unit == "ns"
    o = np.lexsort([ref.anchor, ref.antenna, ref.tag, ref.t_ns])
    np.testing.assert_array_equal(r.t_ns, ref.t_ns[o])
    np.testing.assert_array_equal(r.anchor, ref.anchor[o])
    np.testing.assert_array_equal(r.distance, ref.distance[o])
    assert set(np.unique(r.anchor)) == {100, 101, 102} and "out-of-order" in text
    cal = rec.calibration
    assert cal["uwb"]["gamma_prior"]["mean"] == pytest.approx(0.75)
    assert cal["uwb"]["tags"]["201"]["antennas"] == [[-0.6, 0.45, 0.0], [-0.6, -0.45, 0.0]]
    assert cal["groundtruth"] == {"lever_arm": PRISM_LEVER_ARM, "frame": "prism"}
    odom = rec.read_odometry()
    assert len(odom.t_ns) == 3976
    assert odom.t_ns[0] == 1609059014168936729
    np.testing.assert_allclose(odom.p[0], [0.010072, -0.003225, 0.001989])
    np.testing.assert_allclose(np.diag(odom.cov[0]), [0.03**2] * 3 + [np.deg2rad(0.5) ** 2] * 3)
    gt = rec.read_positions()
    assert len(gt.t_ns) == 6616 and gt.t_ns[0] == 1609059060109753943


def test_folder_bad_ranges_dropped_with_reasons(data_dir, tmp_path):
    seq = tmp_path / "seq"
    seq.mkdir()
    lines = (_seq(data_dir) / "uwb_ranges.csv").read_text().splitlines()[:201]
    bad = lines[5].split(",")
    extra = [
        ",".join(bad[:4] + ["nan"]),
        ",".join(bad[:4] + ["-1.0"]),
        ",".join(bad[:4] + ["1500.0"]),
        lines[7],
    ]
    (seq / "uwb_ranges.csv").write_text("\n".join(lines + extra) + "\n")
    shutil.copy(
        data_dir / "ntu_viral/uwb_antennas.yaml", tmp_path / "uwb_antennas.yaml"
    )  # found in the parent
    out = tmp_path / "b.mcap"
    text = convert_ntu_viral(seq, out)
    rec = RecordingReader(out)
    reasons = {d["reason"]: d["count"] for d in rec.source["dropped"]}
    assert reasons == {
        "distance NaN/inf": 1,
        "negative distance": 1,
        "absurd distance > 1000 m": 1,
        "duplicate stamp (kept the first)": 1,
    }
    assert len(rec.read_ranges()) == 200 and "no slict_odometry.csv" in text
    assert rec.calibration["uwb"]["gamma_prior"]["mean"] == pytest.approx(0.75)


def test_folder_errors(tmp_path):
    (tmp_path / "empty").mkdir()
    with pytest.raises(InputError, match="no uwb_ranges.csv"):
        convert_ntu_viral(tmp_path / "empty", tmp_path / "o.mcap")
    seq = tmp_path / "seq"
    seq.mkdir()
    (seq / "uwb_ranges.csv").write_text("time,tag,anchor,range\n1,2,3,4\n")
    with pytest.raises(
        InputError, match=r"uwb_ranges.csv: header: expected columns stamp,tag,antenna,anchor,distance"
    ):
        convert_ntu_viral(seq, tmp_path / "o.mcap")
    assert not (tmp_path / "o.mcap").exists()


# ---------------------------------------------------------------------------------------------------------------
# synthetic bag from the real rows
# ---------------------------------------------------------------------------------------------------------------
def _header(T, t, frame, seq=0):
    return T["std_msgs/msg/Header"](
        seq=seq,
        stamp=T["builtin_interfaces/msg/Time"](sec=int(t) // 1_000_000_000, nanosec=int(t) % 1_000_000_000),
        frame_id=frame,
    )


def _write_ntu_bag(
    bag: Path, data_dir: Path, n_ranges: int = 300, extra_topic: bool = True, damaged: tuple[int, ...] = ()
) -> dict:
    """A synthetic NTU-VIRAL bag from eee_01's ranges; the range and Leica messages numbered in ``damaged`` are
    written cut short (a corrupt message in an intact bag)."""
    from rosbags.rosbag1 import Writer

    ts = ros1_typestore()
    T = ts.types
    ref, _ = read_ranges_csv(_seq(data_dir) / "uwb_ranges.csv")
    rsel = slice(0, n_ranges)
    t_r = ref.t_ns[rsel]
    t0, t1 = int(t_r.min()), int(t_r.max())
    leica = np.loadtxt(_seq(data_dir) / "leica_prism.csv", delimiter=",", skiprows=1, dtype=str)[:40]
    t_l = leica[:, 2].astype(np.int64) - int(leica[0, 2]) + t0  # shift the Leica rows into the range window
    p_l = leica[:, 3:6].astype(float)
    rng = np.random.default_rng(3)
    t_imu = np.arange(t0, t1, 2_597_403)  # 385 Hz
    imu = rng.normal(size=(len(t_imu), 6))
    t_img = np.arange(t0, t1, 100_000_000)
    Point = T["geometry_msgs/msg/Point"]
    with Writer(bag) as w:
        c_r = w.add_connection("/uwb_endorange_info", UWB_RANGE_ROS1, typestore=ts)
        c_i = w.add_connection("/imu/imu", "sensor_msgs/msg/Imu", typestore=ts)
        c_l = w.add_connection("/leica/pose/relative", "geometry_msgs/msg/PoseStamped", typestore=ts)
        c_c = [
            w.add_connection(t, "sensor_msgs/msg/Image", typestore=ts)
            for t in ("/left/image_raw", "/right/image_raw")
        ]
        c_x = (
            w.add_connection("/uwb_exorange_info", "std_msgs/msg/String", typestore=ts)
            if extra_topic
            else None
        )
        for k in range(n_ranges):
            m = T[UWB_RANGE_ROS1](
                header=_header(T, ref.t_ns[k], "uwb", k),
                msgId=k,
                requester_id=int(ref.tag[k]),
                responder_id=int(ref.anchor[k]),
                requester_idx=9,
                responder_idx=1,
                range_status=0,
                antenna=int(ref.antenna[k]),
                stopwatch_time=3,
                distance=np.float32(ref.distance[k]),
                coarse_range=0.0,
                filtered_range=0.0,
                distance_err=0.024,
                coarse_range_err=0.0,
                filtered_range_err=0.0,
                distance_dot=0.0,
                distance_dot_err=0.0,
                range_meas_type=7,
                requester_LED_flag=0,
                responder_LED_flag=0,
                noise=0,
                vPeak=0,
                coarse_tof_in_bins=0,
                uwb_time=0,
                requester_location=Point(x=99999.0, y=99999.0, z=99999.0),
                responder_location=Point(x=31.3815, y=0.0, z=1.5),
                rqst_antenna_offset=Point(x=-0.6, y=0.45, z=0.0),
                rspd_antenna_offset=Point(x=0.0, y=0.0, z=0.0),
            )
            raw = ts.serialize_ros1(m, UWB_RANGE_ROS1)
            w.write(c_r, int(ref.t_ns[k]) + 700_000, raw[:20] if k in damaged else raw)
        V3 = T["geometry_msgs/msg/Vector3"]
        for k, t in enumerate(t_imu):
            m = T["sensor_msgs/msg/Imu"](
                header=_header(T, t, "imu", k),
                orientation=T["geometry_msgs/msg/Quaternion"](x=0, y=0, z=0, w=1),
                orientation_covariance=np.zeros(9),
                angular_velocity=V3(*imu[k, :3]),
                angular_velocity_covariance=np.zeros(9),
                linear_acceleration=V3(*imu[k, 3:]),
                linear_acceleration_covariance=np.zeros(9),
            )
            w.write(c_i, int(t) + 1000, ts.serialize_ros1(m, "sensor_msgs/msg/Imu"))
        for k, t in enumerate(t_l):
            m = T["geometry_msgs/msg/PoseStamped"](
                header=_header(T, t, "leica", k),
                pose=T["geometry_msgs/msg/Pose"](
                    position=Point(*p_l[k]), orientation=T["geometry_msgs/msg/Quaternion"](x=0, y=0, z=0, w=1)
                ),
            )
            raw = ts.serialize_ros1(m, "geometry_msgs/msg/PoseStamped")
            w.write(c_l, int(t) + 500_000, raw[:30] if k in damaged else raw)
        for k, t in enumerate(t_img):
            for cam, conn in enumerate(c_c):
                img = synthetic_image(2 * k + cam, 32, 24)
                m = T["sensor_msgs/msg/Image"](
                    header=_header(T, t, "cam", k),
                    height=24,
                    width=32,
                    encoding="mono8",
                    is_bigendian=0,
                    step=32,
                    data=img.reshape(-1),
                )
                w.write(conn, int(t) + 3_000_000, ts.serialize_ros1(m, "sensor_msgs/msg/Image"))
            if c_x is not None:
                w.write(
                    c_x,
                    int(t),
                    ts.serialize_ros1(T["std_msgs/msg/String"](data="echo"), "std_msgs/msg/String"),
                )
    return {"ranges": ref, "n": n_ranges, "t_imu": t_imu, "imu": imu, "t_l": t_l, "p_l": p_l, "t_img": t_img}


def test_bag_roundtrip(data_dir, tmp_path):
    bag = tmp_path / "eee_01_synth.bag"
    ref = _write_ntu_bag(bag, data_dir)
    out = tmp_path / "b.mcap"
    text = convert_ntu_viral(bag, out, antennas=data_dir / "ntu_viral/uwb_antennas.yaml")
    rec = RecordingReader(out)
    r = rec.read_ranges()
    rr, n = ref["ranges"], ref["n"]
    o = np.argsort(rr.t_ns[:n], kind="stable")
    assert len(r) == n
    np.testing.assert_array_equal(r.t_ns, rr.t_ns[:n][o])
    np.testing.assert_array_equal(r.tag, rr.tag[:n][o])
    np.testing.assert_array_equal(r.antenna, rr.antenna[:n][o])
    np.testing.assert_array_equal(r.anchor, rr.anchor[:n][o])
    np.testing.assert_array_equal(r.distance, rr.distance[:n][o].astype(np.float32).astype(float))
    imu = rec.read_imu()
    np.testing.assert_array_equal(imu.t_ns, ref["t_imu"])
    np.testing.assert_array_equal(np.c_[imu.gyro, imu.acc], ref["imu"])
    pos = rec.read_positions()
    np.testing.assert_array_equal(pos.t_ns, ref["t_l"])
    np.testing.assert_array_equal(pos.p, ref["p_l"])
    for cam, topic in enumerate(("/cam0/image_raw", "/cam1/image_raw")):
        imgs = list(rec.iter_images(topic))
        assert [t for t, _ in imgs] == ref["t_img"].tolist()
        for k, (_, img) in enumerate(imgs):
            np.testing.assert_array_equal(img, synthetic_image(2 * k + cam, 32, 24))
    dropped = {d["topic"]: d for d in rec.source["dropped"]}
    assert dropped["/uwb_exorange_info"]["count"] == len(ref["t_img"])
    assert "anchors 100" in text
    cal = rec.calibration
    assert cal["uwb"]["gamma_prior"]["mean"] == pytest.approx(0.75)
    assert cal["cameras"]["cam0"]["T_imu_cam"][1][3] == pytest.approx(-0.12431302)  # left camera
    assert cal["groundtruth"]["frame"] == "prism"


def test_bag_damaged_messages_dropped_and_counted(data_dir, tmp_path):
    """A range and a Leica message cut short inside an intact bag: each dropped with its reason and counted,
    the rest converts."""
    bag = tmp_path / "d.bag"
    ref = _write_ntu_bag(bag, data_dir, n_ranges=50, extra_topic=False, damaged=(5,))
    convert_ntu_viral(bag, tmp_path / "d.mcap", antennas=data_dir / "ntu_viral/uwb_antennas.yaml")
    rec = RecordingReader(tmp_path / "d.mcap")
    undecodable = {d["topic"]: d["count"] for d in rec.source["dropped"] if "undecodable" in d["reason"]}
    assert len(undecodable) == 2 and set(undecodable.values()) == {1}
    assert len(rec.read_ranges()) == 49
    assert len(rec.read_positions().t_ns) == len(ref["t_l"]) - 1


def test_bag_truncated(data_dir, tmp_path):
    """A bag cut in its index (after its one chunk) is read like `convert bag` reads it: every message of the
    intact chunk, said in a note; cut inside that chunk, nothing is left and it is refused."""
    bag = tmp_path / "t.bag"
    ref = _write_ntu_bag(bag, data_dir, n_ranges=50, extra_topic=False)
    data = bag.read_bytes()
    bag.write_bytes(data[:-200])
    text = convert_ntu_viral(bag, tmp_path / "t.mcap")
    assert "truncated bag (no index): recovered" in text
    assert len(RecordingReader(tmp_path / "t.mcap").read_ranges()) == ref["n"]
    bag.write_bytes(data[: len(data) // 2])
    with pytest.raises(InputError, match="t.bag: unreadable ROS1 bag"):
        convert_ntu_viral(bag, tmp_path / "t2.mcap")
