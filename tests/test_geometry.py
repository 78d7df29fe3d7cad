"""SO(3) helpers against scipy's Rotation (an independent implementation)."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from uwbcal.pipeline.core.geometry import (
    compose,
    compose_jacobians,
    exp_so3,
    exp_so3_each,
    exp_so3_rodrigues,
    jr_inv_so3,
    jr_so3,
    left_jacobian_so3,
    log_so3,
    log_so3_one,
    se3_exp,
    se3_interpolate,
    se3_log,
)
from uwbcal.pipeline.core.state import Pose


def _rot_err(Ra, Rb):
    return float(np.linalg.norm(log_so3(Ra.T @ Rb)))


@pytest.mark.parametrize("scale", [0.0, 1e-9, 1e-4, 1.0, np.pi - 1e-6])
def test_exp_so3_single_and_batched_match_scipy(scale):
    rng = np.random.default_rng(7)
    w = rng.normal(size=(20, 3))
    w = scale * w / np.linalg.norm(w, axis=1, keepdims=True)
    ref = Rotation.from_rotvec(w).as_matrix()
    np.testing.assert_allclose(exp_so3(w), ref, atol=1e-14)
    for k in range(len(w)):  # the scalar fast path for a single vector
        np.testing.assert_allclose(exp_so3(w[k]), ref[k], atol=1e-14)
    if 0 < scale < np.pi - 1e-3:
        np.testing.assert_allclose(log_so3(exp_so3(w)), w, atol=1e-9)


def test_compose_jacobians_finite_differences():
    rng = np.random.default_rng(3)
    R = exp_so3(rng.normal(size=3))
    p = rng.normal(size=3)
    dR = exp_so3(0.3 * rng.normal(size=3))
    dp = rng.normal(size=3)
    F, G = compose_jacobians(R, dR, dp)
    R1, p1 = compose(R, p, dR, dp)
    eps = 1e-6
    for k in range(6):
        dx = np.zeros(6)
        dx[k] = eps
        x = Pose(R, p).boxplus(dx)
        Ra, pa = compose(x.R, x.p, dR, dp)
        num = np.concatenate([log_so3(R1.T @ Ra), pa - p1]) / eps
        assert np.allclose(num, F[:, k], atol=1e-5)
        Rb, pb = compose(R, p, dR @ exp_so3(dx[0:3]), dp + dx[3:6])
        num = np.concatenate([log_so3(R1.T @ Rb), pb - p1]) / eps
        assert np.allclose(num, G[:, k], atol=1e-5)


def test_se3_exp_log_round_trip_and_constant_twist_interpolation():
    rng = np.random.default_rng(5)
    xi = np.concatenate([0.8 * rng.normal(size=3), rng.normal(size=3)])
    R, p = se3_exp(xi)
    assert np.allclose(se3_log(R, p), xi, atol=1e-12)
    # motion with a constant body twist: T(s) = T0 Exp(s xi); interpolation must be exact
    R0, p0 = exp_so3(rng.normal(size=3)), rng.normal(size=3)
    R1, p1 = compose(R0, p0, R, p)
    for s in (0.0, 0.25, 0.5, 0.9, 1.0):
        Rs, ps = compose(R0, p0, *se3_exp(s * xi))
        Ri, pi = se3_interpolate(R0, p0, R1, p1, s)
        assert _rot_err(Ri, Rs) < 1e-12
        assert np.allclose(pi, ps, atol=1e-12)


@pytest.mark.parametrize("angle", [0.0, 1e-9, 1e-3, 0.5, 2.0, np.pi - 1e-3, np.pi - 1e-7])
def test_scalar_so3_helpers_match_the_vectorised_ones(angle):
    axis = np.array([0.3, -0.5, 0.8]) / np.linalg.norm([0.3, -0.5, 0.8])
    w = angle * axis
    R = exp_so3(w)
    assert np.allclose(exp_so3_rodrigues(w), R, atol=1e-12)
    assert np.allclose(exp_so3(log_so3_one(R)), R, atol=1e-9)
    assert np.allclose(left_jacobian_so3(w), jr_so3(-w), atol=1e-9)
    if angle < 3.0:
        assert np.allclose(left_jacobian_so3(w, inverse=True), jr_inv_so3(-w), atol=1e-9)


def test_exp_so3_each_is_the_one_vector_path_bit_for_bit():
    rng = np.random.default_rng(3)
    w = np.vstack([rng.normal(size=(50, 3)) * 10.0 ** rng.uniform(-9, 0.5, (50, 1)), np.zeros((1, 3))])
    np.testing.assert_allclose(exp_so3_each(w), np.stack([exp_so3(v) for v in w]), rtol=0, atol=1e-15)


def test_norms_are_numpys_norms_bit_for_bit():
    from uwbcal.pipeline.core.geometry import norms

    x = np.random.default_rng(0).normal(size=(200, 3)) * np.logspace(-8, 3, 200)[:, None]
    assert np.array_equal(norms(x), np.linalg.norm(x, axis=-1))
    assert np.array_equal(norms(x[0]), np.linalg.norm(x[0]))
