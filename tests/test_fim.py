"""Fisher information (general Gaussian) and the observability verdict."""

import numpy as np

from uwbcal.pipeline.uwb.fim import assess_observability, fisher_information
from uwbcal.pipeline.uwb.model import jacobians, range_variance


def _planar(n=300, z=1.0):
    t = np.arange(n) * 0.1
    p = np.stack([4 * np.sin(0.3 * t), 3 * np.cos(0.21 * t), np.full_like(t, z)], axis=1)
    R = np.broadcast_to(np.eye(3), (n, 3, 3))
    return R, p


def test_fim_matches_kay_formula_by_finite_differences():
    rng = np.random.default_rng(0)
    n = 50
    R = np.broadcast_to(np.eye(3), (n, 3, 3))
    p = rng.normal(size=(n, 3)) * 3
    pT = np.array([0.1, 0.0, 0.2])
    A = rng.normal(size=(n, 6, 6)) * 0.1
    P = A @ np.swapaxes(A, 1, 2)
    x = np.array([5.0, 4.0, 3.0, 1.0, 0.2])
    F = fisher_information(R, p, pT, P, x, 0.01, params=range(5))
    eps = 1e-6
    dh = np.zeros((n, 5))
    dS = np.zeros((n, 5))
    S, _ = range_variance(R, p, pT, x, P, 0.01)
    for i in range(5):
        dx = np.zeros(5)
        dx[i] = eps
        dh[:, i] = (jacobians(R, p, pT, x + dx).h - jacobians(R, p, pT, x - dx).h) / (2 * eps)
        dS[:, i] = (
            range_variance(R, p, pT, x + dx, P, 0.01)[0] - range_variance(R, p, pT, x - dx, P, 0.01)[0]
        ) / (2 * eps)
    Si = np.diag(1 / S)
    F_num = dh.T @ Si @ dh + 0.5 * np.array(
        [[np.trace(Si @ np.diag(dS[:, i]) @ Si @ np.diag(dS[:, j])) for j in range(5)] for i in range(5)]
    )
    assert np.allclose(F, F_num, rtol=1e-5)
    # the trace term is what makes F depend on the pose covariance beyond the weights: more uncertainty, less info
    F_big = fisher_information(R, p, pT, P * 4, x, 0.01, params=range(5))
    assert np.linalg.slogdet(F_big)[1] < np.linalg.slogdet(F)[1]


def test_planar_flight_flagged_degenerate_in_z():
    R, p = _planar()
    anchor_in_plane = np.array([6.0, 5.0, 1.0, 1.0, 0.3])
    rep = assess_observability(R, p, np.zeros(3), np.eye(6) * 1e-4, anchor_in_plane, 0.01)
    assert rep.status == "refused"
    assert rep.weak_axis.startswith("z")
    assert rep.rcond < 1e-9
    assert any("planar" in m and "weak axis z" in m for m in rep.warnings)
    forced = assess_observability(R, p, np.zeros(3), np.eye(6) * 1e-4, anchor_in_plane, 0.01, force=True)
    assert forced.status == "warning"
    # anchor above the plane: z informative locally but the plane makes it ambiguous -> warning naming z
    above = np.array([6.0, 5.0, 5.0, 1.0, 0.3])
    rep2 = assess_observability(R, p, np.zeros(3), np.eye(6) * 1e-4, above, 0.01)
    assert rep2.status == "warning" and any("weak axis z" in m for m in rep2.warnings)
    assert np.isfinite(rep2.logdet) and rep2.logdet > rep.logdet


def test_3d_flight_ok():
    t = np.arange(300) * 0.1
    p = np.stack([4 * np.sin(0.3 * t), 3 * np.cos(0.21 * t), 1 + 1.5 * np.sin(0.17 * t)], axis=1)
    R = np.broadcast_to(np.eye(3), (300, 3, 3))
    rep = assess_observability(R, p, np.zeros(3), np.eye(6) * 1e-4, np.array([6.0, 5.0, 3.0, 1.0, 0.3]), 0.01)
    assert rep.status == "ok" and not rep.warnings
