"""Guess-free global search for one anchor: position and per-link range offsets from ranges alone.

Model (beta = 1): d_k = ||y_k - b|| + gamma_l(k) + n_k, with y_k the tag position in the frame of the
trajectory's principal axes (origin at its centroid, last axis the normal of its best-fit plane) and gamma_l
one offset per link l (an (anchor, tag antenna) pair; a single link gives the per-anchor model).

1. Consensus over closed forms: (d - gamma)^2 = ||y - b||^2 is linear in (b, gamma, k = ||b||^2 - gamma^2):
   d^2 - ||y||^2 = -2 y.b + 2 d gamma + k. Many random subsets of the ranges (spread over the whole record)
   give one candidate each (batched normal equations); for a planar trajectory the out-of-plane component is
   |b_3| = sqrt(k + gamma^2 - b_1^2 - b_2^2) with both signs. Every candidate and its mirror across the plane
   is scored on all (subsampled) ranges with a truncated quadratic (MSAC), so NLOS junk cannot pull the winner.
2. The best candidates are refined by robust (Cauchy IRLS) Levenberg-Marquardt over (b, gamma_1..gamma_L);
   the lowest robust cost wins, and the winner is verified by its residuals (inlier fraction, residual spread).
3. Truth about the height: the mirror of the winner across the motion plane is refined too; when its cost is
   as low (within ``mirror_chi2`` whitened units) the two basins fit equally and the anchor is reported at the
   plane (between the mirrors) with a height sigma that covers both. Planar or weakly out-of-plane motion flags
   the height unobservable; its sigma then comes from the curvature of the ranges (the squared out-of-plane
   distance s = b_3^2 enters d = sqrt(rho^2 + s): sigma_z = sqrt(s + 2 sigma_s)), never from a guess.

Everything here is a pure function of arrays; `uwb_init` turns the result into the start (and the height
verdict) of the configured initialiser.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from uwbcal.pipeline.core.state import chi2_ppf

PLANAR_RATIO = 0.1  # smallest extent below this x the largest: 2-D closed forms (the 3-D ones are ill-posed)
LINE_RATIO = 0.03  # second extent below this x the first: the tag moved along a line
NORMAL_SNR = 3.0  # the height needs the motion's spread along the normal >= this x what corrupts it there


@dataclass
class SearchResult:
    status: str  # "ok" | "not determined"
    reason: str
    p: np.ndarray  # (3,) world anchor position (at the plane when the mirror is ambiguous)
    gamma: np.ndarray  # (L,) per-link offsets, in the order of ``links``
    links: np.ndarray  # (L,) link ids
    inliers: np.ndarray  # (N,) bool over the input ranges (those used and consistent with the fit)
    scale: float  # robust residual sigma of the inliers [m]
    cov: np.ndarray  # (3+L, 3+L) covariance of (p world, gamma_l), residual-scaled
    planar: bool = False  # the trajectory is planar (smallest extent < PLANAR_RATIO x largest)
    normal_spread: float = float("nan")  # std of the carrier's positions along the plane normal [m]
    normal_sigma: float = 0.0  # what corrupts them there: pose sigma along the normal (+) attitude x arm [m]
    height_observable: bool = True
    mirror: bool = False  # the mirror across the motion plane fits as well
    mirror_p: np.ndarray | None = None  # the other basin (world) when ``mirror``
    sigma_h: float = float("nan")  # honest sigma along the plane normal [m]
    normal: np.ndarray = field(default_factory=lambda: np.array([0.0, 0.0, 1.0]))
    n_used: int = 0
    costs: dict = field(default_factory=dict)
    beta: float = 1.0  # range scale of the fit (1 unless the search estimated it under a beta prior)
    residuals: np.ndarray | None = None  # (n_used,) of the fit over the ranges it used (model tests)
    # why not determined, for callers to act on (the reason is for people): "offset" = the fit needs an implausible
    # range offset (the geometry trades the distance against it), "" otherwise
    code: str = ""

    @property
    def ok(self) -> bool:
        return self.status == "ok"

    @property
    def sigma_horizontal(self) -> float:
        """sqrt of the largest in-plane variance of the position (the horizontal uncertainty)."""
        P = self.cov[:3, :3]
        if not np.all(np.isfinite(P)):
            return float("inf")
        n = self.normal / np.linalg.norm(self.normal)
        T = np.eye(3) - np.outer(n, n)
        return float(np.sqrt(max(np.linalg.eigvalsh(T @ P @ T)[-1], 0.0)))

    def gamma_of(self, link_ids: np.ndarray) -> np.ndarray:
        """The offset of each range's link (links the search did not see: the mean offset)."""
        out = np.full(len(link_ids), float(np.mean(self.gamma)) if len(self.gamma) else 0.0)
        for i, lk in enumerate(self.links):
            out[np.asarray(link_ids) == lk] = self.gamma[i]
        return out


def plane_frame(xyz: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Centroid, rows = principal axes (last = normal of the best-fit plane), principal extents (std dev)."""
    c = xyz.mean(axis=0)
    _, s, Vt = np.linalg.svd(xyz - c, full_matrices=False)
    if np.linalg.det(Vt) < 0:  # a proper rotation, so that mirroring is only the sign of the last axis
        Vt[-1] *= -1
    if Vt[-1, 2] < 0:  # normal up (world z) when it can be
        Vt[-1] *= -1
        Vt[0] *= -1
    return c, Vt, s / np.sqrt(len(xyz))


def subsample(n: int, max_n: int) -> np.ndarray:
    """Indices of at most ``max_n`` of ``n`` items, evenly spread (the items are in time order)."""
    if n <= max_n:
        return np.arange(n)
    return np.unique(np.linspace(0, n - 1, max_n).round().astype(np.int64))


def _link_index(link: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    links, idx = np.unique(np.asarray(link), return_inverse=True)
    return links, idx.reshape(-1)


# ---------------------------------------------------------------------------------------------------------------
def closed_form_candidates(
    y: np.ndarray, d: np.ndarray, samples: np.ndarray, planar: bool, gamma: float | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Batched closed forms with one shared gamma (estimated, or fixed to ``gamma``): (H, 3) out-of-plane-mirrored
    pairs stacked -> (2H, 3) b and (2H,) gamma, from the index rows ``samples`` (H, m) into y (N, 3) / d (N,)."""
    Y = y[samples]  # (H, m, 3)
    D = d[samples]
    dims = 2 if planar else 3
    if gamma is None:
        A = np.concatenate([-2.0 * Y[..., :dims], 2.0 * D[..., None], np.ones(D.shape + (1,))], axis=2)
        rhs = D**2 - np.sum(Y**2, axis=2)
    else:  # (d - gamma)^2 - |y|^2 = -2 y.b + |b|^2: better conditioned on short baselines
        A = np.concatenate([-2.0 * Y[..., :dims], np.ones(D.shape + (1,))], axis=2)
        rhs = (D - gamma) ** 2 - np.sum(Y**2, axis=2)
    AtA = np.einsum("hmi,hmj->hij", A, A)
    Atb = np.einsum("hmi,hm->hi", A, rhs)
    u = AtA.shape[1]
    reg = 1e-13 * np.trace(AtA, axis1=1, axis2=2)[:, None, None] * np.eye(u)
    try:
        sol = np.linalg.solve(AtA + reg, Atb[..., None])[..., 0]
    except np.linalg.LinAlgError:
        sol = np.stack([np.linalg.lstsq(a, b, rcond=None)[0] for a, b in zip(A, rhs, strict=True)])
    b = np.zeros((len(sol), 3))
    b[:, :dims] = sol[:, :dims]
    g = sol[:, dims] if gamma is None else np.full(len(sol), float(gamma))
    if planar:
        b[:, 2] = np.sqrt(np.maximum(sol[:, -1] + g**2 - b[:, 0] ** 2 - b[:, 1] ** 2, 0.0))
    mirrored = b * np.array([1.0, 1.0, -1.0])
    return np.concatenate([b, mirrored]), np.concatenate([g, g])


def msac_costs(y: np.ndarray, d: np.ndarray, B: np.ndarray, G: np.ndarray, thr: float) -> np.ndarray:
    """Truncated quadratic cost of each candidate (b, gamma) over all ranges, (H,)."""
    out = np.empty(len(B))
    step = max(1, 2_000_000 // max(len(d), 1))
    for i in range(0, len(B), step):
        rho = np.linalg.norm(y[None, :, :] - B[i : i + step, None, :], axis=2)
        r = d[None, :] - rho - G[i : i + step, None]
        out[i : i + step] = np.sum(np.minimum(r**2, thr**2), axis=1)
    return out


@dataclass
class _Refined:
    b: np.ndarray
    g: np.ndarray
    cost: float
    r: np.ndarray
    w: np.ndarray
    info: np.ndarray  # (3+L, 3+L) robust Gauss-Newton information (unit residual variance)
    beta: float = 1.0


def _residuals(y, d, li, b, g, beta=1.0):
    diff = y - b
    rho = np.maximum(np.linalg.norm(diff, axis=1), 1e-9)
    return d - beta * rho - g[li], diff / rho[:, None], rho


def refine_robust(
    y: np.ndarray,
    d: np.ndarray,
    li: np.ndarray,
    n_links: int,
    b0: np.ndarray,
    g0: np.ndarray,
    scale: float,
    *,
    max_iter: int = 30,
    fix_normal: bool = False,
    gamma_prior: tuple[float, float, float] | None = None,
    beta_prior: tuple[float, float, float] | None = None,
    beta0: float | None = None,
) -> _Refined:
    """Cauchy-IRLS Levenberg-Marquardt over (b, gamma_l) from (b0, g0); ``scale`` [m] is the Cauchy scale.
    ``fix_normal``: the out-of-plane component stays at b0[2] (its column is left out). ``gamma_prior``
    (mean, sigma, range sigma): a Gaussian prior on every gamma_l, weighted as (range sigma / sigma)^2 against
    the squared range residuals. ``beta_prior`` (mean, sigma, range sigma): the range scale beta (d = beta
    ||y - b|| + gamma) is estimated too, from ``beta0`` (default its mean), under that prior, and marginalised
    out of ``info`` (None: beta = 1). On a short one-sided arc a scale error is otherwise absorbed by trading
    the anchor's distance against gamma."""
    b, g = np.asarray(b0, float).copy(), np.asarray(g0, float).copy()
    est_beta = beta_prior is not None
    beta = (float(beta_prior[0]) if beta0 is None else float(beta0)) if est_beta else 1.0
    bw = (beta_prior[2] / beta_prior[1]) ** 2 if est_beta else 0.0
    bm = float(beta_prior[0]) if est_beta else 1.0
    if g.shape == ():
        g = np.full(n_links, float(g))
    c2 = scale**2
    cols = [0, 1] + ([] if fix_normal else [2]) + [3 + i for i in range(n_links)]

    pw = 0.0 if gamma_prior is None else (gamma_prior[2] / gamma_prior[1]) ** 2
    gm = 0.0 if gamma_prior is None else float(gamma_prior[0])
    gi = np.arange(3, 3 + n_links)
    gi_cols = [cols.index(i) for i in gi]

    def cost_of(r, g=None, bt=1.0):
        prior = 0.0 if g is None or not pw else pw * float(np.sum((g - gm) ** 2))
        prior += bw * (bt - bm) ** 2
        return float(np.sum(c2 * np.log1p(r**2 / c2))) + prior

    r, u, rho = _residuals(y, d, li, b, g, beta)
    cost = cost_of(r, g, beta)
    nc = len(cols)
    lam = 1e-3
    E = np.zeros((len(d), n_links))
    E[np.arange(len(d)), li] = 1.0
    small = False
    for _ in range(max_iter):
        w = 1.0 / (1.0 + r**2 / c2)
        J = np.concatenate([beta * u, -E], axis=1)[:, cols]  # dr/d(b, gamma); r = d - beta ||y - b|| - gamma
        if est_beta:
            J = np.concatenate([J, -rho[:, None]], axis=1)
        A = (J * w[:, None]).T @ J
        gr = -(J * w[:, None]).T @ r
        if pw:
            A[gi_cols, gi_cols] += pw
            gr[gi_cols] -= pw * (g - gm)
        if est_beta:
            A[nc, nc] += bw
            gr[nc] -= bw * (beta - bm)
        improved = False
        while lam < 1e10:
            try:
                step = np.linalg.solve(A + lam * np.diag(np.maximum(np.diag(A), 1e-12)), gr)
            except np.linalg.LinAlgError:
                lam *= 10
                continue
            full = np.zeros(3 + n_links)
            full[cols] = step[:nc]
            b_new, g_new = b + full[:3], g + full[3:]
            bt_new = beta + float(step[nc]) if est_beta else beta
            r_new, u_new, rho_new = _residuals(y, d, li, b_new, g_new, bt_new)
            c_new = cost_of(r_new, g_new, bt_new)
            if np.isfinite(c_new) and c_new <= cost:
                small = np.linalg.norm(step) < 1e-7 * (1.0 + np.linalg.norm(b))
                b, g, r, u, rho, beta, cost = b_new, g_new, r_new, u_new, rho_new, bt_new, c_new
                lam = max(lam / 10, 1e-9)
                improved = True
                break
            lam *= 10
        if not improved or small:
            break
    w = 1.0 / (1.0 + r**2 / c2)
    J = np.concatenate([-beta * u, E], axis=1)  # dh/d(b, gamma)
    info = (J * w[:, None]).T @ J
    if (
        est_beta
    ):  # beta marginalised out under its prior (it is a nuisance here, the initialiser estimates it)
        jb = rho * w
        ib = J.T @ jb
        info = info - np.outer(ib, ib) / (float(jb @ rho) + bw)
    # (the information is the ranges' alone: the gamma prior steadies the estimate, it does not vouch for it;
    # a sigma that leans on it lets an anchor join before its own ranges pin it down)
    return _Refined(b, g, cost, r, w, info, beta)


def _robust_sigma(r: np.ndarray) -> float:
    return float(1.4826 * np.median(np.abs(r - np.median(r)))) if len(r) else float("nan")


def _not_determined(reason: str, n: int, links: np.ndarray, **kw) -> SearchResult:
    L = len(links)
    return SearchResult(
        "not determined",
        reason,
        np.full(3, np.nan),
        np.full(L, np.nan),
        links,
        np.zeros(n, bool),
        float("nan"),
        np.full((3 + L, 3 + L), np.nan),
        **kw,
    )


def search_anchor(
    xyz: np.ndarray,
    d: np.ndarray,
    link: np.ndarray | None = None,
    *,
    t_ns: np.ndarray | None = None,
    sigma_range: float = 0.1,
    max_samples: int = 2000,
    n_hypotheses: int = 200,
    n_score: int = 600,
    sample_size: int | None = None,
    threshold_m: float | None = None,
    min_ranges: int = 30,
    min_inlier_fraction: float = 0.3,
    max_spread_factor: float = 5.0,
    mirror_chi2: float = 9.0,
    height_sigma_max: float = 0.5,
    static_extent_m: float = 0.3,
    max_sigma_horizontal: float | None = None,
    max_abs_gamma: float = 2.0,
    gamma_prior: tuple[float, float] | None = None,
    beta_prior: tuple[float, float] | None = None,
    pos_cov: np.ndarray | None = None,
    arm_xyz: np.ndarray | None = None,
    attitude_sigma: np.ndarray | None = None,
    seed: int = 0,
) -> SearchResult:
    """Global search for the anchor ranged by the tag positions ``xyz`` (N, 3) with ranges ``d`` (N,) over links
    ``link`` (N,) (None: one link). Returns "not determined" with the reason when the data cannot place it:
    too few ranges, static trajectory, no consensus, residuals that do not verify the fit, or a horizontal
    sigma above ``max_sigma_horizontal``, or an implausible range offset (|gamma| > ``max_abs_gamma``: UWB
    offsets are decimetres; a fit that needs metres has traded the anchor's distance against the offset on a
    short arc). ``threshold_m``: consensus inlier threshold (default max(1 m,
    5 sigma_range)); ``height_sigma_max``: height sigma above which the height is flagged unobservable.
    ``beta_prior`` (mean, sigma): estimate the range scale too (as the initialiser does), marginalised out of
    the covariance; None: beta = 1.

    The height (the anchor's component along the motion plane's normal) is observable only when (a) the
    carrier's own spread along the normal (the tag positions less their world-rotated antenna arms ``arm_xyz``
    (N, 3): the arms' swing out of the plane rests on the arms' calibration and the attitude, so it is not
    taken as signal) is at least ``NORMAL_SNR`` x what corrupts it there (`normal_corruption`: the pose sigma
    along the normal from ``pos_cov`` (N, 3, 3) and the arms' direction error from the attitude sigma
    ``attitude_sigma`` (N,) [rad]), (b) its sigma from the ranges, inflated by the errors-in-variables term
    |b_3| x corruption / spread, is <= ``height_sigma_max`` and (c) the mirror across the plane fits
    distinctly worse (cost difference over the residuals' correlation inflation kappa >= ``mirror_chi2``).
    Otherwise it is flagged with an honest sigma that reaches the other basin.
    """
    xyz = np.asarray(xyz, float).reshape(-1, 3)
    d = np.asarray(d, float).reshape(-1)
    n_all = len(d)
    link = np.zeros(n_all, np.int64) if link is None else np.asarray(link).reshape(-1)
    fin = np.isfinite(d) & np.all(np.isfinite(xyz), axis=1) & (d > 0)
    links_all = np.unique(link[fin]) if fin.any() else np.zeros(0, np.int64)
    if fin.sum() < min_ranges:
        return _not_determined(f"only {int(fin.sum())} usable ranges (< {min_ranges})", n_all, links_all)
    sel = np.flatnonzero(fin)
    if t_ns is not None:
        sel = sel[np.argsort(np.asarray(t_ns)[sel], kind="stable")]
    sel = sel[subsample(len(sel), max_samples)]
    c, Vt, ext = plane_frame(xyz[sel])
    if ext[0] < static_extent_m:
        return _not_determined(
            f"static: the tag moved {ext[0]:.2f} m (std) while ranging it (< {static_extent_m} m)",
            n_all,
            links_all,
        )
    if ext[1] < LINE_RATIO * ext[0]:
        return _not_determined(
            f"the tag moved along a line (extents {ext[0]:.1f}/{ext[1]:.2f} m): the anchor is ambiguous around it",
            n_all,
            links_all,
        )
    planar = bool(ext[2] < PLANAR_RATIO * ext[0])
    arms = None if arm_xyz is None else np.asarray(arm_xyz, float).reshape(-1, 3)[sel]
    sig_n = normal_corruption(
        Vt[2],
        None if pos_cov is None else np.asarray(pos_cov, float).reshape(-1, 3, 3)[sel],
        arms,
        None if attitude_sigma is None else np.asarray(attitude_sigma, float).reshape(-1)[sel],
    )
    spread_n = ext[2] if arms is None else float(np.std((xyz[sel] - arms) @ Vt[2]))
    y = (xyz[sel] - c) @ Vt.T
    dd = d[sel]
    links, li = _link_index(link[sel])
    L = len(links)
    thr = threshold_m if threshold_m is not None else max(1.0, 5.0 * sigma_range)
    rng = np.random.default_rng(seed)
    m = sample_size or (4 if planar else 5) + 4
    m = min(m, len(dd))
    samples = np.stack([rng.choice(len(dd), m, replace=False) for _ in range(n_hypotheses)])
    B, G = closed_form_candidates(y, dd, samples, planar)
    # and with the offset fixed at zero (ranges ~ distances): stable where the free offset is ill-conditioned
    g_fix = 0.0 if gamma_prior is None else float(gamma_prior[0])
    B0, G0 = closed_form_candidates(y, dd, samples, planar, gamma=g_fix)
    gp = None if gamma_prior is None else (float(gamma_prior[0]), float(gamma_prior[1]), sigma_range)
    kw = {"gamma_prior": gp}
    if beta_prior is not None:
        kw["beta_prior"] = (float(beta_prior[0]), float(beta_prior[1]), sigma_range)
    B, G = np.concatenate([B, B0]), np.concatenate([G, G0])
    good = np.all(np.isfinite(B), axis=1) & np.isfinite(G) & (np.abs(G - g_fix) <= max_abs_gamma)
    B, G = B[good], G[good]
    if not len(B):
        return _not_determined(
            f"no closed-form candidate with a plausible range offset (|gamma| <= {max_abs_gamma:g} m)",
            n_all,
            links_all,
            planar=planar,
            code="offset",
        )
    # score and pre-refine on a coarser even subset; the final passes use every sampled range
    q = subsample(len(dd), n_score)
    yq, dq, lq = y[q], dd[q], li[q]
    costs = msac_costs(yq, dq, B, G, thr)
    order = np.argsort(costs)
    # refine a few distinct best candidates (and their mirrors, which are in B too)
    picks: list[int] = []
    for i in order:
        if all(np.linalg.norm(B[i] - B[j]) > 0.5 for j in picks):
            picks.append(int(i))
        if len(picks) >= 2:
            break
    scale = max(thr / 2.0, 3.0 * sigma_range)
    fits: list[_Refined] = []
    for i in picks:
        for b0 in (B[i], B[i] * [1, 1, -1], B[i] * [1, 1, 0]) if planar else (B[i], B[i] * [1, 1, -1]):
            f = refine_robust(yq, dq, lq, L, b0, np.full(L, G[i]), scale, **kw)
            fits.append(f)
    best = min(fits, key=lambda f: f.cost)
    best = refine_robust(y, dd, li, L, best.b, best.g, scale, beta0=best.beta, **kw)
    # second pass at the residuals' own scale (down-weights NLOS junk harder once the basin is found)
    s_in = _robust_sigma(best.r[np.abs(best.r) < thr])
    scale2 = max(3.0 * s_in, 3.0 * sigma_range * 0.2, 0.02)
    best = refine_robust(y, dd, li, L, best.b, best.g, scale2, beta0=best.beta, **kw)
    r = best.r
    inl = np.abs(r) < max(4.0 * s_in, thr / 4)
    frac = float(inl.mean())
    sig = _robust_sigma(r[inl]) if inl.any() else float("nan")
    if frac < min_inlier_fraction:
        return _not_determined(
            f"no consensus: only {frac:.0%} of the ranges fit the best position (< {min_inlier_fraction:.0%})",
            n_all,
            links_all,
            planar=planar,
        )
    # mirror basin across the motion plane
    mir = refine_robust(y, dd, li, L, best.b * [1, 1, -1], best.g, scale2, beta0=best.beta, **kw)
    if mir.cost < best.cost:  # the mirror basin is the better one
        best, mir = mir, best
        r = best.r
    whit = scale2**2 / max(sig, 1e-3) ** 2  # cost units -> whitened squared residuals
    # covariance (residual-scaled, inflated for time-correlated errors)
    tsel = None if t_ns is None else np.asarray(t_ns)[sel]
    kappa = noise_inflation(tsel, r / max(sig, 1e-6), inl.astype(float)) if tsel is not None else 1.0
    dcost = (mir.cost - best.cost) * whit / kappa  # correlated residuals carry kappa x less evidence
    mirror = bool(dcost < mirror_chi2 and np.linalg.norm(mir.b - best.b) > 1e-3)
    info = best.info / max(sig, 1e-6) ** 2 / kappa
    try:
        cov_y = np.linalg.inv(info)
    except np.linalg.LinAlgError:
        cov_y = np.linalg.pinv(info)
    # height along the normal: the ranges' sigma, plus the errors-in-variables term (the tag's normal
    # coordinate, which carries the height's information, is off by sig_n against its spread spread_n)
    sig_fim = float(np.sqrt(max(cov_y[2, 2], 0.0)))
    sig_b3 = float(np.hypot(sig_fim, abs(best.b[2]) * sig_n / max(spread_n, 1e-9)))
    b = best.b.copy()
    normal_ok = bool(spread_n >= NORMAL_SNR * sig_n)
    height_ok = normal_ok and sig_b3 <= height_sigma_max and not mirror
    inflate = not height_ok
    if planar and not height_ok:
        # both signs fit by construction: the basin on the normal's side (up), whose ranges are the same as the
        # mirror's, with a sigma from the ranges' curvature that reaches the mirror within 2 sigma
        s_hat, s_sig = _height_squared(y, dd, li, L, best, sig, kappa)
        bound = float(np.sqrt(max(s_hat, b[2] ** 2, 0.0) + 2.0 * s_sig))
        b[2] = abs(best.b[2])
        sigma_h = max(bound, abs(best.b[2]))
    elif not height_ok:  # the data prefer this basin, not enough: the sigma reaches the other one
        reach = 0.5 * abs(best.b[2] - mir.b[2]) if mirror else 0.0
        sigma_h = max(sig_b3, reach, 0.0 if normal_ok else abs(best.b[2]))
    else:
        sigma_h = sig_b3
    T = np.zeros((3 + L, 3 + L))
    T[:3, :3] = Vt.T
    T[3:, 3:] = np.eye(L)
    cov = T @ cov_y @ T.T
    # honest height: replace the normal direction's variance (and its correlations) by sigma_h
    if inflate:
        n = Vt[2]
        P = np.eye(3) - np.outer(n, n)
        Tp = np.eye(3 + L)
        Tp[:3, :3] = P
        cov = Tp @ cov @ Tp.T
        cov[:3, :3] += sigma_h**2 * np.outer(n, n)
    else:  # the errors-in-variables part of the height's variance
        cov[:3, :3] += (sig_b3**2 - sig_fim**2) * np.outer(Vt[2], Vt[2])
    p_world = c + b @ Vt
    # keep the search's inliers over the input ranges
    inliers = np.zeros(n_all, bool)
    r_all, _, _ = _residuals(
        (xyz[fin] - c) @ Vt.T,
        d[fin],
        np.searchsorted(links, link[fin]).clip(0, L - 1),
        best.b,
        best.g,
        best.beta,
    )
    known = np.isin(link[fin], links)
    inliers[np.flatnonzero(fin)] = known & (np.abs(r_all) < max(4.0 * sig, thr / 4))
    res = SearchResult(
        "ok",
        "",
        p_world,
        best.g.copy(),
        links,
        inliers,
        sig,
        cov,
        planar=planar,
        normal_spread=float(spread_n),
        normal_sigma=float(sig_n),
        height_observable=bool(height_ok),
        mirror=mirror,
        mirror_p=(c + mir.b @ Vt) if mirror else None,
        sigma_h=float(sigma_h),
        normal=Vt[2].copy(),
        n_used=len(dd),
        costs={
            "best": best.cost * whit,
            "mirror": mir.cost * whit,
            "inlier_fraction": frac,
            "kappa": kappa,
        },
        beta=float(best.beta),
        residuals=best.r.copy(),
    )
    spread_ok = sig <= max_spread_factor * max(sigma_range, 0.05)
    if np.any(np.abs(best.g - g_fix) > max_abs_gamma):
        res.status = "not determined"
        res.code = "offset"
        res.reason = (
            f"the best fit needs a range offset of {best.g[np.argmax(np.abs(best.g - g_fix))]:.1f} m (more than "
            f"{max_abs_gamma:g} m from {g_fix:g} m): the "
            "geometry trades the anchor's distance against the offset"
        )
    elif not spread_ok:
        res.status = "not determined"
        res.reason = (
            f"residuals do not verify the fit: inlier spread {sig:.2f} m > {max_spread_factor:g} x "
            f"{max(sigma_range, 0.05):.2f} m"
        )
    elif max_sigma_horizontal is not None and res.sigma_horizontal > max_sigma_horizontal:
        res.status = "not determined"
        res.reason = (
            f"horizontal sigma {res.sigma_horizontal:.2f} m > {max_sigma_horizontal:g} m "
            "(the ranges so far do not pin it down)"
        )
    return res


def normal_corruption(
    n: np.ndarray,
    pos_cov: np.ndarray | None = None,
    arm_xyz: np.ndarray | None = None,
    attitude_sigma: np.ndarray | None = None,
) -> float:
    """What corrupts the tag positions along the unit normal ``n`` [m]: the rms pose sigma along it (position
    covariances (N, 3, 3)) and the world-rotated antenna arms' (N, 3) direction error from the attitude sigma
    (N,) [rad], added in quadrature."""
    v = 0.0
    if pos_cov is not None and len(pos_cov):
        pn = np.einsum("i,nij,j->n", n, pos_cov, n)
        v += float(np.mean(np.where(np.isfinite(pn), np.maximum(pn, 0.0), 0.0)))
    if arm_xyz is not None and attitude_sigma is not None and len(attitude_sigma):
        v += float(np.mean((np.nan_to_num(attitude_sigma) * np.linalg.norm(arm_xyz, axis=1)) ** 2))
    return float(np.sqrt(v))


def _height_squared(y, d, li, L, fit: _Refined, sig: float, kappa: float) -> tuple[float, float]:
    """(s, sigma_s) of the squared out-of-plane distance s = b_3^2 from the curvature of the ranges:
    rho^2 = |y_12 - b_12|^2 + y_3^2 + s (the mirror-breaking -2 b_3 y_3 is left out), linearised at the fit."""
    diff = y - fit.b * [1, 1, 0]
    rho = np.maximum(np.sqrt(np.sum(diff[:, :2] ** 2, axis=1) + y[:, 2] ** 2 + fit.b[2] ** 2), 1e-9)
    E = np.zeros((len(d), L))
    E[np.arange(len(d)), li] = 1.0
    J = np.concatenate([fit.beta * diff[:, :2] / rho[:, None], (0.5 * fit.beta / rho)[:, None], E], axis=1)
    A = (J * fit.w[:, None]).T @ J / max(sig, 1e-6) ** 2 / kappa
    try:
        var_s = float(np.linalg.inv(A)[2, 2])
    except np.linalg.LinAlgError:
        var_s = float("inf")
    return float(fit.b[2] ** 2), float(np.sqrt(max(var_s, 0.0)))


def noise_inflation(
    t_ns: np.ndarray | None,
    e: np.ndarray,
    weights: np.ndarray | None = None,
    *,
    block_s: float = 10.0,
    min_blocks: int = 4,
    quantile: float = 0.99,
) -> float:
    """Variance inflation kappa >= 1 for time-correlated range errors, from the post-fit whitened residuals.

    The estimator treats the ranges as independent. Real UWB errors are not: multipath and the antenna pattern
    make them vary slowly with the geometry (NTU-VIRAL: per-anchor residuals keep correlating over tens of
    seconds), so N ranges carry far less than N independent ranges' information and the inverse information
    is over-confident by a factor kappa (docs/results/measurements.md). Batch means:
    with blocks of ``block_s`` seconds holding n_b inlier residuals, kappa = mean(n_b mean_b^2) / mean(e^2),
    which is chi2(B)/B-distributed around 1 for white errors; it is used only when it exceeds that
    distribution's ``quantile`` (white noise, as in the simulator, keeps kappa = 1).
    """
    e = np.asarray(e, float)
    if t_ns is None or len(e) < 2 * min_blocks:
        return 1.0
    ok = np.isfinite(e)
    if weights is not None:
        ok &= np.asarray(weights, float) > 0.5
    e = e[ok]
    t = (np.asarray(t_ns, np.int64)[ok] - int(np.min(t_ns))) * 1e-9
    if len(e) < 2 * min_blocks:
        return 1.0
    e = e - e.mean()
    b = np.floor(t / block_s).astype(np.int64)
    cnt = np.bincount(b)
    tot = np.bincount(b, e)
    m = cnt >= 3
    nb = int(m.sum())
    if nb < min_blocks:
        return 1.0
    kappa = float(np.sum(tot[m] ** 2 / cnt[m]) / nb / np.mean(e**2))
    return kappa if kappa > chi2_ppf(quantile, nb) / nb else 1.0
