"""One anchor from its ranges alone: a robust position fit, and every optional parameter by the same evidence rule.

Model: d_k = beta ||x_k - p|| + gamma_l(k) + n_k, with x_k the tag position and l(k) the range's link. The base
model is the position alone (beta = 1, no offset), fitted by a soft-L1 robust Gauss-Newton from the linear
least-squares multilateration (and from its mirror across the motion plane). The optional families

- ``gamma``: one range offset per anchor, prior N(0, gamma_sigma^2) (what UWB hardware has: decimetres),
- ``beta``: the range scale, prior N(1, beta_sigma^2),
- ``link``: one offset per (tag, antenna) link, each under the offset prior,

enter only by one rule (`choose_model`): time-blocked K-fold cross-validation of the robust loss of held-out
ranges; the simplest model within one standard error of the best one wins (one-standard-error rule), so a
parameter that trades against the distance on the training folds, and predicts the held-out ones worse, stays out.

Observability is read from the eigen-decomposition of the position's covariance: the information's (ranges
weighted by their noise plus the pose covariance along the line of sight, offsets and scale marginalised,
inflated by the residuals' time correlation and scaled by their spread), with a prior that limits every direction
to the largest range (the anchor is within reach of the tag), plus the block jackknife of the leave-one-block-out
fits (what time-correlated errors and a direction-dependent bias do to the estimate). A direction whose sigma exceeds ``max_sigma`` is weak: the anchor is
not determined when a weak direction has a horizontal component (the horizontal position is what is asked for);
a weak vertical is reported as an undetermined height with its prior-limited sigma. Two basins (the mirror
across the motion plane) are told apart by the same held-out rule; when they cannot be, both are reported.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from uwbcal.pipeline.uwb.search import SearchResult, noise_inflation, plane_frame, subsample

FAMILIES = ("position", "gamma", "gamma+beta", "link")
VERTICAL_COS = 0.9  # a weak direction this close to vertical is a height the geometry leaves open


@dataclass
class FitSpec:
    """Priors and thresholds of `fit_anchor` (the hardware class' priors; the UWB layer's config)."""

    sigma_range: float = 0.1  # nominal range noise [m]; also the soft-L1 scale
    gamma_mean: float = 0.0  # prior mean of a range offset [m]
    gamma_sigma: float = 0.3  # prior sigma of a range offset [m]
    beta_sigma: float = 0.05  # prior sigma of the range scale
    max_sigma: float = 1.0  # a direction with a larger sigma [m] is weak
    folds: int = 10
    min_ranges: int = 30
    max_ranges: int = 2000
    static_extent_m: float = 0.3
    # how much less a range tells than the nominal noise says: (residual spread / sigma_range)^2 x kappa (time
    # correlation) of the position fit; the priors weigh this much more against the ranges
    deflate: float = 1.0


@dataclass
class _Model:
    name: str
    p: np.ndarray
    beta: float
    g: np.ndarray  # (L,) offset per link
    cost: float
    info: np.ndarray  # Gauss-Newton information of the parameters (position first), priors included
    r: np.ndarray  # residuals over the fitted ranges
    w: np.ndarray  # robust weights


@dataclass
class Evidence:
    """The held-out robust loss of each family (lower is better) and the one chosen."""

    chosen: str
    cv_loss: dict = field(default_factory=dict)
    cv_se: dict = field(default_factory=dict)

    def summary(self) -> dict:
        return {
            "model": self.chosen,
            "cv_loss": {k: round(float(v), 3) for k, v in self.cv_loss.items()},
            "cv_se": {k: round(float(v), 3) for k, v in self.cv_se.items()},
        }


def _soft_l1(r: np.ndarray, c: float) -> tuple[np.ndarray, np.ndarray]:
    """rho(r) = 2 c^2 (sqrt(1 + (r/c)^2) - 1) (r^2 near 0) and its IRLS weight rho'(r) / (2 r)."""
    q = np.sqrt(1.0 + (r / c) ** 2)
    return 2.0 * c**2 * (q - 1.0), 1.0 / q


def _columns(name: str) -> tuple[bool, bool, bool]:
    """(offset, scale, per-link) of a family."""
    return name != "position", name == "gamma+beta", name == "link"


def _fit(
    xyz: np.ndarray,
    d: np.ndarray,
    li: np.ndarray,
    L: int,
    s2: np.ndarray,
    name: str,
    p0: np.ndarray,
    spec: FitSpec,
    max_iter: int = 30,
    g0: np.ndarray | None = None,
) -> _Model:
    """Soft-L1 Levenberg-damped IRLS of one family from ``p0``; ``s2`` (N,) the ranges' variances."""
    off, scale, per_link = _columns(name)
    ng = (L if per_link else 1) if off else 0
    theta = np.r_[
        p0, 1.0 if scale else [], np.full(ng, spec.gamma_mean) if g0 is None or not off else g0[:ng]
    ]
    gi = li if per_link else np.zeros(len(d), np.int64)
    prior_sd = np.r_[np.full(3, np.inf), [spec.beta_sigma] if scale else [], np.full(ng, spec.gamma_sigma)]
    prior_mu = np.r_[np.zeros(3), [1.0] if scale else [], np.full(ng, spec.gamma_mean)]
    pw = np.where(np.isfinite(prior_sd), spec.deflate / prior_sd**2, 0.0)
    c = spec.sigma_range

    def evaluate(th):
        diff = th[:3] - xyz
        rho = np.maximum(np.linalg.norm(diff, axis=1), 1e-9)
        b = th[3] if scale else 1.0
        g = th[3 + scale :][gi] if off else spec.gamma_mean
        r = d - b * rho - g
        loss, w = _soft_l1(r / np.sqrt(s2), c / spec.sigma_range)
        cost = float(np.sum(loss)) + float(np.sum(pw * (th - prior_mu) ** 2))
        J = [b * diff / rho[:, None]]
        if scale:
            J.append(rho[:, None])
        if off:
            E = np.zeros((len(d), ng))
            E[np.arange(len(d)), gi] = 1.0
            J.append(E)
        return cost, np.hstack(J), r, w

    cost, J, r, w = evaluate(theta)
    lam = 1e-3
    for _ in range(max_iter):
        W = w / s2
        A = (J * W[:, None]).T @ J + np.diag(pw)
        gr = (J * W[:, None]).T @ r - pw * (theta - prior_mu)
        done = True
        while lam < 1e10:
            step = np.linalg.solve(A + lam * np.diag(np.maximum(np.diag(A), 1e-9)), gr)
            res = evaluate(theta + step)
            if res[0] <= cost:
                theta, (cost, J, r, w) = theta + step, res
                lam = max(lam / 10, 1e-9)
                done = np.linalg.norm(step) < 1e-6 * (1 + np.linalg.norm(theta[:3]))
                break
            lam *= 10
        if done:
            break
    W = w / s2
    info = (J * W[:, None]).T @ J + np.diag(pw)
    g = theta[3 + scale :] if off else np.zeros(0)
    g_links = (g if per_link else np.full(L, g[0] if ng else spec.gamma_mean)).copy()
    return _Model(name, theta[:3].copy(), float(theta[3]) if scale else 1.0, g_links, cost, info, r, w)


def _held_out(xyz, d, li, L, s2, name: str, full: _Model, spec: FitSpec) -> tuple[np.ndarray, np.ndarray]:
    """Per fold (contiguous time blocks of the time-ordered ranges): the soft-L1 loss of the held-out ranges
    under the family fitted to the others (started at the full fit), and that fit's position (K, 3)."""
    K = spec.folds
    fold = np.minimum(np.arange(len(d)) * K // len(d), K - 1)
    out, pos = np.zeros(K), np.zeros((K, 3))
    for k in range(K):
        tr, te = fold != k, fold == k
        m = _fit(xyz[tr], d[tr], li[tr], L, s2[tr], name, full.p, spec, max_iter=15, g0=full.g)
        rho = np.linalg.norm(xyz[te] - m.p, axis=1)
        r = d[te] - m.beta * rho - m.g[li[te]]
        out[k] = float(np.sum(_soft_l1(r / np.sqrt(s2[te]), 1.0)[0]))
        pos[k] = m.p
    return out, pos


def _spread(r: np.ndarray) -> float:
    return float(max(1.4826 * np.median(np.abs(r - np.median(r))), 1e-3))


def _deflation(m: _Model, spec: FitSpec, t_ns: np.ndarray | None) -> float:
    """(residual spread / nominal sigma)^2 x kappa of a fit (`FitSpec.deflate`), at least 1."""
    sig = _spread(m.r)
    kappa = noise_inflation(t_ns, m.r / sig, (m.w > 0.5).astype(float)) if t_ns is not None else 1.0
    return max(sig / spec.sigma_range, 1.0) ** 2 * kappa


def _jackknife(pos: np.ndarray) -> np.ndarray:
    """Block-jackknife covariance of the position from the leave-one-block-out fits: what time-correlated range
    errors (multipath, pose error, an antenna pattern met along the path) do to the estimate."""
    K = len(pos)
    dp = pos - pos.mean(axis=0)
    return (K - 1) / K * dp.T @ dp


def choose_model(scores: dict[str, np.ndarray]) -> Evidence:
    """The simplest family (in `FAMILIES` order) whose held-out loss is within one standard error of the best
    family's (the standard error of the per-fold differences)."""
    total = {k: float(np.sum(v)) for k, v in scores.items()}
    best = min(total, key=total.get)
    se = {}
    for k, v in scores.items():
        diff = v - scores[best]
        se[k] = float(np.std(diff, ddof=1) * np.sqrt(len(diff))) if len(diff) > 1 else 0.0
    tie = 1e-6 * max(abs(total[best]), 1.0)
    for k in FAMILIES:
        if k in total and total[k] - total[best] <= se[k] + tie:
            return Evidence(k, total, se)
    return Evidence(best, total, se)


def _linear_start(xyz: np.ndarray, d: np.ndarray) -> np.ndarray:
    A = np.c_[-2.0 * xyz, np.ones(len(d))]
    sol, *_ = np.linalg.lstsq(A, d**2 - np.sum(xyz**2, axis=1), rcond=None)
    return sol[:3]


def _nd(reason: str, n: int, links: np.ndarray, **kw) -> SearchResult:
    L = len(links)
    return SearchResult(
        "not determined",
        reason,
        np.full(3, np.nan),
        np.zeros(L),
        links,
        np.zeros(n, bool),
        float("nan"),
        np.full((3 + L, 3 + L), np.nan),
        **kw,
    )


def _position_cov(m: _Model, spec: FitSpec, reach: float) -> np.ndarray:
    """Covariance of (position, links' offsets): the ranges' information deflated by ``spec.deflate``, the priors,
    and the prior that keeps the anchor within ``reach`` of the tags."""
    n = m.info.shape[0]
    has_beta = m.name == "gamma+beta"
    prior = np.zeros(n)
    prior[3 + has_beta :] = 1.0 / spec.gamma_sigma**2
    if has_beta:
        prior[3] = 1.0 / spec.beta_sigma**2
    f = spec.deflate
    A = (m.info - np.diag(prior * f)) / f + np.diag(prior)
    A[:3, :3] += np.eye(3) / reach**2
    cov = np.linalg.inv(A)
    keep = [0, 1, 2] + list(range(3 + has_beta, n))
    return cov[np.ix_(keep, keep)]


def fit_anchor(
    xyz: np.ndarray,
    d: np.ndarray,
    link: np.ndarray | None = None,
    *,
    t_ns: np.ndarray | None = None,
    pos_cov: np.ndarray | None = None,
    spec: FitSpec | None = None,
) -> SearchResult:
    """The anchor ranged by tag positions ``xyz`` (N, 3) with ranges ``d`` over links ``link``: position, offsets
    (per link, in ``links`` order) and their covariance, the family the evidence chose (``costs["evidence"]``),
    or "not determined" with the reason. ``pos_cov`` (N, 3, 3): the tag positions' covariance."""
    spec = spec or FitSpec()
    xyz = np.asarray(xyz, float).reshape(-1, 3)
    d = np.asarray(d, float).reshape(-1)
    n_all = len(d)
    link = np.zeros(n_all, np.int64) if link is None else np.asarray(link, np.int64).reshape(-1)
    fin = np.isfinite(d) & np.all(np.isfinite(xyz), axis=1) & (d > 0)
    links = np.unique(link[fin])
    if fin.sum() < spec.min_ranges:
        return _nd(f"only {int(fin.sum())} usable ranges (< {spec.min_ranges})", n_all, links)
    sel = np.flatnonzero(fin)
    if t_ns is not None:
        sel = sel[np.argsort(np.asarray(t_ns)[sel], kind="stable")]
    sel = sel[subsample(len(sel), spec.max_ranges)]
    x, dd = xyz[sel], d[sel]
    c, Vt, ext = plane_frame(x)
    if ext[0] < spec.static_extent_m:
        reason = f"static: the tag moved {ext[0]:.2f} m (std) while ranging it (< {spec.static_extent_m} m)"
        return _nd(reason, n_all, links)
    li = np.searchsorted(links, link[sel])
    L = len(links)
    s2 = np.full(len(dd), spec.sigma_range**2)
    p0 = _linear_start(x, dd)
    if pos_cov is not None:  # the pose's uncertainty along the line of sight, at the start
        u = (p0 - x) / np.maximum(np.linalg.norm(p0 - x, axis=1), 1e-9)[:, None]
        s2 = s2 + np.maximum(np.einsum("ni,nij,nj->n", u, np.asarray(pos_cov, float)[sel], u), 0.0)
    n = Vt[2]
    mirror0 = p0 - 2.0 * n * float(n @ (p0 - c))
    fams = [f for f in FAMILIES if f != "link" or L > 1]
    base = min((_fit(x, dd, li, L, s2, "position", s, spec) for s in (p0, mirror0)), key=lambda m: m.cost)
    spec = replace(spec, deflate=_deflation(base, spec, None if t_ns is None else np.asarray(t_ns)[sel]))
    fits = {}
    for f in fams:
        a, b = (_fit(x, dd, li, L, s2, f, s, spec) for s in (p0, mirror0))
        fits[f] = (a, b) if a.cost <= b.cost else (b, a)
    if t_ns is None:
        ev = Evidence("position")
        best, other = fits["position"]
        return _verdict(
            best, other, ev, np.zeros((3, 3)), False, x, dd, sel, n_all, links, Vt, ext, spec, None
        )
    scores = {f: _held_out(x, dd, li, L, s2, f, fits[f][0], spec) for f in fams}
    ev = choose_model({f: v[0] for f, v in scores.items()})
    best, other = fits[ev.chosen]
    held, pos = scores[ev.chosen]
    # the other basin by the same rule: the evidence picks one only when it can
    held_o, pos_o = _held_out(x, dd, li, L, s2, ev.chosen, other, spec)
    basin = choose_model(
        {"position": held, "gamma": held_o}
    )  # the first name stands for the lower-cost basin
    mirror = bool(
        np.linalg.norm(other.p - best.p) > 1e-3 and np.sum(held_o) - np.sum(held) <= basin.cv_se["gamma"]
    )
    if basin.chosen == "gamma" and not mirror:
        best, other, pos = other, best, pos_o
    ev.cv_loss["other_basin"] = float(np.sum(held_o))
    return _verdict(best, other, ev, _jackknife(pos), mirror, x, dd, sel, n_all, links, Vt, ext, spec, t_ns)


def _verdict(best, other, ev, cov_jk, mirror, x, dd, sel, n_all, links, Vt, ext, spec, t_ns) -> SearchResult:
    """The SearchResult of the chosen fit: weak directions from the eigen-decomposition of its covariance (the
    information's plus the block jackknife's), the other basin when the evidence cannot tell them apart."""
    sig = _spread(best.r)
    kappa = spec.deflate / max(sig / spec.sigma_range, 1.0) ** 2
    reach = float(np.max(dd)) + float(np.max(ext))
    cov = _position_cov(best, spec, reach)
    cov[:3, :3] += cov_jk
    lam, V = np.linalg.eigh(cov[:3, :3])
    sd = np.sqrt(np.maximum(lam, 0.0))
    weak = sd > spec.max_sigma
    dcost = (other.cost - best.cost) / spec.deflate
    planar = bool(ext[2] < 0.1 * ext[0])
    inl = np.zeros(n_all, bool)
    inl[sel] = np.abs(best.r) < 4.0 * sig
    axes = [{"direction": np.round(V[:, i], 3).tolist(), "sigma_m": float(sd[i])} for i in range(3)]
    kw = dict(
        planar=planar,
        n_used=len(dd),
        costs={
            "best": best.cost,
            "mirror": other.cost,
            "kappa": kappa,
            "evidence": ev.summary() | {"axes": axes, "mirror_delta_chi2": float(dcost)},
        },
        beta=best.beta,
        residuals=best.r.copy(),
    )
    horiz = [i for i in np.flatnonzero(weak) if abs(V[2, i]) < VERTICAL_COS]
    if horiz:
        i = max(horiz, key=lambda j: sd[j])
        v = V[:, i] * np.sign(V[np.argmax(np.abs(V[:, i])), i])
        reason = (
            f"weak direction ({v[0]:.2f}, {v[1]:.2f}, {v[2]:.2f}): sigma {sd[i]:.2f} m > {spec.max_sigma:g} m "
            "(the motion does not pin the anchor down along it)"
        )
        return _nd(reason, n_all, links, **kw)
    height_ok = not weak.any() and not mirror
    normal = V[:, int(np.argmax(sd))] if weak.any() else Vt[2]
    normal = normal * np.sign(normal[2] if abs(normal[2]) > 1e-9 else 1.0)
    reach_h = 0.5 * float(abs(normal @ (other.p - best.p))) if mirror else 0.0
    sigma_h = float(max(np.sqrt(max(normal @ cov[:3, :3] @ normal, 0.0)), reach_h))
    if mirror:  # the height's sigma reaches the other basin
        cov[:3, :3] += max(sigma_h**2 - float(normal @ cov[:3, :3] @ normal), 0.0) * np.outer(normal, normal)
    return SearchResult(
        "ok",
        "",
        best.p.copy(),
        best.g.copy(),
        links,
        inl,
        sig,
        cov,
        normal_spread=float(ext[2]),
        height_observable=bool(height_ok),
        mirror=mirror,
        mirror_p=other.p.copy() if mirror else None,
        sigma_h=sigma_h,
        normal=normal,
        **kw,
    )
