"""MSCKF on the real EuRoC excerpt (V1_01_micro, 4.7 s, KLT tracks from our front-end).

The excerpt is the start of V1_01_easy: the MAV stands on the ground with its rotors running (|acc| std 0.25
m/s^2) and takes off at its very end. Without a zero-velocity update the filter is IMU dead reckoning (the
zero-parallax tracks carry no translation information) and drifts 0.65 m even from the ground-truth state and
biases; the ZUPT fires in the frames where the vibration passes the IMU at-rest test (~15 of 95) and keeps it
within a few centimetres. Initialisation: ground truth with the EuRoC bias estimate carried by the converter
(/groundtruth/imu_bias), or the static initialiser (then compared after a position+yaw alignment).
"""

import numpy as np
import pytest

from uwbcal.benchmarks.vio_mh01 import posyaw_align
from uwbcal.convert.recording import MergedReader, RecordingReader


@pytest.fixture(scope="module")
def euroc_vi(euroc_micro, tmp_path_factory):
    from uwbcal.pipeline.vio.config import FrontendConfig
    from uwbcal.pipeline.vio.frontend import run_frontend

    rec = euroc_micro[0]  # the session's one conversion (conftest), with the V1_01_easy ground truth
    fe = tmp_path_factory.mktemp("euroc_vio") / "fe.mcap"
    run_frontend(RecordingReader(rec), fe, FrontendConfig())
    return RecordingReader(rec), MergedReader(RecordingReader(rec), RecordingReader(fe))


def _errors(est, gt, align=False):
    h = est.history().arrays()
    i = np.clip(np.searchsorted(gt.t_ns, h["t_ns"], side="right") - 1, 0, len(gt.t_ns) - 2)
    s = (h["t_ns"] - gt.t_ns[i]) / (gt.t_ns[i + 1] - gt.t_ns[i])
    p_gt = (1 - s)[:, None] * gt.p[i] + s[:, None] * gt.p[i + 1]
    p = h["p"]
    if align:
        Rz, tz = posyaw_align(p, p_gt)
        p = p @ Rz.T + tz
    return np.linalg.norm(p - p_gt, axis=1), (h["t_ns"][-1] - h["t_ns"][0]) * 1e-9


def test_euroc_converter_carries_groundtruth_biases(euroc_vi):
    from uwbcal.pipeline.core.topics import TOPIC_GT_IMU_BIAS
    from uwbcal.pipeline.vio.groundtruth import groundtruth_state

    rec, _ = euroc_vi
    assert TOPIC_GT_IMU_BIAS in rec.topics()
    b = rec.read_imu(TOPIC_GT_IMU_BIAS)
    # V1_01_easy.csv first row: b_w = (-0.00224703, 0.0215352, 0.0770299), b_a = (-0.0180115, 0.0659796, 0.0309774)
    assert b.t_ns[0] == 1403715273262142976
    assert np.allclose(b.gyro[0], [-0.00224703, 0.0215352, 0.0770299])
    assert np.allclose(b.acc[0], [-0.0180115, 0.0659796, 0.0309774])
    x0 = groundtruth_state(rec, rec.topics()["/imu"].start_ns)
    assert abs(x0.bg[2] - 0.077) < 1e-3


def test_msckf_real_euroc_excerpt_within_10cm(euroc_vi):
    from uwbcal.pipeline.run.driver import msckf_from_recording, run_estimator
    from uwbcal.pipeline.vio.config import VioConfig

    rec, reader = euroc_vi
    gt = rec.read_poses("/groundtruth/pose")
    est = msckf_from_recording(reader, VioConfig())
    run_estimator(est, reader, None, None)
    e, span = _errors(est, gt)
    print(f"\nV1_01_micro, GT init with GT biases: max {e.max():.3f} m, final {e[-1]:.3f} m, {est.stats}")
    assert span > 4.5 and est.stats.frames >= 94
    assert est.stats.zupt_updates > 5
    assert e.max() < 0.1


def test_msckf_real_euroc_excerpt_static_init(euroc_vi):
    from uwbcal.pipeline.run.driver import msckf_from_recording, run_estimator
    from uwbcal.pipeline.vio.config import VioConfig
    from uwbcal.pipeline.vio.static_init import static_init_from_recording

    rec, reader = euroc_vi
    gt = rec.read_poses("/groundtruth/pose")
    si = static_init_from_recording(rec)
    est = msckf_from_recording(reader, VioConfig(init_from_groundtruth=False), si.state, si.P)
    run_estimator(est, reader, None, None)
    e, _ = _errors(est, gt, align=True)
    print(f"\nV1_01_micro, static init: posyaw-aligned max {e.max():.3f} m")
    assert e.max() < 0.1
