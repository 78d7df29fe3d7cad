"""Anchor initialisation over the first window (paper stage 1): closed-form start, LSI, RI, RI-robust.

All methods estimate theta = (p_a, gamma) with beta fixed to 1 (paper Sec. III), or theta = (p_a, beta, gamma)
when a prior on beta is given (``beta_prior``): beta is then estimated under that prior, so that a scale error
that the window can observe is not forced into p_a and gamma, and the prior keeps it bounded where it cannot.

- ``lsi``: plain least squares, sum_k (d_k - h_k)^2 (the baseline used by VIRO);
- ``ri``: the paper's robust initialisation, sum_k (d_k - h_k)^2 / Sigma_k with Sigma_k = Q_d + H_Ik P_k H_Ik^T
  re-evaluated at every iterate (iteratively re-weighted Gauss-Newton with Levenberg damping);
- ``ri-robust``: RI with a Huber or Cauchy loss on the whitened residual (IRLS) against NLOS outliers.

Priors on gamma and beta enter as residuals. Local minima are guarded against by a
multi-start: the closed-form multilateration, its mirror across the best-fit plane of the trajectory (the classic
ambiguity of a near-planar flight), the same with gamma fixed to its prior, and a few perturbed starts; the lowest
final cost wins.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from uwbcal.pipeline.core.names import INIT_METHODS
from uwbcal.pipeline.core.state import chi2_ppf
from uwbcal.pipeline.uwb.fim import FimReport, assess_observability
from uwbcal.pipeline.uwb.model import jacobians, range_variance, tag_positions
from uwbcal.pipeline.uwb.search import NORMAL_SNR, SearchResult, noise_inflation, plane_frame, subsample

_AG = [0, 1, 2, 4]  # indices of (p_a, gamma) in x_U
_ABG = [0, 1, 2, 3, 4]  # (p_a, beta, gamma)
OUTLIER_SIGMAS = 3.0

BASIN_REJECT_CHI2 = 13.8  # chi2(2 dof) at 99.9 %


@dataclass
class InitWindow:
    """The ranges of one anchor over the initialisation window, with the pose estimates at their stamps."""

    d: np.ndarray  # (N,) ranges [m]
    p_T: np.ndarray  # (N,3) antenna lever arm in the IMU frame
    R: np.ndarray  # (N,3,3) world_from_body estimates
    p: np.ndarray  # (N,3)
    P_pose: np.ndarray  # (N,6,6) pose covariance, error [dtheta, dp]
    t_ns: np.ndarray | None = None
    link: np.ndarray | None = None  # (N,) link id of each range (tag * 256 + antenna); None: one link

    def __post_init__(self) -> None:
        self.d = np.asarray(self.d, float).reshape(-1)
        n = self.d.shape[0]
        self.p_T = np.broadcast_to(np.asarray(self.p_T, float).reshape(-1, 3), (n, 3)).copy()
        self.R = np.asarray(self.R, float).reshape(n, 3, 3)
        self.p = np.asarray(self.p, float).reshape(n, 3)
        self.P_pose = np.broadcast_to(np.asarray(self.P_pose, float).reshape(-1, 6, 6), (n, 6, 6)).copy()
        if self.t_ns is not None:
            self.t_ns = np.asarray(self.t_ns, np.int64).reshape(n)
        if self.link is not None:
            self.link = np.asarray(self.link, np.int64).reshape(n)

    def __len__(self) -> int:
        return self.d.shape[0]

    def subset(self, mask: np.ndarray) -> InitWindow:
        t = None if self.t_ns is None else self.t_ns[mask]
        lk = None if self.link is None else self.link[mask]
        return InitWindow(self.d[mask], self.p_T[mask], self.R[mask], self.p[mask], self.P_pose[mask], t, lk)

    def links(self) -> np.ndarray:
        return np.zeros(len(self), np.int64) if self.link is None else self.link

    @property
    def tag_xyz(self) -> np.ndarray:
        return tag_positions(self.R, self.p, self.p_T)


@dataclass
class InitResult:
    anchor: str
    method: str
    status: str  # "ok" | "warning" | "refused" | "skipped" | "not determined"
    x: np.ndarray  # (5,) [p_a, beta, gamma] (beta = 1 unless estimated)
    cov: np.ndarray  # (5,5) inverse information (beta fixed: its prior variance, uncorrelated)
    costs: list[float] = field(default_factory=list)  # cost per iteration of the winning start
    iterations: int = 0
    n_used: int = 0
    n_rejected: int = 0
    noise_inflation: float = 1.0  # kappa: variance factor of the ranges (time correlation x robust sandwich)
    residual_rms: float = float("nan")
    residual_robust_sigma: float = float("nan")
    fim: FimReport | None = None
    warnings: list[str] = field(default_factory=list)
    starts: list[dict] = field(default_factory=list)  # label, start, final estimate, final cost
    weights: np.ndarray | None = None  # (N,) robust weights of the window's ranges (1 when not robust)
    window: InitWindow | None = None  # the (cleaned) window the estimate was computed from
    params: tuple[int, ...] = tuple(_AG)  # indices of x_U that were estimated (beta fixed: _AG)
    verdict: dict = field(
        default_factory=dict
    )  # observability verdict (height, mirror, reason) for the report
    link_offsets: dict = field(default_factory=dict)  # link id -> offset relative to gamma (per-link bias)
    link_cov: np.ndarray | None = None  # (L, L) covariance of the offsets (in link_offsets' order; sum-zero)
    join_ns: int | None = None  # when the anchor joins the refinement (per-anchor schedule)
    # (gamma prior, beta prior) of the range model the evidence chose (`evidence.fit_anchor`); the refinement
    # keeps them (a parameter left out stays at its mean). None: the recording's priors
    model_priors: tuple | None = None
    excess_cov: np.ndarray | None = (
        None  # (5,5) what the chosen range model leaves out (evidence.mixture_cov)
    )

    @property
    def reason(self) -> str:
        return str(self.verdict.get("reason", ""))

    @property
    def ok(self) -> bool:
        return self.status in ("ok", "warning")

    @classmethod
    def without_estimate(
        cls,
        anchor: str,
        method: str,
        status: str,
        window: InitWindow,
        warnings: list,
        verdict: dict | None = None,
    ) -> InitResult:
        """An anchor the initialiser gives no estimate (``status`` "skipped" or "not determined"), NaN state."""
        return cls(
            anchor,
            method,
            status,
            np.full(5, np.nan),
            np.full((5, 5), np.nan),
            warnings=warnings,
            window=window,
            verdict={} if verdict is None else verdict,
        )


# ---------------------------------------------------------------------------------------------------------------
# closed form
_plane_frame = plane_frame


def multilateration(
    tag_xyz: np.ndarray, d: np.ndarray, gamma: float | None = None, planar_ratio: float = 0.05
) -> list[np.ndarray]:
    """Closed-form (p_a, gamma) candidates with beta = 1, from (d - gamma)^2 = ||x - p_a||^2.

    In the frame of the trajectory's principal axes (y = V (x - c)), d^2 - ||y||^2 = -2 y^T b + 2 d gamma + k with
    k = ||b||^2 - gamma^2: linear in (b, gamma, k). ``gamma`` given: fixed instead of estimated. For a near-planar
    trajectory the out-of-plane component b_3 is recovered from k, with both signs (the mirror ambiguity); otherwise
    the linear solution and its mirror across the plane are returned. Each candidate is [p_a(3), gamma].
    """
    c, Vt, ext = _plane_frame(tag_xyz)
    y = (tag_xyz - c) @ Vt.T
    planar = ext[2] < planar_ratio * max(ext[0], 1e-12)
    dims = 2 if planar else 3
    cols = [-2.0 * y[:, :dims]]
    if gamma is None:
        rhs = d**2 - np.sum(y**2, axis=1)
        cols.append(2.0 * d[:, None])
    else:
        rhs = (d - gamma) ** 2 - np.sum(y**2, axis=1)
    cols.append(np.ones((len(d), 1)))
    A = np.hstack(cols)
    sol, *_ = np.linalg.lstsq(A, rhs, rcond=None)
    b = np.zeros(3)
    b[:dims] = sol[:dims]
    g = float(sol[dims]) if gamma is None else float(gamma)
    k = float(sol[-1])
    if planar:
        b3 = np.sqrt(max(k + g**2 - b[0] ** 2 - b[1] ** 2, 0.0))
        bs = [np.array([b[0], b[1], b3]), np.array([b[0], b[1], -b3])]
    else:
        bs = [b, np.array([b[0], b[1], -b[2]])]
    return [np.r_[c + bb @ Vt, g] for bb in bs]


# ---------------------------------------------------------------------------------------------------------------
# iterative solvers
def _loss(e: np.ndarray, kind: str | None, c: float) -> tuple[np.ndarray, np.ndarray]:
    """rho(e) (scaled so that rho = e^2 near 0) and the IRLS weight rho'(e) / (2 e)."""
    if kind is None:
        return e**2, np.ones_like(e)
    a = np.abs(e)
    if kind == "huber":
        rho = np.where(a <= c, e**2, 2 * c * a - c**2)
        return rho, np.where(a <= c, 1.0, c / np.maximum(a, 1e-12))
    if kind == "cauchy":
        return c**2 * np.log1p((e / c) ** 2), 1.0 / (1.0 + (e / c) ** 2)
    raise ValueError(f"unknown robust loss {kind!r} (huber or cauchy)")


@dataclass
class _Fit:
    theta: np.ndarray
    cost: float
    costs: list[float]
    iterations: int
    e: np.ndarray  # whitened residuals
    r: np.ndarray  # raw residuals
    sigma2: np.ndarray
    weights: np.ndarray
    info: np.ndarray  # Gauss-Newton information incl. priors (4x4, or 5x5 with beta)


def _x_u(theta: np.ndarray, beta: float = 1.0) -> np.ndarray:
    """x_U from theta = (p_a, gamma) (beta fixed to ``beta``) or (p_a, beta, gamma)."""
    theta = np.asarray(theta, float)
    if theta.shape[0] == 5:
        return theta.copy()
    return np.array([theta[0], theta[1], theta[2], beta, theta[3]])


def _priors(n: int, gamma_prior, beta_prior) -> list[tuple[int, float, float]]:
    """(index in theta, mean, sigma) of the priors; beta only when it is estimated (n == 5)."""
    out = []
    if gamma_prior is not None:
        out.append((n - 1, float(gamma_prior[0]), float(gamma_prior[1])))
    if n == 5 and beta_prior is not None:
        out.append((3, float(beta_prior[0]), float(beta_prior[1])))
    return out


def ri_cost(w: InitWindow, theta, weighted, sigma2_d, gamma_prior, robust, c, beta_prior=None):
    """The initialisation cost at ``theta``: sum_k loss(r_k / s_k) + priors with r_k = d_k - range_model(...);
    RI (``weighted``): s_k^2 = `range_variance` (the pose covariance propagated into the range), LSI: s_k^2 the
    range noise. Returns (cost, H_U columns of theta, r, whitened e, s^2, IRLS weights)."""
    bfix = float(beta_prior[0]) if beta_prior is not None else 1.0
    x = _x_u(theta, bfix)
    idx = _ABG if len(theta) == 5 else _AG
    J = jacobians(w.R, w.p, w.p_T, x)
    r = w.d - J.h
    if weighted:
        s2, _ = range_variance(w.R, w.p, w.p_T, x, w.P_pose, sigma2_d)
    else:
        s2 = np.full_like(r, sigma2_d)
    e = r / np.sqrt(s2)
    rho, wt = _loss(e, robust, c)
    cost = float(np.sum(rho))
    for i, m, sd in _priors(len(theta), gamma_prior, beta_prior):
        cost += ((theta[i] - m) / sd) ** 2
    return cost, J.H_U[:, idx], r, e, s2, wt


def solve_from(
    w: InitWindow,
    theta0: np.ndarray,
    *,
    weighted: bool,
    sigma_range: float,
    gamma_prior: tuple[float, float] | None = None,
    robust: str | None = None,
    robust_scale: float = 0.5,
    max_iter: int = 50,
    tol: float = 1e-7,
    beta_prior: tuple[float, float] | None = None,
) -> _Fit:
    """Levenberg-damped iteratively re-weighted Gauss-Newton from ``theta0`` = (p_a, gamma), or (p_a, beta, gamma)
    (then ``beta_prior`` is its prior; with 4 parameters beta is fixed to the prior mean, else 1).

    The weights 1/Sigma_k (RI) and the robust weights are re-evaluated at every iterate and held fixed within a
    step; a step is accepted when it lowers the cost. ``robust_scale`` is in metres of range residual at the
    nominal sigma (the whitened threshold is robust_scale / sigma_range).
    """
    s2d = sigma_range**2
    c = robust_scale / sigma_range
    theta = np.asarray(theta0, float).copy()
    lam = 1e-4
    priors = _priors(len(theta), gamma_prior, beta_prior)
    cost, Hu, r, e, s2, wt = ri_cost(w, theta, weighted, s2d, gamma_prior, robust, c, beta_prior)
    costs = [cost]
    iterations = 0
    for it in range(1, max_iter + 1):
        iterations = it
        W = wt / s2
        A = (Hu * W[:, None]).T @ Hu
        g = (Hu * W[:, None]).T @ r
        for i, m, sd in priors:
            A[i, i] += 1.0 / sd**2
            g[i] += (m - theta[i]) / sd**2
        improved = False
        while lam < 1e12:
            D = np.diag(np.maximum(np.diag(A), 1e-12))
            try:
                step = np.linalg.solve(A + lam * D, g)
            except np.linalg.LinAlgError:
                lam *= 10
                continue
            cand = theta + step
            res = ri_cost(w, cand, weighted, s2d, gamma_prior, robust, c, beta_prior)
            if np.isfinite(res[0]) and res[0] <= cost:
                theta = cand
                cost, Hu, r, e, s2, wt = res
                lam = max(lam / 10, 1e-9)
                improved = True
                break
            lam *= 10
        costs.append(cost)
        if not improved or np.linalg.norm(step) < tol * (1 + np.linalg.norm(theta)):
            break
    W = wt / s2
    info = (Hu * W[:, None]).T @ Hu
    for i, _, sd in priors:
        info[i, i] += 1.0 / sd**2
    return _Fit(theta, cost, costs, iterations, e, r, s2, wt, info)


# ---------------------------------------------------------------------------------------------------------------
def _psi_slope(e: np.ndarray, kind: str, c: float) -> np.ndarray:
    """psi'(e) of the robust loss (psi = w e, `_loss` weight w): the curvature the estimate really has."""
    a = np.abs(e)
    if kind == "huber":
        return (a <= c).astype(float)
    if kind == "cauchy":
        return (1.0 - (e / c) ** 2) / (1.0 + (e / c) ** 2) ** 2
    raise ValueError(f"unknown robust loss {kind!r} (huber or cauchy)")


def robust_noise_factor(e: np.ndarray, kind: str, c: float, quantile: float = 0.99) -> float:
    """Variance factor >= 1 of a robust fit's estimate: its M-estimator (sandwich) covariance relative to the
    IRLS covariance the fit reports.

    The IRLS covariance takes the ranges as nominal noise with their weights: G^-1 (sum w_k^2 h_k h_k^T) G^-1,
    G = sum w_k h_k h_k^T (whitened). An M-estimator's covariance is B^-1 (sum psi_k^2 h_k h_k^T) B^-1 with
    B = sum psi'_k h_k h_k^T (Huber's sandwich, psi = w e). They agree on Gaussian ranges; on junk they do not: a
    down-weighted outlier keeps an influence psi ~ c^2 / e (Cauchy) however large it is, and where the loss
    redescends psi' < 0 flattens the cost the estimate sits in. As one scalar per anchor,
    f = [sum (w e)^2 / sum w^2] [sum w / sum psi']^2. The first factor is chi2(n_eff) / n_eff-distributed on
    Gaussian ranges (n_eff = (sum w^2)^2 / sum w^4): f is used only when that factor exceeds the distribution's
    ``quantile`` (evidence of heavy tails; clean ranges keep 1)."""
    e = np.asarray(e, float)
    e = e[np.isfinite(e)]
    _, w = _loss(e, kind, c)
    w2 = float(np.sum(w**2))
    if len(e) < 2 or w2 <= 0:
        return 1.0
    f_psi = float(np.sum((w * e) ** 2) / w2)
    n_eff = max(round(w2**2 / float(np.sum(w**4))), 1)
    if f_psi <= chi2_ppf(quantile, n_eff) / n_eff:
        return 1.0
    slope = float(np.sum(_psi_slope(e, kind, c)))
    curv = (float(np.sum(w)) / slope) ** 2 if slope > 0 else 1.0
    return max(f_psi * curv, 1.0)


def _clean(w: InitWindow, label: str) -> tuple[InitWindow, list[str]]:
    ok = (
        np.isfinite(w.d)
        & np.all(np.isfinite(w.p), axis=1)
        & np.all(np.isfinite(w.R.reshape(-1, 9)), axis=1)
        & np.all(np.isfinite(w.P_pose.reshape(-1, 36)), axis=1)
        & np.all(np.isfinite(w.p_T), axis=1)
    )
    warns = []
    if not ok.all():
        warns.append(
            f"{label}: {int((~ok).sum())} of {len(ok)} ranges dropped (NaN/inf in range, pose or covariance)"
        )
        w = w.subset(ok)
    return w, warns


def initialize_anchor(
    window: InitWindow,
    method: str = "ri",
    *,
    anchor: str = "anchor",
    sigma_range: float = 0.1,
    gamma_prior: tuple[float, float] | None = None,
    beta_sigma: float = 0.05,
    beta_prior: tuple[float, float] | None = None,
    robust_loss: str = "cauchy",
    robust_scale: float = 0.5,
    min_ranges: int = 20,
    n_perturbed: int = 4,
    force: bool = False,
    seed: int = 0,
    residual_factor: float = 3.0,
    correlation_block_s: float | None = 10.0,
    search: SearchResult | None = None,
    per_link: bool = False,
    max_ranges: int | None = None,
    z_prior: tuple[float, float] | None = None,
) -> InitResult:
    """Estimate (p_a, gamma) (beta = 1, prior sigma ``beta_sigma``) of one anchor with ``method`` in
    lsi | ri | ri-robust; with ``beta_prior`` (mean, sigma), (p_a, beta, gamma) under that prior.

    Returns status "skipped" (too few usable ranges), "refused" (rank-deficient Fisher information and not
    ``force``), "warning" (static/planar window, suspicious post-fit residuals, gamma far from its prior,
    many outliers) or "ok". ``correlation_block_s``: block length of the time-correlation check of the residuals
    (`noise_inflation`; None: off), whose kappa scales the range part of the covariance.

    ``search`` (`anchor_search.search_anchor` on this window): its verdict decides — "not determined" (with
    its reason) when it could not place the anchor; otherwise it starts the solver beside the closed forms (and its mirror when the
    two fit equally), its per-link offsets correct the ranges (``per_link``), and a height it found
    unobservable is reported at its value with its honest sigma (the FIM verdict then covers the in-plane
    parameters). ``max_ranges``: the window is evenly subsampled to this many ranges (dense ranging).
    ``z_prior`` (mean, sigma): a prior on the anchor's height, fused into the estimate.
    """
    if method not in INIT_METHODS:
        raise ValueError(f"unknown init method {method!r}; one of {', '.join(INIT_METHODS)}")
    weighted = method != "lsi"
    robust = robust_loss if method == "ri-robust" else None
    w, warns = _clean(window, anchor)
    if len(w) < max(min_ranges, 5):
        warns.append(f"{anchor}: only {len(w)} usable ranges (< {max(min_ranges, 5)}); anchor skipped")
        return InitResult.without_estimate(anchor, method, "skipped", w, warns)

    verdict: dict = {}
    link_offsets: dict = {}
    link_cov = None
    if search is not None:
        verdict = search_verdict(search)
        if not search.ok:
            warns.append(f"{anchor}: not determined: {search.reason}")
            return InitResult.without_estimate(anchor, method, "not determined", w, warns, verdict)
        if max_ranges is not None and len(w) > max_ranges:
            keep = np.zeros(len(w), bool)
            keep[subsample(len(w), max_ranges)] = True
            w = w.subset(keep)
        if per_link and len(search.links) > 1:
            off = search.gamma - float(np.mean(search.gamma))
            link_offsets = {int(lk): float(o) for lk, o in zip(search.links, off, strict=True)}
            T = np.eye(len(off)) - 1.0 / len(off)  # offsets relative to their mean: sum-zero
            link_cov = T @ np.asarray(search.cov, float)[3:, 3:] @ T
            corr = np.array([link_offsets.get(int(lk), 0.0) for lk in w.links()])
            w = InitWindow(w.d - corr, w.p_T, w.R, w.p, w.P_pose, w.t_ns, w.link)
        n_perturbed = 0

    kw = dict(
        weighted=weighted,
        sigma_range=sigma_range,
        gamma_prior=gamma_prior,
        robust=robust,
        robust_scale=robust_scale,
        beta_prior=beta_prior,
    )
    est_beta = beta_prior is not None
    b0 = float(beta_prior[0]) if est_beta else 1.0

    def full(th: np.ndarray) -> np.ndarray:
        """(p_a, gamma) start -> the solver's theta (with beta at its prior mean when it is estimated)."""
        return np.r_[th[:3], b0, th[3]] if est_beta else th

    xyz = w.tag_xyz
    starts: list[tuple[str, np.ndarray]] = []
    if search is not None:
        g0 = float(np.mean(search.gamma))
        starts.append(("search", full(np.r_[search.p, g0])))
        if search.mirror_p is not None:
            starts.append(("search-mirror", full(np.r_[search.mirror_p, g0])))
    for lbl, cands in (  # beside the search: the lowest cost wins, `_stay_in_basin` guards the basin
        ("closed-form", multilateration(xyz, w.d)),
        ("closed-form-gamma-prior", multilateration(xyz, w.d, gamma_prior[0]) if gamma_prior else []),
    ):
        for i, th in enumerate(cands):
            if np.all(np.isfinite(th)):
                starts.append((lbl + ("" if i == 0 else "-mirror"), full(th)))
    if not starts:
        starts.append(("centroid", full(np.r_[xyz.mean(axis=0) + [0, 0, 1.0], 0.0])))
    fits = [(lbl, th0, solve_from(w, th0, **kw)) for lbl, th0 in starts]
    rng = np.random.default_rng(seed)
    best = min(fits, key=lambda f: f[2].cost)[2]
    spread = float(np.max(np.ptp(xyz, axis=0)))
    for i in range(n_perturbed):
        th0 = best.theta.copy()
        th0[:3] += rng.normal(0.0, 0.3 * spread + 1.0, 3)
        fits.append((f"perturbed-{i}", th0, solve_from(w, th0, **kw)))
    lbl_best, _, best = min(fits, key=lambda f: f[2].cost)

    x = _x_u(best.theta, b0)
    idx = _ABG if est_beta else _AG
    kappa = (
        noise_inflation(w.t_ns, best.e, best.weights if robust else None, block_s=correlation_block_s)
        if correlation_block_s
        else 1.0
    )
    if robust:  # the outliers' influence the weights leave (one-sided NLOS junk): robust_noise_factor
        kappa *= robust_noise_factor(best.e, robust, robust_scale / sigma_range)
    prior_info = np.zeros(len(idx))
    for i, _, sd in _priors(len(idx), gamma_prior, beta_prior):
        prior_info[i] += 1.0 / sd**2
    cov = np.zeros((5, 5))
    try:  # the ranges' information shrinks by kappa, the priors' does not
        cov_est = np.linalg.inv((best.info - np.diag(prior_info)) / kappa + np.diag(prior_info))
    except np.linalg.LinAlgError:
        cov_est = np.full((len(idx), len(idx)), np.inf)
    cov[np.ix_(idx, idx)] = cov_est
    if not est_beta:
        cov[3, 3] = beta_sigma**2

    if search is not None and not _data_reject_search_point(w, search, full, best.cost, kappa, kw):
        x, cov, moved = _stay_in_basin(x, cov, search, b0)
        if moved:
            warns.append(
                f"{anchor}: the {method} fit left the search's basin by {moved:.2f} m horizontally (a direction "
                "the window cannot see, e.g. range scale against distance); the search's estimate is kept"
            )
    if search is not None and not search.height_observable:
        x, cov = _honest_height(x, cov, search)
    if z_prior is not None:
        x, cov = _fuse_z_prior(x, cov, z_prior)
        verdict["z_prior"] = [float(z_prior[0]), float(z_prior[1])]

    outlier = np.abs(best.e) > OUTLIER_SIGMAS
    n_rej = int(outlier.sum())
    res = InitResult(
        anchor=anchor,
        method=method,
        status="ok",
        x=x,
        cov=cov,
        costs=best.costs,
        iterations=best.iterations,
        n_used=len(w) - (n_rej if robust else 0),
        n_rejected=n_rej,
        residual_rms=float(np.sqrt(np.mean(best.r**2))),
        residual_robust_sigma=float(1.4826 * np.median(np.abs(best.r - np.median(best.r)))),
        warnings=warns,
        starts=[
            {"label": lb, "start": t0.tolist(), "estimate": f.theta.tolist(), "cost": f.cost}
            for lb, t0, f in fits
        ],
        weights=best.weights if robust else np.ones(len(w)),
        window=w,
        params=tuple(idx),
        noise_inflation=kappa,
        verdict=verdict,
        link_offsets=link_offsets,
        link_cov=link_cov,
    )
    height_free = search is not None and not search.height_observable
    fim = assess_observability(
        w.R,
        w.p,
        w.p_T,
        w.P_pose if weighted else np.zeros((6, 6)),
        x,
        sigma_range**2,
        params=(0, 1, 4) if height_free else (0, 1, 2, 4),
        weights=res.weights,
        force=force,
        label=anchor,
    )
    res.fim = fim
    if height_free:  # the geometric planar warning is the search's, stated once
        fim.warnings = [m for m in fim.warnings if "planar window" not in m]
        fim.status = "warning" if fim.status == "ok" else fim.status
        res.warnings.append(verdict["message"])
    res.warnings.extend(fim.warnings)
    if verdict:
        verdict["fim_status"] = fim.status
    if fim.status == "refused":
        res.status = "refused"
        return res
    expected = float(np.sqrt(np.median(best.sigma2)))
    if res.residual_robust_sigma > residual_factor * expected:
        res.warnings.append(
            f"{anchor}: post-fit residual spread {res.residual_robust_sigma:.2f} m >> expected {expected:.2f} m "
            f"(NLOS or wrong model); estimate not trustworthy"
        )
    if n_rej > 0.5 * len(w):
        res.warnings.append(f"{anchor}: {n_rej} of {len(w)} ranges are outliers (> {OUTLIER_SIGMAS} sigma)")
    if gamma_prior is not None and abs(x[4] - gamma_prior[0]) > 3 * gamma_prior[1]:
        res.warnings.append(
            f"{anchor}: gamma {x[4]:.2f} m is {abs(x[4] - gamma_prior[0]) / gamma_prior[1]:.1f} sigma from "
            f"its prior {gamma_prior[0]:.2f} m"
        )
    if res.warnings:
        res.status = "warning"
    if lbl_best != "closed-form":
        res.starts.append(
            {
                "label": "winner",
                "start": [],
                "estimate": best.theta.tolist(),
                "cost": best.cost,
                "winner": lbl_best,
            }
        )
    return res


def search_verdict(search: SearchResult) -> dict:
    """The observability verdict of a search, for init.json / metrics.json and the run summary."""
    out: dict = {
        "status": search.status,
        "reason": search.reason,
        "planar_motion": bool(search.planar),
        "height_observable": bool(search.height_observable),
        "mirror_ambiguity": bool(search.mirror),
    }
    if not search.ok:
        return out
    out["sigma_height_m"] = float(search.sigma_h)
    out["sigma_horizontal_m"] = float(search.sigma_horizontal)
    out["residual_sigma_m"] = float(search.scale)
    if search.mirror_p is not None:
        out["mirror_position"] = [float(v) for v in search.mirror_p]
    out["normal_spread_m"] = float(search.normal_spread)
    out["normal_sigma_m"] = float(search.normal_sigma)
    if not search.height_observable:
        if search.normal_spread < NORMAL_SNR * search.normal_sigma:
            why = (
                f"the carrier's spread along the motion plane's normal, {search.normal_spread:.3f} m, is under "
                f"{NORMAL_SNR:g} x what corrupts it there ({search.normal_sigma:.3f} m: pose sigma, attitude x arm)"
            )
        elif search.mirror:
            why = "the mirror across the motion plane fits as well"
        else:
            why = "planar tag motion" if search.planar else "weak out-of-plane geometry"
        where = "the basin above the motion plane" if search.planar else "the basin the ranges prefer"
        msg = (
            f"height unobservable ({why}): reported at {search.p[2]:.2f} +- {search.sigma_h:.2f} m ({where}; "
            "its sigma reaches the mirror across it); horizontal position estimated"
        )
        if search.mirror:
            msg += "; the mirror across the motion plane fits equally (two basins)"
        out["message"] = msg
    return out


def _data_reject_search_point(
    w, search: SearchResult, full, best_cost: float, kappa: float, kw: dict
) -> bool:
    """True when the window's own cost rejects the search's point against the fit (difference over a 2-dof
    chi2 at 99.9 %, in units of the correlation-inflated noise): the fit then left the search's basin because
    the data demand it (e.g. a range scale beta != 1, which the search's model lacks), not along a direction the
    window cannot see, and `_stay_in_basin` must not pull it back."""
    th = full(np.r_[search.p, float(np.mean(search.gamma))])
    c = kw["robust_scale"] / kw["sigma_range"]
    cost = ri_cost(
        w, th, kw["weighted"], kw["sigma_range"] ** 2, kw["gamma_prior"], kw["robust"], c, kw["beta_prior"]
    )[0]
    return bool(np.isfinite(cost) and (cost - best_cost) / max(kappa, 1.0) > BASIN_REJECT_CHI2)


def _stay_in_basin(
    x: np.ndarray,
    cov: np.ndarray,
    search: SearchResult,
    beta0: float,
    chi2_2dof: float = 11.8,
    min_move_m: float = 1.0,
) -> tuple[np.ndarray, np.ndarray, float]:
    """The initialiser's (x, cov), unless its horizontal position left the search's basin (squared
    Mahalanobis distance in the motion plane > ``chi2_2dof`` under the search's covariance, and more than
    ``min_move_m``: a different basin, not a prior pulling within one): then the search's
    estimate (beta at ``beta0``, gamma the links' mean) and covariance. Returns (x, cov, horizontal move [m]
    when replaced, else 0)."""
    n = search.normal / np.linalg.norm(search.normal)
    T = np.eye(3) - np.outer(n, n)
    dp = T @ (x[:3] - search.p)
    P = T @ search.cov[:3, :3] @ T + 1e-12 * np.outer(n, n)
    try:
        d2 = float(dp @ np.linalg.pinv(P, hermitian=True) @ dp)
    except np.linalg.LinAlgError:
        d2 = 0.0
    if not np.isfinite(d2) or d2 <= chi2_2dof or float(np.linalg.norm(dp)) <= min_move_m:
        return x, cov, 0.0
    L = len(search.gamma)
    xs = np.r_[search.p, beta0, float(np.mean(search.gamma))]
    cs = np.zeros((5, 5))
    cs[:3, :3] = search.cov[:3, :3]
    wg = np.full(L, 1.0 / L)
    cs[4, 4] = float(wg @ search.cov[3:, 3:] @ wg)
    cs[:3, 4] = cs[4, :3] = search.cov[:3, 3:] @ wg
    cs[3, 3] = cov[3, 3] if np.isfinite(cov[3, 3]) and cov[3, 3] > 0 else 0.05**2
    return xs, cs, float(np.linalg.norm(dp))


def _honest_height(x: np.ndarray, cov: np.ndarray, search: SearchResult) -> tuple[np.ndarray, np.ndarray]:
    """The anchor moved along the motion-plane normal to the search's height, whose sigma replaces the
    normal direction's variance (and its correlations)."""
    n = search.normal / np.linalg.norm(search.normal)
    x = x.copy()
    x[:3] = x[:3] - n * float(n @ (x[:3] - search.p))
    T = np.eye(5)
    T[:3, :3] -= np.outer(n, n)
    cov = T @ cov @ T.T
    cov[:3, :3] += search.sigma_h**2 * np.outer(n, n)
    return x, cov


def _fuse_z_prior(
    x: np.ndarray, cov: np.ndarray, z_prior: tuple[float, float]
) -> tuple[np.ndarray, np.ndarray]:
    """Kalman fusion of a prior z ~ N(mean, sigma^2) on the anchor height into (x, cov)."""
    H = np.zeros(5)
    H[2] = 1.0
    S = float(H @ cov @ H) + float(z_prior[1]) ** 2
    if not np.isfinite(S) or S <= 0:
        return x, cov
    K = cov @ H / S
    x = x + K * (float(z_prior[0]) - x[2])
    cov = cov - np.outer(K, H @ cov)
    return x, 0.5 * (cov + cov.T)
