"""IMU propagation: Phi and Q against finite differences of the nonlinear propagation; FEJ nullspace."""

import numpy as np
import pytest

from uwbcal.pipeline.core.geometry import exp_so3, skew
from uwbcal.pipeline.core.state import ImuState
from uwbcal.pipeline.vio.imu import GRAVITY, ImuNoise, error_between, imu_intervals, propagate

NOISE = ImuNoise(1.7e-4, 2e-3, 1.9e-5, 3e-3, 200.0)


def _setup(seed=0, n=12):
    rng = np.random.default_rng(seed)
    x = ImuState(
        exp_so3(rng.normal(size=3)),
        rng.normal(size=3),
        rng.normal(size=3),
        0.01 * rng.normal(size=3),
        0.1 * rng.normal(size=3),
    )
    dt = rng.uniform(0.002, 0.006, n)
    gyro = rng.normal(size=(n, 3))
    acc = rng.normal(size=(n, 3)) + np.array([0, 0, 9.81])
    return x, dt, gyro, acc


def test_phi_matches_finite_differences():
    x, dt, gyro, acc = _setup()
    prop = propagate(x, dt, gyro, acc, NOISE)
    eps = 1e-6
    Phi_fd = np.zeros((15, 15))
    for i in range(15):
        e = np.zeros(15)
        e[i] = eps
        xp = propagate(x.boxplus(e), dt, gyro, acc, NOISE).state
        xm = propagate(x.boxplus(-e), dt, gyro, acc, NOISE).state
        Phi_fd[:, i] = (error_between(prop.state, xp) - error_between(prop.state, xm)) / (2 * eps)
    err = np.abs(prop.Phi - Phi_fd).max()
    assert err < 1e-6, err


def test_white_noise_q_matches_finite_differences():
    x, dt, gyro, acc = _setup(1, 8)
    prop = propagate(x, dt, gyro, acc, NOISE)
    eps = 1e-6
    Qref = np.zeros((15, 15))
    for k in range(len(dt)):
        for which, sig in ((gyro, NOISE.sigma_g), (acc, NOISE.sigma_a)):
            for j in range(3):
                cols = []
                for s in (1, -1):
                    m = which.copy()
                    m[k, j] += s * eps
                    args = (m, acc) if which is gyro else (gyro, m)
                    cols.append(error_between(prop.state, propagate(x, dt, *args, NOISE).state))
                J = (cols[0] - cols[1]) / (2 * eps)
                Qref += np.outer(J, J) * sig**2 / min(dt[k], 1 / NOISE.rate_hz)
    np.testing.assert_allclose(prop.Q[:9, :9], Qref[:9, :9], atol=1e-12, rtol=1e-6)
    assert np.allclose(np.diag(prop.Q)[9:12], NOISE.sigma_bg**2 * dt.sum())


def test_fej_phi_maps_unobservable_directions():
    x, dt, gyro, acc = _setup(2)
    rng = np.random.default_rng(5)
    x_fej = x.boxplus(0.05 * rng.normal(size=15))  # first estimate differs from the updated estimate

    def nullspace(s: ImuState) -> np.ndarray:
        N = np.zeros((15, 4))
        ez = -GRAVITY / np.linalg.norm(GRAVITY)
        N[0:3, 0] = s.R.T @ ez
        N[3:6, 0] = -skew(s.p) @ ez
        N[6:9, 0] = -skew(s.v) @ ez
        N[3:6, 1:4] = np.eye(3)
        return N

    fej = propagate(x, dt, gyro, acc, NOISE, x_fej=x_fej)
    assert np.abs(fej.Phi @ nullspace(x_fej) - nullspace(fej.state)).max() < 1e-10
    plain = propagate(x, dt, gyro, acc, NOISE)
    assert np.abs(plain.Phi @ nullspace(x_fej) - nullspace(plain.state)).max() > 1e-3


def test_intervals_interpolate_and_cover():
    t = np.arange(0, 100_000_000, 5_000_000, dtype=np.int64)
    g = np.stack([t * 1e-9, np.zeros_like(t, float), np.ones_like(t, float)], axis=1)
    dt, w, a = imu_intervals(t, g, g, 12_000_000, 31_000_000)
    assert dt.sum() == pytest.approx(0.019)
    mid = 0.012 + np.concatenate([[0], np.cumsum(dt)])[:-1] + dt / 2
    np.testing.assert_allclose(w[:, 0], mid, atol=1e-12)
