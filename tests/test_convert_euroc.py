"""EuRoC converters: real ASL excerpt, synthetic ASL folders and synthetic ROS1 bags, round trips value by value."""

from __future__ import annotations

import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest

from uwbcal.benchmarks.convert_bag import synthetic_image, write_euroc_bag
from uwbcal.convert.euroc import EUROC_T_B_VICON, convert_euroc, read_groundtruth
from uwbcal.convert.recording import RecordingReader
from uwbcal.pipeline.core.errors import InputError


def _micro(data_dir: Path) -> Path:
    return data_dir / "euroc" / "V1_01_micro"


@pytest.fixture(scope="module")
def micro_rec(euroc_micro) -> tuple[Path, str]:
    return euroc_micro  # the session's one conversion (conftest)


def test_real_micro_counts_and_drops(micro_rec, data_dir):
    out, text = micro_rec
    rec = RecordingReader(out)
    topics = rec.topics()
    imu_rows = len((_micro(data_dir) / "mav0/imu0/data.csv").read_text().strip().splitlines()) - 1
    assert topics["/imu"].count == imu_rows == 29120
    assert topics["/cam0/image_raw"].count == 95
    assert topics["/cam1/image_raw"].count == 95
    dropped = rec.source["dropped"]
    assert dropped == [
        {
            "topic": "/cam1/image_raw",
            "reason": "image listed in data.csv but missing on disk",
            "count": 4,
            "example": "1403715278012143104.png",
        }
    ]
    assert "missing on disk" in text and "29120" in text
    assert rec.source["converter"].startswith("uwbcal ")
    assert all(len(f["sha256"]) == 64 for f in rec.source["files"])


def test_real_micro_pixels_identical(micro_rec, data_dir):
    out, _ = micro_rec
    rec = RecordingReader(out)
    n = 0
    for cam, topic in (("cam0", "/cam0/image_raw"), ("cam1", "/cam1/image_raw")):
        for t, img in rec.iter_images(topic):
            png = cv2.imread(str(_micro(data_dir) / f"mav0/{cam}/data/{t}.png"), cv2.IMREAD_UNCHANGED)
            assert png.dtype == np.uint8 and png.shape == (480, 752)
            np.testing.assert_array_equal(img, png)
            n += 1
    assert n == 190


def test_real_micro_imu_and_calibration(micro_rec, data_dir):
    out, _ = micro_rec
    rec = RecordingReader(out)
    raw = np.loadtxt(_micro(data_dir) / "mav0/imu0/data.csv", delimiter=",", skiprows=1, dtype=str)
    imu = rec.read_imu()
    np.testing.assert_array_equal(imu.t_ns, raw[:, 0].astype(np.int64))
    np.testing.assert_array_equal(imu.gyro, raw[:, 1:4].astype(float))
    np.testing.assert_array_equal(imu.acc, raw[:, 4:7].astype(float))
    cal = rec.calibration
    assert cal["imu"]["gyroscope_noise_density"] == 1.6968e-04
    assert cal["imu"]["accelerometer_random_walk"] == 3.0e-3 and cal["imu"]["rate_hz"] == 200
    c0 = cal["cameras"]["cam0"]
    assert c0["intrinsics"] == [458.654, 457.296, 367.215, 248.375]
    assert c0["distortion_model"] == "radtan" and c0["resolution"] == [752, 480] and c0["rate_hz"] == 20
    T = np.asarray(c0["T_imu_cam"])
    assert T[0, 3] == pytest.approx(-0.0216401454975) and np.allclose(
        T[:3, :3] @ T[:3, :3].T, np.eye(3), atol=1e-6
    )
    assert cal["cameras"]["cam1"]["distortion"][0] == -0.28368365
    assert cal["groundtruth"]["frame"] == "body"


@pytest.mark.parametrize("name", ["V1_01_easy.csv", "V1_01_easy_original.txt"])
def test_external_groundtruth(data_dir, tmp_path, name):
    gt_file = data_dir / "euroc/groundtruth" / name
    out = tmp_path / "gt.mcap"
    convert_euroc(_micro(data_dir), out, groundtruth=gt_file)
    poses = RecordingReader(out).read_poses()
    ref = read_groundtruth(gt_file)
    assert len(poses.t_ns) == len(ref.t_ns) > 2000
    np.testing.assert_array_equal(poses.t_ns, ref.t_ns)
    np.testing.assert_allclose(poses.p, ref.p)
    np.testing.assert_allclose(poses.q_xyzw, ref.q_xyzw / np.linalg.norm(ref.q_xyzw, axis=1)[:, None])
    if name.endswith(".csv"):  # EuRoC CSV is (w, x, y, z): first row 0.069433,-0.824237,-0.106942,-0.551702
        np.testing.assert_allclose(poses.q_xyzw[0], [-0.824237, -0.106942, -0.551702, 0.069433], atol=1e-6)
        assert poses.t_ns[0] == 1403715273262142976
    else:  # TUM seconds with 5 decimals -> exact integer ns
        assert poses.t_ns[0] == 1403715274302140000


# ---------------------------------------------------------------------------------------------------------------
# synthetic ASL folders: bad input
# ---------------------------------------------------------------------------------------------------------------
EUROC_SIZE = (752, 480)  # the cameras' resolution in EuRoC's sensor.yaml: the images must have it


def _asl(tmp_path: Path, data_dir: Path | None = None, n_img: int = 3) -> Path:
    """A tiny ASL folder: sensor.yaml copied from the real excerpt (or written), synthetic IMU/images."""
    root = tmp_path / "seq"
    mav0 = root / "mav0"
    for s in ("imu0", "cam0/data", "cam1/data"):
        (mav0 / s).mkdir(parents=True, exist_ok=True)
    src = Path(__file__).resolve().parents[2] / "shared/data/euroc/V1_01_micro/mav0"
    if data_dir is not None:
        src = _micro(data_dir) / "mav0"
    for s in ("imu0", "cam0", "cam1"):
        shutil.copy(src / s / "sensor.yaml", mav0 / s / "sensor.yaml")
    t0 = 1_000_000_000_000_000_000
    imu_t = t0 + np.arange(20) * 5_000_000
    rows = ["#timestamp [ns],w_x,w_y,w_z,a_x,a_y,a_z"] + [f"{t},0.1,0.2,0.3,0.0,0.0,9.81" for t in imu_t]
    (mav0 / "imu0/data.csv").write_text("\n".join(rows) + "\n")
    for cam in ("cam0", "cam1"):
        lines = ["#timestamp [ns],filename"]
        for k in range(n_img):
            t = t0 + k * 50_000_000
            cv2.imwrite(str(mav0 / cam / "data" / f"{t}.png"), synthetic_image(k, *EUROC_SIZE))
            lines.append(f"{t},{t}.png")
        (mav0 / cam / "data.csv").write_text("\n".join(lines) + "\n")
    return root


def test_synthetic_folder_roundtrip_and_imu_dups(data_dir, tmp_path):
    root = _asl(tmp_path, data_dir)
    csv = root / "mav0/imu0/data.csv"
    lines = csv.read_text().splitlines()
    lines = (
        lines[:1] + lines[1:6] + [lines[3]] + lines[7:] + [lines[6]]
    )  # a duplicate and an out-of-order row
    csv.write_text("\n".join(lines) + "\n")
    out = tmp_path / "o.mcap"
    text = convert_euroc(root, out)
    rec = RecordingReader(out)
    imu = rec.read_imu()
    assert len(imu.t_ns) == 20 and np.all(np.diff(imu.t_ns) > 0)
    assert "duplicate stamp" in text and "out-of-order" in text
    for k, (_, img) in enumerate(rec.iter_images("/cam1/image_raw")):
        np.testing.assert_array_equal(img, synthetic_image(k, *EUROC_SIZE))


def test_missing_sensor_yaml(data_dir, tmp_path):
    root = _asl(tmp_path, data_dir)
    (root / "mav0/cam0/sensor.yaml").unlink()
    with pytest.raises(InputError, match=r"cam0/sensor.yaml: missing"):
        convert_euroc(root, tmp_path / "o.mcap")
    assert not (tmp_path / "o.mcap").exists()


def test_empty_folder(tmp_path):
    (tmp_path / "empty").mkdir()
    with pytest.raises(InputError, match="no EuRoC ASL layout"):
        convert_euroc(tmp_path / "empty", tmp_path / "o.mcap")


def test_wrong_csv_columns(data_dir, tmp_path):
    root = _asl(tmp_path, data_dir)
    (root / "mav0/imu0/data.csv").write_text("#timestamp,wx,wy\n1,2,3\n")
    with pytest.raises(InputError, match=r"imu0/data.csv: header: expected 7 columns, found 3"):
        convert_euroc(root, tmp_path / "o.mcap")


def test_bad_value_names_row(data_dir, tmp_path):
    root = _asl(tmp_path, data_dir)
    csv = root / "mav0/imu0/data.csv"
    lines = csv.read_text().splitlines()
    lines[4] = lines[4].replace("9.81", "abc")
    csv.write_text("\n".join(lines) + "\n")
    with pytest.raises(InputError, match=r"data.csv: line 5: column .*'abc' is not a number"):
        convert_euroc(root, tmp_path / "o.mcap")


# ---------------------------------------------------------------------------------------------------------------
# synthetic ROS1 bags
# ---------------------------------------------------------------------------------------------------------------
def _rot(q):
    from uwbcal.convert.euroc import _quat_to_rot

    return _quat_to_rot(np.asarray(q, float))


@pytest.mark.parametrize("gt", ["vicon", "leica"])
def test_bag_roundtrip(tmp_path, gt):
    bag = tmp_path / "s.bag"
    content = write_euroc_bag(
        bag, duration_s=0.5, width=40, height=30, gt=gt, extra_topic=True, record=True, n_textures=3
    )
    out = tmp_path / "s.mcap"
    text = convert_euroc(bag, out)
    rec = RecordingReader(out)
    imu = rec.read_imu()
    np.testing.assert_array_equal(imu.t_ns, content.imu_t)  # header stamps, not bag time
    vals = np.asarray(content.imu)
    np.testing.assert_array_equal(imu.gyro, vals[:, :3])
    np.testing.assert_array_equal(imu.acc, vals[:, 3:])
    for cam in (0, 1):
        got = list(rec.iter_images(f"/cam{cam}/image_raw"))
        assert [t for t, _ in got] == content.img_t
        for (_, img), i in zip(got, content.img_seed, strict=True):
            np.testing.assert_array_equal(img, synthetic_image((i + cam) % 3, 40, 30))
    g = np.asarray(content.gt)
    if gt == "leica":
        pos = rec.read_positions()
        np.testing.assert_array_equal(pos.t_ns, content.gt_t)
        np.testing.assert_array_equal(pos.p, g)
        assert rec.calibration["groundtruth"]["frame"] == "prism"
    else:
        poses = rec.read_poses()
        np.testing.assert_array_equal(poses.t_ns, content.gt_t)
        T_V_B = np.linalg.inv(EUROC_T_B_VICON)
        for p, q, ref in zip(poses.p, poses.q_xyzw, g, strict=True):
            R_WV = _rot(ref[3:])
            np.testing.assert_allclose(p, R_WV @ T_V_B[:3, 3] + ref[:3], atol=1e-12)
            np.testing.assert_allclose(_rot(q), R_WV @ T_V_B[:3, :3], atol=1e-5)  # T_BS is not exactly SO(3)
    dropped = {d["topic"]: d for d in rec.source["dropped"]}
    assert (
        dropped["/custom/thing"]["count"] == 2
        and "custom_msgs/msg/Thing" in dropped["/custom/thing"]["reason"]
    )
    assert "/custom/thing" in text
    assert rec.calibration["cameras"]["cam0"]["intrinsics"][0] == 458.654


def test_truncated_bag(tmp_path):
    bag = tmp_path / "t.bag"
    write_euroc_bag(bag, duration_s=0.3, width=40, height=30)
    data = bag.read_bytes()
    bag.write_bytes(data[: len(data) // 2])
    with pytest.raises(InputError, match=r"t.bag: unreadable ROS1 bag"):
        convert_euroc(bag, tmp_path / "t.mcap")
    assert not (tmp_path / "t.mcap").exists()


def test_bag_wrong_type_on_known_topic(tmp_path):
    from rosbags.rosbag1 import Writer
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS1_NOETIC)
    bag = tmp_path / "w.bag"
    content = write_euroc_bag(tmp_path / "ok.bag", duration_s=0.1, width=8, height=6, gt=None, record=True)
    with Writer(bag) as w:
        c = w.add_connection("/imu0", "std_msgs/msg/String", typestore=ts)
        for k in range(5):
            w.write(
                c, 10 + k, ts.serialize_ros1(ts.types["std_msgs/msg/String"](data="x"), "std_msgs/msg/String")
            )
    assert content.imu_t  # the good bag next to it does hold IMU messages on /imu0
    with pytest.raises(InputError, match="no IMU messages"):
        convert_euroc(bag, tmp_path / "w.mcap")
    assert not (tmp_path / "w.mcap").exists()  # atomic: nothing half-written is left behind
