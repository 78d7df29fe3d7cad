"""The state container and the one EKF update: closed forms, Schmidt behaviour, initialisation."""

import numpy as np
import pytest

from uwbcal.pipeline.core.geometry import exp_so3, log_so3
from uwbcal.pipeline.core.state import (
    ImuState,
    Kind,
    Pose,
    State,
    Vec,
    _lower_solve,
    covariance_upper_bound,
    ekf_update,
)


def _random_spd(rng, n):
    A = rng.normal(size=(n, n))
    return A @ A.T + n * np.eye(n)


def _two_var_state(rng):
    s = State()
    s.add("a", Vec(np.zeros(3)), np.eye(3))
    s.add("b", Vec(np.zeros(2)), np.eye(2))
    P = _random_spd(rng, 5)
    s.P = P
    return s


def test_ekf_update_matches_closed_form_kalman():
    rng = np.random.default_rng(1)
    s = _two_var_state(rng)
    P0 = s.P.copy()
    H = rng.normal(size=(2, 5))
    R = np.diag([0.3, 0.5])
    r = rng.normal(size=2)
    res = ekf_update(s, {"a": H[:, :3], "b": H[:, 3:]}, r, R)
    S = H @ P0 @ H.T + R
    K = P0 @ H.T @ np.linalg.inv(S)
    np.testing.assert_allclose(s.P, P0 - K @ S @ K.T, atol=1e-12)
    np.testing.assert_allclose(np.r_[s.value("a").x, s.value("b").x], K @ r, atol=1e-12)
    assert res.accepted and res.nis == pytest.approx(r @ np.linalg.solve(S, r))


def test_schmidt_keeps_considered_block_and_updates_cross_covariance():
    rng = np.random.default_rng(2)
    s = _two_var_state(rng)
    P0 = s.P.copy()
    H = rng.normal(size=(1, 5))
    R = np.array([[0.2]])
    ekf_update(s, {"a": H[:, :3], "b": H[:, 3:]}, np.array([0.7]), R, schmidt={"a"})
    np.testing.assert_array_equal(s.value("a").x, np.zeros(3))
    np.testing.assert_allclose(s.P[:3, :3], P0[:3, :3], atol=1e-14)
    # paper: P_UU -= K_U S K_U^T and P_rU -= P_r H^T S^-1 H P_U (with the optimal gain rows)
    S = H @ P0 @ H.T + R
    K = P0 @ H.T @ np.linalg.inv(S)
    np.testing.assert_allclose(s.P[3:, 3:], P0[3:, 3:] - K[3:] @ S @ K[3:].T, atol=1e-12)
    np.testing.assert_allclose(s.P[:3, 3:], P0[:3, 3:] - K[:3] @ S @ K[3:].T, atol=1e-12)
    assert np.linalg.eigvalsh(s.P).min() > 0


def test_chi2_gate_rejects_outlier_without_change():
    s = State()
    s.add("x", Vec(np.zeros(1)), np.eye(1))
    res = ekf_update(s, {"x": np.eye(1)}, np.array([100.0]), 1.0, chi2_gate=0.95)
    assert not res.accepted
    assert s.value("x").x[0] == 0 and s.P[0, 0] == 1


def test_augment_clone_has_exact_covariance():
    rng = np.random.default_rng(3)
    s = State()
    s.add("imu", ImuState(np.eye(3), np.zeros(3), np.zeros(3)), _random_spd(rng, 15), kind=Kind.NAV)
    J = np.zeros((6, 15))
    J[:, :6] = np.eye(6)
    s.augment("clone/0", s.value("imu").pose, {"imu": J}, kind=Kind.CLONE, key=0)
    assert s.clones == [(0, "clone/0")] and s.nav == "imu"
    np.testing.assert_allclose(s.cov("clone/0"), s.cov("imu")[:6, :6])
    np.testing.assert_allclose(s.cov("clone/0", "imu"), s.cov("imu")[:6, :])
    s.remove("clone/0")
    assert s.size == 15 and s.names == ["imu"]


def test_initialize_equals_joint_batch_estimate():
    """Initialising a new variable then updating equals a batch solution on the joint linear system."""
    rng = np.random.default_rng(4)
    s = State()
    P0 = _random_spd(rng, 3) * 0.1
    s.add("x", Vec(np.zeros(3)), P0)
    x_true = rng.multivariate_normal(np.zeros(3), P0)
    y_true = rng.normal(size=2)
    m = 6
    Hx = rng.normal(size=(m, 3))
    Hy = rng.normal(size=(m, 2))
    Rv = np.full(m, 0.05)
    z = Hx @ x_true + Hy @ y_true + rng.normal(size=m) * np.sqrt(Rv)
    # Batch: information form of prior on x + measurements
    Hj = np.hstack([Hx, Hy])
    info = Hj.T @ np.diag(1 / Rv) @ Hj
    info[:3, :3] += np.linalg.inv(P0)
    P_batch = np.linalg.inv(info)
    mean_batch = P_batch @ (Hj.T @ (z / Rv))
    # Filter: estimate y from the linear system at x_hat = 0 (the optimal y given x_hat = 0 for the QR part)
    Q, Rr = np.linalg.qr(Hy, mode="complete")
    y0 = np.linalg.solve(Rr[:2], (Q.T @ z)[:2])
    r = z - Hy @ y0
    s.initialize("y", Vec(y0), {"x": Hx}, Hy, r, Rv)
    np.testing.assert_allclose(s.P, P_batch, atol=1e-10)
    np.testing.assert_allclose(np.r_[s.value("x").x, s.value("y").x], mean_batch, atol=1e-10)


def test_pose_boxplus_is_right_perturbation():
    R = exp_so3(np.array([0.1, -0.2, 0.3]))
    pose = Pose(R, np.zeros(3))
    dx = np.array([0.01, 0.02, -0.03, 1, 2, 3])
    out = pose.boxplus(dx)
    np.testing.assert_allclose(log_so3(R.T @ out.R), dx[:3], atol=1e-12)
    np.testing.assert_allclose(out.p, dx[3:])


def test_fej_switch():
    s = State(use_fej=True)
    s.add("a", Vec(np.zeros(1)), np.eye(1))
    s.set_value("a", Vec(np.ones(1)))
    assert s.fej("a").x[0] == 0
    s.use_fej = False
    assert s.fej("a").x[0] == 1


def test_considered_variables_and_pose_probes():
    """A probe keeps the pose of its time as a considered variable: no update changes it or its own block, its
    cross-covariances follow the updates exactly (as an explicit Schmidt update would), and it can be dropped."""
    from uwbcal.pipeline.core.state import add_probe, remove_probes

    rng = np.random.default_rng(5)
    s = State()
    s.add(
        "imu",
        Pose(exp_so3(rng.normal(size=3)), rng.normal(size=3)),
        _random_spd(rng, 6) * 1e-2,
        kind=Kind.NAV,
    )
    name = add_probe(s, 1_000)
    assert s.probes == [(1_000, name)] and name in s.considered
    np.testing.assert_allclose(s.cov(name), s.cov("imu"), atol=1e-15)  # a copy of the pose at its time
    P0, x0 = s.P.copy(), s.value("imu")
    H = rng.normal(size=(2, 6))
    r = rng.normal(size=2)
    ekf_update(s, {"imu": H}, r, 0.1)
    # the Schmidt-Kalman update written out (Joseph form with the probe's gain rows zeroed), independently of
    # ekf_update's Schmidt branch
    Hf = np.hstack([H, np.zeros((2, 6))])
    Rm = 0.1 * np.eye(2)
    S = Hf @ P0 @ Hf.T + Rm
    K = P0 @ Hf.T @ np.linalg.inv(S)
    K[6:] = 0.0
    A = np.eye(12) - K @ Hf
    np.testing.assert_allclose(s.P, A @ P0 @ A.T + K @ Rm @ K.T, atol=1e-13)
    np.testing.assert_array_equal(s.P[6:, 6:], P0[6:, 6:])  # the probe's own block: untouched
    assert np.abs(s.P[:6, 6:] - P0[:6, 6:]).max() > 1e-4  # its cross-covariance did follow the update
    np.testing.assert_allclose(log_so3(x0.R.T @ s.value("imu").R), (K @ r)[0:3], atol=1e-12)
    np.testing.assert_allclose(s.value("imu").p, x0.p + (K @ r)[3:6], atol=1e-12)
    np.testing.assert_array_equal(s.value(name).p, x0.p)
    remove_probes(s)
    assert s.probes == [] and not s.considered and s.names == ["imu"]


# -- the robust (IRLS-weighted) update: closed form -----------------------------------------------------------------
def _robust_case(seed=6):
    rng = np.random.default_rng(seed)
    s = _two_var_state(rng)
    H = rng.normal(size=(1, 5))
    return s, H, s.P.copy()


@pytest.mark.parametrize("loss", ["huber", "cauchy"])
@pytest.mark.parametrize("sigmas", [0.5, 2.0, 8.0])
def test_robust_update_is_the_reweighted_kalman_update(loss, sigmas):
    """A one-row update with robust=(loss, c) equals the plain update with S -> S / w: gain w K, P - w K S K^T,
    state w K r; w from the whitened innovation e = |r| / sqrt(S) (Huber: min(1, c/e); Cauchy: 1/(1+(e/c)^2))."""
    c = 1.5
    s, H, P0 = _robust_case()
    R = 0.2
    S = float((H @ P0 @ H.T)[0, 0]) + R
    r = np.array([sigmas * np.sqrt(S)])
    w = min(1.0, c / sigmas) if loss == "huber" else 1.0 / (1.0 + (sigmas / c) ** 2)
    res = ekf_update(s, {"a": H[:, :3], "b": H[:, 3:]}, r, R, robust=(loss, c))
    K = (P0 @ H.T / S)[:, 0]
    assert res.accepted and res.nis == pytest.approx(sigmas**2)
    np.testing.assert_allclose(s.P, P0 - w * S * np.outer(K, K), atol=1e-12)
    np.testing.assert_allclose(np.r_[s.value("a").x, s.value("b").x], w * K * r[0], atol=1e-12)
    if loss == "huber" and sigmas < c:  # inside the Huber threshold: exactly the plain update
        ref = _robust_case()[0]
        ekf_update(ref, {"a": H[:, :3], "b": H[:, 3:]}, r, R)
        np.testing.assert_allclose(s.P, ref.P, atol=1e-14)


def test_robust_update_whitens_with_robust_R():
    """robust_R replaces R in the whitening variance only: e = |r| / sqrt(S - R + robust_R); the update itself
    still uses R."""
    s, H, P0 = _robust_case(7)
    c = 1.0
    HPH = float((H @ P0 @ H.T)[0, 0])
    R, R_w = 20.0 * HPH, 0.01 * HPH  # R inflated (e.g. for correlated errors), R_w the per-sample noise
    S = HPH + R
    r = np.array([2.0 * np.sqrt(HPH + R_w)])
    e = abs(r[0]) / np.sqrt(HPH + R_w)
    w = min(1.0, c / e)
    assert w < 1.0 and abs(r[0]) / np.sqrt(S) < c  # the inflated R alone would not have down-weighted it
    ekf_update(s, {"a": H[:, :3], "b": H[:, 3:]}, r, R, robust=("huber", c), robust_R=R_w)
    K = (P0 @ H.T / S)[:, 0]
    np.testing.assert_allclose(s.P, P0 - w * S * np.outer(K, K), atol=1e-12)
    with pytest.raises(ValueError, match="unknown robust"):
        ekf_update(_robust_case()[0], {"a": H[:, :3], "b": H[:, 3:]}, np.array([5.0]), R, robust=("l1", 1.0))


def test_propagate_is_phi_p_phi_t_plus_q_on_the_joint_covariance():
    rng = np.random.default_rng(8)
    s = _two_var_state(rng)
    P0 = s.P.copy()
    Phi = rng.normal(size=(3, 3))
    Q = _random_spd(rng, 3)
    s.propagate("a", Phi, Q)
    F = np.eye(5)
    F[:3, :3] = Phi
    Qf = np.zeros((5, 5))
    Qf[:3, :3] = Q
    np.testing.assert_allclose(s.P, F @ P0 @ F.T + Qf, atol=1e-12)


def test_clone_window_reuses_slots_without_reallocating():
    """Adding and removing clones keeps the covariance buffer (no whole-matrix copy): a removed clone's slot is
    zeroed and taken by the next clone; the capacity doubles only when the buffer is full. The covariance equals
    that of a dense reference that appends and deletes rows and columns (closed-form Kalman update)."""
    rng = np.random.default_rng(9)
    s = State(capacity=64)
    P_imu = _random_spd(rng, 15)
    s.add("imu", ImuState(np.eye(3), np.zeros(3), np.zeros(3)), P_imu, kind=Kind.NAV)
    J = np.zeros((6, 15))
    J[:, :6] = np.eye(6)
    names, Pd = ["imu"], P_imu.copy()  # the dense reference, in the order of names
    buf = s._buf
    for k in range(30):
        s.augment(f"clone/{k}", s.value("imu").pose, {"imu": J}, kind=Kind.CLONE, key=k)
        Jd = np.zeros((6, len(Pd)))
        Jd[:, :6] = np.eye(6)
        Pd = np.block([[Pd, Pd @ Jd.T], [Jd @ Pd, Jd @ Pd @ Jd.T]])
        names.append(f"clone/{k}")
        Hc, Hi = rng.normal(size=(2, 6)), rng.normal(size=(2, 15))
        ekf_update(s, {f"clone/{k}": Hc, "imu": Hi}, rng.normal(size=2), 1.0)
        Hd = np.zeros((2, len(Pd)))
        Hd[:, :15], Hd[:, -6:] = Hi, Hc
        Kd = Pd @ Hd.T @ np.linalg.inv(Hd @ Pd @ Hd.T + np.eye(2))
        Pd = Pd - Kd @ Hd @ Pd
        if len(s.clones) > 5:
            oldest = s.clones[0][1]
            s.remove(oldest)
            i = 15 + 6 * (names.index(oldest) - 1)
            Pd = np.delete(np.delete(Pd, np.s_[i : i + 6], 0), np.s_[i : i + 6], 1)
            names.remove(oldest)
        assert s._buf is buf  # 15 + 6 * 6 <= 64: never reallocated
    assert [t for t, _ in s.clones] == list(range(25, 30)) and s.names == names
    idx = s.index(names)
    assert len(set(idx)) == s.size - 6  # one free slot (zero rows and columns) waits for the next clone
    free = np.setdiff1d(np.arange(s.size), idx)
    assert not s.P[free].any() and not s.P[:, free].any()
    np.testing.assert_allclose(s.P[np.ix_(idx, idx)], Pd, atol=1e-9)
    for k in range(20):  # growth: doubling keeps every block
        before = {n: s.cov(n).copy() for n in s.names}
        s.augment(f"clone/{100 + k}", s.value("imu").pose, {"imu": J}, kind=Kind.CLONE, key=100 + k)
        assert all(np.array_equal(s.cov(n), c) for n, c in before.items())
    assert s._buf.shape[0] >= s.size and s._buf is not buf


def test_dropping_most_of_the_state_packs_the_covariance():
    """Probes dropped at once leave more free slots than used ones: the state packs them (P shrinks to the
    variables left) and keeps every remaining block."""
    from uwbcal.pipeline.core.state import add_probe, remove_probes

    rng = np.random.default_rng(10)
    s = State()
    s.add("imu", ImuState(np.eye(3), np.zeros(3), np.zeros(3)), _random_spd(rng, 15), kind=Kind.NAV)
    for k in range(40):
        add_probe(s, k)
    s.add("anchor/1", Vec(np.ones(5)), _random_spd(rng, 5), kind=Kind.ANCHOR, key=1)
    ekf_update(
        s, {"imu": rng.normal(size=(3, 15)), "anchor/1": rng.normal(size=(3, 5))}, rng.normal(size=3), 1.0
    )
    keep = {(a, b): s.cov(a, b).copy() for a in ("imu", "anchor/1") for b in ("imu", "anchor/1")}
    remove_probes(s)
    assert s.names == ["imu", "anchor/1"] and s.anchors == {1: "anchor/1"}
    assert s.size <= 2 * 20  # 40 probes (240 rows) gone: at most as many free rows as used ones are left
    assert all(np.array_equal(s.cov(a, b), c) for (a, b), c in keep.items())


def test_boxplus_of_many_poses_is_pose_boxplus():
    rng = np.random.default_rng(4)
    s = State()
    s.add("v", Vec(rng.normal(size=2)), np.eye(2))
    for k in range(5):
        s.add(f"c{k}", Pose(exp_so3(rng.normal(size=3)), rng.normal(size=3)), np.eye(6))
    dx = rng.normal(size=s.size) * 1e-2
    dx[s.slice("c2")] = 0.0  # no correction: the value object stays
    before = {n: s.value(n) for n in s.names}
    s.boxplus(dx)
    for n in s.names:
        expect = before[n].boxplus(dx[s.slice(n)]) if dx[s.slice(n)].any() else before[n]
        got = s.value(n)
        for name in ("R", "p") if isinstance(got, Pose) else ("x",):
            # vectorised vs one pose at a time: equal to rounding (BLAS kernels differ between machines)
            np.testing.assert_allclose(getattr(got, name), getattr(expect, name), rtol=1e-14, atol=1e-14)
    assert s.value("c2") is before["c2"]


def test_lower_solve_is_scipys_solve_triangular():
    from scipy.linalg import solve_triangular

    rng = np.random.default_rng(5)
    for n, k in [(1, 1), (3, 2), (40, 70)]:
        L = np.linalg.cholesky(_random_spd(rng, n))
        for b in (rng.normal(size=n), rng.normal(size=(k, n)).T):
            ref = solve_triangular(L, b, lower=True, check_finite=False)
            np.testing.assert_allclose(_lower_solve(L, b), ref, rtol=1e-12, atol=1e-12 * np.abs(ref).max())


def test_covariance_upper_bound_is_the_larger_along_common_axes():
    """Against its definition on random pairs: it bounds both, lies below their sum, is one of them when that one
    is the larger, and a change of units (T) commutes with it. (The positive part of their difference added to
    one of them exceeds their sum on every one of these pairs.)"""
    rng = np.random.default_rng(3)

    def spd():  # correlated, in units four decades apart (an anchor's metres against its scale)
        S = np.diag(10.0 ** rng.uniform(-2, 2, 5))
        M = rng.normal(size=(5, 5))
        return S @ (M @ M.T + 0.1 * np.eye(5)) @ S

    for _ in range(50):
        A, B = spd(), spd()
        C = covariance_upper_bound(A, B)
        for lower in (A, B):
            assert np.linalg.eigvalsh(C - lower).min() > -1e-9 * np.trace(C)
        assert np.linalg.eigvalsh(A + B - C).min() > -1e-9 * np.trace(C)
        tol = {"rtol": 1e-6, "atol": 1e-9 * np.abs(A + B).max()}
        np.testing.assert_allclose(covariance_upper_bound(B, A + B), A + B, **tol)
        np.testing.assert_allclose(covariance_upper_bound(A + B, B), A + B, **tol)
        T = np.diag(10.0 ** rng.uniform(-2, 2, 5)) @ _random_spd(rng, 5)
        np.testing.assert_allclose(
            covariance_upper_bound(T @ A @ T.T, T @ B @ T.T),
            T @ C @ T.T,
            rtol=1e-7,
            atol=1e-9 * np.abs(T @ C @ T.T).max(),
        )


def test_covariance_upper_bound_of_a_singular_covariance():
    """A rank-deficient B (a variable nothing constrains in one of the two) still gives a bound of both."""
    rng = np.random.default_rng(5)
    M = rng.normal(size=(5, 3))
    A, B = _random_spd(rng, 5), M @ M.T
    C = covariance_upper_bound(A, B)
    for lower in (A, B):
        assert np.linalg.eigvalsh(C - lower).min() > -1e-9 * np.trace(C)
