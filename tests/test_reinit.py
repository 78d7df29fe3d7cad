"""Online recovery of the MSCKF: the online health checks (`health.OnlineHealth`) fire on a window built to fail
them, not before a re-initialisation's stamp; the re-initialisation (`state.reset_window`) keeps the navigation
estimate and its cross-covariances, drops clones and landmarks, keeps P PSD and moves the first estimate."""

import numpy as np

from uwbcal.pipeline.core.state import ImuState, Kind, Pose, State, Vec, reset_window
from uwbcal.pipeline.vio.config import VioConfig
from uwbcal.pipeline.vio.estimator import TrajectoryRecord
from uwbcal.pipeline.vio.health import OnlineHealth, assess
from uwbcal.pipeline.vio.stats import VioStats

S = 1_000_000_000


def _stats(rates: list[tuple[int, int, int]]) -> VioStats:
    st = VioStats()
    for t, used, rej in rates:
        st.update_t.append(t)
        st.update_used.append(used)
        st.update_rejected.append(rej)
    return st


def _record(n: int, v: float) -> TrajectoryRecord:
    h = TrajectoryRecord()
    for k in range(n):
        h.append(k * S // 10, np.eye(3), np.array([v * k / 10, 0.0, 0.0]), np.eye(6) * 1e-4)
    return h


def test_the_chi2_check_fires_on_its_window_and_restarts_after_a_reinit():
    cfg = VioConfig()
    det = OnlineHealth(cfg)
    t = [k * S // 3 for k in range(30)]  # 3 Hz updates of 20 tracks, failing from the 20th on
    st = _stats([(tk, 18 if k < 20 else 5, 2 if k < 20 else 15) for k, tk in enumerate(t)])
    hist = _record(100, 0.5)
    rates = list(zip(t, st.update_used, st.update_rejected, strict=True))
    for k in range(20):  # healthy up to the 20th update
        assert det.check(t[k], _stats(rates[: k + 1]), hist, 0.1) is None
    f = det.check(t[-1], st, hist, 0.1)
    assert f is not None and f.check == "chi2" and f.value > cfg.consistency_max_rejected
    det.restart(t[-1])  # the update that fired is not judged again
    assert det.check(t[-1], st, hist, 0.1) is None
    # the same figure after the fact: assess from the re-initialisation on finds nothing either
    t_r, frac, n = st.rejection_rate(cfg.consistency_window_s, cfg.consistency_min_tracks, t[-1] + 1)
    assert assess(hist.arrays(), cfg, (t_r, frac, n), online_from_ns=t[-1] + 1) is None
    f2 = assess(hist.arrays(), cfg, st.rejection_rate(cfg.consistency_window_s, cfg.consistency_min_tracks))
    assert f2.check == "chi2" and t[20] <= f2.t_ns <= t[-1]


def test_speed_and_position_sigma_fire_online():
    cfg = VioConfig()
    det = OnlineHealth(cfg)
    fast = _record(20, 2 * cfg.max_speed)
    f = det.check(fast.t_ns[-1], VioStats(), fast, 0.1)
    assert f.check == "velocity" and f.value > cfg.max_speed
    det.restart(fast.t_ns[-1])  # no baseline inside the new stretch yet
    assert det.check(fast.t_ns[-1], VioStats(), fast, 0.1) is None
    slow = _record(20, 0.5)
    assert det.check(slow.t_ns[-1], VioStats(), slow, 2 * cfg.max_position_sigma).check == "covariance"


def _state() -> State:
    rng = np.random.default_rng(3)
    st = State(use_fej=True)
    x = ImuState(np.eye(3), np.zeros(3), np.ones(3), np.zeros(3), np.zeros(3))
    A = rng.normal(size=(15, 15)) * 0.1
    st.add("imu", x, A @ A.T + np.eye(15) * 1e-4, kind=Kind.NAV)
    st.add("anchor/1", Vec(np.array([1.0, 2.0, 3.0, 1.0, 0.0])), np.eye(5) * 0.01, kind=Kind.ANCHOR, key=1)
    for k in range(3):  # clones and a landmark correlated with the IMU and the anchor
        J = np.zeros((6, 15))
        J[:, :6] = np.eye(6)
        st.augment(f"clone/{k}", Pose(np.eye(3), np.full(3, k)), {"imu": J}, kind=Kind.CLONE, key=k)
    st.augment(
        "lm/7",
        Vec(np.ones(3)),
        {"imu": np.eye(3, 15), "anchor/1": np.eye(3, 5)},
        np.eye(3) * 1e-2,
        kind=Kind.LANDMARK,
        key=7,
    )
    H = np.zeros((2, st.size))
    H[:, st.slice("anchor/1")][:, :2] = np.eye(2)
    H[:, :2] += rng.normal(size=(2, 2))
    P = st.P
    K = P @ H.T @ np.linalg.inv(H @ P @ H.T + np.eye(2))
    st.P = P - K @ H @ P  # an update: the IMU and the anchor correlated
    return st


def test_reset_window_keeps_the_imu_estimate_and_its_cross_covariance_and_p_psd():
    st = _state()
    x = st.value("imu")
    st.set_value("imu", x.boxplus(np.full(15, 0.01)))  # an update moved the estimate away from its FEJ
    cross = st.cov("imu", "anchor/1").copy()
    P_imu = st.cov("imu").copy()
    infl = np.diag(np.repeat([0.05, 0.3, 0.5, 0.0, 0.0], 3) ** 2)
    reset_window(st, infl)
    assert st.of_kind(Kind.CLONE) == [] and st.of_kind(Kind.LANDMARK) == []
    assert sorted(st.names) == ["anchor/1", "imu"]
    assert np.allclose(st.cov("imu"), P_imu + infl) and np.allclose(st.cov("imu", "anchor/1"), cross)
    idx = st.index(["imu", "anchor/1"])
    P = st.P[np.ix_(idx, idx)]
    assert np.allclose(P, P.T) and np.linalg.eigvalsh(P).min() > 0
    assert np.allclose(st.fej("imu").p, st.value("imu").p) and np.allclose(st.fej("imu").v, st.value("imu").v)
