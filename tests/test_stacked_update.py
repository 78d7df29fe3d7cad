"""Stacked range updates per epoch: ekf_update(per_row=True) against sequential scalar updates and closed forms;
UwbUpdater.update_epoch against UwbUpdater.update."""

from __future__ import annotations

import copy

import numpy as np
import pytest
from scipy.stats import chi2

from uwbcal.pipeline.core.geometry import exp_so3
from uwbcal.pipeline.core.state import Kind, Pose, State, Vec, ekf_update
from uwbcal.pipeline.uwb.updater import UwbUpdater
from uwbcal.pipeline.vio.estimator import RangeMeasurement

ARMS = {(1, 0): np.array([0.2, 0.3, 0.0]), (2, 0): np.array([0.2, -0.3, 0.1])}


def _state(n_anchors: int = 3, seed: int = 0) -> State:
    rng = np.random.default_rng(seed)
    st = State()
    A = rng.normal(size=(6, 6)) * 0.05
    st.add(
        "imu",
        Pose(exp_so3(np.array([0.1, -0.2, 0.3])), np.array([1.0, 2.0, 0.5])),
        A @ A.T + 1e-4 * np.eye(6),
        kind=Kind.NAV,
    )
    st.add("clone/1", Pose(np.eye(3), np.zeros(3)), np.eye(6) * 0.01, kind=Kind.CLONE, key=1)
    st.P[0:6, 6:12] = st.P[6:12, 0:6] = 0.005 * np.eye(6)
    for a in range(n_anchors):
        J = np.zeros((5, 6))
        J[0:3, 3:6] = -np.eye(3)
        pos = np.array([6.0 * np.cos(2.1 * a), 6.0 * np.sin(2.1 * a), 2.0 + a])
        Q = np.diag([0.04] * 3 + [2.5e-3, 0.04])
        st.augment(f"anchor/{a}", Vec(np.r_[pos, 1.0, 0.2]), {"imu": J}, Q=Q, kind=Kind.ANCHOR, key=a)
    return st


def _linear_rows(st: State, m: int, seed: int = 1):
    rng = np.random.default_rng(seed)
    H = {
        "imu": rng.normal(size=(m, 6)),
        "anchor/0": rng.normal(size=(m, 5)),
        "anchor/2": rng.normal(size=(m, 5)),
    }
    r = rng.normal(size=m) * 0.2
    Rd = rng.uniform(0.005, 0.02, m)
    return H, r, Rd


def _flat(st: State) -> np.ndarray:
    return np.concatenate(
        [st.value(n).x if isinstance(st.value(n), Vec) else st.value(n).p for n in st.names]
    )


def _vec_state(seed: int = 0) -> State:
    """Vector variables only: boxplus is addition, so sequential linear updates compose exactly."""
    rng = np.random.default_rng(seed)
    st = State()
    for name, dim in (("imu", 6), ("anchor/0", 5), ("anchor/2", 5)):
        A = rng.normal(size=(dim, dim)) * 0.1
        st.add(name, Vec(rng.normal(size=dim)), A @ A.T + 1e-3 * np.eye(dim))
    C = 0.002 * rng.normal(size=(6, 5))
    st.P[0:6, 6:11], st.P[6:11, 0:6] = C, C.T
    return st


def test_stacked_equals_sequential_for_a_linear_model():
    """EKF: one stacked update of m independent rows = m sequential scalar updates of the same linear model."""
    st = _vec_state()
    H, r, Rd = _linear_rows(st, 6)
    seq, stk = copy.deepcopy(st), copy.deepcopy(st)
    x0 = _flat(st)
    for i in range(6):  # a later row's residual is r_i - H_i (x - x0): the model is linear
        Hi = {v: h[i : i + 1] for v, h in H.items()}
        dx = _flat(seq) - x0
        pred = sum(Hi[v] @ dx[st.slice(v)] for v in H)[0]
        ekf_update(seq, Hi, np.array([r[i] - pred]), Rd[i])
    res = ekf_update(stk, H, r, Rd[None, :], per_row=True)
    assert res.accepted and res.row_accepted.all() and res.dof == 6
    np.testing.assert_allclose(stk.P, seq.P, atol=1e-12)
    np.testing.assert_allclose(_flat(stk), _flat(seq), atol=1e-12)


def test_stacked_schmidt_is_the_dense_joseph_update():
    """Schmidt (sequential Schmidt updates are order-dependent, so no sequential reference): the stacked update
    against a dense textbook one, K = P H^T S^-1 with the considered rows zeroed, Joseph form."""
    st = _vec_state()
    H, r, Rd = _linear_rows(st, 6)
    Hf = np.zeros((6, st.size))
    for v, h in H.items():
        Hf[:, st.slice(v)] = h
    P = st.P
    K = P @ Hf.T @ np.linalg.inv(Hf @ P @ Hf.T + np.diag(Rd))
    K[st.slice("imu")] = 0.0
    IKH = np.eye(st.size) - K @ Hf
    P_ref = IKH @ P @ IKH.T + K @ np.diag(Rd) @ K.T
    x_ref = _flat(st) + K @ r
    ekf_update(st, H, r, Rd[None, :], schmidt=["imu"], per_row=True)
    np.testing.assert_allclose(st.P, P_ref, atol=1e-13)
    np.testing.assert_allclose(_flat(st), x_ref, atol=1e-13)


def test_per_row_gate_drops_the_outlier_row_only():
    st = _state()
    H, r, Rd = _linear_rows(st, 5)
    r[2] = 50.0  # gross outlier
    a, b = copy.deepcopy(st), copy.deepcopy(st)
    res = ekf_update(a, H, r, Rd[None, :], chi2_gate=0.99, per_row=True)
    assert res.row_accepted.tolist() == [True, True, False, True, True] and res.dof == 4
    keep = [0, 1, 3, 4]
    ekf_update(b, {v: h[keep] for v, h in H.items()}, r[keep], Rd[keep][None, :], per_row=True)
    # the same update along two code paths (a gated row dropped vs never there): equal to rounding, relative to
    # the covariance's scale (BLAS kernels differ between machines in the last bits)
    np.testing.assert_allclose(a.P, b.P, rtol=0, atol=1e-12 * np.abs(st.P).max())
    np.testing.assert_allclose(_flat(a), _flat(b), rtol=0, atol=1e-12 * (1 + np.abs(_flat(st)).max()))
    # the row NIS is r_i^2 / S_ii, S = H P H^T + R (closed form)
    Hf = np.zeros((5, st.size))
    for v, h in H.items():
        Hf[:, st.slice(v)] = h
    S = Hf @ st.P @ Hf.T + np.diag(Rd)
    np.testing.assert_allclose(res.row_nis, r**2 / np.diag(S), rtol=1e-12)
    assert res.gate == pytest.approx(chi2.ppf(0.99, 1))
    none = ekf_update(copy.deepcopy(st), H, r * 1e3, Rd[None, :], chi2_gate=0.9, per_row=True)
    assert not none.accepted and not none.row_accepted.any()


def test_per_row_cauchy_weights_inflate_each_row_by_hand():
    st = _state()
    H, r, Rd = _linear_rows(st, 3)
    r[1] = 3.0
    Hf = np.zeros((3, st.size))
    for v, h in H.items():
        Hf[:, st.slice(v)] = h
    d = np.diag(Hf @ st.P @ Hf.T) + Rd
    c = np.array([1.5, 2.0, 2.5])
    w = 1.0 / (1.0 + (np.abs(r) / np.sqrt(d) / c) ** 2)
    a, b = copy.deepcopy(st), copy.deepcopy(st)
    ekf_update(a, H, r, Rd[None, :], robust=("cauchy", c), per_row=True)
    ekf_update(b, H, r, (Rd + d / w - d)[None, :], per_row=True)  # R_ii + (1/w_i - 1) S_ii
    np.testing.assert_allclose(a.P, b.P, atol=1e-14)
    np.testing.assert_allclose(_flat(a), _flat(b), atol=1e-14)


def test_one_row_is_the_scalar_update_bit_for_bit():
    st = _state()
    H, r, Rd = _linear_rows(st, 1)
    a, b = copy.deepcopy(st), copy.deepcopy(st)
    ra = ekf_update(a, H, r, Rd[0], chi2_gate=0.95, robust=("cauchy", 1.0), robust_R=Rd[0] / 2)
    rb = ekf_update(b, H, r, Rd[0], chi2_gate=0.95, robust=("cauchy", 1.0), robust_R=Rd[0] / 2, per_row=True)
    assert np.array_equal(a.P, b.P) and np.array_equal(_flat(a), _flat(b)) and ra == rb


def _epoch(st: State, k: int) -> list[RangeMeasurement]:
    pose = st.value("imu")
    out = []
    for i in range(k):
        a, tag = i % 3, 1 + (i // 3) % 2
        x = st.value(f"anchor/{a}").x
        d = x[3] * np.linalg.norm(pose.p + pose.R @ ARMS[(tag, 0)] - x[:3]) + x[4] + 0.05 * np.sin(7 * i)
        out.append(RangeMeasurement(10, tag, 0, a, float(d)))
    return out


@pytest.mark.parametrize("mode", ["ekf", "skf"])
def test_update_epoch_matches_sequential_updates(mode):
    st = _state()
    batch = _epoch(st, 6)
    seq, stk = copy.deepcopy(st), copy.deepcopy(st)
    us = UwbUpdater(mode, ARMS, sigma_range=0.1, chi2_quantile=0.95)
    ub = UwbUpdater(mode, ARMS, sigma_range=0.1, chi2_quantile=0.95)
    for m in batch:
        us.update(seq, m)
    ub.update_epoch(stk, batch)
    assert ub.counts == us.counts and ub.counts["accepted"] == 6
    # the same information: the sequential residuals are re-predicted at the moving estimate, its R follows the
    # moving beta, and sequential Schmidt updates are order-dependent; the two agree to a small part of the update
    x0, P0 = _flat(st), st.P
    step_x, step_P = np.abs(_flat(seq) - x0).max(), np.abs(seq.P - P0).max()
    tol = 0.05 if mode == "ekf" else 0.2  # Schmidt: the sequential result depends on the order of the ranges
    assert np.abs(_flat(stk) - _flat(seq)).max() < tol * step_x
    assert np.abs(stk.P - seq.P).max() < tol * step_P
    for a in range(3):
        A, B = ub.arrays()[a], us.arrays()[a]
        assert A["t_ns"].tolist() == B["t_ns"].tolist() and A["x"].shape == B["x"].shape
    # the epoch's first range sees the same prior in both
    np.testing.assert_allclose(ub.arrays()[0]["residual"][0], us.arrays()[0]["residual"][0], atol=1e-12)


def test_frozen_epoch_is_the_batch_consider_update():
    """Frozen (localisation): one epoch is the batch Schmidt update written out here: S = H P H^T + R over
    [imu, clone, anchors], the gain P H^T S^-1 with the anchors' rows zeroed, Joseph form; the anchors' estimates
    and own covariance unchanged. (Sequential consider updates are not the batch one: each leaves the considered
    covariance as it was, so the order and the grouping matter; the epoch is the exact one.)"""
    from uwbcal.pipeline.uwb.model import jacobians

    st = _state()
    batch = _epoch(st, 6)
    P0 = st.P.copy()
    pose = st.value("imu")
    n = st.size
    H = np.zeros((6, n))
    r = np.zeros(6)
    for i, m in enumerate(batch):
        x = st.value(f"anchor/{m.anchor}").x
        J = jacobians(pose.R, pose.p, ARMS[(m.tag, 0)], x)
        H[i, 0:6] = J.H_I[0]
        H[i, st.slice(f"anchor/{m.anchor}")] = J.H_U[0]
        r[i] = m.distance - J.h[0]
    R = np.diag([(0.1 * st.value(f"anchor/{m.anchor}").x[3]) ** 2 for m in batch])
    S = H @ P0 @ H.T + R
    K = np.linalg.solve(S, H @ P0).T
    anchors = np.concatenate([np.arange(n)[st.slice(f"anchor/{a}")] for a in range(3)])
    K[anchors] = 0.0
    IKH = np.eye(n) - K @ H
    upd = UwbUpdater("frozen", ARMS, sigma_range=0.1, chi2_quantile=None)
    x_a = {a: st.value(f"anchor/{a}").x.copy() for a in range(3)}
    upd.update_epoch(st, batch)
    np.testing.assert_allclose(st.P, IKH @ P0 @ IKH.T + K @ R @ K.T, atol=1e-13)
    dx = K @ r
    np.testing.assert_allclose(st.value("imu").p, pose.p + dx[3:6], atol=1e-12)
    np.testing.assert_allclose(st.value("imu").R, pose.R @ exp_so3(dx[0:3]), atol=1e-12)
    for a in range(3):
        assert np.array_equal(st.value(f"anchor/{a}").x, x_a[a])
    np.testing.assert_array_equal(st.P[np.ix_(anchors, anchors)], P0[np.ix_(anchors, anchors)])
    assert upd.counts["accepted"] == 6


def test_update_epoch_of_one_range_is_update_and_skips_unknown_anchors():
    st = _state()
    m = _epoch(st, 1)
    a, b = copy.deepcopy(st), copy.deepcopy(st)
    ua, ub = UwbUpdater("ekf", ARMS, robust=("cauchy", 0.5)), UwbUpdater("ekf", ARMS, robust=("cauchy", 0.5))
    ua.update(a, m[0])
    ub.update_epoch(b, m + [RangeMeasurement(10, 1, 0, 42, 5.0)])  # anchor 42 unknown: skipped
    assert np.array_equal(a.P, b.P) and np.array_equal(_flat(a), _flat(b))
    assert ub.counts["skipped"] == 1 and ub.counts["accepted"] == 1


def test_driver_hands_each_stamp_to_an_epoch_handler_once(tmp_path):
    """Odometry + ranges to 3 anchors at each stamp: an epoch handler gets one batch per stamp; a plain handler
    every range (the updates themselves: the tests above)."""
    from uwbcal.convert.recording import RecordingReader
    from uwbcal.convert.tabular import convert_tabular
    from uwbcal.pipeline.run.driver import odometry_from_recording, run_estimator

    t0 = 1_700_000_000_000_000_000
    (tmp_path / "p.tum").write_text(
        "".join(f"{1_700_000_000 + 0.1 * k:.1f} {0.1 * k} 1 0 0 0 0 1\n" for k in range(40))
    )
    anchors = np.array([[5.0, 5.0, 2.0], [-3.0, 4.0, 1.0], [2.0, -6.0, 3.0]])
    rows = []
    for k in range(60):  # 60 stamps x 3 anchors, stamps between the odometry messages
        t = t0 + 5_000_000 + k * 50_000_000
        p = np.array([0.1 * (t - t0) * 1e-8, 1.0, 0.0])
        rows += [f"{t},1,0,{a},{np.linalg.norm(p - anchors[a]) + 0.3:.4f}" for a in range(3)]
    (tmp_path / "r.csv").write_text("stamp,tag,antenna,anchor,distance\n" + "\n".join(rows) + "\n")
    rec = tmp_path / "o.mcap"
    convert_tabular(tmp_path / "p.tum", tmp_path / "r.csv", rec)
    reader = RecordingReader(rec)

    class Counting:
        def __init__(self, epochs: bool) -> None:
            self.calls, self.sizes = 0, []
            if epochs:
                self.epoch = lambda est, batch: self.sizes.append(len(batch))

        def __call__(self, est, m) -> None:
            self.calls += 1

    for epochs, calls, sizes in ((True, 0, [3] * 60), (False, 3 * 60, [])):
        h = Counting(epochs)
        est = odometry_from_recording(reader)
        run_estimator(est, reader, None, None, on_range=h)
        assert h.calls == calls and h.sizes == sizes
        assert est.stats.ranges == 180 and est.stats.ranges_after_odometry == 0
