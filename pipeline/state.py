"""Error-state container and the one EKF update (OpenVINS StateHelper style).

The state is an ordered list of named variables; each knows its block in the covariance. New variables are
added either independent (`add`), as functions of existing ones (`augment`, stochastic clones) or from
measurements (`initialize`, the OpenVINS "state variable initialisation" with a QR split). `ekf_update` is
the only place that changes estimates and covariance from a measurement; Schmidt behaviour is a per-update
choice of variables whose gain is zeroed, plus the state's own *considered* variables (``State.considered``, e.g.
past poses kept so that a later initialisation knows their cross-covariances), which no update ever changes.
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field

import numpy as np
from scipy.linalg import qr
from scipy.stats import chi2

from .core.geometry import exp_so3


@dataclass
class Vec:
    """A vector-space variable (anchors, biases, calibration)."""

    x: np.ndarray

    def __post_init__(self) -> None:
        self.x = np.asarray(self.x, dtype=float).copy()

    @property
    def dim(self) -> int:
        return self.x.shape[0]

    def boxplus(self, dx: np.ndarray) -> Vec:
        return Vec(self.x + dx)


@dataclass
class Pose:
    """world_from_body pose; error [dtheta, dp] with R = R_hat Exp(dtheta), p = p_hat + dp."""

    R: np.ndarray
    p: np.ndarray

    def __post_init__(self) -> None:
        self.R = np.asarray(self.R, dtype=float).copy()
        self.p = np.asarray(self.p, dtype=float).copy()

    dim = 6

    def boxplus(self, dx: np.ndarray) -> Pose:
        return Pose(self.R @ exp_so3(dx[0:3]), self.p + dx[3:6])


@dataclass
class ImuState:
    """IMU navigation state; error ordering [dtheta, dp, dv, dbg, dba]."""

    R: np.ndarray
    p: np.ndarray
    v: np.ndarray
    bg: np.ndarray = field(default_factory=lambda: np.zeros(3))
    ba: np.ndarray = field(default_factory=lambda: np.zeros(3))

    def __post_init__(self) -> None:
        for name in ("R", "p", "v", "bg", "ba"):
            setattr(self, name, np.asarray(getattr(self, name), dtype=float).copy())

    dim = 15

    def boxplus(self, dx: np.ndarray) -> ImuState:
        return ImuState(
            self.R @ exp_so3(dx[0:3]),
            self.p + dx[3:6],
            self.v + dx[6:9],
            self.bg + dx[9:12],
            self.ba + dx[12:15],
        )

    @property
    def pose(self) -> Pose:
        return Pose(self.R, self.p)


Value = Vec | Pose | ImuState


@dataclass
class UpdateResult:
    accepted: bool
    nis: float
    dof: int
    gate: float | None = None


class State:
    """Named error-state variables with one joint covariance ``P``."""

    def __init__(self, use_fej: bool = True) -> None:
        self.use_fej = use_fej
        self.P = np.zeros((0, 0))
        self._names: list[str] = []
        self._values: dict[str, Value] = {}
        self._fej: dict[str, Value] = {}
        self._slices: dict[str, slice] = {}
        # Schmidt (considered) variables: zero gain in every update, cross-covariances tracked
        self.considered: set[str] = set()

    # -- bookkeeping -------------------------------------------------------------------------------------
    @property
    def names(self) -> list[str]:
        return list(self._names)

    @property
    def size(self) -> int:
        return self.P.shape[0]

    def __contains__(self, name: str) -> bool:
        return name in self._values

    def slice(self, name: str) -> slice:
        return self._slices[name]

    def dim(self, name: str) -> int:
        return self._values[name].dim

    def value(self, name: str) -> Value:
        return self._values[name]

    def set_value(self, name: str, value: Value) -> None:
        """Replace an estimate without touching the covariance (e.g. IMU propagation)."""
        self._values[name] = value

    def fej(self, name: str) -> Value:
        """Linearisation point: the first estimate when FEJ is on, else the current estimate."""
        return self._fej[name] if self.use_fej else self._values[name]

    def set_fej(self, name: str, value: Value) -> None:
        self._fej[name] = dataclasses.replace(value)  # __post_init__ copies the arrays

    def cov(self, name: str, other: str | None = None) -> np.ndarray:
        return self.P[self._slices[name], self._slices[other or name]]

    def _reindex(self) -> None:
        start = 0
        self._slices = {}
        for n in self._names:
            d = self._values[n].dim
            self._slices[n] = slice(start, start + d)
            start += d

    def _index(self, names: Iterable[str]) -> np.ndarray:
        return np.concatenate([np.arange(self._slices[n].start, self._slices[n].stop) for n in names])

    # -- adding and removing variables ---------------------------------------------------------------------
    def add(self, name: str, value: Value, P_block: np.ndarray) -> None:
        """Add an independent variable with covariance ``P_block``."""
        self._append(name, value, np.asarray(P_block, float), np.zeros((value.dim, self.size)))

    def _append(self, name: str, value: Value, P_new: np.ndarray, cross: np.ndarray) -> None:
        if name in self._values:
            raise KeyError(f"state variable {name!r} exists already")
        n = self.size
        d = value.dim
        P = np.zeros((n + d, n + d))
        P[:n, :n] = self.P
        P[n:, :n] = cross
        P[:n, n:] = cross.T
        P[n:, n:] = 0.5 * (P_new + P_new.T)
        self.P = P
        self._names.append(name)
        self._values[name] = value
        self._fej[name] = dataclasses.replace(value)  # __post_init__ copies the arrays
        self._reindex()

    def augment(
        self,
        name: str,
        value: Value,
        J: Mapping[str, np.ndarray],
        Q: np.ndarray | None = None,
        *,
        considered: bool = False,
    ) -> None:
        """Add ``name`` = f(existing) (+ noise Q) with Jacobians ``J[var]``: P_new = J P J^T + Q, cross = J P.
        ``considered``: a Schmidt variable of the state (see ``State.considered``)."""
        JP = np.zeros((value.dim, self.size))
        for var, Jb in J.items():
            JP += Jb @ self.P[self._slices[var], :]
        P_new = np.zeros((value.dim, value.dim))
        for var, Jb in J.items():
            P_new += JP[:, self._slices[var]] @ Jb.T
        if Q is not None:
            P_new = P_new + Q
        self._append(name, value, P_new, JP)
        if considered:
            self.considered.add(name)

    def initialize(
        self,
        name: str,
        value: Value,
        H_old: Mapping[str, np.ndarray],
        H_new: np.ndarray,
        r: np.ndarray,
        R: np.ndarray,
        *,
        update_rest: bool = True,
    ) -> UpdateResult | None:
        """OpenVINS-style initialisation of a new variable from linearised measurements.

        ``r = H_old x_old + H_new x_new + n`` (n ~ N(0, R), R full or diagonal). A QR decomposition of
        ``H_new`` splits the system into an invertible part, which defines the new variable's covariance and
        its cross-covariance with the existing state, and the rest, which updates the enlarged state (unless
        ``update_rest`` is False). ``value`` is the estimate of the new variable, assumed already optimal.
        """
        r = np.asarray(r, float).reshape(-1)
        m, d = H_new.shape
        if m < d:
            raise ValueError(f"initialize({name}): {m} measurements cannot determine {d} states")
        R = np.asarray(R, float)
        if R.ndim == 1:
            R = np.diag(R)
        # Whiten so that the QR rotation keeps the noise white.
        L = np.linalg.cholesky(R)
        Linv = np.linalg.inv(L)
        Hn = Linv @ H_new
        rw = Linv @ r
        Ho = {k: Linv @ v for k, v in H_old.items()}
        Qm, _ = qr(Hn, mode="full")
        Hn = Qm.T @ Hn
        rw = Qm.T @ rw
        Ho = {k: Qm.T @ v for k, v in Ho.items()}
        H1 = Hn[:d]
        H1inv = np.linalg.inv(H1)
        # new = H1^-1 (r1 - Ho1 x_old - n1): covariance and cross-covariance with the old state
        HoP = np.zeros((d, self.size))
        for k, v in Ho.items():
            HoP += v[:d] @ self.P[self._slices[k], :]
        S1 = np.eye(d)
        for k, v in Ho.items():
            S1 = S1 + HoP[:, self._slices[k]] @ v[:d].T
        P_new = H1inv @ S1 @ H1inv.T
        cross = -H1inv @ HoP
        self._append(name, value, P_new, cross)
        if update_rest and m > d:
            H_rest = {k: v[d:] for k, v in Ho.items()}
            H_rest[name] = Hn[d:]
            return ekf_update(self, H_rest, rw[d:], np.eye(m - d))
        return None

    def remove(self, name: str) -> None:
        """Marginalise a variable: drop its rows and columns."""
        sl = self._slices[name]
        keep = np.r_[0 : sl.start, sl.stop : self.size]
        self.P = self.P[np.ix_(keep, keep)]
        self.considered.discard(name)
        self._names.remove(name)
        del self._values[name]
        del self._fej[name]
        self._reindex()

    def boxplus(self, dx: np.ndarray, names: Iterable[str] | None = None) -> None:
        for n in names if names is not None else self._names:
            sl = self._slices[n]
            if dx[sl].any():  # Schmidt (considered) variables get exactly zero corrections
                self._values[n] = self._values[n].boxplus(dx[sl])


PROBE_PREFIX = "probe/"


def add_probe(state: State, t_ns: int, pose_var: str = "imu") -> str:
    """Keep the pose of ``pose_var`` at ``t_ns`` as a considered (Schmidt) variable ``probe/<t_ns>``: its value
    stays the filtered estimate of that time, its cross-covariances with the state stay exact (the paper's window
    states X_I, for the covariance initialisation of the anchors). Returns the name."""
    name = f"{PROBE_PREFIX}{int(t_ns)}"
    if name not in state:
        x = state.value(pose_var)
        J = np.zeros((6, state.dim(pose_var)))
        J[:, :6] = np.eye(6)
        state.augment(name, Pose(x.R, x.p), {pose_var: J}, considered=True)
    return name


def probes(state: State) -> list[tuple[int, str]]:
    """(t_ns, name) of the state's pose probes in time order."""
    return sorted((int(n[len(PROBE_PREFIX) :]), n) for n in state.names if n.startswith(PROBE_PREFIX))


def remove_probes(state: State) -> None:
    for _, n in probes(state):
        state.remove(n)


@functools.lru_cache(maxsize=4096)
def _chi2_gate(quantile: float, dof: int) -> float:
    return float(chi2.ppf(quantile, dof))


def ekf_update(
    state: State,
    H: Mapping[str, np.ndarray],
    r: np.ndarray,
    R: np.ndarray | float,
    *,
    schmidt: Iterable[str] = (),
    chi2_gate: float | None = None,
    robust: tuple[str, float] | None = None,
    robust_R: float | None = None,
) -> UpdateResult:
    """The one EKF update: ``r = sum_v H[v] dx_v + n``, n ~ N(0, R).

    ``schmidt`` names variables that are *considered* but not estimated (Schmidt-Kalman filter; the state's own
    ``considered`` variables are always among them): their
    gain rows are zero, so their estimates and their own covariance block stay unchanged, while the
    cross-covariances with the estimated variables are updated. The covariance update is the Joseph form,
    which is exact for any gain, so the zeroed gain needs no special formula. ``chi2_gate`` is a quantile
    (e.g. 0.95): the update is rejected when the NIS exceeds it. ``robust = (loss, c)`` with loss ``huber`` or
    ``cauchy`` (one-row updates): instead of a hard gate the innovation covariance is inflated to S / w with the
    IRLS weight w of the whitened innovation e = r / sqrt(S) (scale ``c`` in sigmas), i.e. R grows by
    (1/w - 1) S: a large residual still informs, with a bounded (Huber) or vanishing (Cauchy) influence.
    ``robust_R`` replaces R in the variance that whitens e (e.g. the per-sample noise when R is inflated for
    time-correlated errors, so that the loss keeps its scale in metres).
    """
    r = np.asarray(r, float).reshape(-1)
    m = r.shape[0]
    R = np.atleast_2d(np.asarray(R, float))
    if R.shape == (1, 1) and m > 1:
        R = np.eye(m) * R[0, 0]
    elif R.ndim == 2 and R.shape[0] == 1 and R.shape[1] == m:
        R = np.diag(R[0])
    n = state.size
    PHt = np.zeros((n, m))
    for var, Hb in H.items():
        PHt += state.P[:, state.slice(var)] @ Hb.T
    S = np.zeros((m, m))
    for var, Hb in H.items():
        S += Hb @ PHt[state.slice(var), :]
    S = 0.5 * (S + S.T) + R
    try:
        cho = np.linalg.cholesky(S)
    except np.linalg.LinAlgError as exc:
        raise FloatingPointError(f"innovation covariance not positive definite ({m} rows)") from exc
    y = np.linalg.solve(cho, r)
    nis = float(y @ y)
    gate = _chi2_gate(chi2_gate, m) if chi2_gate is not None else None
    if gate is not None and nis > gate:
        return UpdateResult(False, nis, m, gate)
    if robust is not None and m == 1:
        kind, c = robust
        e = float(np.sqrt(nis))
        if robust_R is not None:
            s_w = float(S[0, 0]) - float(R[0, 0]) + float(robust_R)
            e = abs(float(r[0])) / np.sqrt(max(s_w, 1e-300))
        if kind == "huber":
            wt = 1.0 if e <= c else c / e
        elif kind == "cauchy":
            wt = 1.0 / (1.0 + (e / c) ** 2)
        else:
            raise ValueError(f"unknown robust update loss {kind!r} (huber or cauchy)")
        if wt < 1.0:
            S = S / wt
            cho = cho / np.sqrt(wt)
    schmidt = list(schmidt)
    schmidt += [v for v in getattr(state, "considered", ()) if v not in schmidt]
    # Joseph form: P+ = (I - K H) P (I - K H)^T + K R K^T, written with PHt to avoid forming I - KH.
    if not schmidt:
        K = np.linalg.solve(cho.T, np.linalg.solve(cho, PHt.T)).T  # K = P H^T S^-1
        KHP = K @ PHt.T
        P = state.P - KHP - KHP.T + K @ S @ K.T
        state.P = 0.5 * (P + P.T)
        state.boxplus(K @ r)
        return UpdateResult(True, nis, m, gate)
    # Schmidt: only the estimated rows e of K are non-zero, so only rows and columns e of P change
    # (P_ee - (KHP)_ee - (KHP)_ee^T + K_e S K_e^T, P_ec - (KHP)_ec); the considered block stays as it is.
    mask = np.ones(n, bool)
    mask[state._index(schmidt)] = False
    e = np.flatnonzero(mask)
    K_e = np.linalg.solve(cho.T, np.linalg.solve(cho, PHt[e].T)).T
    KHP = K_e @ PHt.T  # (n_e, n)
    P = state.P
    P[e, :] -= KHP
    P[:, e] -= KHP.T
    P[np.ix_(e, e)] += K_e @ S @ K_e.T
    Pe = P[e, :]
    P[e, :] = 0.5 * (Pe + P[:, e].T)
    P[:, e] = P[e, :].T
    dx = np.zeros(n)
    dx[e] = K_e @ r
    state.boxplus(dx)
    return UpdateResult(True, nis, m, gate)
