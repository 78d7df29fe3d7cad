"""UWB on the filter side: anchor covariance initialisation, refinement (EKF / SKF) and localisation updates.

- `windows_from_trajectory` builds the per-anchor initialisation windows (poses + 6x6 covariances interpolated at
  the range stamps) from a `TrajectoryRecord` and the ranges;
- `initialize_anchors` runs the initialiser (`uwb_init`) on every anchor;
- `add_anchor_to_state` adds an initialised anchor to the filter state with its covariance and cross-covariances
  (paper Sec. III-B, OpenVINS-style "state variable initialisation");
- `UwbUpdater` is the `on_range` handler of an `Estimator`: modes ekf, skf, none, frozen.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING, Any, Literal

import numpy as np

from uwbcal.pipeline.core.errors import InputError
from uwbcal.pipeline.core.geometry import quat_slerp, quat_to_rot
from uwbcal.pipeline.core.series import bracket, correlated_errors_covariance, sliding_mean
from uwbcal.pipeline.core.state import (
    Kind,
    State,
    UpdateResult,
    Vec,
    chi2_ppf,
    covariance_upper_bound,
    ekf_update,
    nearest_psd,
    remove_probes,
    schmidt_update,
)
from uwbcal.pipeline.uwb.config import UwbConfig
from uwbcal.pipeline.uwb.evidence import (
    TWR_SCALE_SIGMA,
    AnchorFit,
    FitSpec,
    fit_anchor,
    init_result,
    not_determined,
)
from uwbcal.pipeline.uwb.initializer import InitResult, initialize_anchor, prior_terms
from uwbcal.pipeline.uwb.model import jacobians, range_model, range_variance
from uwbcal.pipeline.uwb.window import InitWindow

if TYPE_CHECKING:
    from uwbcal.pipeline.vio.estimator import RangeMeasurement

# Method names of tables and CLI: (initialiser, refinement).
METHODS: dict[str, tuple[str, str]] = {
    "viro": ("lsi", "ekf"),
    "lsi+ekf": ("lsi", "ekf"),
    "lsi+skf": ("lsi", "skf"),
    "ri+ekf": ("ri", "ekf"),
    "ri+skf": ("ri", "skf"),
    "ri-robust+ekf": ("ri-robust", "ekf"),
    "ri-robust+skf": ("ri-robust", "skf"),
}


def anchor_var(anchor: Any) -> str:
    return f"anchor/{anchor}"


def link_var(anchor: Any) -> str:
    """The per-link offsets of an anchor (`Kind.LINK`, one entry per link of ``InitResult.link_offsets``)."""
    return f"links/{anchor}"


def link_columns(links: Sequence[int]) -> dict[int, int]:
    """link id -> entry of an anchor's offset variable (the order of ``InitResult.link_offsets``)."""
    return {int(lk): i for i, lk in enumerate(links)}


def lever_arms(calibration: Mapping) -> dict[tuple[int, int], np.ndarray]:
    """(tag, antenna) -> p_T from calibration uwb.tags; a missing table means a tag at the IMU origin."""
    tags = ((calibration or {}).get("uwb", {}) or {}).get("tags", {}) or {}
    out: dict[tuple[int, int], np.ndarray] = {}
    for tag, spec in tags.items():
        for i, a in enumerate(spec.get("antennas", [])):
            out[(int(tag), i)] = np.asarray(a, float)
    return out


def _lever_arm(arms: Mapping[tuple[int, int], np.ndarray], tag: int, antenna: int) -> np.ndarray:
    if not arms:
        return np.zeros(3)
    try:
        return arms[(int(tag), int(antenna))]
    except KeyError:
        raise InputError(
            f"calibration: uwb.tags: no lever arm for tag {tag} antenna {antenna}; add it to the antenna table"
        ) from None


def range_lever_arms(calibration: Mapping, tag: np.ndarray, antenna: np.ndarray) -> np.ndarray:
    """p_T of every range (N, 3) from its (tag, antenna), one lookup per distinct link."""
    arms = lever_arms(calibration)
    tag, antenna = np.asarray(tag), np.asarray(antenna)
    out = np.zeros((len(tag), 3))
    for key in {(int(a), int(b)) for a, b in zip(tag.tolist(), antenna.tolist(), strict=True)}:
        out[(tag == key[0]) & (antenna == key[1])] = _lever_arm(arms, *key)
    return out


# -----------------------------------------------------------------------------------------------------------------
def interpolate_poses(traj: Mapping[str, np.ndarray], t_ns: np.ndarray):
    """Pose (R, p) and 6x6 covariance linearly interpolated (slerp for R) at the stamps ``t_ns`` inside the
    trajectory's span (`series.bracket`); mask of those."""
    tt = np.asarray(traj["t_ns"], np.int64)
    t_ns = np.asarray(t_ns, np.int64)
    inside = (t_ns >= tt[0]) & (t_ns <= tt[-1]) if len(tt) > 1 else np.zeros(len(t_ns), bool)
    i0, i1, s = bracket(tt, t_ns[inside])
    p = traj["p"][i0] + s[:, None] * (traj["p"][i1] - traj["p"][i0])
    q = quat_slerp(traj["q_xyzw"][i0], traj["q_xyzw"][i1], s)
    cov = traj["cov"][i0] + s[:, None, None] * (traj["cov"][i1] - traj["cov"][i0])
    return quat_to_rot(q), p, cov, inside


def windows_from_trajectory(
    traj: Mapping[str, np.ndarray],
    ranges: Mapping[str, np.ndarray],
    calibration: Mapping,
    start_ns: int | None = None,
    end_ns: int | None = None,
    pose_cov: np.ndarray | None = None,
) -> dict[int, InitWindow]:
    """Per-anchor windows: ranges (``t_ns, tag, antenna, anchor, distance``) in [start, end) with the pose
    estimates interpolated at their stamps. ``pose_cov`` (6x6) replaces the trajectory's covariances."""
    t = np.asarray(ranges["t_ns"], np.int64)
    sel = np.ones(len(t), bool)
    if start_ns is not None:
        sel &= t >= start_ns
    if end_ns is not None:
        sel &= t < end_ns
    idx = np.flatnonzero(sel)
    R, p, cov, inside = interpolate_poses(traj, t[idx])
    idx = idx[inside]
    if pose_cov is not None:
        cov = np.broadcast_to(np.asarray(pose_cov, float), (len(idx), 6, 6))
    tag = np.asarray(ranges["tag"])[idx]
    ant = np.asarray(ranges["antenna"])[idx]
    pT = range_lever_arms(calibration, tag, ant)
    anchors = np.asarray(ranges["anchor"])[idx]
    d = np.asarray(ranges["distance"], float)[idx]
    link = link_id(tag, ant)
    out = {}
    for a in np.unique(anchors):
        m = anchors == a
        out[int(a)] = InitWindow(d[m], pT[m], R[m], p[m], cov[m], t[idx][m], link[m])
    return out


def link_id(tag, antenna):
    """One id per (tag, antenna) pair: tag * 256 + antenna (vectorised)."""
    return np.asarray(tag, np.int64) * 256 + np.asarray(antenna, np.int64)


def auto_init_method(dataset: str | None) -> str:
    """The initialiser ``init_method = "auto"`` stands for: ri-robust on real data (NLOS ranges are the rule:
    eee_01 anchor 100 throws plain RI off by metres), the paper's ri on simulated recordings."""
    return "ri" if str(dataset or "simulation").lower() == "simulation" else "ri-robust"


def initialize_anchors(
    windows: Mapping[Any, InitWindow],
    config: UwbConfig,
    calibration: Mapping | None = None,
    method: str | None = None,
    searches: dict[Any, AnchorFit] | None = None,
    cheap: bool = False,
    pose_tau_s: float | None = None,
) -> dict[Any, InitResult]:
    """Every anchor window's initialisation (``auto``: see `auto_init_method`; the pipeline resolves it from the
    recording's source, here it means ri): the evidence fit with the method's weighting and loss
    (`evidence.init_result`; ``searches``: fits already made), or with ``uwb.search = false`` the paper's
    multi-start (`initializer.initialize_anchor`). ``cheap``: the evidence fit's model-mixture covariance only (an
    initialiser run for comparison). ``pose_tau_s``: the correlation time of a pose source of bounded error."""
    sigma = config.sigma(calibration) * config.sigma_scale
    method = method or config.init_method
    method = auto_init_method(None) if method == "auto" else method
    out = {}
    searches = searches if searches is not None else {}
    for a, raw in windows.items():
        w = raw
        if config.pose_sigma_floor_m > 0:
            w = InitWindow(w.d, w.p_T, w.R, w.p, w.P_pose.copy(), w.t_ns, w.link)
            w.P_pose[:, 3:6, 3:6] += np.eye(3) * config.pose_sigma_floor_m**2
        if config.search:
            # search_window adds the floor itself
            sr = searches.get(a) or search_window(raw, config, sigma, calibration, method, cheap, pose_tau_s)
            spec = evidence_spec(config, sigma, calibration, method, pose_tau_s)
            out[a] = init_result(w, sr, method, str(a), spec)
            continue
        out[a] = initialize_anchor(
            w,
            method,
            anchor=str(a),
            sigma_range=sigma,
            gamma_prior=config.gamma_prior(calibration),
            beta_sigma=config.beta_prior(calibration)[1],
            beta_prior=config.init_beta_prior(calibration),
            robust_loss=config.robust_loss,
            robust_scale=config.robust_scale,
            min_ranges=config.min_ranges,
            n_perturbed=config.n_perturbed_starts,
            force=config.force,
            residual_factor=config.residual_factor,
            correlation_block_s=config.correlation_block_s,
            z_prior=config.z_prior(a),
        )
    return out


def evidence_spec(
    config: UwbConfig, sigma: float, calibration: Mapping | None, method: str, pose_tau_s: float | None = None
) -> FitSpec:
    """The evidence fit's priors and thresholds: the offset prior of the calibration (else the hardware's), the
    range scale's stated prior (else a TWR clock's), the method's loss (robust for ri-robust); a parameter the
    calibration states a prior for is in every model (the rule decides the rest). ``pose_tau_s``: the correlation
    time of a pose source of bounded error (None: its errors are not declared bounded)."""
    uwb = (calibration or {}).get("uwb") or {}
    stated = uwb.get("beta_prior") or {}
    return FitSpec(
        sigma_range=sigma,
        gamma_mean=config.offset_prior(calibration)[0],
        gamma_sigma=config.offset_prior(calibration)[1],
        beta_sigma=float(config.beta_sigma or stated.get("sigma") or TWR_SCALE_SIGMA),
        max_sigma=config.max_sigma_horizontal_m,
        min_ranges=max(config.min_ranges, 30),
        max_ranges=config.max_init_ranges,
        robust=method == "ri-robust",
        pattern_sigma=config.pattern_sigma(calibration),
        pose_tau_s=pose_tau_s or 0.0,
        stated=tuple(p for p, key in (("gamma", "gamma_prior"), ("beta", "beta_prior")) if uwb.get(key)),
    )


def search_window(
    w: InitWindow,
    config: UwbConfig,
    sigma: float,
    calibration: Mapping | None = None,
    method: str = "ri-robust",
    cheap: bool = False,
    pose_tau_s: float | None = None,
) -> AnchorFit:
    """The evidence fit of an init window (`evidence.fit_anchor`): the robust position fit, the range model the
    evidence chooses, the anchor's weak directions (``cheap``: its model-mixture covariance only, for a start), or
    "not determined" with the reason (also when the anchor was ranged for less than ``min_duration_s``); RI and
    RI-robust weigh each range by the pose's uncertainty along its line of sight, LSI does not."""
    if len(w) == 0:
        return not_determined("no ranges", np.zeros(0, np.int64))
    if w.t_ns is not None and (w.t_ns.max() - w.t_ns.min()) * 1e-9 < config.min_duration_s:
        span = (w.t_ns.max() - w.t_ns.min()) * 1e-9
        return not_determined(
            f"ranged for only {span:.1f} s (< {config.min_duration_s:g} s)", np.unique(w.links())
        )
    spec = replace(evidence_spec(config, sigma, calibration, method, pose_tau_s), refine_cov=not cheap)
    pos_cov = None
    if method != "lsi":
        pos_cov = w.P_pose[:, 3:6, 3:6] + np.eye(3) * config.pose_sigma_floor_m**2
    return fit_anchor(w.tag_xyz, w.d, w.links(), t_ns=w.t_ns, pos_cov=pos_cov, spec=spec)


# -----------------------------------------------------------------------------------------------------------------
def anchor_init_covariance(
    result: InitResult,
    state: State,
    *,
    sigma_range: float,
    gamma_prior: tuple[float, float] | None,
    beta_prior: tuple[float, float],
    pose_var: str | None = None,
    links: str | None = None,
    pose_correlation_s: float | None = None,
) -> tuple[dict[str, np.ndarray], np.ndarray]:
    """(J, Q) such that x~_U = sum_v J[v] e_v + n, n ~ N(0, Q) independent of the filter state.

    ``links``: the name of the anchor's per-link offset variable when the window's ranges were corrected by
    estimated offsets (``result.link_offsets``): their error delta~_l enters every range of link l like a
    constant noise, x~_U = ... - sum_l (sum_(k in l) G^-1 H_Bk^T w_k) delta~_l, so J[links] holds that map and
    the offsets' uncertainty reaches the anchor covariance and its cross-covariances.

    Stacked linearisation over the window (paper eqs. H_A, H_B): r = H_A X~ + H_B x~_U + n. At the optimum of the
    (weighted) least squares the normal equations give the estimator's error map
    x~_(p_a,gamma) = -G^-1 [sum_k H_Bk^T w_k (H_Ak X~_k + h_beta,k beta~ + n_k) + e_gamma eps / s^2],
    G = sum H_Bk^T w_k H_Bk + prior, i.e. x~_U = sum_k B_k e_k + (noise, prior and fixed-beta terms). For the GLS
    weights this is exactly the invertible block of the paper's QR split (x~_U = H_B1^-1 (r_1 - H_A1 X~ - n_1));
    written this way it also holds for LSI's unit weights, RI's weights, robust weights, beta fixed at its prior
    mean (beta~ ~ N(0, sigma^2) of ``beta_prior = (mean, sigma)``, independent) and the gamma prior. When the
    initialiser estimated beta (``result.params`` has index 3) the same holds with (p_a, beta, gamma) and the beta
    prior, whose mean error enters like the gamma prior's.

    The window's pose errors e_k (X_I of the paper):
    - with pose probes in the state (`state.add_probe`, kept by the MSCKF over the window as considered
      variables), e_k is interpolated linearly in time between the probes around t_k, so J holds one block per
      probe and the cross-covariances with everything in the filter are the filter's own (exact up to the
      interpolation);
    - without probes only the marginal covariances P_k are known: the pose errors are taken as a random walk in
      the world frame ([R dtheta, dp]) up to now, Cov(e_j, e_k) = P_min(j,k), Cov(e_k, e_now) = P_k, increments
      clipped to PSD; the part correlated with the current pose enters J[pose_var], the rest Q. Exact for a
      pose-only random-walk filter (the odometry filter); for the MSCKF it ignores how its updates decorrelate past
      from present errors (over-confident anchors after refinement; docs/results/measurements.md).
    """
    w = result.window
    assert w is not None
    n = len(w)
    beta_sigma = float(beta_prior[1])
    est_beta = 3 in result.params
    J, L, Ginv, a, priors = _estimator_gain(result, sigma_range, gamma_prior, beta_sigma)
    La = a @ L.T  # (n,5)
    # world-frame pose Jacobians: e_k = [R_k dtheta_k, dp_k]
    HW = J.H_I.copy()
    HW[:, 0:3] = np.einsum("nj,nij->ni", J.H_I[:, 0:3], w.R)  # H_theta R_k^T
    B = -La[:, :, None] * HW[:, None, :]  # (n,5,6)
    t_k = w.t_ns if w.t_ns is not None else np.arange(n)
    pr = state.probes
    if pr and w.t_ns is not None:
        Jd, cov = _probe_map(state, B, np.asarray(t_k, np.int64), pr)
    else:  # bounded pose errors (a correlation time) need stamps
        tau = pose_correlation_s if w.t_ns is not None else None
        Jd, cov = _pose_error_map(state, B, w, np.asarray(t_k, np.int64), pose_var or state.nav, tau)
    # range noise (robust weights are inside a_k), inflated by kappa for time-correlated errors
    cov += result.noise_inflation * sigma_range**2 * (La.T @ La)
    if links is not None and result.link_offsets:
        Jd = {**Jd, links: -_link_offset_map(result, La)}
    if not est_beta:
        g_beta = np.zeros(5)
        g_beta[3] = 1.0
        g_beta -= L @ (a.T @ J.rho)
        cov += np.outer(g_beta, g_beta) * beta_sigma**2
    for i, _, sd in priors:  # the error of each prior mean, N(0, sd^2), enters through G^-1 e_i / sd^2
        gp = L @ Ginv[:, i] / sd
        cov += np.outer(gp, gp)
    return Jd, nearest_psd(cov)


def _estimator_gain(result: InitResult, sigma_range: float, gamma_prior, beta_sigma: float):
    """The initialiser's linearised error map over its window: the Jacobians J, the selection L (5,na) of the
    estimated parameters, G^-1 of the weighted normal equations with the priors, the gains a_k = G^-1 H_Bk^T w_k
    (n,na) and the priors (`initializer.prior_terms`)."""
    w, x = result.window, result.x
    J = jacobians(w.R, w.p, w.p_T, x)
    ag = list(result.params)
    na = len(ag)
    HB = J.H_U[:, ag]
    if result.method == "lsi":
        s2 = np.full(len(w), sigma_range**2)
    else:
        s2, _ = range_variance(w.R, w.p, w.p_T, x, w.P_pose, sigma_range**2)
    wk = (result.weights if result.weights is not None else np.ones(len(w))) / s2
    G = (HB * wk[:, None]).T @ HB
    priors = prior_terms(na, gamma_prior, (1.0, beta_sigma))
    for i, _, sd in priors:
        G[i, i] += 1.0 / sd**2
    Ginv = np.linalg.inv(G)
    L = np.zeros((5, na))
    L[ag, range(na)] = 1.0
    return J, L, Ginv, (Ginv @ (HB * wk[:, None]).T).T, priors


def _link_offset_map(result: InitResult, La: np.ndarray) -> np.ndarray:
    """(5, K): how each per-link offset's error reaches the anchor's error (summed gains of that link's ranges)."""
    col = link_columns(list(result.link_offsets))
    li = np.array([col.get(int(lk), -1) for lk in result.window.links()])
    return np.stack([La[li == j].sum(axis=0) for j in range(len(col))], axis=1)


def _probe_map(
    state: State, B: np.ndarray, t_k: np.ndarray, pr: list[tuple[int, str]]
) -> tuple[dict[str, np.ndarray], np.ndarray]:
    """e_k = (1 - s) e_j + s e_j+1 between the probes around t_k (the first / last probe outside them); the probe
    errors are body-frame [dtheta, dp], so the world-frame B_k is mapped with each probe's rotation."""
    tp = np.array([t for t, _ in pr], np.int64)
    j0 = np.clip(np.searchsorted(tp, t_k, side="right") - 1, 0, len(tp) - 1)
    j1 = np.minimum(j0 + 1, len(tp) - 1)
    span = (tp[j1] - tp[j0]).astype(float)
    frac = np.where(span > 0, np.clip((t_k - tp[j0]) / np.where(span > 0, span, 1.0), 0.0, 1.0), 0.0)
    Bp = np.zeros((len(tp), 5, 6))
    np.add.at(Bp, j0, (1.0 - frac)[:, None, None] * B)
    np.add.at(Bp, j1, frac[:, None, None] * B)
    Jd = {}
    for j, (_, name) in enumerate(pr):
        if Bp[j].any():
            T = np.eye(6)
            T[0:3, 0:3] = state.value(name).R
            Jd[name] = Bp[j] @ T
    return Jd, np.zeros((5, 5))


def _pose_error_map(
    state: State, B: np.ndarray, w: InitWindow, t_ns: np.ndarray, pose_var: str, tau_s: float | None
) -> tuple[dict[str, np.ndarray], np.ndarray]:
    """No probes: the window's world-frame pose errors modelled from their marginal covariances P_k
    (`core.series.correlated_errors_covariance`), the part correlated with the current pose in J[pose_var], the
    rest in Q. ``tau_s`` None: the random walk of `anchor_init_covariance`, Cov(e_k, e_now) = P_k; else bounded
    errors (the pose source's model), stationary with correlation exp(-|dt| / tau), Cov(e_k, e_now) =
    rho_k,now P_k with "now" the window's last stamp; Q clipped to PSD."""
    T = np.zeros((len(B), 6, 6))
    T[:, 0:3, 0:3] = w.R
    T[:, 3:6, 3:6] = np.eye(3)
    order = np.argsort(t_ns, kind="stable")
    B, PW = B[order], (T @ w.P_pose @ np.swapaxes(T, 1, 2))[order]
    t = (t_ns[order] - t_ns.min()) * 1e-9
    cov_pose = correlated_errors_covariance(B, PW, t, tau_s)
    rho = np.ones(len(t)) if tau_s is None else np.exp(-(t.max() - t) / tau_s)
    C = np.einsum("n,nij,njk->ik", rho, B, PW)
    Tn = np.eye(6)
    Tn[0:3, 0:3] = state.value(pose_var).R
    C = C @ Tn  # Cov(x~_U, e_now (body))
    P_now = state.cov(pose_var)[0:6, 0:6]
    P_now = 0.5 * (P_now + P_now.T)
    Jn = np.linalg.solve(P_now.T, C.T).T
    Jfull = np.zeros((5, state.dim(pose_var)))
    Jfull[:, 0:6] = Jn
    Q = cov_pose - Jn @ P_now @ Jn.T
    return {pose_var: Jfull}, nearest_psd(Q)


def add_anchor_to_state(
    state: State,
    anchor: Any,
    result: InitResult,
    *,
    sigma_range: float,
    gamma_prior: tuple[float, float] | None,
    beta_prior: tuple[float, float] = (1.0, 0.05),
    pose_var: str | None = None,
    pose_correlation_s: float | None = None,
) -> None:
    """Add ``anchor/<id>`` = result.x with covariance and cross-covariances (see `anchor_init_covariance`).

    Per-link bias (``result.link_offsets`` with ``link_cov``): first ``links/<id>`` = the offsets with their
    covariance (the search's, relative to their mean), then the anchor with its map from the offsets' error, so
    the range updates estimate the offsets too (OpenVINS-style: one augment per variable, cross-covariances
    from the Jacobians)."""
    if not result.ok:
        raise ValueError(f"anchor {anchor}: initialisation {result.status}; not added to the state")
    pose_var = pose_var or state.nav
    if result.model_priors is not None:
        gamma_prior, beta_prior = result.model_priors
    P_now = state.cov(pose_var)[0:6, 0:6]
    if not np.all(np.isfinite(P_now)):
        raise FloatingPointError(f"anchor {anchor}: the filter's pose covariance has NaN/inf")
    links = None
    if result.link_offsets and result.link_cov is not None:
        links = link_var(anchor)
        offsets = np.array(list(result.link_offsets.values()), float)
        Q_links = nearest_psd(np.asarray(result.link_cov, float))
        state.augment(links, Vec(offsets), {}, Q=Q_links, kind=Kind.LINK, key=anchor)
    J, Q = anchor_init_covariance(
        result,
        state,
        sigma_range=sigma_range,
        gamma_prior=gamma_prior,
        beta_prior=beta_prior,
        pose_var=pose_var,
        links=links,
        pose_correlation_s=pose_correlation_s,
    )
    if not result.verdict.get("height_observable", True):
        # unobservable height: independent of everything, with the init's honest sigma (the range updates
        # leave it alone, UwbUpdater.fixed_height)
        J = {v: np.where(np.arange(5)[:, None] == 2, 0.0, M) for v, M in J.items()}
        Q = Q.copy()
        Q[2, :] = Q[:, 2] = 0.0
        Q[2, 2] = float(result.cov[2, 2])
    if result.model_priors is not None:
        # along each axis the larger of the evidence fit's covariance (its model average, its widening, the
        # declared errors' floor) and the error map's: an anchor reads at least as uncertain as it did at init, and
        # the pose errors both count are counted once
        mapped = sum(Mj @ state.cov(v) @ Mj.T for v, Mj in J.items()) + Q
        Q = Q + (covariance_upper_bound(result.cov, mapped) - mapped)
    state.augment(anchor_var(anchor), Vec(result.x), J, Q=Q, kind=Kind.ANCHOR, key=anchor)


def add_initialised_anchors(
    state: State,
    results: Mapping[Any, InitResult],
    config: UwbConfig,
    calibration: Mapping | None,
    pose_correlation_s: float | None = None,
) -> list[str]:
    """Every initialised anchor of ``results`` into ``state`` (`add_anchor_to_state`) with the configured range
    noise and the recording's priors, then drop the pose probes; warnings name the anchors left out.
    ``pose_correlation_s``: the pose source's bounded-error correlation time (`OdometryEstimator.
    pose_correlation_s`; None: drift)."""
    warns = []
    for a, r in results.items():
        if not r.ok:
            warns.append(f"refine: anchor {a} not initialised ({r.status}); left out")
            continue
        if r.join_ns is not None:  # joins later (UwbUpdater.schedule)
            continue
        add_anchor_to_state(
            state,
            a,
            r,
            sigma_range=config.sigma(calibration) * config.sigma_scale,
            gamma_prior=config.gamma_prior(calibration),
            beta_prior=config.beta_prior(calibration),
            pose_correlation_s=pose_correlation_s,
        )
    remove_probes(state)  # they only served the anchors' cross-covariances
    return warns


# -----------------------------------------------------------------------------------------------------------------
@dataclass
class AnchorRecord:
    t_ns: list[int] = field(default_factory=list)
    x: list[np.ndarray] = field(default_factory=list)
    cov: list[np.ndarray] = field(default_factory=list)
    residual: list[float] = field(default_factory=list)
    nis: list[float] = field(default_factory=list)
    rejected: list[bool] = field(default_factory=list)

    def arrays(self) -> dict[str, np.ndarray]:
        n = len(self.t_ns)
        return {
            "t_ns": np.asarray(self.t_ns, np.int64),
            "x": np.asarray(self.x, float).reshape(n, 5),
            "cov": np.asarray(self.cov, float).reshape(n, 5, 5),
            "residual": np.asarray(self.residual, float),
            "nis": np.asarray(self.nis, float),
            "rejected": np.asarray(self.rejected, bool),
        }


class UwbUpdater:
    """`on_range` handler. Modes: ``ekf`` (joint update of navigation state and anchor), ``skf`` (Schmidt: every
    non-anchor variable considered, not estimated), ``none`` (no update; residuals recorded), ``frozen``
    (localisation: the anchors' estimates stay where calibration left them, only the navigation state is
    updated; an anchor of the state is *considered* (Schmidt: its Jacobian and covariance enter the innovation
    covariance and the cross-covariances, its estimate and own covariance do not change), so the poses carry the
    calibration's uncertainty instead of taking the anchors as exact; an anchor given only as a constant
    (``anchors``, not in the state) enters with H_I alone).

    Anchor Jacobians use the anchor's first estimate (``state.fej``) when ``state.use_fej``; residuals use the
    current estimates. Updates whose NIS exceeds the chi-square ``chi2_quantile`` gate are rejected and counted.
    """

    def __init__(
        self,
        mode: Literal["ekf", "skf", "none", "frozen"],
        lever_arms: Mapping[tuple[int, int], np.ndarray],
        *,
        sigma_range: float = 0.1,
        chi2_quantile: float | None = 0.95,
        anchors: Mapping[Any, np.ndarray] | None = None,
        pose_var: str | None = None,
        inflation: Mapping[Any, float] | None = None,
        robust: tuple[str, float] | None = None,
    ) -> None:
        if mode not in ("ekf", "skf", "none", "frozen"):
            raise ValueError(f"unknown UWB update mode {mode!r}")
        self.mode = mode
        self.arms = dict(lever_arms)
        self.sigma = float(sigma_range)
        self.chi2_quantile = chi2_quantile
        self.frozen = {k: np.asarray(v, float) for k, v in (anchors or {}).items()}
        self.pose_var = pose_var
        # per-anchor variance factor kappa of time-correlated range errors (from init; 1 when absent)
        self.inflation = {k: float(v) for k, v in (inflation or {}).items()}
        # robust update (loss, scale [m]) instead of the chi2 gate
        self.robust = robust
        self.records: dict[Any, AnchorRecord] = {}
        self.counts = {"accepted": 0, "rejected": 0, "skipped": 0, "recorded": 0}
        # per-link bias: anchor -> {link id: offset relative to the anchor's gamma}, subtracted from the range;
        # while the anchor's offsets are a state variable (links/<id>, refinement) its current estimate is used
        # and the update estimates it (column link_cols[anchor][link])
        self.link_offsets: dict[Any, dict[int, float]] = {}
        self.link_cols: dict[Any, dict[int, int]] = {}
        # per-anchor schedule: anchors that join the state at their first range at or after result.join_ns
        self.pending: dict[Any, InitResult] = {}
        self.join_kw: dict = {}
        self.joined: dict[Any, int] = {}
        # anchors whose height the init found unobservable: range updates leave it alone (no z column), so a
        # tilting tag's lever arm cannot walk it to either side of the motion plane
        self.fixed_height: set = set()
        # a planar carrier's estimated lever arms (planar_levers.PlanarLevers): p_T from the attitude
        self.planar_arms: Any = None

    @classmethod
    def from_config(
        cls,
        config: UwbConfig,
        calibration: Mapping,
        mode: str | None = None,
        anchors: Mapping[Any, np.ndarray] | None = None,
        inflation: Mapping[Any, float] | None = None,
    ) -> UwbUpdater:
        loss = config.update_loss
        if loss == "auto":
            loss = "cauchy" if config.init_method == "ri-robust" else "gate"
        robust = None if loss == "gate" else (loss, config.robust_scale)
        return cls(
            mode or config.refine_method,  # type: ignore[arg-type]
            lever_arms(calibration),
            sigma_range=config.sigma(calibration) * config.sigma_scale,
            chi2_quantile=config.chi2_quantile if robust is None else None,
            anchors=anchors,
            inflation=inflation,
            robust=robust,
        )

    def __call__(self, estimator: Any, meas: RangeMeasurement) -> UpdateResult | None:
        return self.update(estimator.state, meas)

    def schedule(self, results: Mapping[Any, InitResult], join_kw: dict) -> None:
        """Anchors initialised later than the refinement's start join the state at their ``join_ns``."""
        self.pending = {a: r for a, r in results.items() if r.ok and r.join_ns is not None}
        self.join_kw = dict(join_kw)
        self.fixed_height = {
            a for a, r in results.items() if r.ok and not r.verdict.get("height_observable", True)
        }
        self.link_offsets = {a: r.link_offsets for a, r in results.items() if r.ok and r.link_offsets}
        self.link_cols = {a: link_columns(list(off)) for a, off in self.link_offsets.items()}

    def _offset(self, state: State, meas: RangeMeasurement) -> tuple[float, str | None, int]:
        """(offset of the range's link, its state variable or None, its column): the state's estimate while
        the offsets are in the state (estimated in refinement, considered like their anchor in localisation),
        else the fixed table."""
        lk = int(meas.tag) * 256 + int(meas.antenna)
        name = link_var(meas.anchor)
        col = self.link_cols.get(meas.anchor, {}).get(lk)
        if col is not None and name in state:
            return float(state.value(name).x[col]), name, col
        return self.link_offsets.get(meas.anchor, {}).get(lk, 0.0), None, -1

    def offsets(self, state: State) -> dict[Any, dict[int, float]]:
        """The per-link offsets now: the state's estimates where they are variables, else the fixed table."""
        out = {a: dict(off) for a, off in self.link_offsets.items()}
        for a, cols in self.link_cols.items():
            if link_var(a) in state:
                x = state.value(link_var(a)).x
                out[a] = {lk: float(x[c]) for lk, c in cols.items()}
        return out

    def offset_covariances(self, state: State) -> dict[Any, np.ndarray]:
        """The covariance of each anchor's offset variable (in ``link_cols`` order)."""
        return {a: state.cov(link_var(a)).copy() for a in self.link_cols if link_var(a) in state}

    @staticmethod
    def _estimated(state: State) -> list[str]:
        """The variables range updates estimate: anchors and their per-link offsets."""
        return [n for _, n in state.of_kind(Kind.ANCHOR)] + [n for _, n in state.of_kind(Kind.LINK)]

    def _arms(self, R: np.ndarray, rows: Sequence[RangeMeasurement]) -> np.ndarray:
        """p_T (k, 3) of the ranges ``rows`` at the attitude R: the calibration's, or the planar model's."""
        if self.planar_arms is None:
            return np.stack([_lever_arm(self.arms, m.tag, m.antenna) for m in rows])
        link = link_id([m.tag for m in rows], [m.antenna for m in rows])
        return self.planar_arms.body_arms(np.broadcast_to(R, (len(rows), 3, 3)), link)

    def _join(self, state: State, meas: RangeMeasurement) -> bool:
        r = self.pending.get(meas.anchor)
        if r is None or r.join_ns is None or meas.t_ns < r.join_ns or self.mode in ("frozen",):
            return False
        add_anchor_to_state(state, meas.anchor, r, pose_var=self.pose_var, **self.join_kw)
        del self.pending[meas.anchor]
        self.joined[meas.anchor] = int(meas.t_ns)
        return True

    def epoch(self, estimator: Any, batch: Sequence[RangeMeasurement]) -> UpdateResult | None:
        """All ranges of one stamp: `update_epoch` (the estimators' range loop hands them over together)."""
        return self.update_epoch(estimator.state, batch)

    def update(self, state: State, meas: RangeMeasurement) -> UpdateResult | None:
        """One range: the epoch of it alone (`update_epoch`)."""
        return self.update_epoch(state, [meas])

    def _apply(self, state: State, H: dict, r: np.ndarray, R, options: dict) -> UpdateResult:
        """One update in the updater's mode: ``frozen`` considers the anchors (the ranges correct the pose only),
        ``skf`` the navigation state (only the anchors are estimated), ``ekf`` estimates everything."""
        anchors = self._estimated(state)
        if self.mode == "frozen":
            return ekf_update(state, H, r, R, schmidt=anchors, **options)
        if self.mode == "skf":
            return schmidt_update(state, H, r, R, estimated=anchors, **options)
        return ekf_update(state, H, r, R, **options)

    def _record(self, meas: RangeMeasurement, x, P, residual: float, nis: float, rejected: bool) -> None:
        """The anchor's record of one judged range (``P`` None: an anchor outside the state, zero covariance)."""
        rec = self.records.setdefault(meas.anchor, AnchorRecord())
        rec.t_ns.append(int(meas.t_ns))
        rec.x.append(np.asarray(x, float).copy())
        rec.cov.append(np.zeros((5, 5)) if P is None else P)
        rec.residual.append(float(residual))
        rec.nis.append(float(nis))
        rec.rejected.append(bool(rejected))

    def update_epoch(self, state: State, batch: Sequence[RangeMeasurement]) -> UpdateResult | None:
        """All ranges of one epoch (the same stamp, hence the same pose) in one stacked `ekf_update`: block
        Jacobians (the pose block of every row, each anchor's block on its rows), per-row gate / robust weight
        on the marginal innovation variance (``per_row``; one range: the scalar update), one covariance update.
        Mode ``none`` only records each range's NIS of the would-be update. The records get the anchor state
        after the epoch."""
        rows, names, xs_cur, xs_lin = self._epoch_rows(state, batch)
        if not rows:
            return None
        k = len(rows)
        H, r, R, sig = self._epoch_model(state, rows, names, np.stack(xs_cur), np.stack(xs_lin))
        if self.mode == "none":  # record only: each range's NIS of the would-be joint update
            S = R[0] + np.diag(sum(Ha @ state.cov(a, b) @ Hb.T for a, Ha in H.items() for b, Hb in H.items()))
            nis, ok = r * r / S, np.ones(k, bool)
            res = UpdateResult(True, float(np.sum(nis)), k, None, nis, ok)
            self.counts["recorded"] += k
        else:  # the robust scale in sigmas of the per-sample noise, as at init
            robust = None if self.robust is None else (self.robust[0], self.robust[1] / sig)
            options = {"chi2_gate": self.chi2_quantile, "robust": robust, "robust_R": sig**2, "per_row": True}
            res = self._apply(state, H, r, R, options)
            one = res.row_accepted is None  # one row: the scalar update
            ok = np.array([res.accepted]) if one else res.row_accepted
            nis = np.array([res.nis]) if one else res.row_nis
            self.counts["accepted"] += int(ok.sum())
            self.counts["rejected"] += int(k - ok.sum())
        after = {n: (state.value(n).x.copy(), state.cov(n).copy()) for n in set(names) if n in state}
        for i, (meas, name) in enumerate(zip(rows, names, strict=True)):
            x, P = after.get(name, (xs_cur[i], None))
            self._record(meas, x, P, r[i], nis[i], not ok[i])
        return res

    def _epoch_model(
        self, state: State, rows: list, names: list, X_cur: np.ndarray, X_lin: np.ndarray
    ) -> tuple[dict[str, np.ndarray], np.ndarray, np.ndarray, np.ndarray]:
        """The stacked model of an epoch's judged ranges ``rows`` (anchor variables ``names``, their current and
        first estimates): the Jacobian blocks, the residuals (the links' offsets taken off), the noise variances
        (1, k) (inflated per anchor) and the per-sample sigmas."""
        k = len(rows)
        pose_var = self.pose_var or state.nav
        # Jacobians at the first estimates of pose and anchor (FEJ: a range at a camera stamp comes after that
        # frame's update, when the pose estimate already differs from its propagated first estimate)
        pose, pose_lin = state.value(pose_var), state.fej(pose_var)
        p_T = self._arms(pose_lin.R, rows)
        J = jacobians(pose_lin.R, pose_lin.p, p_T, X_lin)
        same_pose = pose_lin is pose or (
            np.array_equal(pose_lin.p, pose.p) and np.array_equal(pose_lin.R, pose.R)
        )
        h = J.h if same_pose and np.array_equal(X_lin, X_cur) else range_model(pose.R, pose.p, p_T, X_cur)
        d = np.array([m.distance for m in rows], float)
        link_rows = []  # (row, variable, column) of the ranges whose link offset is a state variable
        if self.link_offsets:  # per-link bias: the link's offset relative to the anchor's gamma
            for i, m in enumerate(rows):
                off, lvar, lcol = self._offset(state, m)
                d[i] -= off
                if lvar is not None:
                    link_rows.append((i, lvar, lcol))
        sig = self.sigma * X_cur[:, 3]
        R = (np.array([self.inflation.get(m.anchor, 1.0) for m in rows]) * sig**2)[None, :]
        H_imu = np.zeros((k, state.dim(pose_var)))
        H_imu[:, 0:6] = J.H_I
        H: dict[str, np.ndarray] = {pose_var: H_imu}
        for i, name in enumerate(names):
            if name in state:  # frozen: only the anchors of the state have a covariance to consider
                H.setdefault(name, np.zeros((k, 5)))[i] = J.H_U[i]
                if rows[i].anchor in self.fixed_height:  # an unobservable height is left alone
                    H[name][i, 2] = 0.0
        for i, lvar, lcol in link_rows:
            H.setdefault(lvar, np.zeros((k, state.dim(lvar))))[i, lcol] = 1.0
        return H, d - h, R, sig

    def _epoch_rows(self, state: State, batch: Sequence[RangeMeasurement]) -> tuple[list, list, list, list]:
        """The epoch's ranges the updater judges (an anchor in the state, joining it, or frozen) with their anchor
        variables and the anchors' current and first estimates; the others counted as skipped."""
        rows, names, xs_cur, xs_lin = [], [], [], []
        for meas in batch:
            name = anchor_var(meas.anchor)
            if self.mode == "frozen" and meas.anchor in self.frozen:
                x_cur = x_lin = self.frozen[meas.anchor]
            elif name in state or (bool(self.pending) and self._join(state, meas)):
                x_cur, x_lin = state.value(name).x, state.fej(name).x
            else:
                self.counts["skipped"] += 1
                continue
            rows.append(meas)
            names.append(name)
            xs_cur.append(x_cur)
            xs_lin.append(x_lin)
        return rows, names, xs_cur, xs_lin

    def arrays(self) -> dict[Any, dict[str, np.ndarray]]:
        return {a: rec.arrays() for a, rec in self.records.items()}

    def range_nis(self) -> tuple[np.ndarray, np.ndarray]:
        """(stamps, NIS) of every range the updater judged, all anchors pooled (the health check's input)."""
        recs = list(self.records.values())
        if not recs:
            return np.zeros(0, np.int64), np.zeros(0)
        return (
            np.concatenate([np.asarray(r.t_ns, np.int64) for r in recs]),
            np.concatenate([np.asarray(r.nis, float) for r in recs]),
        )

    def gate_rates(
        self, window_s: float, min_ranges: int, quantile: float | None
    ) -> dict[Any, tuple[np.ndarray, np.ndarray, np.ndarray]]:
        """Per anchor: its range stamps, which failed the chi2 gate at ``quantile`` (rejected by it, or, with a
        robust loss and no gate, NIS beyond it), and for every run of k consecutive ranges (k: ``window_s`` at the
        anchor's mean range rate in the records, at least ``min_ranges``; an anchor with fewer is not judged) the
        fraction that failed; from the records, once at the stage's end."""
        gate = chi2_ppf(quantile, 1) if quantile is not None else np.inf
        out = {}
        for a, rec in self.records.items():
            t = np.asarray(rec.t_ns, np.int64)
            if len(t) < max(min_ranges, 2):
                continue
            k = max(min_ranges, round(window_s * (len(t) - 1) / max((t[-1] - t[0]) * 1e-9, 1e-9)))
            if len(t) < k:
                continue
            failed = np.asarray(rec.rejected, bool) | (np.asarray(rec.nis, float) > gate)  # NaN: False
            out[a] = (t, failed, sliding_mean(failed, k))
        return out

    def gate_excess_warning(self, stage: str, alpha: float = 1e-3) -> list[str]:
        """A warning when the stage's gate rejected more ranges than a consistent filter would, over all ranges
        or over one anchor's: k of n rejected at the gate (``chi2_quantile``, q) with the binomial tail
        P(K >= k | n, 1 - q) below ``alpha`` (per anchor: ``alpha`` / anchors). A consistent filter rejects
        ~1 - q of its ranges; counting any rejection cried wolf on every clean run. A burst inside the stage (one
        anchor, a stretch of NLOS) is `gate_warnings`' job; this one sees an anchor whose estimate or covariance
        is off over the whole stage. Counted from the records, as `gate_rates`."""
        from scipy.special import bdtrc

        q = self.chi2_quantile
        if q is None:
            return []

        def tail(k: int, n: int) -> float:
            return float(bdtrc(k - 1, n, 1.0 - q)) if k else 1.0

        def shown(p: float) -> str:  # a tail below the smallest double prints as such, not as 0
            return f"{p:.1e}" if p > 0.0 else "< 1e-308"

        judged = {a: r.rejected for a, r in self.records.items()}
        per = {a: (int(np.sum(rej)), len(rej)) for a, rej in judged.items() if rej}
        bad = {a: kn for a, kn in per.items() if tail(*kn) < alpha / len(per)}
        k, n = sum(kn[0] for kn in per.values()), sum(kn[1] for kn in per.values())
        if not bad and not (n and tail(k, n) < alpha):
            return []
        named = "".join(
            f"; anchor {a}: {ka} of {na} ({ka / na:.0%}, tail {shown(tail(ka, na))})"
            for a, (ka, na) in sorted(bad.items(), key=lambda kv: str(kv[0]))
        )
        return [
            f"{stage}: {k} of {n} ranges ({k / n:.1%}; tail {shown(tail(k, n))}) rejected by the chi2 gate{named}: "
            f"more than the {1 - q:.0%} a consistent filter rejects (binomial tail < {alpha:g}, per anchor < "
            f"{alpha:g} / anchors): the ranges' noise (uwb.sigma_range), the anchors' or the poses' covariance is "
            "too small, or the ranges carry NLOS"
        ]

    def gate_warnings(
        self,
        stage: str,
        window_s: float,
        min_ranges: int,
        max_rejected: float,
        quantile: float | None,
        t0_ns: int,
    ) -> list[str]:
        """One warning naming the anchors of which more than ``max_rejected`` of the ranges of some ``window_s``
        window failed the chi2 gate, each with its largest fraction and the span (s after ``t0_ns``) from the first
        to the last failed range of those windows; the likely cause from the pattern (some anchors: their ranges
        or estimates; every anchor judged: the pose)."""
        rates = self.gate_rates(window_s, min_ranges, quantile)
        parts = []
        for a, (t, failed, rate) in sorted(rates.items(), key=lambda kv: str(kv[0])):
            bad = np.flatnonzero(rate > max_rejected)
            if len(bad):
                edge = np.zeros(len(t) + 1, int)  # the ranges of the windows over the threshold
                np.add.at(edge, bad, 1)
                np.add.at(edge, bad + len(t) - len(rate) + 1, -1)
                hit = np.flatnonzero((np.cumsum(edge[:-1]) > 0) & failed)
                first, last = (t[hit[[0, -1]]] - t0_ns) * 1e-9
                parts.append(f"anchor {a} from {first:.1f} s to {last:.1f} s (up to {rate.max():.0%})")
        if not parts:
            return []
        cause = (
            "every anchor: the pose is likely off (a drifting or diverged pose source)"
            if len(parts) == len(rates) > 1
            else "only these anchors: their ranges are biased there (NLOS, multipath) or their estimates walked off"
        )
        return [
            f"{stage}: more than {max_rejected:.0%} of the ranges of a {window_s:g} s window failed the chi2 gate "
            f"(uwb.chi2_quantile; threshold uwb.gate_max_rejected = {max_rejected:g}), in s after the start: "
            + ", ".join(parts)
            + "; "
            + cause
        ]
