"""Fisher information of the anchor parameters and the observability verdict (paper Sec. III-C).

The ranges of a window are modelled as d ~ N(h(x_U), Sigma(x_U)), Sigma = diag(Q_d + H_Ik P_k H_Ik^T): a
general Gaussian whose covariance depends on the parameters. Its FIM (Kay 1993, Sec. 3.9) is

    F_ij = dh/dx_i^T Sigma^-1 dh/dx_j + 1/2 tr(Sigma^-1 dSigma/dx_i Sigma^-1 dSigma/dx_j).

(The paper prints dh in the trace term; that is a typo, the trace term involves dSigma.) With a diagonal Sigma the
trace is sum_k dSigma_k/dx_i dSigma_k/dx_j / (2 Sigma_k^2).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from uwbcal.pipeline.uwb.model import jacobians, range_variance, tag_positions
from uwbcal.pipeline.uwb.window import plane_frame

PARAM_NAMES = ("x", "y", "z", "beta", "gamma")


def fisher_information(
    R: np.ndarray,
    p: np.ndarray,
    p_T: np.ndarray,
    P_pose: np.ndarray,
    x_U: np.ndarray,
    q_d: float,
    params: Sequence[int] = (0, 1, 2, 4),
    weights: np.ndarray | None = None,
) -> np.ndarray:
    """FIM over the parameters ``params`` (indices into [x, y, z, beta, gamma]; default beta fixed = init).

    ``weights`` (N,) in [0, 1] drops or down-weights ranges (e.g. outliers of a robust fit).
    """
    idx = list(params)
    J = jacobians(R, p, p_T, x_U).H_U[:, idx]
    S, dS = range_variance(R, p, p_T, x_U, P_pose, q_d)
    dS = dS[:, idx]
    w = np.ones_like(S) if weights is None else np.asarray(weights, float)
    F = (J * (w / S)[:, None]).T @ J + 0.5 * (dS * (w / S**2)[:, None]).T @ dS
    return 0.5 * (F + F.T)


@dataclass
class FimReport:
    F: np.ndarray
    params: tuple[str, ...]
    eigvals: np.ndarray
    logdet: float
    cond: float
    rcond: float  # smallest / largest eigenvalue
    weak_axis: str  # parameter(s) dominating the weakest direction, e.g. "z" or "z/gamma"
    extents: np.ndarray  # principal extents (std dev) of the tag trajectory, descending
    plane_normal: np.ndarray  # up when it can be (`plane_frame`)
    status: str = "ok"  # "ok" | "warning" | "refused"
    warnings: list[str] = field(default_factory=list)

    def summary(self) -> dict:
        return {
            "logdet": self.logdet,
            "cond": self.cond,
            "rcond": self.rcond,
            "weak_axis": self.weak_axis,
            "eigvals": self.eigvals.tolist(),
            "extents_m": self.extents.tolist(),
            "status": self.status,
            "warnings": list(self.warnings),
        }


def _axis_name(v: np.ndarray, names: Sequence[str]) -> str:
    a = np.abs(v)
    order = np.argsort(a)[::-1]
    picked = [names[order[0]]]
    if len(order) > 1 and a[order[1]] > 0.5 * a[order[0]]:
        picked.append(names[order[1]])
    return "/".join(picked)


def _world_axis(n: np.ndarray) -> str:
    return "xyz"[int(np.argmax(np.abs(n)))]


def fim_report(F: np.ndarray, params: Sequence[int], tag_xyz: np.ndarray) -> FimReport:
    names = tuple(PARAM_NAMES[i] for i in params)
    # Scale-free spectrum: the FIM mixes no units here (all parameters in metres except beta).
    w, V = np.linalg.eigh(F)
    w = np.maximum(w, 0.0)
    wmax = float(w[-1]) if w[-1] > 0 else 1.0
    rcond = float(w[0] / wmax)
    logdet = float(np.sum(np.log(np.maximum(w, 1e-300))))
    _, Vt, extents = plane_frame(tag_xyz)
    return FimReport(
        F=F,
        params=names,
        eigvals=w,
        logdet=logdet,
        cond=float(np.inf if w[0] <= 0 else wmax / w[0]),
        rcond=rcond,
        weak_axis=_axis_name(V[:, 0], names),
        extents=extents,
        plane_normal=Vt[-1],
    )


def assess_observability(
    R: np.ndarray,
    p: np.ndarray,
    p_T: np.ndarray,
    P_pose: np.ndarray,
    x_U: np.ndarray,
    q_d: float,
    *,
    params: Sequence[int] = (0, 1, 2, 4),
    weights: np.ndarray | None = None,
    static_extent_m: float = 0.3,
    planar_ratio: float = 0.05,
    rcond_min: float = 1e-9,
    force: bool = False,
    label: str = "anchor",
) -> FimReport:
    """FIM figures and the verdict: warn on a static or planar window, refuse a rank-deficient one.

    Static: largest principal extent (std dev) of the tag positions < ``static_extent_m``. Planar: smallest extent
    < ``planar_ratio`` x the largest; the weak axis is the plane normal (mirror ambiguity of the anchor across the
    plane). Refused: rcond(F) < ``rcond_min``, status "refused" unless ``force`` (then status is "warning" and
    the figures are kept).
    """
    tag_xyz = tag_positions(R, p, p_T)
    F = fisher_information(R, p, p_T, P_pose, x_U, q_d, params, weights)
    rep = fim_report(F, params, tag_xyz)
    ext = rep.extents
    if ext[0] < static_extent_m:
        rep.warnings.append(
            f"{label}: static window (trajectory spread {ext[0]:.3f} m < {static_extent_m} m); anchor not determined"
        )
    elif ext[-1] < planar_ratio * ext[0]:
        axis = _world_axis(rep.plane_normal)
        rep.warnings.append(
            f"{label}: planar window (extents {ext[0]:.2f}/{ext[1]:.2f}/{ext[2]:.3f} m); weak axis {axis}: "
            f"the anchor is ambiguous across the plane (FIM logdet {rep.logdet:.1f}, cond {rep.cond:.3g})"
        )
    if rep.rcond < rcond_min:
        msg = (
            f"{label}: Fisher information rank-deficient (rcond {rep.rcond:.2e} < {rcond_min:g}, logdet "
            f"{rep.logdet:.1f}); weak direction {rep.weak_axis}"
        )
        if not force:
            rep.status = "refused"
            rep.warnings.append(msg + "; initialisation refused (force=True to override)")
            return rep
        rep.warnings.append(msg + "; forced")
    if rep.warnings:
        rep.status = "warning"
    return rep
