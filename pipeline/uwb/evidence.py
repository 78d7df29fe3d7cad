"""One anchor from its ranges: a robust position fit, and every optional parameter by one evidence rule.

Model: d_k = beta ||x_k - p|| + gamma_l(k) + n_k, with x_k the tag position and l(k) the range's link. The base
family is the position alone (beta = 1, the offset held at its prior mean, as `init_result` reports it), fitted by a soft-L1 robust Gauss-Newton from the linear
least-squares multilateration and from its mirror across the motion plane. The optional families

- ``gamma``: one range offset per anchor, prior N(gamma_mean, gamma_sigma^2) (what UWB hardware has: decimetres),
- ``gamma+beta``: and the range scale, prior N(1, beta_sigma^2) (a TWR clock's error: parts per million),
- ``link``: one offset per (tag, antenna) link, each under the offset prior,

enter by one rule (`choose`): each family's log evidence (the Laplace approximation of its marginal likelihood,
i.e. the ranges' sequential one-step-ahead predictive probability, with its parameters integrated over their
priors) with the ranges' likelihood deflated by how much less they tell than independent ranges do (`deflation`:
the residual spread over the nominal sigma, squared, times the variance factor of block means over time and over
directions of arrival). The simplest family within a Bayes factor `BAYES_FACTOR` of the best one is chosen; the
two basins of the mirror across the motion plane are told apart by the same rule, on each one's evidence summed over
the families (`basin_evidence`), and both are reported when it cannot tell them apart.

The covariance is the evidence-weighted mixture of every family and basin fitted (each one's covariance plus the
spread of its estimate about the chosen one): what the chosen model leaves out (an offset it did not fit, the
other basin) stays in the sigma. Observability is read from the eigen-decomposition of the position's covariance:
an anchor whose horizontal sigma exceeds ``max_sigma`` in any direction is not determined (with that direction); a
weak vertical is an open height with its prior-limited sigma.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from functools import partial

import numpy as np
from scipy.cluster.vq import kmeans2
from scipy.special import logsumexp

from uwbcal.pipeline.core.robust import mad_sigma, robust_loss
from uwbcal.pipeline.core.series import autocorrelation_time, correlated_errors_covariance, noise_inflation
from uwbcal.pipeline.core.state import chi2_ppf, covariance_upper_bound
from uwbcal.pipeline.core.state import nearest_psd as _psd
from uwbcal.pipeline.uwb.fim import assess_observability
from uwbcal.pipeline.uwb.initializer import InitResult
from uwbcal.pipeline.uwb.model import lines_of_sight
from uwbcal.pipeline.uwb.window import InitWindow, plane_frame, subsample

FAMILIES = ("position", "gamma", "gamma+beta", "link", "link+beta")
BAYES_FACTOR = 3.0  # Jeffreys' "substantial" evidence: a richer model must beat a simpler one by this factor
WARM_ITERATIONS = 10  # a refit from a fit of nearly the same problem (profiles, clock scan)
PIN_PRECISION = 1e8  # [1/m^2] a profile's pinned coordinate
CAUCHY_SCALE = 2.0  # [range sigmas] of the robust fit's redescending loss
VERTICAL_COS = 0.9  # a weak direction this close to vertical is a height the geometry leaves open
TWR_SCALE_SIGMA = 1e-3  # range scale of two-way ranging: the clocks' error, parts per million (unless stated)
# the priors that hold an offset / the scale at its mean when the evidence leaves it out of an anchor's model
STATED_SIGMAS = (
    3.0  # an offset this many stated sigmas from a stated prior's mean is one the statement excludes
)
FIXED_OFFSET_SIGMA = 1e-3  # [m]
FIXED_BETA_SIGMA = 1e-5


@dataclass
class AnchorFit:
    """One anchor's evidence fit: its position, links' offsets and covariance, or "not determined" with the
    reason; the chosen model, its evidence and the axes in ``costs["evidence"]``."""

    status: str  # "ok" | "not determined"
    reason: str
    p: np.ndarray  # (3,) world anchor position (at the plane when the mirror is ambiguous)
    gamma: np.ndarray  # (L,) per-link offsets, in the order of ``links``
    links: np.ndarray  # (L,) link ids
    scale: float  # robust residual sigma of the inliers [m]
    cov: np.ndarray  # (3+L, 3+L) covariance of (p world, gamma_l), residual-scaled
    planar: bool = False  # the trajectory is planar (smallest extent < 0.1 x largest)
    height_observable: bool = True
    mirror: bool = False  # the mirror across the motion plane fits as well
    mirror_p: np.ndarray | None = None  # the other basin (world) when ``mirror``
    sigma_h: float = float("nan")  # sigma along ``normal`` [m]
    normal: np.ndarray = field(default_factory=lambda: np.array([0.0, 0.0, 1.0]))
    n_used: int = 0
    costs: dict = field(default_factory=dict)
    beta: float = 1.0  # range scale of the fit (1 unless its model estimates it)
    residuals: np.ndarray | None = None  # (n_used,) of the fit over the ranges it used (model tests)

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


@dataclass(frozen=True)
class FitSpec:
    """Priors and thresholds of `fit_anchor` (the hardware class' priors; the UWB layer's config)."""

    sigma_range: float = 0.1  # nominal range noise [m]; also the soft-L1 scale
    gamma_mean: float = 0.0  # prior mean of a range offset [m]
    gamma_sigma: float = 0.3  # prior sigma of a range offset [m]
    beta_sigma: float = TWR_SCALE_SIGMA  # prior sigma of the range scale
    max_sigma: float = 1.0  # a horizontal sigma [m] above this: not determined
    min_ranges: int = 30
    max_ranges: int = 2000
    static_extent_m: float = 0.3
    block_s: float = 10.0  # time blocks of the deflation's batch means [s]
    robust: bool = True  # soft-L1 loss (False: least squares)
    deflate: float = 1.0  # set by `fit_anchor` from the base fit (`deflation`)
    # [m] size of an antenna pattern's direction-dependent bias (`declared_errors_cov`)
    pattern_sigma: float = 0.05
    # [s] the poses' errors are bounded and correlated over this time (Gauss-Markov, the pose source's declared
    # model): their effect on the anchor floors its covariance (`declared_errors_cov`); 0: none declared
    pose_tau_s: float = 0.0
    # the covariance's profile widening and the declared errors' floor (False: a start or a scan's fit, its
    # model-mixture covariance only)
    refine_cov: bool = True
    stated: tuple[
        str, ...
    ] = ()  # parameters the recording states a prior for ("gamma", "beta"): in every model


@dataclass
class Model:
    """One family fitted from one basin's start."""

    name: str
    basin: int  # 0: the basin of the lower-cost position fit, 1: its mirror
    p: np.ndarray
    beta: float
    g: np.ndarray  # (L,) offset per link
    cost: float  # deflated robust data cost + prior terms
    info: np.ndarray  # information of (p, [beta], offsets), deflated, priors included
    r: np.ndarray  # residuals [m]
    w: np.ndarray  # robust weights
    J: np.ndarray | None = None  # the ranges' whitened Jacobian in (p, [beta], offsets) at the fit
    log_evidence: float = float("nan")


def _losses(spec: FitSpec) -> tuple[tuple[str | None, float], ...]:
    """The (loss, scale) pairs of `robust_loss` a fit runs through: the convex soft-L1 first, then the
    redescending Cauchy (scale `CAUCHY_SCALE`) from its optimum; least squares when not robust."""
    return (("soft_l1", 1.0), ("cauchy", CAUCHY_SCALE)) if spec.robust else ((None, 1.0),)


def range_losses(m: Model, s2: np.ndarray, spec: FitSpec) -> np.ndarray:
    """Each range's deflated robust loss under the fit ``m`` (its share of the data cost)."""
    return robust_loss(m.r / np.sqrt(s2), *_losses(spec)[-1])[0] / spec.deflate


def has_scale(name: str) -> bool:
    """The family estimates the range scale beta."""
    return name.endswith("+beta")


def per_link(name: str) -> bool:
    """The family estimates one offset per link."""
    return name.startswith("link")


def _prior(name: str, L: int, spec: FitSpec) -> tuple[np.ndarray, np.ndarray]:
    """(mean, precision) of the family's parameters (position first, flat; then beta; then the offsets)."""
    scale = has_scale(name)
    ng = 0 if name == "position" else L if per_link(name) else 1
    mu = np.r_[np.zeros(3), [1.0] * scale, np.full(ng, spec.gamma_mean)]
    prec = np.r_[np.zeros(3), [spec.beta_sigma**-2] * scale, np.full(ng, spec.gamma_sigma**-2)]
    return mu, prec


def fit_family(
    xyz: np.ndarray,
    d: np.ndarray,
    li: np.ndarray,
    L: int,
    s2: np.ndarray,
    name: str,
    p0,
    spec: FitSpec,
    pin: tuple[np.ndarray, float] | None = None,
    warm: Model | None = None,
) -> Model:
    """Levenberg-damped IRLS of one family from ``p0`` (priors as residuals, data deflated by ``spec.deflate``)
    through the losses of `_losses`; ``s2`` (N,) the ranges' variances, ``li`` their link index. ``pin`` (v, c):
    the position's component along the unit vector v held at c (a profile of the cost along v). ``warm``: a fit of
    the same family on nearly the same problem to start from (its offsets too; the final loss only, a few
    iterations)."""
    mu, prec = _prior(name, L, spec)
    Lam = np.diag(prec)
    if pin is not None:
        v, c = np.asarray(pin[0], float), float(pin[1])
        Lam[:3, :3] += PIN_PRECISION * np.outer(v, v)
        mu = mu.copy()
        mu[:3] = c * v
    scale, links, ng = has_scale(name), per_link(name), len(mu) - 3 - has_scale(name)
    gi = li if links else np.zeros(len(d), np.int64)
    sd, f = np.sqrt(s2), 1.0 / spec.deflate

    def evaluate(th, loss):
        diff = th[:3] - xyz
        rho = np.maximum(np.linalg.norm(diff, axis=1), 1e-9)
        b = th[3] if scale else 1.0
        r = (
            d - b * rho - (th[3 + scale :][gi] if ng else spec.gamma_mean)
        )  # no offset family: held at its mean
        cost_k, w = robust_loss(r / sd, *loss)
        J = [b * diff / rho[:, None]] + ([rho[:, None]] if scale else [])
        if ng:
            J.append(np.eye(ng)[gi])
        dt = th - mu
        cost = f * float(np.sum(cost_k)) + float(dt @ Lam @ dt)
        return cost, np.hstack(J) / sd[:, None], r, w

    theta = np.r_[np.asarray(p0, float), mu[3:]]
    losses, iters = _losses(spec), 60
    if warm is not None:
        g = warm.g if links else warm.g[:1]
        theta = np.r_[np.asarray(p0, float), [warm.beta] * scale, g if ng else []]
        losses, iters = losses[-1:], WARM_ITERATIONS
    for loss in losses:
        theta, (cost, J, r, w) = _irls(lambda th, k=loss: evaluate(th, k), theta, mu, Lam, f, sd, iters)
    info = (J * (f * w)[:, None]).T @ J + np.diag(prec)
    g = theta[3 + scale :] if ng else np.zeros(0)
    g_links = g.copy() if links else np.full(L, g[0] if ng else spec.gamma_mean)
    return Model(name, 0, theta[:3].copy(), float(theta[3]) if scale else 1.0, g_links, cost, info, r, w, J)


def _irls(evaluate, theta, mu, Lam, f, sd, max_iter: int = 60):
    """Levenberg-damped IRLS of ``evaluate(theta) -> (cost, J, r, w)`` from ``theta``; prior (mu, precision
    matrix Lam)."""
    res = evaluate(theta)
    lam = 1e-3
    for _ in range(max_iter):
        cost, J, r, w = res
        A = (J * (f * w)[:, None]).T @ J + Lam
        grad = (J * (f * w)[:, None]).T @ (r / sd) - Lam @ (theta - mu)
        step = np.zeros_like(theta)
        while lam < 1e10:
            step = np.linalg.solve(A + lam * np.diag(np.maximum(np.diag(A), 1e-9)), grad)
            cand = evaluate(theta + step)
            if cand[0] <= cost:
                theta, res = theta + step, cand
                lam = max(lam / 10, 1e-9)
                break
            lam *= 10
        if lam >= 1e10 or np.linalg.norm(step) < 1e-7 * (1 + np.linalg.norm(theta[:3])):
            break
    return theta, res


def posterior_info(m: Model, reach: float) -> np.ndarray:
    """The fit's information with the position's prior: the anchor within ``reach`` of the tags (N(., reach^2 I))."""
    A = m.info.copy()
    A[:3, :3] += np.eye(3) / reach**2
    return A


def log_evidence(m: Model, spec: FitSpec, reach: float) -> float:
    """Laplace log marginal likelihood of a fit, up to the constant every family of the anchor shares: the
    deflated cost, the Occam factor of the information against the priors (`posterior_info`)."""
    _, prec = _prior(m.name, len(m.g), spec)
    logdet = np.linalg.slogdet(posterior_info(m, reach))[1]
    return float(-0.5 * m.cost - 0.5 * logdet + 0.5 * np.sum(np.log(prec[3:])) + 1.5 * np.log(reach**-2))


def model_families(stated: tuple[str, ...], links: int) -> list[str]:
    """The families the evidence rule chooses among: those holding every parameter the recording states a prior
    for (``stated``: "gamma", "beta"; a stated parameter is part of the hardware's model, the rule decides the
    others), per-link offsets only with several links."""
    need = {"gamma": lambda f: f != "position", "beta": has_scale}
    return [
        f for f in FAMILIES if (not per_link(f) or links > 1) and all(need[p](f) for p in stated if p in need)
    ]


def basin_evidence(models: list[Model], basin: int) -> float:
    """The log evidence of a basin with the range model integrated out (every family's evidence in it, summed):
    which side of the motion plane the anchor is on does not depend on which offsets the ranges carry, and a
    basin one family disfavours another may fit as well."""
    return float(logsumexp([m.log_evidence for m in models if m.basin == basin]))


def choose(models: list[Model]) -> Model:
    """The simplest family (in `FAMILIES` order) whose log evidence is within log `BAYES_FACTOR` of the best
    model's; of its basins, the one of higher evidence."""
    best = max(m.log_evidence for m in models)
    near = [m for m in models if m.log_evidence >= best - np.log(BAYES_FACTOR)]
    return min(near, key=lambda m: (FAMILIES.index(m.name), -m.log_evidence))


def basin_deflation(a: Model, b: Model, data: tuple, spec: FitSpec) -> float:
    """How much less the evidence between two basins tells than the ranges' noise says, >= 1: the variance of
    their log Bayes factor under the declared pose error (Gauss-Markov over ``spec.pose_tau_s``) added to its
    variance under the (deflated) ranges' noise, over the latter. A pose error shared along the path moves every
    range alike and leaves no trace in either fit's residuals, yet it can mimic the carrier's small excursions
    off its plane that tell the two sides apart."""
    xyz, s2 = data[0], data[3]
    if a is b:
        return 1.0
    white = spec.deflate * float(np.sum((b.r - a.r) ** 2 / s2))  # d log BF / d range error: (r_b - r_a) / s2
    # d log BF / d tag position: each basin's residual moves along its own line of sight (a shift shared by every
    # pose moves both anchors with it and cancels)
    gains = (b.r[:, None] * lines_of_sight(b.p, xyz) - a.r[:, None] * lines_of_sight(a.p, xyz)) / s2[:, None]
    return 1.0 + float(declared_pose_cov(gains[:, None, :], data, spec)[0, 0]) / max(white, 1e-12)


def declared_pose_cov(gains: np.ndarray, data: tuple, spec: FitSpec) -> np.ndarray:
    """(m, m): a bounded pose source's declared error (Gauss-Markov over ``spec.pose_tau_s``) through ``gains``
    (N, m, 3), each tag position error's effect on m quantities; zero without one (a drifting source)."""
    t, pose_var = data[4], data[5]
    if pose_var is None or t is None or spec.pose_tau_s <= 0:
        return np.zeros((gains.shape[1], gains.shape[1]))
    return correlated_errors_covariance(gains, pose_var, (t - t[0]) * 1e-9, spec.pose_tau_s)


def _group_inflation(e: np.ndarray, groups: np.ndarray, quantile: float = 0.99) -> float:
    """Variance factor of a mean of ``e`` over what the groups share (one-way ANOVA: the between-group mean
    square over the variance), >= 1; used only beyond the ``quantile`` of its chi2 distribution under
    independence (white residuals keep 1)."""
    _, inv, cnt = np.unique(groups, return_inverse=True, return_counts=True)
    G = len(cnt)
    v = float(np.var(e))
    if G < 4 or v <= 0:
        return 1.0
    m = np.bincount(inv, e) / cnt
    k = float(np.sum(cnt * (m - e.mean()) ** 2) / (G - 1) / v)
    return k if k > chi2_ppf(quantile, G - 1) / (G - 1) else 1.0


def direction_cells(u: np.ndarray, cells: int = 16) -> np.ndarray:
    """A cell per line-of-sight direction (unit vectors ``u``, anchor to tag): k-means of the directions, so that
    the cells split whatever cone of directions the motion spans (a loop around the anchor, an arc, a climb)."""
    if len(u) < 2 * cells:
        return np.zeros(len(u), np.int64)
    _, lab = kmeans2(u, cells, seed=np.random.default_rng(0), minit="++")
    return lab.astype(np.int64)


def deflation(
    m: Model,
    xyz: np.ndarray,
    s2: np.ndarray,
    t_ns: np.ndarray | None,
    spec: FitSpec,
    li: np.ndarray | None = None,
) -> float:
    """How much less the ranges tell than independent ones at their nominal noise: (robust residual spread /
    nominal sigma)^2 times the larger variance factor of block means over time and over directions of arrival
    (multipath, a pose error and an antenna pattern make neighbouring ranges err alike), at least 1. The residuals
    are taken about each link's median (``li``: a constant per link is the offset families' to explain, not
    noise)."""
    e = _standardised(m, s2, li)
    spread = mad_sigma(e)
    ec = np.clip(e / max(spread, 1e-6), -3.0, 3.0)
    u = lines_of_sight(m.p, xyz)
    kt = 1.0
    if t_ns is not None:
        order = np.argsort(t_ns, kind="stable")
        kt = max(noise_inflation(t_ns, ec, block_s=spec.block_s), autocorrelation_time(ec[order]))
    return max(spread, 1.0) ** 2 * max(kt, _group_inflation(ec, direction_cells(u)))


def _standardised(m: Model, s2: np.ndarray, li: np.ndarray | None) -> np.ndarray:
    """The fit's residuals over their nominal sigmas, about each link's median (``li``: a constant per link is the
    offset families' to explain, not noise)."""
    e = m.r / np.sqrt(s2)
    if li is not None:
        for k in np.unique(li):
            e[li == k] -= np.median(e[li == k])
    return e


def _linear_start(xyz: np.ndarray, d: np.ndarray) -> np.ndarray:
    A = np.c_[-2.0 * xyz, np.ones(len(d))]
    sol, *_ = np.linalg.lstsq(A, d**2 - np.sum(xyz**2, axis=1), rcond=None)
    return sol[:3]


def not_determined(reason: str, links: np.ndarray, **kw) -> AnchorFit:
    L = len(links)
    nan = np.full((3 + L, 3 + L), np.nan)
    return AnchorFit(
        "not determined",
        reason,
        np.full(3, np.nan),
        np.zeros(L),
        links,
        float("nan"),
        nan,
        **kw,
    )


def mixture_cov(
    models: list[Model], chosen: Model, reach: float, alternatives: list[Model] = ()
) -> np.ndarray:
    """Covariance of (p, offsets per link) of the chosen model, its position block the larger
    (`covariance_upper_bound`) of its own and the evidence-weighted mixture of every family and basin fitted and of
    ``alternatives`` (fits under another prior: a stated offset the ranges do not confirm): their covariances plus
    the spread of their positions about the chosen one. What the chosen model leaves out (the other basin, an
    offset it holds at its prior mean) stays in the sigma as much as the ranges allow it."""

    def pos_cov(m: Model) -> np.ndarray:
        return np.linalg.inv(posterior_info(m, reach))

    C = pos_cov(chosen)
    every = list(models) + list(alternatives)
    z = np.array([m.log_evidence for m in every])
    wts = np.exp(z - z.max()) / np.sum(np.exp(z - z.max()))
    mix = sum(
        w * (pos_cov(m)[:3, :3] + np.outer(m.p - chosen.p, m.p - chosen.p))
        for m, w in zip(every, wts, strict=True)
    )
    L = len(chosen.g)
    out = np.zeros((3 + L, 3 + L))
    out[:3, :3] = covariance_upper_bound(mix, C[:3, :3])
    k = 3 + has_scale(chosen.name)  # the offsets' rows in C
    if per_link(chosen.name):
        out[:3, 3:], out[3:, 3:] = C[:3, k:], C[k:, k:]
    elif chosen.name != "position":  # one offset shared by every link
        out[:3, 3:] = C[:3, k : k + 1]
        out[3:, 3:] = C[k, k]
    return 0.5 * (out + out.T)


def fit_anchor(
    xyz: np.ndarray,
    d: np.ndarray,
    link: np.ndarray | None = None,
    *,
    t_ns: np.ndarray | None = None,
    pos_cov: np.ndarray | None = None,
    spec: FitSpec | None = None,
) -> AnchorFit:
    """The anchor ranged by tag positions ``xyz`` (N, 3) with ranges ``d`` over links ``link``: position, offsets
    (per link, in ``links`` order) and their covariance, the family the evidence chose (``costs["evidence"]``),
    or "not determined" with the reason. ``pos_cov`` (N, 3, 3): the tag positions' covariance (RI weighting)."""
    spec = spec or FitSpec()
    xyz = np.asarray(xyz, float).reshape(-1, 3)
    d = np.asarray(d, float).reshape(-1)
    link = np.zeros(len(d), np.int64) if link is None else np.asarray(link, np.int64).reshape(-1)
    fin = np.isfinite(d) & np.all(np.isfinite(xyz), axis=1) & (d > 0)
    links = np.unique(link[fin])
    if fin.sum() < spec.min_ranges:
        return not_determined(f"only {int(fin.sum())} usable ranges (< {spec.min_ranges})", links)
    sel = np.flatnonzero(fin)
    if t_ns is not None:
        sel = sel[np.argsort(np.asarray(t_ns)[sel], kind="stable")]
    sel = sel[subsample(len(sel), spec.max_ranges)]
    x, dd = xyz[sel], d[sel]
    t = None if t_ns is None else np.asarray(t_ns)[sel]
    c, Vt, ext = plane_frame(x)
    if ext[0] < spec.static_extent_m:
        reason = f"static: the tag moved {ext[0]:.2f} m (std) while ranging it (< {spec.static_extent_m} m)"
        return not_determined(reason, links)
    li = np.searchsorted(links, link[sel])
    L = len(links)
    s2 = np.full(len(dd), spec.sigma_range**2)
    p0 = _linear_start(x, dd - spec.gamma_mean)
    if pos_cov is not None:  # the pose's uncertainty along the line of sight (RI)
        u = lines_of_sight(p0, x)
        s2 = s2 + np.maximum(np.einsum("ni,nij,nj->n", u, np.asarray(pos_cov, float)[sel], u), 0.0)
    n = Vt[2]
    starts = (p0, p0 - 2.0 * n * float(n @ (p0 - c)))
    base = [fit_family(x, dd, li, L, s2, "position", s, spec) for s in starts]
    if base[1].cost < base[0].cost:
        starts = starts[::-1]
    reach = float(np.max(dd)) + float(np.max(ext))
    families = model_families(spec.stated, L)
    best = min(base, key=lambda m: m.cost)
    fit_all = partial(_fit_families, families, starts, (x, dd, li, L, s2), reach)
    for _ in range(2):  # the deflation is what the chosen model leaves unexplained: measured on its residuals
        d_new = deflation(best, x, s2, t, spec, li)
        if best.name != "position" and abs(np.log(d_new / spec.deflate)) < 0.1:
            break
        spec = replace(spec, deflate=d_new)
        models = fit_all(spec)
        best = choose(models)
        if best.name == "position":
            break
    test, alternatives = None, []
    if "gamma" in spec.stated:
        test, alternatives = _stated_offset(spec, models, best, fit_all, reach)
    # the side of the plane is told by the carrier's excursions along its normal: within twice the poses' own
    # uncertainty along it they are what pose errors alone make (a drifting height or tilt picks a side), whatever
    # the fit's curvature says
    sign_open = pos_cov is not None and ext[2] <= 2.0 * np.sqrt(
        np.median(np.einsum("i,nij,j->n", n, pos_cov[sel], n))
    )
    pose_var = (
        None
        if pos_cov is None
        else np.trace(np.asarray(pos_cov, float)[sel][:, :3, :3], axis1=1, axis2=2) / 3
    )
    data = (x, dd, li, s2, t, pose_var)
    fit = _verdict(best, models, data, links, Vt, ext, spec, reach, sign_open, alternatives)
    if test and "evidence" in fit.costs:
        fit.costs["evidence"]["offset_prior"] = test
    return fit


def _stated_offset(spec: FitSpec, models: list[Model], best: Model, fit_all, reach: float):
    """A stated offset prior is a hypothesis too, tested by the same rule against an offset it does not hold
    (N(0, reach^2)). When that offset lies outside the statement and fits better ("contradicted": by the Bayes
    factor) or as well ("not confirmed"), both are reported as two basins are: the estimate keeps the statement
    (a free offset trades against the distance), the other's fits widen its covariance. Returns (the test's
    record, the alternative fits)."""
    alt = fit_all(replace(spec, gamma_mean=0.0, gamma_sigma=reach))
    free = max(alt, key=lambda m: m.log_evidence)
    log_bf = free.log_evidence - max(m.log_evidence for m in models)
    g = float(np.mean(free.g))
    test = {"stated": [spec.gamma_mean, spec.gamma_sigma], "free_offset_m": round(g, 3)}
    test["log_bayes_factor"] = round(float(log_bf), 2)
    if log_bf <= -np.log(BAYES_FACTOR) or abs(g - spec.gamma_mean) <= STATED_SIGMAS * spec.gamma_sigma:
        return test | {"verdict": "confirmed"}, []
    test["verdict"] = "contradicted" if log_bf > np.log(BAYES_FACTOR) else "not confirmed"
    return test, [m for m in alt if m.name == best.name and m.basin == best.basin]


def _fit_families(families, starts, data, reach, spec: FitSpec) -> list[Model]:
    """Every family from every basin's start under ``spec``, each with its log evidence (``data``: the
    positions, ranges, link indices, link count and variances of `fit_family`)."""
    models = []
    for name in families:
        for k, s in enumerate(starts):
            m = replace(fit_family(*data, name, s, spec), basin=k)
            m.log_evidence = log_evidence(m, spec, reach)
            models.append(m)
    return models


def likelihood_widening(m: Model, data: tuple, spec: FitSpec, cov: np.ndarray, reach: float) -> np.ndarray:
    """The position covariance widened, along each of its axes, to the likelihood's own 1-sigma interval: the
    profile of the deflated cost along the axis (the position pinned there, everything else refitted) rises by 1
    within it (searched in doubling steps up to ``reach``). The quadratic approximation fails where the cost is
    flat far beyond its curvature, along a curved valley (a height seen from a plane: d = sqrt(rho^2 + h^2) trades
    h against rho)."""
    xyz, d, li, s2 = data
    lam, V = np.linalg.eigh(cov[:3, :3])
    sd = np.sqrt(np.maximum(lam, 1e-12))
    out = cov.copy()
    for i in range(3):
        v = V[:, i]
        c0 = float(v @ m.p)
        half = 0.0
        for sign in (1.0, -1.0):
            for step in sd[i] * 2.0 ** np.arange(0.0, 12.0):
                if step > reach:
                    break
                p0 = m.p + sign * step * v
                prof = fit_family(
                    xyz, d, li, len(m.g), s2, m.name, p0, spec, pin=(v, c0 + sign * step), warm=m
                )
                if prof.cost - m.cost > 1.0:
                    break
                half = max(half, step)
        if half > sd[i]:
            out[:3, :3] += (half**2 - sd[i] ** 2) * np.outer(v, v)
    return out


def range_gain(m: Model, s2: np.ndarray, spec: FitSpec, reach: float) -> np.ndarray:
    """(3, N) the fit's linear map from the ranges' errors [m] to its position (robust weights and priors
    included)."""
    whitened = (m.J * (m.w / spec.deflate)[:, None]).T
    return np.linalg.solve(posterior_info(m, reach), whitened)[:3] / np.sqrt(s2)


def declared_errors_cov(m: Model, data: tuple, spec: FitSpec, reach: float) -> np.ndarray:
    """The position's covariance from the errors the recording declares, through the fit's gain G: the ranges
    white at their measured spread; a bounded pose source's error, Gauss-Markov over ``spec.pose_tau_s``; an
    antenna pattern of the hardware's size, a bias b(u) = c . u with c ~ N(0, pattern_sigma^2 I) over the
    direction of arrival u. A floor of the covariance: a pose error shared along a stretch of the path moves the
    anchor with it, and a pattern mimics a displaced anchor, so neither leaves a trace in the residuals that the
    deflation or a regrouping of the ranges could measure."""
    xyz, _, li, s2 = data[:4]
    G = range_gain(m, s2, spec, reach)
    u = lines_of_sight(m.p, xyz)
    cov = max(mad_sigma(_standardised(m, s2, li)), 1.0) ** 2 * (G * s2) @ G.T
    M = G @ u
    cov += spec.pattern_sigma**2 * M @ M.T
    gains = G.T[:, :, None] * u[:, None, :]  # (N, 3, 3): each tag position error -> p
    return cov + declared_pose_cov(gains, data, spec)


def _open_height(cov: np.ndarray, max_sigma: float, reach: float, mirror: bool = False) -> np.ndarray:
    """A height the ranges leave open (the weakest direction near vertical, its sigma over ``max_sigma``, or the
    side of the motion plane undecided: ``mirror``) gets the prior's sigma, the reach of the ranges: far beyond its
    curvature, the likelihood of a height seen from a nearly flat motion is shaped by what the model leaves out (a
    range-dependent error, the other basin), not by the ranges' noise."""
    lam, V = np.linalg.eigh(cov[:3, :3])
    if not mirror and (abs(V[2, -1]) < VERTICAL_COS or np.sqrt(max(lam[-1], 0.0)) <= max_sigma):
        return cov
    out = cov.copy()
    out[2, 2] += max(reach**2 - out[2, 2], 0.0)
    return out


def weak_horizontal(cov: np.ndarray, max_sigma: float) -> str:
    """Why an anchor of position covariance ``cov`` is not determined: its horizontal sigma over ``max_sigma``
    along some direction ("" when it is not)."""
    lam, V = np.linalg.eigh(_psd(np.asarray(cov, float)[:2, :2]))
    if np.sqrt(lam[-1]) <= max_sigma:
        return ""
    v = V[:, -1] * np.sign(V[np.argmax(np.abs(V[:, -1])), -1])
    return (
        f"weak horizontal direction ({v[0]:.2f}, {v[1]:.2f}): sigma {np.sqrt(lam[-1]):.2f} m > {max_sigma:g} m "
        "(the motion does not pin the anchor down along it)"
    )


def _verdict(best, models, data, links, Vt, ext, spec, reach, sign_open=False, alternatives=()):
    """The AnchorFit of the chosen model: weak directions from the eigen-decomposition of its covariance
    (widened to the likelihood's intervals), the other basin when the evidence (deflated for the declared pose
    error, `basin_deflation`) or, with ``sign_open``, the motion cannot tell them apart: then the height is open."""
    dd = data[1]
    twin = [m for m in models if m.name == best.name and m.basin != best.basin]
    other = twin[0] if twin else best
    two = np.linalg.norm(other.p - best.p) > 1e-3
    lead = basin_evidence(models, best.basin) - basin_evidence(models, other.basin)
    side_deflation = basin_deflation(best, other, data, spec)
    close = lead / side_deflation <= np.log(BAYES_FACTOR)
    mirror = bool(sign_open or (two and close))
    if mirror and not two:  # one basin found: the other side is the estimate's mirror across the motion plane
        nrm = Vt[2]
        other = replace(other, p=best.p - 2.0 * nrm * float(nrm @ (best.p - data[0].mean(axis=0))))
    mirror = mirror and bool(np.linalg.norm(other.p - best.p) > 1e-3)  # an anchor on the plane has no mirror
    cov = mixture_cov(models, best, reach, alternatives)
    wide = cov
    if spec.refine_cov:
        wide = likelihood_widening(best, data[:4], spec, cov, reach)
        wide[:3, :3] = covariance_upper_bound(declared_errors_cov(best, data, spec, reach), wide[:3, :3])
    wide = _open_height(wide, spec.max_sigma, reach, mirror)
    cov = wide
    lam, V = np.linalg.eigh(cov[:3, :3])
    sd = np.sqrt(np.maximum(lam, 0.0))
    sig = mad_sigma(best.r)
    evidence = {
        "model": best.name,
        "log_evidence": {f"{m.name}/{m.basin}": round(m.log_evidence - best.log_evidence, 2) for m in models},
        "deflation": round(spec.deflate, 2),
        "side_deflation": round(side_deflation, 2),
        "axes": [{"direction": np.round(V[:, i], 3).tolist(), "sigma_m": float(sd[i])} for i in range(3)],
    }
    kw = dict(
        planar=bool(ext[2] < 0.1 * ext[0]),
        n_used=len(dd),
        costs={
            "best": best.cost,
            "mirror": other.cost,
            "kappa": spec.deflate,
            "evidence": evidence,
        },
        beta=best.beta,
        residuals=best.r.copy(),
    )
    reason = weak_horizontal(cov, spec.max_sigma)
    if reason:
        return not_determined(reason, links, **kw)
    i = int(np.argmax(sd))
    vertical = abs(V[2, i]) >= VERTICAL_COS and sd[i] > spec.max_sigma
    normal = V[:, i] if vertical else Vt[2]
    normal = normal * np.sign(normal[2] if abs(normal[2]) > 1e-9 else 1.0)
    sigma_h = float(np.sqrt(max(normal @ cov[:3, :3] @ normal, 0.0)))
    return AnchorFit(
        "ok",
        "",
        best.p.copy(),
        best.g.copy(),
        links,
        sig,
        cov,
        height_observable=not (vertical or mirror),
        mirror=mirror,
        mirror_p=other.p.copy() if mirror else None,
        sigma_h=sigma_h,
        normal=normal,
        **kw,
    )


def init_result(window: InitWindow, sr: AnchorFit, method: str, anchor: str, spec: FitSpec) -> InitResult:
    """The initialiser's result from an evidence fit (`fit_anchor` on ``window``): x = (p, beta, mean offset), its
    covariance (a parameter the model left out at its prior mean with the sigma that holds it there), the links'
    offsets relative to their mean, the chosen model and its evidence in the verdict."""
    verdict = {"status": sr.status, "reason": sr.reason, "height_observable": bool(sr.height_observable)}
    ev = sr.costs.get("evidence")
    if ev:
        verdict["model"] = ev
    if not sr.ok:
        msg = f"{anchor}: not determined: {sr.reason}"
        warns = [msg] + [w for w in [_offset_warning(anchor, ev or {})] if w]
        return InitResult.without_estimate(anchor, method, "not determined", window, warns, verdict)
    model = ev["model"]
    L = len(sr.links)
    wts = np.full(L, 1.0 / L)
    x = np.r_[sr.p, sr.beta, float(wts @ sr.gamma)]
    cov = np.zeros((5, 5))
    cov[:3, :3] = sr.cov[:3, :3]
    offsets = model != "position"
    if offsets:
        cov[:3, 4] = cov[4, :3] = sr.cov[:3, 3:] @ wts
        cov[4, 4] = float(wts @ sr.cov[3:, 3:] @ wts)
    else:
        cov[4, 4] = FIXED_OFFSET_SIGMA**2
    cov[3, 3] = spec.beta_sigma**2 if has_scale(model) else FIXED_BETA_SIGMA**2
    res = InitResult(
        anchor,
        method,
        "ok",
        x,
        cov,
        n_used=sr.n_used,
        noise_inflation=float(sr.costs.get("kappa", 1.0)),
        residual_rms=float(np.sqrt(np.mean(sr.residuals**2))),
        residual_robust_sigma=sr.scale,
        window=window.subset(subsample(len(window), spec.max_ranges)),
        params=(0, 1, 2, 3, 4) if has_scale(model) else (0, 1, 2, 4),
        verdict=verdict,
    )
    res.fim = assess_observability(  # the paper's Fisher information of the window, for the report
        res.window.R,
        res.window.p,
        res.window.p_T,
        res.window.P_pose,
        x,
        spec.sigma_range**2,
        force=True,
        label=anchor,
    )
    if per_link(model):
        T = np.eye(L) - 1.0 / L
        res.link_offsets = {int(k): float(g - x[4]) for k, g in zip(sr.links, sr.gamma, strict=True)}
        res.link_cov = T @ sr.cov[3:, 3:] @ T
    gamma = (spec.gamma_mean, spec.gamma_sigma if offsets else FIXED_OFFSET_SIGMA)
    res.model_priors = (gamma, (1.0, spec.beta_sigma if has_scale(model) else FIXED_BETA_SIGMA))
    if msg := _offset_warning(anchor, ev):
        res.warnings.append(msg)
        res.status = "warning"
    if not sr.height_observable:
        why = "the mirror across the motion plane fits as well" if sr.mirror else "weak vertical direction"
        res.warnings.append(f"{anchor}: height not determined ({why}): {sr.p[2]:.2f} +- {sr.sigma_h:.2f} m")
        res.status = "warning"
    return res


def _offset_warning(anchor: str, evidence: dict) -> str:
    """The warning of a stated offset prior the ranges contradict or do not confirm (`_stated_offset`), or ""."""
    test = evidence.get("offset_prior") or {}
    if test.get("verdict") not in ("contradicted", "not confirmed"):
        return ""
    (m0, s0), g = test["stated"], test["free_offset_m"]
    return (
        f"{anchor}: ranging offset gamma {g:+.2f} m fits the ranges (log Bayes factor {test['log_bayes_factor']:+.1f}"
        f" over the stated prior {m0:g} +- {s0:g} m: {test['verdict']}; the estimate keeps the statement, its "
        "covariance spans both) — check this anchor's ranging bias"
    )
