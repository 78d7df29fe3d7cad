"""Gravity in a ground truth's frame (`pipeline.core.gravity`) and the levelling of a tilted ground truth
(`evaluate.gravity`): an IMU simulated in a level world, its ground truth written in a frame turned off level by a
known rotation, must give that rotation back; a platform that never turns leaves bias and tilt apart only with
the bias given."""

from __future__ import annotations

import numpy as np
import pytest

from uwbcal.convert.simulator import SimConfig, rel_seconds, simulate_imu
from uwbcal.convert.trajectory import default_trajectory
from uwbcal.pipeline.core.geometry import exp_so3, log_so3, quat_to_rot, rot_to_quat
from uwbcal.pipeline.core.gravity import fit_gravity


@pytest.fixture(scope="module")
def level_flight():
    """60 s of the simulator's figure-8 (turning), its IMU with noise and bias random walk, ground truth at
    100 Hz."""
    traj = default_trajectory(60.0)
    cfg = SimConfig()
    t_ns = traj.t0_ns + np.arange(0, int(60e9), int(1e9 / cfg.imu_rate), dtype=np.int64)
    imu = simulate_imu(traj, t_ns, cfg, np.random.default_rng(3))
    t_gt = t_ns[::2]
    s = traj.evaluate(rel_seconds(traj, t_gt))
    return imu, t_gt, s.p, rot_to_quat(s.R), cfg.gravity


def _tilted(p, q, R_t):
    """The ground truth in a frame turned by R_t (truth_from_level): p -> R_t p, R -> R_t R."""
    return p @ R_t.T, rot_to_quat(R_t @ quat_to_rot(q))


@pytest.mark.parametrize("bias_given", [True, False])
def test_fit_gravity_finds_the_tilt_of_the_frame(level_flight, bias_given):
    imu, t_gt, p, q, g = level_flight
    R_t = exp_so3(np.radians([0.25, -0.15, 0.0]))
    p_t, q_t = _tilted(p, q, R_t)
    fit = fit_gravity(imu.t_ns, imu.acc, t_gt, p_t, q_t, imu.ba if bias_given else None)
    assert fit is not None
    g_true = R_t @ np.array([0.0, 0.0, -g])
    err = np.degrees(np.arccos(np.clip(fit.gravity @ g_true / np.linalg.norm(fit.gravity) / g, -1, 1)))
    assert err < 0.01, err
    assert fit.tilt_deg == pytest.approx(np.hypot(0.25, 0.15), abs=0.01)
    assert err < 4 * fit.tilt_sigma_deg + 2e-3  # its sigma is of the size of its error
    assert abs(np.linalg.norm(fit.gravity) - g) < 0.01
    if not bias_given:  # the bias fitted with it is the simulated one's mean
        assert np.abs(fit.bias - imu.ba.mean(axis=0)).max() < 0.01
    # levelling undoes the tilt and adds no yaw
    L = fit.level()
    assert np.allclose(L.R @ fit.gravity / np.linalg.norm(fit.gravity), [0.0, 0.0, -1.0], atol=1e-12)
    assert abs(log_so3(L.R @ R_t)).max() < np.radians(0.015)
    assert abs(log_so3(L.R)[2]) < 1e-9
    back = quat_to_rot(L.quats(q_t))
    assert np.abs(back - quat_to_rot(q)).max() < 5e-4 and np.abs(L.positions(p_t) - p).max() < 1e-3


def test_fit_gravity_streams_in_chunks(level_flight, monkeypatch):
    """The window sums are accumulated chunk by chunk: chunks of 997 samples (windows cut across them) give the
    fit of one pass."""
    import uwbcal.pipeline.core.gravity as grav

    imu, t_gt, p, q, g = level_flight
    one = fit_gravity(imu.t_ns, imu.acc, t_gt, p, q)
    monkeypatch.setattr(grav, "_CHUNK", 997)
    many = fit_gravity(imu.t_ns, imu.acc, t_gt, p, q)
    np.testing.assert_allclose(many.gravity, one.gravity, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(many.bias, one.bias, rtol=1e-9, atol=1e-12)


def test_fit_gravity_skips_non_finite_samples(level_flight):
    """NaN accelerometer samples (a damaged recording) are left out: the tilt is found as without them, no NaN."""
    imu, t_gt, p, q, g = level_flight
    R_t = exp_so3(np.radians([0.2, 0.0, 0.0]))
    p_t, q_t = _tilted(p, q, R_t)
    acc = imu.acc.copy()
    acc[::97] = np.nan
    fit = fit_gravity(imu.t_ns, acc, t_gt, p_t, q_t, imu.ba)
    assert fit is not None and np.isfinite(fit.gravity).all()
    assert fit.tilt_deg == pytest.approx(0.2, abs=0.01)


def test_fit_gravity_level_frame_is_level(level_flight):
    imu, t_gt, p, q, g = level_flight
    fit = fit_gravity(imu.t_ns, imu.acc, t_gt, p, q, imu.ba)
    assert fit.tilt_deg < 0.01 and fit.tilt_deg < 4 * fit.tilt_sigma_deg + 2e-3


def test_fit_gravity_without_turning_needs_the_bias():
    """Translation only, constant attitude: a constant bias and a tilt give the same specific force, so without
    the bias the fit is undetermined (None); with it the tilt is found."""
    rate, T, g = 200.0, 30.0, 9.81
    t = np.arange(0.0, T, 1 / rate)
    t_ns = (t * 1e9).astype(np.int64)
    p = np.column_stack([np.sin(0.5 * t), 0.5 * np.cos(0.3 * t), 0.1 * np.sin(t)])
    a = np.column_stack([-0.25 * np.sin(0.5 * t), -0.045 * np.cos(0.3 * t), -0.1 * np.sin(t)])
    R_t = exp_so3(np.radians([0.0, 0.3, 0.0]))
    g_w = R_t @ np.array([0.0, 0.0, -g])
    bias = np.array([0.05, -0.02, 0.03])
    acc = (a - g_w) + bias  # R = I
    q = np.tile([0.0, 0.0, 0.0, 1.0], (len(t), 1))
    assert fit_gravity(t_ns, acc, t_ns, p, q) is None
    fit = fit_gravity(t_ns, acc, t_ns, p, q, np.tile(bias, (len(t), 1)))
    assert fit is not None and fit.tilt_deg == pytest.approx(0.3, abs=0.005)


def test_fit_gravity_too_short():
    t_ns = np.arange(0, int(5e9), int(5e6), dtype=np.int64)
    q = np.tile([0.0, 0.0, 0.0, 1.0], (len(t_ns), 1))
    acc = np.tile([0.0, 0.0, 9.81], (len(t_ns), 1))
    assert fit_gravity(t_ns, acc, t_ns, np.zeros((len(t_ns), 3)), q) is None
