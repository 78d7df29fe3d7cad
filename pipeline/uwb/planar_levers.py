"""Planar carrier: the tags' antenna lever arms estimated in the motion plane, jointly with anchors and link offsets.

A ground robot turns about the normal n of its motion plane, so an antenna's offset from the carrier's origin is,
in the world, o_k = Rot(n, s psi_k) lam_l + h_l n: psi_k the carrier's heading (its rotation about its own spin
axis, relative to a reference pose), lam_l the antenna's in-plane offset at heading 0, h_l its height above the
origin. Real rigs give lever arms measured in another frame than the one the poses' attitude is in (a mocap or
SLAM body frame set up upside down, rotated, or its quaternion read in another order) and only to a few cm; the
ranges of a turning carrier see lam_l apart from the anchors (the offset turns with psi, the anchor does not),
so the in-plane lever arms are estimated from the ranges. h_l is not separable from the anchors' heights (planar
motion: unobservable anyway) and stays at the given arm's value.

- `carrier_heading`: psi_k from the attitude alone, about the body axis the attitude spins about (the principal
  axis of the rotations relative to the reference pose), whatever the body frame's convention; whether that
  axis maps onto the plane normal (a consistent attitude: its sense gives s) or not (an attitude read in another
  convention: both senses are tried and the ranges pick one).
- `estimate_planar_levers`: robust (Cauchy IRLS) Levenberg-Marquardt over every anchor's (b_a, gamma_{a,l})
  and every link's lam_l from the per-anchor searches' results (gamma per link: the per-link model), closed-form
  Jacobians (tests/test_planar_levers.py checks them by finite differences).
- `PlanarLevers.body_arms`: the body-frame lever arm p_T = R_k^T o_k of each range, for the init windows and the
  refinement's range updates (the model is then d = beta ||p + Rot(n, s psi) lam_l + h_l n - p_a|| + gamma_a +
  delta_{a,l}).
- `choose_lever_arms`: ``uwb.lever_arms = "auto"`` from the recording's poses.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np
from scipy.spatial.transform import Rotation

from uwbcal.pipeline.core.robust import mad_sigma, robust_loss
from uwbcal.pipeline.core.series import noise_inflation
from uwbcal.pipeline.uwb.evidence import BAYES_FACTOR
from uwbcal.pipeline.uwb.window import plane_frame, subsample

PLANAR_RATIO = 0.05  # out-of-plane extent (std) below this x the largest: the carrier moves in a plane
MIN_TURN = 0.2  # circular variance 1 - |mean exp(i psi)| of the heading: the carrier turns enough
CONSISTENT_COS = np.cos(
    np.radians(20.0)
)  # spin axis within 20 deg of the plane normal: a consistent attitude
MAX_PER_ANCHOR = 1500  # ranges per anchor in the joint fit (evenly spread)
MIN_SHARED = 3  # anchors on a link to measure the installation's offset and its scatter
MIN_OFFSET_SPREAD = 0.01  # [m] offsets closer than a centimetre are not told apart by UWB ranging


@dataclass
class CarrierHeading:
    """The carrier's heading about its spin axis: psi = angle of R_ref^T R about ``axis`` (body frame)."""

    axis: np.ndarray  # (3,) body spin axis
    R_ref: np.ndarray  # (3,3) reference attitude (heading 0)
    normal: np.ndarray  # (3,) world plane normal (up when it can be)
    sense: (
        int | None
    )  # +1 / -1: the world rotation sense about ``normal``; None: the attitude is inconsistent
    turn: float  # circular variance of psi over the poses

    def psi(self, R: np.ndarray) -> np.ndarray:
        rv = Rotation.from_matrix(np.einsum("ji,njk->nik", self.R_ref, np.asarray(R).reshape(-1, 3, 3)))
        return rv.as_rotvec() @ self.axis


def carrier_heading(R: np.ndarray, normal: np.ndarray, max_n: int = 4000) -> CarrierHeading:
    """Spin axis, reference and sense of the attitudes ``R`` (N, 3, 3) of a carrier moving in the plane of
    ``normal``. The spin axis is the principal axis of the rotation vectors of R_ref^T R_k (for a planar carrier
    all along one body axis, whatever the body frame)."""
    R = np.asarray(R, float).reshape(-1, 3, 3)
    R_ref = R[0]
    rv = Rotation.from_matrix(np.einsum("ji,njk->nik", R_ref, R[subsample(len(R), max_n)])).as_rotvec()
    _, _, vt = np.linalg.svd(rv, full_matrices=False)
    axis = vt[0] / np.linalg.norm(vt[0])
    w = R_ref @ axis  # the spin axis in the world
    n = np.asarray(normal, float) / np.linalg.norm(normal)
    c = float(w @ n)
    psi = rv @ axis
    turn = float(1.0 - np.abs(np.mean(np.exp(1j * psi))))
    sense = (1 if c > 0 else -1) if abs(c) >= CONSISTENT_COS else None
    return CarrierHeading(axis, R_ref, n, sense, turn)


def _rot_inplane(e1: np.ndarray, e2: np.ndarray, ang: np.ndarray, lam: np.ndarray) -> np.ndarray:
    """World offsets (N, 3) of the in-plane coordinates ``lam`` (N, 2) on the basis (e1, e2) turned by ``ang``."""
    c, s = np.cos(ang), np.sin(ang)
    a1 = c * lam[:, 0] - s * lam[:, 1]
    a2 = s * lam[:, 0] + c * lam[:, 1]
    return a1[:, None] * e1 + a2[:, None] * e2


@dataclass
class PlanarLevers:
    """In-plane lever arms of a planar carrier (world offsets at heading 0) and the heading they turn with."""

    heading: CarrierHeading
    sense: int
    e1: np.ndarray  # (3,) in-plane basis, e1 x e2 = normal
    e2: np.ndarray
    links: np.ndarray  # (K,) link ids (tag * 256 + antenna)
    lam: np.ndarray  # (K, 2) in-plane offsets at heading 0
    height: np.ndarray  # (K,) offset along the normal (the given arm's)
    lam_given: np.ndarray  # (K, 2) the given arms at heading 0 (the reference pose's attitude)
    lam_sigma: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))  # (K, 2) 1-sigma of lam
    info: dict = field(default_factory=dict)
    # the joint fit's anchors: id -> (position (3,), {link id: offset})
    joint: dict = field(default_factory=dict)

    def world_offsets(self, R: np.ndarray, link: np.ndarray) -> np.ndarray:
        """o_k = Rot(n, s psi_k) lam_l + h_l n for every range (attitude R (N,3,3), link ids (N,))."""
        k = np.searchsorted(self.links, np.asarray(link)).clip(0, len(self.links) - 1)
        ang = self.sense * self.heading.psi(R)
        return (
            _rot_inplane(self.e1, self.e2, ang, self.lam[k]) + self.height[k][:, None] * self.heading.normal
        )

    def body_arms(self, R: np.ndarray, link: np.ndarray) -> np.ndarray:
        """p_T = R_k^T o_k: the body-frame lever arm that puts the antenna at the estimated offset."""
        R = np.asarray(R, float).reshape(-1, 3, 3)
        return np.einsum("nji,nj->ni", R, self.world_offsets(R, link))

    def apply(self, windows: dict) -> dict:
        """The init windows with each range's body-frame arm from the estimated in-plane arms."""
        return {
            a: replace(w, p_T=self.body_arms(w.R, w.links())) if len(w) else w for a, w in windows.items()
        }

    def summary(self) -> dict:
        """For init.json and the run summary: per link the estimated and given in-plane arms, the shift."""
        out = {
            "model": "planar",
            "sense": self.sense,
            "attitude_consistent": self.heading.sense is not None,
            "heading_turn": round(self.heading.turn, 3),
            "links": {},
            **self.info,
        }
        for i, lk in enumerate(self.links):
            out["links"][str(int(lk))] = {
                "tag": int(lk) // 256,
                "antenna": int(lk) % 256,
                "inplane_m": [round(float(v), 4) for v in self.lam[i]],
                "given_inplane_m": [round(float(v), 4) for v in self.lam_given[i]],
                "shift_m": round(float(np.linalg.norm(self.lam[i] - self.lam_given[i])), 4),
                "length_m": round(float(np.linalg.norm(self.lam[i])), 4),
                "given_length_m": round(float(np.linalg.norm(self.lam_given[i])), 4),
                "sigma_m": [round(float(v), 4) for v in self.lam_sigma[i]] if len(self.lam_sigma) else [],
            }
        return out

    def message(self) -> str:
        parts = [
            f"tag {int(lk) // 256}: |arm| {np.linalg.norm(self.lam[i]):.3f} m "
            f"(given {np.linalg.norm(self.lam_given[i]):.3f} m, moved {np.linalg.norm(self.lam[i] - self.lam_given[i]):.3f} m)"
            for i, lk in enumerate(self.links)
        ]
        how = (
            "" if self.heading.sense is not None else " (attitude spins about an in-plane axis: heading only)"
        )
        return "planar lever arms estimated" + how + ": " + "; ".join(parts)


# -----------------------------------------------------------------------------------------------------------------
@dataclass
class LeverData:
    """The ranges of every anchor stacked: anchor index, link index, range, carrier pose."""

    a: np.ndarray  # (N,) anchor index
    k: np.ndarray  # (N,) link index into ``links``
    d: np.ndarray
    p: np.ndarray  # (N, 3) carrier position
    psi: np.ndarray  # (N,) heading
    t_ns: np.ndarray | None = None


def lever_residuals(
    data: LeverData,
    B: np.ndarray,
    G: np.ndarray,
    lam: np.ndarray,
    height: np.ndarray,
    sense: int,
    e1: np.ndarray,
    e2: np.ndarray,
    n: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """r = d - ||x - b_a|| - gamma_{a,l} with x = p + Rot(n, s psi) lam_l + h_l n. Returns r and its
    derivatives dr/db_a (N,3) and dr/dlam_l (N,2). ``B`` (A,3) anchors, ``G`` (A,K) link offsets, ``lam`` (K,2)
    in-plane arms on the basis (e1, e2)."""
    ang = sense * data.psi
    x = data.p + _rot_inplane(e1, e2, ang, lam[data.k]) + height[data.k][:, None] * n
    diff = x - B[data.a]
    rho = np.maximum(np.linalg.norm(diff, axis=1), 1e-9)
    u = diff / rho[:, None]
    r = data.d - rho - G[data.a, data.k]
    c, s = np.cos(ang), np.sin(ang)
    dx1 = c[:, None] * e1 + s[:, None] * e2  # dx/dlam_1
    dx2 = -s[:, None] * e1 + c[:, None] * e2
    dlam = -np.stack([np.sum(u * dx1, 1), np.sum(u * dx2, 1)], 1)
    return r, u, dlam


def fit_planar_levers(
    data: LeverData,
    B0: np.ndarray,
    G0: np.ndarray,
    lam0: np.ndarray,
    height: np.ndarray,
    sense: int,
    e1: np.ndarray,
    e2: np.ndarray,
    n: np.ndarray,
    scale: float,
    *,
    estimate_lever: bool = True,
    lam_prior: tuple[np.ndarray, float] | None = None,
    offset_prior: tuple[np.ndarray, float] | None = None,
    max_nfev: int = 100,
) -> dict:
    """Robust (Cauchy, ``scale`` [m]) trust-region least squares over every anchor's in-plane position (its
    height along ``n`` stays at B0's: not separable from the arms' heights, unobservable for a planar carrier),
    its link offsets gamma_{a,l} and, with ``estimate_lever``, every link's in-plane arm lam_l from (B0, G0,
    lam0). ``lam_prior`` (mean (K,2), sigma [m]): a weak prior on the arms (the gauge when the carrier barely
    turns). ``offset_prior`` (mean (K,) per link, weight of a prior residual against the ranges' metres): the
    installation's shared offsets (`shared_offsets`). Analytic Jacobian (`lever_residuals`); trust region with
    Jacobian scaling, because an anchor's distance and offset are strongly correlated (a damped Gauss-Newton
    crawls along that valley). Returns B, G, lam, cost (sum of the Cauchy loss, m^2), r (range residuals), w (IRLS
    weights)."""
    from scipy.optimize import least_squares

    A, K = G0.shape
    basis = np.stack([e1, e2])
    pres, gidx, nb = _offset_layout(data, A, K)
    P = nb + (2 * K if estimate_lever else 0)
    N = len(data.d)
    rows = np.arange(N)
    B0 = np.asarray(B0, float)
    h0 = B0 @ n
    lam0 = np.asarray(lam0, float)
    # a prior residual of the arms' sigma weighs as one range residual of ``scale``
    arms = None if lam_prior is None or not estimate_lever else (lam_prior[0], scale / float(lam_prior[1]))
    cols, mean, wts = _prior_rows(arms, offset_prior, pres, nb)

    def unpack(x):
        B = x[: 2 * A].reshape(A, 2) @ basis + h0[:, None] * n
        G = np.zeros((A, K))
        G[pres] = x[2 * A : nb]
        lam = x[nb:].reshape(K, 2) if estimate_lever else lam0
        return B, G, lam

    def fun(x):
        B, G, lam = unpack(x)
        r = lever_residuals(data, B, G, lam, height, sense, e1, e2, n)[0]
        return np.concatenate([r, wts * (x[cols] - mean)])

    def jac(x):
        B, G, lam = unpack(x)
        _, u, dlam = lever_residuals(data, B, G, lam, height, sense, e1, e2, n)
        J = np.zeros((N + len(cols), P))
        ub = u @ basis.T
        J[rows, 2 * data.a] = ub[:, 0]  # dr/db = u (r = d - |x - b| - gamma)
        J[rows, 2 * data.a + 1] = ub[:, 1]
        J[rows, gidx[data.a, data.k]] = -1.0
        if estimate_lever:
            J[rows, nb + 2 * data.k] = dlam[:, 0]
            J[rows, nb + 2 * data.k + 1] = dlam[:, 1]
        J[N + np.arange(len(cols)), cols] = wts
        return J

    x0 = np.concatenate([(B0 @ basis.T).ravel(), np.asarray(G0, float)[pres]])
    if estimate_lever:
        x0 = np.concatenate([x0, lam0.ravel()])
    # no step-size test (xtol): with Jacobian scaling and the Cauchy loss it stops short of the optimum
    opts = dict(loss="cauchy", f_scale=scale, x_scale="jac", method="trf", xtol=None, max_nfev=max_nfev)
    sol = least_squares(fun, x0, jac=jac, **opts)
    B, G, lam = unpack(sol.x)
    r = lever_residuals(data, B, G, lam, height, sense, e1, e2, n)[0]
    rho, w = robust_loss(r, "cauchy", scale)
    J = jac(sol.x)[:N]
    cost = float(np.sum(rho))
    return dict(B=B, G=G, lam=lam, cost=cost, r=r, w=w, info=(J * w[:, None]).T @ J, nb=nb, nfev=sol.nfev)


def _prior_rows(arm_prior, offset_prior, seen: np.ndarray, nb: int):
    """The priors, each (mean, weight of a prior residual against the ranges' metres) or None, as rows
    ``weight * (x[columns] - mean)``: the arms' (mean (K, 2), after the ``nb`` non-arm parameters) and the
    offsets' (mean per link; ``seen``: the (anchor, link) offsets in the parameter vector, after the anchors'
    in-plane positions)."""
    parts = []
    if arm_prior is not None and arm_prior[1]:
        mu = np.asarray(arm_prior[0], float).ravel()
        parts.append((nb + np.arange(mu.size), mu, float(arm_prior[1])))
    if offset_prior is not None and offset_prior[1]:
        mu = np.broadcast_to(np.asarray(offset_prior[0], float), seen.shape)[seen]
        parts.append((np.arange(2 * seen.shape[0], nb), mu, float(offset_prior[1])))
    if not parts:
        return np.zeros(0, np.int64), np.zeros(0), np.zeros(0)
    cols, mean, w = zip(*parts, strict=True)
    return (
        np.concatenate(cols),
        np.concatenate(mean),
        np.concatenate([np.full(len(c), x) for c, x in zip(cols, w, strict=True)]),
    )


def _offset_layout(data: LeverData, A: int, K: int) -> tuple[np.ndarray, np.ndarray, int]:
    """Which (anchor, link) offsets the data sees, their column in the parameter vector (after the anchors'
    in-plane positions) and the number of non-arm parameters."""
    pres = np.zeros((A, K), bool)
    pres[data.a, data.k] = True
    gidx = -np.ones((A, K), np.int64)
    gidx[pres] = 2 * A + np.arange(int(pres.sum()))
    return pres, gidx, 2 * A + int(pres.sum())


def estimate_planar_levers(
    R: np.ndarray,
    p: np.ndarray,
    d: np.ndarray,
    anchor: np.ndarray,
    link: np.ndarray,
    given_arms: np.ndarray,
    starts: dict,
    *,
    t_ns: np.ndarray | None = None,
    sigma_range: float = 0.1,
    prior_sigma_m: float = 0.5,
) -> PlanarLevers | None:
    """The in-plane lever arms of a planar carrier from all anchors' ranges at once.

    ``R`` (N,3,3), ``p`` (N,3) carrier poses at the ranges ``d`` (N,) of anchors ``anchor`` (N,) over links
    ``link`` (N,), ``given_arms`` (N,3) the body-frame lever arm each range was given; ``starts``: anchor ->
    (position (3,), {link id: offset}) from the per-anchor searches (anchors without a start are left out).
    Returns None when the carrier does not move in a plane or does not turn enough to see the arms."""
    R = np.asarray(R, float).reshape(-1, 3, 3)
    p = np.asarray(p, float).reshape(-1, 3)
    _, Vt, head = _planar_carrier(R, p)
    if head is None:
        return None
    n, e1 = Vt[2], Vt[0]
    e2 = np.cross(n, e1)
    keep_a = [a for a in starts if np.all(np.isfinite(starts[a][0]))]
    if not keep_a:
        return None
    links = np.unique(link)
    K = len(links)
    # the given arms: world offsets at the reference pose, in-plane coordinates and height
    kk = np.searchsorted(links, link)
    first = np.array([np.flatnonzero(kk == i)[0] for i in range(K)])
    o_ref = given_arms[first] @ head.R_ref.T
    lam_given = np.stack([o_ref @ e1, o_ref @ e2], 1)
    height = o_ref @ n
    data = _joint_data(keep_a, anchor, d, kk, p, head, R, t_ns)
    B0, G0 = _joint_start(starts, keep_a, links)
    fixed = fit_planar_levers(data, B0, G0, lam_given, height, 1, e1, e2, n, 0.5, estimate_lever=False)
    scale = max(3.0 * mad_sigma(fixed["r"]), 0.6 * sigma_range, 0.03)
    fixed = fit_planar_levers(
        data, fixed["B"], fixed["G"], lam_given, height, 1, e1, e2, n, scale, estimate_lever=False
    )
    B1, G1, prior = fixed["B"], fixed["G"], (lam_given, prior_sigma_m)
    fits = []
    for s in [head.sense] if head.sense is not None else [1, -1]:
        f = fit_planar_levers(data, B1, G1, lam_given, height, s, e1, e2, n, scale, lam_prior=prior)
        fits.append((f["cost"], s, f))
    _, sense, best = min(fits, key=lambda t: t[0])
    sig = mad_sigma(best["r"])
    kappa, lam_sigma = _arm_sigma(data, best, sig, K)
    whit = 1.0 / max(sig, 1e-6) ** 2
    dchi2 = float((fixed["cost"] - best["cost"]) * whit / kappa)
    info = {
        "residual_sigma_m": round(sig, 4),
        "residual_sigma_given_m": round(mad_sigma(fixed["r"]), 4),
        "delta_chi2": round(dchi2, 1),
        "log_bayes_factor": round(_log_bayes(best, dchi2, whit / kappa, lam_given, prior_sigma_m), 1),
        "noise_inflation": round(float(kappa), 2),
        "n_ranges": int(len(data.d)),
        "anchors": [str(a) for a in keep_a],
    }
    if head.sense is None and len(fits) == 2:
        info["other_sense_delta_chi2"] = round(
            float((max(f[0] for f in fits) - best["cost"]) * whit / kappa), 1
        )
    joint = {
        a: (best["B"][i].copy(), {int(lk): float(g) for lk, g in zip(links, best["G"][i], strict=True)})
        for i, a in enumerate(keep_a)
    }
    return PlanarLevers(head, sense, e1, e2, links, best["lam"], height, lam_given, lam_sigma, info, joint)


def _joint_data(keep_a, anchor, d, kk, p, head: CarrierHeading, R, t_ns) -> LeverData:
    """Every kept anchor's finite ranges (evenly subsampled to `MAX_PER_ANCHOR`) as one `LeverData`."""
    sel, aidx = [], []
    for i, a in enumerate(keep_a):
        ii = np.flatnonzero((anchor == a) & np.isfinite(d))
        sel.append(ii[subsample(len(ii), MAX_PER_ANCHOR)])
        aidx.append(np.full(len(sel[-1]), i, np.int64))
    idx, aidx = np.concatenate(sel), np.concatenate(aidx)
    return LeverData(aidx, kk[idx], d[idx], p[idx], head.psi(R[idx]), None if t_ns is None else t_ns[idx])


def _stacked(windows: dict) -> dict:
    """The ranges of the non-empty ``windows`` (anchor -> InitWindow) stacked as `estimate_planar_levers` takes
    them: poses, ranges, anchor ids, link ids, lever arms and stamps (None unless every window has them)."""
    ws = {a: w for a, w in windows.items() if len(w)}
    cat = lambda f: np.concatenate([f(w) for w in ws.values()])  # noqa: E731
    stamped = all(w.t_ns is not None for w in ws.values())
    return dict(
        R=cat(lambda w: w.R),
        p=cat(lambda w: w.p),
        d=cat(lambda w: w.d),
        anchor=np.concatenate([np.full(len(w), a, object) for a, w in ws.items()]),
        link=cat(lambda w: w.links()),
        given_arms=cat(lambda w: w.p_T),
        t_ns=cat(lambda w: w.t_ns) if stamped else None,
    )


def _joint_start(starts: dict, keep_a: list, links: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Anchor positions (A,3) and link offsets (A,K) to start from; a link an anchor's start lacks takes the mean
    of its other links."""
    B0 = np.stack([np.asarray(starts[a][0], float) for a in keep_a])
    G0 = np.zeros((len(keep_a), len(links)))
    for i, a in enumerate(keep_a):
        offs = starts[a][1]
        mean = float(np.mean(list(offs.values()))) if offs else 0.0
        G0[i] = [offs.get(int(lk), mean) for lk in links]
    return B0, G0


def _arm_sigma(data: LeverData, best: dict, sig: float, K: int) -> tuple[float, np.ndarray]:
    """The noise inflation of the residuals' time correlation and the arms' (K,2) standard deviations."""
    kappa = 1.0
    if data.t_ns is not None:
        order = np.argsort(data.t_ns, kind="stable")
        kappa = noise_inflation(data.t_ns[order], (best["r"] / max(sig, 1e-6))[order], best["w"][order])
    try:
        cov = np.linalg.inv(best["info"] / max(sig, 1e-6) ** 2 / kappa)
        return kappa, np.sqrt(np.maximum(np.diag(cov)[best["nb"] :], 0.0)).reshape(K, 2)
    except np.linalg.LinAlgError:
        return kappa, np.full((K, 2), np.inf)


def _log_bayes(fit: dict, dchi2: float, whit: float, lam_given: np.ndarray, prior_sigma: float) -> float:
    """Log evidence of the estimated arms over the given ones (Laplace; prior N(given, ``prior_sigma``^2) per
    in-plane coordinate): half the deflated chi2 drop, less the prior's penalty and the Occam factor of the arms'
    information (the anchors' and offsets' marginalised)."""
    nb, I = fit["nb"], fit["info"] * whit
    try:
        S = I[nb:, nb:] - I[nb:, :nb] @ np.linalg.solve(I[:nb, :nb], I[:nb, nb:])
    except np.linalg.LinAlgError:
        return float("-inf")
    occam = np.linalg.slogdet(np.eye(len(S)) + prior_sigma**2 * S)[1]
    penalty = float(np.sum((fit["lam"] - lam_given) ** 2)) / prior_sigma**2
    return 0.5 * dchi2 - 0.5 * penalty - 0.5 * float(occam)


def choose_lever_arms(R: np.ndarray, p: np.ndarray, n_antennas: int = 2) -> tuple[str, str]:
    """``uwb.lever_arms = "auto"``: planar when the carrier carries several antennas (``n_antennas``), moves in a
    plane and turns (its arms are then seen apart from the anchors), else given. Returns (choice, why)."""
    if n_antennas < 2:
        return "given", "one antenna: its arm's error is at most its length, the calibration's arm is kept"
    p = np.asarray(p, float).reshape(-1, 3)
    if len(p) < 10:
        return "given", "too few poses"
    why, _, head = _planar_carrier(R, p)
    return "given" if head is None else "planar", why


def _planar_carrier(R: np.ndarray, p: np.ndarray) -> tuple[str, np.ndarray, CarrierHeading | None]:
    """Whether the carrier's arms are seen apart from the anchors, and why: the principal axes of its positions
    ``p`` (N, 3) (rows, the last the plane's normal) and its heading, None unless it moves in a plane and turns."""
    _, Vt, ext = plane_frame(p[subsample(len(p), 20000)])
    if ext[0] <= 0 or ext[2] > PLANAR_RATIO * ext[0]:
        return f"the carrier does not move in a plane (extents {ext.round(2).tolist()} m)", Vt, None
    head = carrier_heading(R, Vt[2])
    turn = f"heading circular variance {head.turn:.2f}"
    if head.turn < MIN_TURN:
        return f"planar carrier that barely turns ({turn} < {MIN_TURN})", Vt, None
    return f"planar carrier that turns ({turn}): in-plane arms estimated", Vt, head


def planar_windows(
    windows: dict, search, sigma_range: float, max_search: int = 3000
) -> tuple[dict, PlanarLevers | None]:
    """The init windows with the planar carrier's estimated lever arms (`estimate_planar_levers`, started from
    ``search`` (InitWindow -> AnchorFit) on every anchor's window, evenly subsampled to ``max_search``
    ranges), and the model; the windows unchanged and None when the carrier is not planar, does not turn or no
    anchor could be searched."""

    starts = {}
    for a, w in windows.items():
        if len(w) == 0:
            continue
        sr = search(w.subset(subsample(len(w), max_search)))
        if sr.ok:
            starts[a] = (sr.p, {int(lk): float(g) for lk, g in zip(sr.links, sr.gamma, strict=True)})
    if not starts:
        return windows, None
    pl = estimate_planar_levers(**_stacked(windows), starts=starts, sigma_range=sigma_range)
    if pl is None or pl.info["log_bayes_factor"] <= np.log(
        BAYES_FACTOR
    ):  # the arms enter by the evidence rule
        return windows, None
    return pl.apply(windows), pl


def shared_offsets(G: np.ndarray, seen: np.ndarray) -> tuple[np.ndarray, float] | None:
    """The installation's offsets: the links of one installation share their hardware (each tag's antenna delay
    enters every anchor's ranges), so each link's offsets over the anchors scatter about a common value.
    Returns per link the median over the anchors of the free fit's offsets ``G`` (A, K) (``seen``: which the
    data hold) and their robust spread about it (at least `MIN_OFFSET_SPREAD`), or None with fewer than
    `MIN_SHARED` anchors on a link (no scatter to measure)."""
    if np.any(seen.sum(axis=0) < MIN_SHARED):
        return None
    Gm = np.where(seen, G, np.nan)
    mu = np.nanmedian(Gm, axis=0)
    dev = (Gm - mu)[seen]
    return mu, max(mad_sigma(dev), MIN_OFFSET_SPREAD)


def refit_searches(levers: PlanarLevers, windows: dict, searches: dict, sigma_range: float) -> dict:
    """The per-anchor searches on the corrected windows, their in-plane positions and link offsets re-fitted
    together with the arms held (`fit_planar_levers`, heights kept: they carry the searches' verdicts and
    sigmas). The search's own damped refinement stops short along the distance/offset valley of an anchor
    ranged from one side; the trust-region fit converges (same minimum from any start). Along that valley the
    data hardly fix the offset: the fit is repeated from its optimum under the installation's offsets
    (`shared_offsets`, an empirical-Bayes prior weighted against ranges of the robust residual sigma deflated by
    the arms' fit's noise inflation; its Cauchy tail leaves an offset many spreads from the installation's alone)."""
    import copy

    ok = {a: s for a, s in searches.items() if s is not None and s.ok and len(windows[a])}
    if not ok:
        return searches
    keep_a, links = list(ok), levers.links
    s = _stacked({a: windows[a] for a in keep_a})
    kk = np.searchsorted(links, s["link"]).clip(0, len(links) - 1)
    data = _joint_data(keep_a, s["anchor"], s["d"], kk, s["p"], levers.heading, s["R"], None)
    B0 = np.stack([ok[a].p for a in keep_a])
    G0 = np.stack([[ok[a].gamma_of(np.array([lk]))[0] for lk in links] for a in keep_a])
    args = (levers.height, levers.sense, levers.e1, levers.e2, levers.heading.normal)
    s0 = mad_sigma(lever_residuals(data, B0, G0, levers.lam, *args)[0])
    scale = max(3.0 * s0, 0.6 * sigma_range, 0.03)
    f = fit_planar_levers(data, B0, G0, levers.lam, *args, scale, estimate_lever=False)
    shared = shared_offsets(f["G"], _offset_layout(data, len(keep_a), len(links))[0])
    if shared is not None:  # the fit again under the installation's offsets, from its optimum
        s_range = np.sqrt(float(levers.info.get("noise_inflation", 1.0))) * max(s0, 1e-3)
        prior = (shared[0], s_range / shared[1])
        f = fit_planar_levers(
            data, f["B"], f["G"], levers.lam, *args, scale, estimate_lever=False, offset_prior=prior
        )
    out = dict(searches)
    for i, a in enumerate(keep_a):
        s = copy.copy(ok[a])
        s.p = f["B"][i].copy()
        s.gamma = np.array([f["G"][i, int(np.searchsorted(links, lk))] for lk in s.links])
        out[a] = s
    return out
