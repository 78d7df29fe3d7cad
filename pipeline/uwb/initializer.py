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
from uwbcal.pipeline.core.robust import mad_sigma, psi_slope, robust_loss
from uwbcal.pipeline.core.series import noise_inflation
from uwbcal.pipeline.core.state import chi2_ppf
from uwbcal.pipeline.uwb.fim import FimReport, assess_observability
from uwbcal.pipeline.uwb.model import jacobians, range_variance
from uwbcal.pipeline.uwb.window import InitWindow, plane_frame

_AG = [0, 1, 2, 4]  # indices of (p_a, gamma) in x_U
_ABG = [0, 1, 2, 3, 4]  # (p_a, beta, gamma)
OUTLIER_SIGMAS = 3.0


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
def multilateration(
    tag_xyz: np.ndarray, d: np.ndarray, gamma: float | None = None, planar_ratio: float = 0.05
) -> list[np.ndarray]:
    """Closed-form (p_a, gamma) candidates with beta = 1, from (d - gamma)^2 = ||x - p_a||^2.

    In the frame of the trajectory's principal axes (y = V (x - c)), d^2 - ||y||^2 = -2 y^T b + 2 d gamma + k with
    k = ||b||^2 - gamma^2: linear in (b, gamma, k). ``gamma`` given: fixed instead of estimated. For a near-planar
    trajectory the out-of-plane component b_3 is recovered from k, with both signs (the mirror ambiguity); otherwise
    the linear solution and its mirror across the plane are returned. Each candidate is [p_a(3), gamma].
    """
    c, Vt, ext = plane_frame(tag_xyz)
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


def _x_u(theta: np.ndarray, beta_prior: tuple[float, float] | None = None) -> np.ndarray:
    """x_U from theta = (p_a, beta, gamma) or (p_a, gamma), beta then fixed at ``beta_prior``'s mean (else 1)."""
    theta = np.asarray(theta, float)
    if theta.shape[0] == 5:
        return theta.copy()
    beta = float(beta_prior[0]) if beta_prior is not None else 1.0
    return np.array([theta[0], theta[1], theta[2], beta, theta[3]])


def prior_terms(n: int, gamma_prior, beta_prior) -> list[tuple[int, float, float]]:
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
    x = _x_u(theta, beta_prior)
    idx = _ABG if len(theta) == 5 else _AG
    J = jacobians(w.R, w.p, w.p_T, x)
    r = w.d - J.h
    if weighted:
        s2, _ = range_variance(w.R, w.p, w.p_T, x, w.P_pose, sigma2_d)
    else:
        s2 = np.full_like(r, sigma2_d)
    e = r / np.sqrt(s2)
    rho, wt = robust_loss(e, robust, c)
    cost = float(np.sum(rho))
    for i, m, sd in prior_terms(len(theta), gamma_prior, beta_prior):
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
    priors = prior_terms(len(theta), gamma_prior, beta_prior)
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
    _, w = robust_loss(e, kind, c)
    w2 = float(np.sum(w**2))
    if len(e) < 2 or w2 <= 0:
        return 1.0
    f_psi = float(np.sum((w * e) ** 2) / w2)
    n_eff = max(round(w2**2 / float(np.sum(w**4))), 1)
    if f_psi <= chi2_ppf(quantile, n_eff) / n_eff:
        return 1.0
    slope = float(np.sum(psi_slope(e, kind, c)))
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
    z_prior: tuple[float, float] | None = None,
) -> InitResult:
    """The paper's initialisation of one anchor: (p_a, gamma) (beta = 1, prior sigma ``beta_sigma``) with
    ``method`` in lsi | ri | ri-robust from a multi-start (the closed form, its mirror, the same with gamma at its
    prior, ``n_perturbed`` perturbed starts; the lowest cost wins); with ``beta_prior`` (mean, sigma),
    (p_a, beta, gamma) under that prior.

    Returns status "skipped" (too few usable ranges), "refused" (rank-deficient Fisher information and not
    ``force``), "warning" (static/planar window, suspicious post-fit residuals, gamma far from its prior,
    many outliers) or "ok". ``correlation_block_s``: block length of the time-correlation check of the residuals
    (`noise_inflation`; None: off), whose kappa scales the range part of the covariance. ``z_prior`` (mean,
    sigma): a prior on the anchor's height, fused into the estimate.
    """
    if method not in INIT_METHODS:
        raise ValueError(f"unknown init method {method!r}; one of {', '.join(INIT_METHODS)}")
    robust = robust_loss if method == "ri-robust" else None
    w, warns = _clean(window, anchor)
    if len(w) < max(min_ranges, 5):
        warns.append(f"{anchor}: only {len(w)} usable ranges (< {max(min_ranges, 5)}); anchor skipped")
        return InitResult.without_estimate(anchor, method, "skipped", w, warns)
    kw = dict(
        weighted=method != "lsi",
        sigma_range=sigma_range,
        gamma_prior=gamma_prior,
        robust=robust,
        robust_scale=robust_scale,
        beta_prior=beta_prior,
    )
    fits = _multi_start(w, kw, n_perturbed, seed)
    lbl_best, _, best = min(fits, key=lambda f: f[2].cost)
    x = _x_u(best.theta, beta_prior)
    idx = _ABG if beta_prior is not None else _AG
    kappa = _inflation(w, best, kw, correlation_block_s)
    cov = _covariance(best, idx, kappa, gamma_prior, beta_prior, beta_sigma)
    verdict: dict = {}
    if z_prior is not None:
        x, cov = _fuse_z_prior(x, cov, z_prior)
        verdict["z_prior"] = [float(z_prior[0]), float(z_prior[1])]
    res = _result(anchor, method, w, fits, lbl_best, best, (x, cov, idx, kappa), robust, warns, verdict)
    return _assess(res, best, kw, force, residual_factor)


def _result(anchor, method, w, fits, lbl_best, best, est, robust, warns, verdict) -> InitResult:
    """The `InitResult` of the winning start (``est`` = x, cov, estimated indices, kappa), every start recorded."""
    x, cov, idx, kappa = est
    n_rej = int(np.sum(np.abs(best.e) > OUTLIER_SIGMAS))
    starts = [
        {"label": lb, "start": t0.tolist(), "estimate": f.theta.tolist(), "cost": f.cost}
        for lb, t0, f in fits
    ]
    if lbl_best != "closed-form":
        starts.append(
            {
                "label": "winner",
                "start": [],
                "estimate": best.theta.tolist(),
                "cost": best.cost,
                "winner": lbl_best,
            }
        )
    return InitResult(
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
        residual_robust_sigma=mad_sigma(best.r),
        warnings=warns,
        starts=starts,
        weights=best.weights if robust else np.ones(len(w)),
        window=w,
        params=tuple(idx),
        noise_inflation=kappa,
        verdict=verdict,
    )


def _multi_start(w: InitWindow, kw: dict, n_perturbed: int, seed: int) -> list[tuple[str, np.ndarray, _Fit]]:
    """(label, start, fit) of every start: the closed form and its mirror, the same with gamma at its prior
    mean, then ``n_perturbed`` starts around the best of those."""
    beta_prior, gamma_prior = kw["beta_prior"], kw["gamma_prior"]

    def full(th: np.ndarray) -> np.ndarray:
        """(p_a, gamma) start -> the solver's theta (with beta at its prior mean when it is estimated)."""
        return _x_u(th, beta_prior) if beta_prior is not None else th

    xyz = w.tag_xyz
    starts: list[tuple[str, np.ndarray]] = []
    for lbl, cands in (
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
    return fits


def _inflation(w: InitWindow, best: _Fit, kw: dict, correlation_block_s: float | None) -> float:
    """kappa: the ranges' variance factor, time correlation (batch means) x the robust fit's sandwich factor (the
    outliers' influence the weights leave: one-sided NLOS junk)."""
    robust = kw["robust"]
    kappa = (
        noise_inflation(w.t_ns, best.e, best.weights if robust else None, block_s=correlation_block_s)
        if correlation_block_s
        else 1.0
    )
    if robust:
        kappa *= robust_noise_factor(best.e, robust, kw["robust_scale"] / kw["sigma_range"])
    return kappa


def _covariance(best: _Fit, idx, kappa: float, gamma_prior, beta_prior, beta_sigma: float) -> np.ndarray:
    """(5, 5) covariance of x_U: the ranges' information shrunk by kappa, the priors' not; beta fixed: its
    prior variance."""
    prior_info = np.zeros(len(idx))
    for i, _, sd in prior_terms(len(idx), gamma_prior, beta_prior):
        prior_info[i] += 1.0 / sd**2
    cov = np.zeros((5, 5))
    try:
        cov_est = np.linalg.inv((best.info - np.diag(prior_info)) / kappa + np.diag(prior_info))
    except np.linalg.LinAlgError:
        cov_est = np.full((len(idx), len(idx)), np.inf)
    cov[np.ix_(idx, idx)] = cov_est
    if beta_prior is None:
        cov[3, 3] = beta_sigma**2
    return cov


def _assess(res: InitResult, best: _Fit, kw: dict, force: bool, residual_factor: float) -> InitResult:
    """The Fisher information's verdict (refused when rank-deficient and not ``force``) and the warnings on the
    fit: residual spread beyond the expected, many outliers, gamma far from its prior."""
    w, x, anchor = res.window, res.x, res.anchor
    assert w is not None
    fim = assess_observability(
        w.R,
        w.p,
        w.p_T,
        w.P_pose if kw["weighted"] else np.zeros((6, 6)),
        x,
        kw["sigma_range"] ** 2,
        params=(0, 1, 2, 4),
        weights=res.weights,
        force=force,
        label=anchor,
    )
    res.fim = fim
    res.warnings.extend(fim.warnings)
    if fim.status == "refused":
        res.status = "refused"
        return res
    expected = float(np.sqrt(np.median(best.sigma2)))
    if res.residual_robust_sigma > residual_factor * expected:
        res.warnings.append(
            f"{anchor}: post-fit residual spread {res.residual_robust_sigma:.2f} m >> expected {expected:.2f} m "
            f"(NLOS or wrong model); estimate not trustworthy"
        )
    if res.n_rejected > 0.5 * len(w):
        res.warnings.append(
            f"{anchor}: {res.n_rejected} of {len(w)} ranges are outliers (> {OUTLIER_SIGMAS} sigma)"
        )
    gp = kw["gamma_prior"]
    if gp is not None and abs(x[4] - gp[0]) > 3 * gp[1]:
        res.warnings.append(
            f"{anchor}: gamma {x[4]:.2f} m is {abs(x[4] - gp[0]) / gp[1]:.1f} sigma from its prior {gp[0]:.2f} m"
        )
    if res.warnings:
        res.status = "warning"
    return res


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
