"""Constants and helpers shared by the tests (imported as ``from support import ...``)."""

import numpy as np

from uwbcal.convert.euroc import EUROC_CAMERAS, EUROC_IMU
from uwbcal.convert.recording import META_CALIBRATION, META_TRUTH, RecordingWriter
from uwbcal.pipeline.core.geometry import exp_so3, log_so3, quat_to_rot, rot_to_quat
from uwbcal.pipeline.vio.camera import Camera
from uwbcal.pipeline.vio.imu import GRAVITY

# One absolute start stamp for every synthetic recording: EuRoC-like (whole seconds, > 2**53 ns, so a float64
# round trip of a stamp would lose nanoseconds and a test would see it).
T0 = 1_403_636_579_000_000_000

CAM = Camera.from_calibration({"cameras": EUROC_CAMERAS})


# ---------------------------------------------------------------------------------------------------------------
# a small visual-inertial simulator (independent of convert/simulator.py)
# ---------------------------------------------------------------------------------------------------------------
def _traj(t: np.ndarray):
    """Smooth 3-D motion: position, acceleration and rotation (world_from_imu) at times t [s]."""
    w = 0.5
    p = np.stack([3 * np.cos(w * t), 3 * np.sin(w * t), 1.2 + 0.3 * np.sin(2 * w * t)], axis=1)
    acc = np.stack(
        [-3 * w * w * np.cos(w * t), -3 * w * w * np.sin(w * t), -1.2 * w * w * np.sin(2 * w * t)], 1
    )
    yaw = w * t + np.pi  # look towards the centre-ish / walls
    rot = np.stack([0.1 * np.sin(1.3 * t), 0.1 * np.cos(0.9 * t), yaw], axis=1)
    # imu z up, x forward; camera looks along imu x (EuRoC T_imu_cam has the camera z ~ imu x)
    return p, acc, rot


def body_rotation(rot: np.ndarray) -> np.ndarray:
    rz = exp_so3(np.column_stack([np.zeros(len(rot)), np.zeros(len(rot)), rot[:, 2]]))
    ry = exp_so3(np.column_stack([np.zeros(len(rot)), rot[:, 1], np.zeros(len(rot))]))
    rx = exp_so3(np.column_stack([rot[:, 0], np.zeros(len(rot)), np.zeros(len(rot))]))
    # EuRoC mounting: the camera looks along the IMU z axis, the IMU x axis points up
    R_mount = np.array([[0.0, 0.0, 1.0], [0.0, -1.0, 0.0], [1.0, 0.0, 0.0]])
    return rz @ ry @ rx @ R_mount


def simulate_vi(path, duration=20.0, seed=0, pixel_sigma=1.0, noise=True, n_landmarks=700):
    rng = np.random.default_rng(seed)
    rate = 200.0
    t = np.arange(0, duration + 1e-9, 1 / rate)
    t_ns = (t * 1e9).round().astype(np.int64) + 1_000_000_000
    p, acc_w, rot = _traj(t)
    R = body_rotation(rot)
    h = 1e-5
    Rp, Rm = body_rotation(_traj(t + h)[2]), body_rotation(_traj(t - h)[2])
    wB = log_so3(np.swapaxes(Rm, 1, 2) @ Rp) / (2 * h)
    aB = np.einsum("kji,kj->ki", R, acc_w - GRAVITY)
    cal = dict(EUROC_IMU)
    dt = 1 / rate
    bg0 = rng.normal(0, 2e-3, 3) if noise else np.zeros(3)
    ba0 = rng.normal(0, 2e-2, 3) if noise else np.zeros(3)
    bg = bg0 + (
        np.cumsum(rng.normal(0, cal["gyroscope_random_walk"] * np.sqrt(dt), (len(t), 3)), 0) if noise else 0
    )
    ba = ba0 + (
        np.cumsum(rng.normal(0, cal["accelerometer_random_walk"] * np.sqrt(dt), (len(t), 3)), 0)
        if noise
        else 0
    )
    gyro = (
        wB + bg + (rng.normal(0, cal["gyroscope_noise_density"] / np.sqrt(dt), (len(t), 3)) if noise else 0)
    )
    acc = (
        aB
        + ba
        + (rng.normal(0, cal["accelerometer_noise_density"] / np.sqrt(dt), (len(t), 3)) if noise else 0)
    )
    # landmarks on a cylinder wall around the motion
    ang = rng.uniform(0, 2 * np.pi, n_landmarks)
    rad = rng.uniform(6.0, 9.0, n_landmarks)
    L = np.column_stack([rad * np.cos(ang), rad * np.sin(ang), rng.uniform(-1.0, 4.0, n_landmarks)])
    calib = {"imu": cal, "cameras": {"cam0": EUROC_CAMERAS["cam0"]}}
    with RecordingWriter(path) as w:
        w.set_metadata(META_CALIBRATION, calib)
        w.set_metadata(
            META_TRUTH, {"imu": {"gyro_bias": bg0.tolist(), "accel_bias": ba0.tolist()}, "seed": seed}
        )
        w.write_imu_batch(t_ns, gyro, acc)
        w.write_pose_batch(t_ns, p, rot_to_quat(R))
        for i in range(0, len(t), 10):  # 20 Hz
            Rc = R[i] @ CAM.R_imu_cam
            pc = p[i] + R[i] @ CAM.p_imu_cam
            P = (L - pc) @ Rc
            vis = P[:, 2] > 0.3
            uv = CAM.project(P[vis])
            inside = (uv[:, 0] > 5) & (uv[:, 0] < 747) & (uv[:, 1] > 5) & (uv[:, 1] < 475)
            ids = np.flatnonzero(vis)[inside]
            uv = uv[inside] + (rng.normal(0, pixel_sigma, uv[inside].shape) if noise else 0)
            w.write_features(int(t_ns[i]) + 1, ids, uv)  # camera a little after the IMU sample
    return t_ns, p, R


def errors_vs_truth(est, t_ns, p, R):
    """(history arrays, orientation errors, position errors) of an estimator against the truth at its stamps."""
    h = est.history().arrays()
    idx = np.clip(np.searchsorted(t_ns, h["t_ns"], side="right") - 1, 0, len(t_ns) - 1)
    Rh = quat_to_rot(h["q_xyzw"])
    # GT at the (1 ns later) stamps: interpolation error is negligible
    dth = log_so3(np.swapaxes(Rh, 1, 2) @ R[idx])
    dp = p[idx] - h["p"]
    return h, dth, dp


def surveyed_links(folder):
    """A surveyed folder (`poses.tum`, `ranges.csv`, `antennas.yaml`, `anchors_truth.csv`) as the ranges of each
    anchor with the ground-truth tag antenna positions at their stamps: {anchor: (xyz, d, link, t_ns)}, truth."""
    import csv

    import yaml
    from scipy.spatial.transform import Rotation

    P = np.loadtxt(folder / "poses.tum")
    R = np.genfromtxt(folder / "ranges.csv", delimiter=",", names=True, dtype=None, encoding=None)
    truth = {
        r["anchor"]: np.array([float(r[k]) for k in "xyz"])
        for r in csv.DictReader(open(folder / "anchors_truth.csv"))
    }
    ao = (yaml.safe_load(open(folder / "antennas.yaml")) or {}).get("antenna_offset") or []
    arms, i = {}, 0
    while i < len(ao):  # [tag, n, x, y, z (n times), ...]
        for k in range(int(ao[i + 1])):
            arms[(int(ao[i]), k)] = np.array(ao[i + 2 + 3 * k : i + 5 + 3 * k], float)
        i += 2 + 3 * int(ao[i + 1])
    t, ts = P[:, 0], R["stamp"] * 1e-9
    ok = (ts >= t[0]) & (ts <= t[-1]) & np.isfinite(R["distance"])
    out = {}
    for a in np.unique(R["anchor"][ok]):
        m = ok & (R["anchor"] == a)
        pos = np.stack([np.interp(ts[m], t, P[:, j]) for j in (1, 2, 3)], axis=1)
        rot = Rotation.from_quat(P[np.clip(np.searchsorted(t, ts[m]), 0, len(t) - 1), 4:8])
        arm = np.array(
            [
                arms.get((int(g), int(n)), np.zeros(3))
                for g, n in zip(R["tag"][m], R["antenna"][m], strict=True)
            ]
        )
        link = R["tag"][m].astype(np.int64) * 256 + R["antenna"][m].astype(np.int64)
        out[str(a)] = (
            pos + rot.apply(arm),
            R["distance"][m].astype(float),
            link,
            R["stamp"][m].astype(np.int64),
        )
    return out, truth


def naive_anchor(xyz, d):
    """The naive reference of a surveyed folder: the position alone by soft-L1 least squares from the linear
    least-squares multilateration (no offset, no scale)."""
    from scipy.optimize import least_squares

    s = np.linalg.lstsq(np.c_[-2 * xyz, np.ones(len(d))], d**2 - np.sum(xyz**2, axis=1), rcond=None)[0]
    return least_squares(lambda p: np.linalg.norm(xyz - p, axis=1) - d, s[:3], loss="soft_l1", f_scale=0.1).x


def surveyed_half(folder, half: int, out):
    """The first (``half`` 0) or second (1) half in time of a surveyed folder, written to ``out`` as a folder of
    the same layout: a recording of the same setup that the development never saw whole."""
    import shutil

    P = np.loadtxt(folder / "poses.tum", ndmin=2)
    t0, t1 = P[0, 0], P[-1, 0]
    lo, hi = t0 + half * (t1 - t0) / 2, t0 + (half + 1) * (t1 - t0) / 2
    out.mkdir(parents=True, exist_ok=True)
    keep = (P[:, 0] >= lo) & (P[:, 0] <= hi)
    np.savetxt(out / "poses.tum", P[keep], fmt=["%.9f"] + ["%.9f"] * 7)
    lines = (folder / "ranges.csv").read_text().splitlines()
    rows = [r for r in lines[1:] if r and lo <= int(r.split(",")[0]) * 1e-9 <= hi]
    (out / "ranges.csv").write_text("\n".join([lines[0], *rows]) + "\n")
    for f in ("antennas.yaml", "anchors_truth.csv"):
        shutil.copy(folder / f, out / f)
    return out
