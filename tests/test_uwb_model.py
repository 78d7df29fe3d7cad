"""UWB range model: Jacobians and the range-variance derivative against finite differences."""

import numpy as np

from uwbcal.pipeline.core.geometry import exp_so3
from uwbcal.pipeline.uwb.model import jacobians, range_model, range_variance


def _setup(n=7, seed=0):
    rng = np.random.default_rng(seed)
    R = exp_so3(rng.normal(size=(n, 3)))
    p = rng.normal(size=(n, 3)) * 3
    pT = rng.normal(size=(n, 3)) * 0.4
    x = np.array([5.0, -3.0, 2.0, 1.03, 0.4])
    A = rng.normal(size=(n, 6, 6)) * 0.05
    P = A @ np.swapaxes(A, 1, 2) + np.eye(6) * 1e-3
    return R, p, pT, x, P


def test_jacobians_match_finite_differences():
    R, p, pT, x, _ = _setup()
    J = jacobians(R, p, pT, x)
    assert np.allclose(J.h, range_model(R, p, pT, x))
    eps = 1e-6
    for i in range(6):
        dx = np.zeros(6)
        dx[i] = eps
        Rp = R @ exp_so3(dx[:3])  # right perturbation
        num = (range_model(Rp, p + dx[3:], pT, x) - range_model(R, p, pT, x)) / eps
        assert np.allclose(J.H_I[:, i], num, atol=1e-5)
    for i in range(5):
        dx = np.zeros(5)
        dx[i] = eps
        num = (range_model(R, p, pT, x + dx) - range_model(R, p, pT, x)) / eps
        assert np.allclose(J.H_U[:, i], num, atol=1e-5)


def test_range_variance_derivative_matches_finite_differences():
    R, p, pT, x, P = _setup()
    S, dS = range_variance(R, p, pT, x, P, 0.01)
    J = jacobians(R, p, pT, x)
    assert np.allclose(S, 0.01 + np.einsum("ni,nij,nj->n", J.H_I, P, J.H_I))
    eps = 1e-6
    for i in range(5):
        dx = np.zeros(5)
        dx[i] = eps
        num = (
            range_variance(R, p, pT, x + dx, P, 0.01)[0] - range_variance(R, p, pT, x - dx, P, 0.01)[0]
        ) / (2 * eps)
        assert np.allclose(dS[:, i], num, atol=1e-7)
