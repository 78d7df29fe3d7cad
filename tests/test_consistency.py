"""Two-sided filter consistency over Monte Carlo runs, and a test of these tests.

- The odometry filter against drift drawn *here*, from a noise formula written out in this file (not the filter's
  `increment_noise`, which the simulator uses): pooled pose ANEES at fixed checkpoints inside two-sided χ² bounds.
- The MSCKF over 20 seeds of the small visual-inertial simulator (tests/support.py): time-averaged 6-DoF pose
  NEES, averaged over the runs, inside the χ² bounds of the run average; FEJ not worse than no FEJ.
- The test of the tests: the covariance the filters report (`TrajectoryRecord.arrays`) scaled by 1.5 or 0.67
  makes every consistency check fail, and by 1.0 pass.

The runs are computed once per module (fixtures) and kept on one xdist worker (``xdist_group``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pytest
from scipy.stats import chi2

from uwbcal.convert.recording import RecordingReader, RecordingWriter
from uwbcal.pipeline.core.geometry import exp_so3, log_so3, quat_to_rot, rot_to_quat
from uwbcal.pipeline.run.driver import msckf_from_recording, odometry_from_recording, run_estimator
from uwbcal.pipeline.vio.config import VioConfig
from uwbcal.pipeline.vio.estimator import TrajectoryRecord
from uwbcal.pipeline.vio.groundtruth import groundtruth_state
from uwbcal.pipeline.vio.odometry_filter import OdometryFilterConfig

from support import T0, errors_vs_truth, simulate_vi

pytestmark = pytest.mark.xdist_group("consistency")


@dataclass
class Verdict:
    anees: float
    lo: float
    hi: float

    @property
    def inside(self) -> bool:
        return self.lo < self.anees < self.hi


def _nees(e: np.ndarray, cov: np.ndarray) -> np.ndarray:
    return np.einsum("ki,ki->k", e, np.linalg.solve(cov, e[..., None])[..., 0])


# ---------------------------------------------------------------------------------------------------------------
# odometry filter: drift drawn from a hand-written noise model
# ---------------------------------------------------------------------------------------------------------------
# sigmas deliberately unlike the defaults: the filter gets them through its config
NOISE = dict(
    sigma_p_per_sqrt_m=0.03,
    sigma_theta_per_sqrt_rad=0.02,
    sigma_theta_per_sqrt_m=0.004,
    sigma_p_per_sqrt_s=0.004,
    sigma_theta_per_sqrt_s=0.001,
    initial_sigma_p=0.02,
    initial_sigma_theta_deg=1.0,
)
ODO_RUNS, ODO_RATE, ODO_SECONDS = 40, 10.0, 20.0
CHECKPOINTS_S = (5.0, 10.0, 15.0, 20.0)


def _truth(t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A smooth 3-D path, ~1 m/s, turning: world_from_body rotations and positions at t [s]."""
    p = np.column_stack([4 * np.sin(0.25 * t), 3 * np.sin(0.5 * t), 0.5 * np.sin(0.3 * t)])
    w = np.column_stack([0.15 * np.sin(0.7 * t), 0.1 * np.cos(0.4 * t), 0.25 * t])
    return exp_so3(w), p


def _drifting_odometry(rng: np.random.Generator, R: np.ndarray, p: np.ndarray, dt: float):
    """Dead reckoning of the true increments, each perturbed by an independent draw whose variance is written
    out here: per increment of angle a [rad] over distance d [m] in dt [s],
    var(theta) = s_th_rad^2 a + s_th_m^2 d + s_th_s^2 dt, var(p) = s_p_m^2 d + s_p_s^2 dt, per axis; the first pose
    is off by a draw of the initial sigmas. Measured increment = true increment with the noise applied on the
    right (dR Exp(n_theta), dp + n_p)."""
    n = NOISE
    k = len(p)
    Rm, pm = np.empty_like(R), np.empty_like(p)
    Rm[0] = R[0] @ exp_so3(rng.normal(0, np.radians(n["initial_sigma_theta_deg"]), 3))
    pm[0] = p[0] + rng.normal(0, n["initial_sigma_p"], 3)
    for i in range(1, k):
        dR = R[i - 1].T @ R[i]
        dp = R[i - 1].T @ (p[i] - p[i - 1])
        angle = np.linalg.norm(log_so3(dR))
        dist = np.linalg.norm(dp)
        var_th = (
            n["sigma_theta_per_sqrt_rad"] ** 2 * angle
            + n["sigma_theta_per_sqrt_m"] ** 2 * dist
            + n["sigma_theta_per_sqrt_s"] ** 2 * dt
        )
        var_p = n["sigma_p_per_sqrt_m"] ** 2 * dist + n["sigma_p_per_sqrt_s"] ** 2 * dt
        dRm = dR @ exp_so3(rng.normal(0, np.sqrt(var_th), 3))
        dpm = dp + rng.normal(0, np.sqrt(var_p), 3)
        Rm[i] = Rm[i - 1] @ dRm
        pm[i] = pm[i - 1] + Rm[i - 1] @ dpm
    return Rm, pm


@pytest.fixture(scope="module")
def odometry_runs(tmp_path_factory):
    """(history, truth R, truth p) of the odometry filter on ODO_RUNS independent drifting odometries."""
    d = tmp_path_factory.mktemp("odo_mc")
    t = np.arange(0.0, ODO_SECONDS + 1e-9, 1.0 / ODO_RATE)
    t_ns = T0 + np.round(t * 1e9).astype(np.int64)
    R, p = _truth(t)
    out = []
    for seed in range(ODO_RUNS):
        Rm, pm = _drifting_odometry(np.random.default_rng(seed), R, p, 1.0 / ODO_RATE)
        path = d / f"odo{seed}.mcap"
        with RecordingWriter(path) as w:
            w.write_odometry_batch(t_ns, pm, rot_to_quat(Rm), np.zeros((len(t), 6, 6)))
        rd = RecordingReader(path)
        est = odometry_from_recording(rd, OdometryFilterConfig(error_model="drift", **NOISE))
        run_estimator(est, rd, None, None)
        out.append((est.history(), t_ns, R, p))
    return out


def odometry_verdicts(runs) -> list[Verdict]:
    """Pose NEES (6 DoF) pooled over the runs at each checkpoint: each is an average of len(runs) independent
    χ²(6) draws when the filter is consistent, so the two-sided 99% bounds of that average apply exactly."""
    n = len(runs)
    lo, hi = chi2.ppf([0.005, 0.995], 6 * n) / n
    nees = np.zeros((n, len(CHECKPOINTS_S)))
    for j, (hist, t_ns, R, p) in enumerate(runs):
        h = hist.arrays()
        idx = np.searchsorted(h["t_ns"], T0 + np.round(np.array(CHECKPOINTS_S) * 1e9).astype(np.int64))
        i_gt = np.searchsorted(t_ns, h["t_ns"][idx])
        Rh = quat_to_rot(h["q_xyzw"][idx])
        # the filter's error convention: R_true = R_hat Exp(dtheta), p_true = p_hat + dp
        e = np.concatenate([log_so3(np.swapaxes(Rh, 1, 2) @ R[i_gt]), p[i_gt] - h["p"][idx]], axis=1)
        nees[j] = _nees(e, h["cov"][idx])
    return [Verdict(float(a), float(lo), float(hi)) for a in nees.mean(0)]


def test_odometry_filter_is_consistent_with_independently_drawn_drift(odometry_runs):
    verdicts = odometry_verdicts(odometry_runs)
    print(
        "odometry ANEES at",
        CHECKPOINTS_S,
        [round(v.anees, 2) for v in verdicts],
        "bounds",
        verdicts[0].lo,
        verdicts[0].hi,
    )
    assert all(v.inside for v in verdicts), verdicts


def test_odometry_covariance_growth_matches_the_hand_written_formula(odometry_runs):
    """The covariance the filter reports at the end of a run equals the propagation written out here: initial
    sigmas, then per odometry increment (angle a, distance d, dt) P <- F P F^T + G diag(q_th, q_p) G^T with the
    hand-written q_th, q_p of `_drifting_odometry` and the error transition of T_new = T dT
    (dtheta' = dR^T dtheta + n_theta, dp' = dp - R [dp_inc]x dtheta + R n_p)."""
    hist, t_ns, R, p = odometry_runs[0]
    h = hist.arrays()
    n = NOISE
    Rh = quat_to_rot(h["q_xyzw"])
    P = np.diag([np.radians(n["initial_sigma_theta_deg"]) ** 2] * 3 + [n["initial_sigma_p"] ** 2] * 3)
    dt = 1.0 / ODO_RATE
    for i in range(1, len(Rh)):
        dR = Rh[i - 1].T @ Rh[i]
        dp = Rh[i - 1].T @ (h["p"][i] - h["p"][i - 1])
        angle, dist = np.linalg.norm(log_so3(dR)), np.linalg.norm(dp)
        q_th = (
            n["sigma_theta_per_sqrt_rad"] ** 2 * angle
            + n["sigma_theta_per_sqrt_m"] ** 2 * dist
            + n["sigma_theta_per_sqrt_s"] ** 2 * dt
        )
        q_p = n["sigma_p_per_sqrt_m"] ** 2 * dist + n["sigma_p_per_sqrt_s"] ** 2 * dt
        hat = np.array([[0, -dp[2], dp[1]], [dp[2], 0, -dp[0]], [-dp[1], dp[0], 0]])
        F = np.block([[dR.T, np.zeros((3, 3))], [-Rh[i - 1] @ hat, np.eye(3)]])
        G = np.block([[np.eye(3), np.zeros((3, 3))], [np.zeros((3, 3)), Rh[i - 1]]])
        P = F @ P @ F.T + G @ np.diag([q_th] * 3 + [q_p] * 3) @ G.T
    np.testing.assert_allclose(h["cov"][-1], P, rtol=1e-9, atol=1e-15)


# ---------------------------------------------------------------------------------------------------------------
# MSCKF: 20 seeds of the small visual-inertial simulator
# ---------------------------------------------------------------------------------------------------------------
MSCKF_SEEDS, MSCKF_SECONDS, FEJ_SEEDS, BURN_IN = 20, 15.0, 10, 50
SLAM_FEATURES = 20


@pytest.fixture(scope="module")
def msckf_runs(tmp_path_factory):
    """{fej: [(history, t_ns, p, R)]}: FEJ on MSCKF_SEEDS seeds, no FEJ on the first FEJ_SEEDS of them; "slam":
    FEJ with SLAM features on the first FEJ_SEEDS."""
    d = tmp_path_factory.mktemp("msckf_mc")
    out = {True: [], False: [], "slam": []}
    for seed in range(MSCKF_SEEDS):
        path = d / f"vi{seed}.mcap"
        truth = simulate_vi(path, duration=MSCKF_SECONDS, seed=seed)
        rd = RecordingReader(path)
        # the filter starts from the truth moved by a draw of its own initial covariance (starting exactly at
        # the truth with that covariance would make it under-confident by construction)
        c = VioConfig()
        P0 = np.diag(np.repeat([c.sigma_theta0, c.sigma_p0, c.sigma_v0, c.sigma_bg0, c.sigma_ba0], 3) ** 2)
        x_true = groundtruth_state(rd, rd.topics()["/imu"].start_ns)
        x0 = x_true.boxplus(np.random.default_rng(1000 + seed).multivariate_normal(np.zeros(15), P0))
        for key in (True, False, "slam") if seed < FEJ_SEEDS else (True,):
            rd = RecordingReader(path)
            cfg = VioConfig(max_slam_features=SLAM_FEATURES) if key == "slam" else VioConfig(fej=key)
            est = msckf_from_recording(rd, cfg, x0, P0)
            run_estimator(est, rd, None, None)
            out[key].append((est, truth))
    return out


def msckf_verdict(runs) -> Verdict:
    """Time-averaged 6-DoF pose NEES per run (after a burn-in), averaged over the runs, against the two-sided
    95% χ² bounds of an average of len(runs) χ²(6) draws: conservative (a time average varies less than one
    draw), so a bound crossed is a real inconsistency."""
    per_run = []
    for est, (t_ns, p, R) in runs:
        h, dth, dp = errors_vs_truth(est, t_ns, p, R)
        per_run.append(_nees(np.concatenate([dth, dp], 1), h["cov"])[BURN_IN:].mean())
    n = len(per_run)
    lo, hi = chi2.ppf([0.025, 0.975], 6 * n) / n
    return Verdict(float(np.mean(per_run)), float(lo), float(hi))


def test_msckf_anees_inside_two_sided_bounds(msckf_runs):
    v = msckf_verdict(msckf_runs[True])
    print(f"MSCKF (FEJ) ANEES {v.anees:.2f} over {MSCKF_SEEDS} runs, bounds [{v.lo:.2f}, {v.hi:.2f}]")
    assert v.inside, v


def test_slam_features_consistent_and_more_accurate(msckf_runs):
    """SLAM features (landmarks in the state, FEJ at their first estimate) on the same data and initial errors:
    the ANEES inside the two-sided bounds, and the position error pooled over the runs below the MSCKF's (the
    landmarks hold the drift while the scene stays in view)."""
    slam = msckf_verdict(msckf_runs["slam"])
    errs = {}
    for key, runs in (("msckf", msckf_runs[True][:FEJ_SEEDS]), ("slam", msckf_runs["slam"])):
        sq = [errors_vs_truth(est, *truth)[2] ** 2 for est, truth in runs]
        errs[key] = float(np.sqrt(np.concatenate(sq).sum(axis=1).mean()))
    print(f"SLAM ANEES {slam.anees:.2f} [{slam.lo:.2f}, {slam.hi:.2f}], position RMSE {errs}")
    assert slam.inside, slam
    assert errs["slam"] < errs["msckf"]
    assert all(est.stats.slam_initialized > 0 for est, _ in msckf_runs["slam"])


def test_fej_not_worse_than_no_fej(msckf_runs):
    """Same data and initial errors, FEJ on/off: the FEJ filter is inside the two-sided bounds and not more
    over-confident than without FEJ (ANEES at most 10% above). Measured on these 15 s runs: FEJ 6.48, no FEJ 6.20
    (10 runs), final yaw variances equal to 3 digits: too short for the no-FEJ filter's spurious yaw information to
    grow, so "better" is not measurable here; a FEJ that linearised at the wrong points would be caught."""
    fej = msckf_verdict(msckf_runs[True][:FEJ_SEEDS])
    nofej = msckf_verdict(msckf_runs[False])
    print(
        f"ANEES FEJ {fej.anees:.3f} vs no FEJ {nofej.anees:.3f} ({FEJ_SEEDS} runs, [{fej.lo:.2f}, {fej.hi:.2f}])"
    )
    assert fej.inside and nofej.inside
    assert fej.anees <= 1.1 * nofej.anees


# ---------------------------------------------------------------------------------------------------------------
# the test of the tests
# ---------------------------------------------------------------------------------------------------------------
@pytest.fixture
def reported_covariance_scale(monkeypatch):
    """Inject a scale on the covariance every filter reports (its trajectory record): ``set(k)``."""
    original = TrajectoryRecord.arrays

    def set_scale(k: float) -> None:
        def scaled(self):
            out = original(self)
            out["cov"] = out["cov"] * k
            return out

        monkeypatch.setattr(TrajectoryRecord, "arrays", scaled)

    return set_scale


@pytest.mark.parametrize("scale", [1.5, 0.67, 1.0])
def test_consistency_checks_catch_a_scaled_covariance(
    scale, reported_covariance_scale, odometry_runs, msckf_runs
):
    """×1.5 (under-confident) and ×0.67 (over-confident) must fail every consistency check above, ×1.0 pass."""
    reported_covariance_scale(scale)
    odo = odometry_verdicts(odometry_runs)
    vio = msckf_verdict(msckf_runs[True])
    print(f"x{scale}: odometry ANEES {[round(v.anees, 2) for v in odo]}, MSCKF ANEES {vio.anees:.2f}")
    expect = scale == 1.0
    assert all(v.inside for v in odo) == expect  # the odometry test fails (some checkpoint out) or passes
    assert vio.inside == expect  # the MSCKF test
