"""Benchmark: convert a synthetic EuRoC-like ROS1 bag (752x480 mono8 stereo at 20 Hz, IMU at 200 Hz, Vicon) with
``uwbcal convert euroc`` and with ``rosbags-convert`` (ROS1 -> ROS2) in the same run; report wall time and peak
memory of both. ``python -m uwbcal.benchmarks.convert_bag [--size-gb 1.0] [--keep DIR] [-o JSON]``.

`write_euroc_bag` is also used by the tests (small sizes) to build bags value by value.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from uwbcal.pipeline.core.atomic import write_text_atomic

T0_NS = 1_403_715_273_262_142_976
W, H = 752, 480


@dataclass
class BagContent:
    """What was written into a synthetic bag (for value-by-value comparisons in tests)."""

    imu_t: list[int] = field(default_factory=list)
    imu: list[tuple] = field(default_factory=list)
    img_t: list[int] = field(default_factory=list)
    img_seed: list[int] = field(default_factory=list)
    gt_t: list[int] = field(default_factory=list)
    gt: list[tuple] = field(default_factory=list)


def synthetic_image(k: int, width: int = W, height: int = H) -> np.ndarray:
    """A deterministic textured mono8 frame (gradient + blobs + noise): compresses like a real image, not like
    random bytes."""
    rng = np.random.default_rng(k)
    yy, xx = np.mgrid[0:height, 0:width]
    base = (xx * 0.3 + yy * 0.2 + 40 * np.sin((xx + 3 * k) / 23.0) * np.cos(yy / 17.0) + 100).astype(np.int16)
    noise = rng.integers(-6, 7, size=(height, width), dtype=np.int16)
    return np.clip(base + noise, 0, 255).astype(np.uint8)


def _ros1():
    from rosbags.typesys import Stores, get_typestore

    return get_typestore(Stores.ROS1_NOETIC)


def _header(T, t_ns: int, frame: str, seq: int = 0):
    return T["std_msgs/msg/Header"](
        seq=seq,
        stamp=T["builtin_interfaces/msg/Time"](sec=t_ns // 1_000_000_000, nanosec=t_ns % 1_000_000_000),
        frame_id=frame,
    )


def write_euroc_bag(
    path: Path,
    *,
    duration_s: float | None = None,
    size_gb: float | None = None,
    width: int = W,
    height: int = H,
    cam_hz: float = 20.0,
    imu_hz: float = 200.0,
    gt: str | None = "vicon",
    extra_topic: bool = False,
    bag_delay_ns: int = 1_000_000,
    n_textures: int = 8,
    record: bool = False,
) -> BagContent:
    """Write a EuRoC-like ROS1 bag; give ``duration_s`` or ``size_gb`` (stereo images dominate the size).
    ``gt``: "vicon" (TransformStamped), "leica" (PointStamped) or None. ``extra_topic`` adds a topic of a
    custom, unconvertible type. Bag time = header stamp + ``bag_delay_ns`` (as recorded by rosbag)."""
    from rosbags.rosbag1 import Writer
    from rosbags.typesys import get_types_from_msg

    ts = _ros1()
    if extra_topic:
        ts.register(get_types_from_msg("float64 value\nstring note\n", "custom_msgs/msg/Thing"))
    T = ts.types
    if duration_s is None:
        frame_bytes = width * height
        duration_s = float(size_gb or 0.01) * 1e9 / (2 * frame_bytes * cam_hz)
    n_img = max(1, int(duration_s * cam_hz))
    n_imu = max(1, int(duration_s * imu_hz))
    textures = [synthetic_image(k, width, height) for k in range(n_textures)]
    rng = np.random.default_rng(1)
    out = BagContent()
    path.unlink(missing_ok=True)
    with Writer(path) as w:
        c_imu = w.add_connection("/imu0", "sensor_msgs/msg/Imu", typestore=ts)
        c_cam = [
            w.add_connection(f"/cam{i}/image_raw", "sensor_msgs/msg/Image", typestore=ts) for i in (0, 1)
        ]
        c_gt = None
        if gt == "vicon":
            c_gt = w.add_connection(
                "/vicon/firefly_sbx/firefly_sbx", "geometry_msgs/msg/TransformStamped", typestore=ts
            )
        elif gt == "leica":
            c_gt = w.add_connection("/leica/position", "geometry_msgs/msg/PointStamped", typestore=ts)
        c_x = (
            w.add_connection("/custom/thing", "custom_msgs/msg/Thing", typestore=ts) if extra_topic else None
        )
        imu_dt = int(round(1e9 / imu_hz))
        img_dt = int(round(1e9 / cam_hz))
        events = sorted(
            [(T0_NS + i * imu_dt, 0, i) for i in range(n_imu)]
            + [(T0_NS + i * img_dt, 1, i) for i in range(n_img)]
        )
        for t, kind, i in events:
            if kind == 0:
                g, a = rng.normal(0, 0.1, 3), rng.normal(0, 0.5, 3) + (0, 0, 9.81)
                msg = _imu_msg(T, t, i, g, a)
                w.write(c_imu, t + bag_delay_ns, ts.serialize_ros1(msg, "sensor_msgs/msg/Imu"))
                if record:
                    out.imu_t.append(t)
                    out.imu.append((*g, *a))
                if c_gt is not None and i % 2 == 0:
                    m, msgtype, p, q = _gt_msg(T, gt, t, i)
                    w.write(c_gt, t + bag_delay_ns, ts.serialize_ros1(m, msgtype))
                    if record:
                        out.gt_t.append(t)
                        out.gt.append((*p, *q))
                if c_x is not None and i % 50 == 0:
                    m = T["custom_msgs/msg/Thing"](value=float(i), note="x")
                    w.write(c_x, t + bag_delay_ns, ts.serialize_ros1(m, "custom_msgs/msg/Thing"))
            else:
                for cam, conn in enumerate(c_cam):
                    msg = _image_msg(T, t, cam, i, textures[(i + cam) % n_textures])
                    w.write(conn, t + bag_delay_ns, ts.serialize_ros1(msg, "sensor_msgs/msg/Image"))
                if record:
                    out.img_t.append(t)
                    out.img_seed.append(i)
    return out


def _imu_msg(T: dict, t: int, i: int, g: np.ndarray, a: np.ndarray) -> Any:
    return T["sensor_msgs/msg/Imu"](
        header=_header(T, t, "imu4", i),
        orientation=T["geometry_msgs/msg/Quaternion"](x=0, y=0, z=0, w=1),
        orientation_covariance=np.zeros(9),
        angular_velocity=T["geometry_msgs/msg/Vector3"](*g),
        angular_velocity_covariance=np.zeros(9),
        linear_acceleration=T["geometry_msgs/msg/Vector3"](*a),
        linear_acceleration_covariance=np.zeros(9),
    )


def _gt_msg(T: dict, gt: str, t: int, i: int) -> tuple[Any, str, tuple, tuple]:
    """Ground truth ``i`` (every other IMU sample): the message, its type, position and quaternion (vicon) or
    () (leica)."""
    p = (np.sin(i * 1e-3), np.cos(i * 1e-3), 1.0 + 0.1 * np.sin(i * 1e-2))
    if gt == "vicon":
        ang = i * 1e-3
        q = (0.0, 0.0, np.sin(ang / 2), np.cos(ang / 2))
        m = T["geometry_msgs/msg/TransformStamped"](
            header=_header(T, t, "world", i),
            child_frame_id="firefly_sbx",
            transform=T["geometry_msgs/msg/Transform"](
                translation=T["geometry_msgs/msg/Vector3"](*p),
                rotation=T["geometry_msgs/msg/Quaternion"](*q),
            ),
        )
        return m, "geometry_msgs/msg/TransformStamped", p, q
    m = T["geometry_msgs/msg/PointStamped"](
        header=_header(T, t, "world", i), point=T["geometry_msgs/msg/Point"](*p)
    )
    return m, "geometry_msgs/msg/PointStamped", p, ()


def _image_msg(T: dict, t: int, cam: int, i: int, img: np.ndarray) -> Any:
    height, width = img.shape
    return T["sensor_msgs/msg/Image"](
        header=_header(T, t, f"cam{cam}", i),
        height=height,
        width=width,
        encoding="mono8",
        is_bigendian=0,
        step=width,
        data=img.reshape(-1),
    )


# ---------------------------------------------------------------------------------------------------------------
# timing
# ---------------------------------------------------------------------------------------------------------------
def _timed(cmd: list[str]) -> dict:
    """Run a command as a direct child; wall time, its CPU time (user + system, all its threads) and its own peak
    RSS (os.wait4 rusage)."""
    t0 = time.perf_counter()
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    _, status, ru = os.wait4(proc.pid, 0)
    wall = time.perf_counter() - t0
    out = proc.stdout.read().decode(errors="replace") if proc.stdout else ""
    err = proc.stderr.read().decode(errors="replace") if proc.stderr else ""
    code = os.waitstatus_to_exitcode(status)
    return {
        "cmd": " ".join(cmd),
        "wall_s": round(wall, 3),
        "cpu_s": round(ru.ru_utime + ru.ru_stime, 3),
        "peak_rss_mb": round(ru.ru_maxrss / 1024, 1),
        "exit": code,
        **({"stderr": err[-2000:]} if code else {}),
        "stdout_tail": out[-600:],
    }


def run(size_gb: float, work: Path) -> dict:
    bag = work / "synthetic_euroc.bag"
    t0 = time.perf_counter()
    write_euroc_bag(bag, size_gb=size_gb)
    synth_s = time.perf_counter() - t0
    bin_dir = Path(sys.executable).parent
    (work / "ours.mcap").unlink(missing_ok=True)
    ours = _timed(
        [
            sys.executable,
            "-c",
            "import sys; from uwbcal.convert.euroc import convert_euroc; "
            "print(convert_euroc(sys.argv[1], sys.argv[2]))",
            str(bag),
            str(work / "ours.mcap"),
        ]
    )
    dst = work / "rosbags_out"
    shutil.rmtree(dst, ignore_errors=True)
    theirs = _timed([str(bin_dir / "rosbags-convert"), "--src", str(bag), "--dst", str(dst)])
    theirs_mcap_dst = work / "rosbags_out_mcap"
    shutil.rmtree(theirs_mcap_dst, ignore_errors=True)
    theirs_mcap = _timed(
        [
            str(bin_dir / "rosbags-convert"),
            "--src",
            str(bag),
            "--dst",
            str(theirs_mcap_dst),
            "--dst-storage",
            "mcap",
        ]
    )
    res = {
        "bag_bytes": bag.stat().st_size,
        "synthesis_s": round(synth_s, 2),
        "uwbcal": ours,
        "rosbags_convert_sqlite3": theirs,
        "rosbags_convert_mcap": theirs_mcap,
        "uwbcal_out_bytes": (work / "ours.mcap").stat().st_size if (work / "ours.mcap").exists() else None,
    }
    res["time_ratio_vs_sqlite3"] = round(ours["wall_s"] / theirs["wall_s"], 3)
    res["time_ratio_vs_mcap"] = round(ours["wall_s"] / theirs_mcap["wall_s"], 3)
    # on a loaded machine the wall ratio follows the CPU one (a second thread only pays on a free core)
    res["cpu_ratio_vs_sqlite3"] = round(ours["cpu_s"] / max(theirs["cpu_s"], 1e-9), 3)
    res["target_met"] = bool(
        ours["exit"] == 0 and res["time_ratio_vs_sqlite3"] <= 1.2 and ours["peak_rss_mb"] < 1024
    )
    return res


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size-gb", type=float, default=1.0)
    ap.add_argument("--keep", type=Path, default=None, help="work directory to keep (default: a temp dir)")
    ap.add_argument("-o", "--output", type=Path, default=None)
    a = ap.parse_args(argv)
    if a.keep:
        a.keep.mkdir(parents=True, exist_ok=True)
        res = run(a.size_gb, a.keep)
    else:
        with tempfile.TemporaryDirectory(prefix="uwbcal-bench-bag-") as tmp:
            res = run(a.size_gb, Path(tmp))
    text = json.dumps(res, indent=2)
    print(text)
    if a.output:
        write_text_atomic(a.output, text + "\n")
    return 0 if res["uwbcal"]["exit"] == 0 else 1


if __name__ == "__main__":
    sys.exit(main())
