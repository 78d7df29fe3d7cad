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
import enum
import functools
import operator
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from scipy.linalg import qr
from scipy.linalg.lapack import dtrtrs
from scipy.special import gammaincinv

from uwbcal.pipeline.core.geometry import exp_so3, exp_so3_each
from uwbcal.pipeline.core.robust import robust_loss


def _fresh(cls, **arrays: np.ndarray):
    """An instance of the dataclass ``cls`` from newly computed float arrays, without ``__post_init__``'s
    defensive copies (boxplus runs for every variable of every update)."""
    obj = object.__new__(cls)
    obj.__dict__.update(arrays)
    return obj


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
        return _fresh(Vec, x=self.x + dx)


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
        return _fresh(Pose, R=self.R @ exp_so3(dx[0:3]), p=self.p + dx[3:6])


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
        return _fresh(
            ImuState,
            R=self.R @ exp_so3(dx[0:3]),
            p=self.p + dx[3:6],
            v=self.v + dx[6:9],
            bg=self.bg + dx[9:12],
            ba=self.ba + dx[12:15],
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
    # per-row updates (``ekf_update(..., per_row=True)``, m > 1): each row's marginal NIS r_i^2 / S_ii and
    # whether it was used (not gated out)
    row_nis: np.ndarray | None = None
    row_accepted: np.ndarray | None = None


class Kind(enum.Enum):
    """What a state variable is; stages and updaters ask the state for its variables by kind, never by name."""

    NAV = (
        "nav"  # the variable poses come from: ImuState (MSCKF) or Pose (odometry filter); columns 0:6 = pose
    )
    CLONE = "clone"  # MSCKF stochastic clone of the pose at a camera frame (key: t_ns)
    PROBE = "probe"  # considered pose of the initialisation window (key: t_ns)
    ANCHOR = "anchor"  # UWB anchor [p_a, beta, gamma] (key: anchor id)
    LINK = "link"  # per-link range offsets of an anchor [delta_l, ...] relative to its gamma (key: anchor id)
    LANDMARK = "landmark"  # MSCKF SLAM feature: world position of a long visual track (key: track id)
    OTHER = "other"


@dataclass(frozen=True)
class VarInfo:
    kind: Kind
    key: Any = None


class State:
    """Named error-state variables with one joint covariance ``P``.

    The covariance lives in a preallocated buffer whose capacity doubles when it is full; a variable occupies a
    block of it (its *slot*). Removing a variable zeroes its slot and frees it for the next variable of the same
    dimension (the MSCKF's clone window: one clone leaves, the next takes its slot), so adding and removing a
    clone touches only that clone's rows and columns, never the whole matrix; when free slots make up more than
    half of P (the init window's pose probes dropped at once) the slots in use are packed (`_compact`). A free
    slot is a block of zero rows and columns: it takes part in no product that changes another variable. ``P``
    is the view of the slots in use (up to the last one); the order of the slots is not the order of ``names``.
    """

    def __init__(self, use_fej: bool = True, capacity: int = 32) -> None:
        self.use_fej = use_fej
        self._buf = np.zeros((capacity, capacity))
        self._n = 0  # end of the last slot in use
        self._free: list[slice] = []  # zeroed slots below _n
        self._names: list[str] = []
        self._values: dict[str, Value] = {}
        self._fej: dict[str, Value] = {}
        self._slices: dict[str, slice] = {}
        self._info: dict[str, VarInfo] = {}
        self._nav: str | None = None
        # Schmidt (considered) variables: zero gain in every update, cross-covariances tracked
        self.considered: set[str] = set()
        self._pose_stack: tuple | None = None  # the last `_boxplus_poses` result (values, R, p)
        self._plan: tuple | None = None  # `_box_plan`
        self._rows_cache: tuple | None = None  # `estimated_rows`

    # -- the covariance ------------------------------------------------------------------------------------
    @property
    def P(self) -> np.ndarray:
        """The joint covariance (a view of the buffer: in-place changes are changes of the state)."""
        return self._buf[: self._n, : self._n]

    @P.setter
    def P(self, value: np.ndarray) -> None:
        value = np.asarray(value, float)
        if value.shape != (self._n, self._n):
            raise ValueError(f"covariance of shape {value.shape}; the state has size {self._n}")
        self._buf[: self._n, : self._n] = value

    @property
    def size(self) -> int:
        return self._n

    def propagate(self, name: str, Phi: np.ndarray, Q: np.ndarray, *, symmetrize: bool = False) -> None:
        """``x_name <- Phi x_name + w``, w ~ N(0, Q): rows and columns of ``name`` times Phi, plus Q on its block
        (the cross-covariances with every other variable follow). ``symmetrize``: re-symmetrise all of P."""
        sl = self._slices[name]
        P = self.P
        P[sl, :] = Phi @ P[sl, :]
        P[:, sl] = P[:, sl] @ Phi.T
        P[sl, sl] += Q
        if symmetrize:
            np.multiply(P + P.T, 0.5, out=P)

    # -- bookkeeping -------------------------------------------------------------------------------------
    @property
    def names(self) -> list[str]:
        return list(self._names)

    def __contains__(self, name: str) -> bool:
        return name in self._values

    def slice(self, name: str) -> slice:
        return self._slices[name]

    def index(self, names: Iterable[str]) -> np.ndarray:
        """The rows of P of ``names`` (in that order)."""
        names = list(names)
        if not names:
            return np.zeros(0, int)
        sls = [self._slices[n] for n in names]
        return _ranges(np.array([sl.start for sl in sls]), np.array([sl.stop - sl.start for sl in sls]))

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

    def set_propagated(self, name: str, value: Value) -> None:
        """A propagated estimate, which is also the variable's new first estimate: one object for both (values are
        replaced, never changed in place), no copy."""
        self._values[name] = value
        self._fej[name] = value

    def set_fej(self, name: str, value: Value) -> None:
        self._fej[name] = dataclasses.replace(value)  # __post_init__ copies the arrays

    def cov(self, name: str, other: str | None = None) -> np.ndarray:
        return self.P[self._slices[name], self._slices[other or name]]

    # -- typed views ---------------------------------------------------------------------------------------
    def kind(self, name: str) -> Kind:
        return self._info[name].kind

    def key(self, name: str) -> Any:
        return self._info[name].key

    def of_kind(self, kind: Kind) -> list[tuple[Any, str]]:
        """(key, name) of the variables of ``kind``, in the order they were added."""
        return [(self._info[n].key, n) for n in self._names if self._info[n].kind is kind]

    @property
    def nav(self) -> str:
        """Name of the navigation variable (the pose source's own state; its columns 0:6 are the pose)."""
        if self._nav is None:
            raise KeyError("the state has no navigation variable (add one with kind=Kind.NAV)")
        return self._nav

    @property
    def clones(self) -> list[tuple[int, str]]:
        """(t_ns, name) of the MSCKF clones in time order (kept until a variable is added or removed: the MSCKF
        asks for it several times per frame)."""
        cached = getattr(self, "_clones", None)
        if cached is None:
            cached = self._clones = sorted(self.of_kind(Kind.CLONE))
        return list(cached)

    @property
    def probes(self) -> list[tuple[int, str]]:
        """(t_ns, name) of the pose probes in time order."""
        return sorted(self.of_kind(Kind.PROBE))

    @property
    def anchors(self) -> dict[Any, str]:
        """anchor id -> name of its variable."""
        return dict(self.of_kind(Kind.ANCHOR))

    # -- adding and removing variables ---------------------------------------------------------------------
    def add(
        self, name: str, value: Value, P_block: np.ndarray, *, kind: Kind = Kind.OTHER, key: Any = None
    ) -> None:
        """Add an independent variable with covariance ``P_block``."""
        self._append(name, value, np.asarray(P_block, float), None, VarInfo(kind, key))

    def _slot(self, d: int) -> slice:
        """A free slot of dimension ``d`` (first fit), else a new one at the end (the buffer grows by doubling)."""
        for i, sl in enumerate(self._free):
            if sl.stop - sl.start == d:
                return self._free.pop(i)
        n = self._n
        if n + d > self._buf.shape[0]:
            cap = max(2 * self._buf.shape[0], n + d)
            buf = np.zeros((cap, cap))
            buf[:n, :n] = self._buf[:n, :n]
            self._buf = buf
        self._n = n + d
        return slice(n, n + d)

    def _append(
        self, name: str, value: Value, P_new: np.ndarray, cross: np.ndarray | None, info: VarInfo
    ) -> None:
        """``cross``: (d, size) cross-covariance with the current slots (None: independent)."""
        if name in self._values:
            raise KeyError(f"state variable {name!r} exists already")
        n_old = self._n
        sl = self._slot(value.dim)
        P = self.P
        if cross is not None:
            P[sl, :n_old] = cross
            P[:n_old, sl] = cross.T
        P[sl, sl] = 0.5 * (P_new + P_new.T)
        self._names.append(name)
        self._clones = self._plan = None
        self._values[name] = value
        self._fej[name] = dataclasses.replace(value)  # __post_init__ copies the arrays
        self._slices[name] = sl
        self._info[name] = info
        if info.kind is Kind.NAV:
            if self._nav is not None:
                raise KeyError(f"state variable {name!r}: the state has a navigation variable already")
            self._nav = name

    def augment(
        self,
        name: str,
        value: Value,
        J: Mapping[str, np.ndarray],
        Q: np.ndarray | None = None,
        *,
        considered: bool = False,
        kind: Kind = Kind.OTHER,
        key: Any = None,
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
        self._append(name, value, P_new, JP, VarInfo(kind, key))
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
        kind: Kind = Kind.OTHER,
        key: Any = None,
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
        # Whiten so that the QR rotation keeps the noise white (a diagonal R: a row scaling).
        if R.ndim == 1:
            w = 1.0 / np.sqrt(R)
            Hn = w[:, None] * H_new
            rw = w * r
            Ho = {k: w[:, None] * v for k, v in H_old.items()}
        else:
            Linv = np.linalg.inv(np.linalg.cholesky(R))
            Hn = Linv @ H_new
            rw = Linv @ r
            Ho = {k: Linv @ v for k, v in H_old.items()}
        # without the rest's update only the invertible part's rotation is needed (economic QR)
        Qm, _ = qr(Hn, mode="full" if update_rest else "economic")
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
        self._append(name, value, P_new, cross, VarInfo(kind, key))
        if update_rest and m > d:
            H_rest = {k: v[d:] for k, v in Ho.items()}
            H_rest[name] = Hn[d:]
            return ekf_update(self, H_rest, rw[d:], np.eye(m - d))
        return None

    def remove(self, name: str) -> None:
        """Marginalise a variable: zero its rows and columns and free its slot."""
        sl = self._slices.pop(name)
        P = self.P
        P[sl, :] = 0.0
        P[:, sl] = 0.0
        self._free.append(sl)
        # slots at the end shrink the view instead of staying free
        while True:
            last = next((f for f in self._free if f.stop == self._n), None)
            if last is None:
                break
            self._free.remove(last)
            self._n = last.start
        self.considered.discard(name)
        self._names.remove(name)
        self._clones = self._plan = None
        del self._values[name]
        del self._fej[name]
        del self._info[name]
        if self._nav == name:
            self._nav = None
        if sum(f.stop - f.start for f in self._free) > self._n // 2:
            self._compact()

    def _compact(self) -> None:
        """Close the free slots when they are more than half of P (e.g. after the pose probes are dropped): one
        copy of the slots in use, in their order, to the front of the buffer; amortised over the removals."""
        order = sorted(self._names, key=lambda n: self._slices[n].start)
        idx = self.index(order)
        P = self.P[np.ix_(idx, idx)]
        n = len(idx)
        self._buf[:n, :n] = P
        self._buf[n : self._n, : self._n] = 0.0
        self._buf[: self._n, n : self._n] = 0.0
        start = 0
        for name in order:
            d = self._slices[name].stop - self._slices[name].start
            self._slices[name] = slice(start, start + d)
            start += d
        self._n = n
        self._free = []
        self._plan = None

    def boxplus(self, dx: np.ndarray, names: Iterable[str] | None = None) -> None:
        considered = self.considered
        poses: list[tuple[str, int]] = []
        if names is None:  # every variable: which ones have a nonzero correction, in one array operation
            plan, bounds = self._box_plan()
            nonzero = np.logical_or.reduceat(dx != 0, bounds)[::2] if len(bounds) else ()
            for (n, sl, is_pose), moved in zip(plan, nonzero, strict=True):
                if not moved or n in considered:  # considered (Schmidt) variables: exactly zero corrections
                    continue
                if is_pose:  # the clones: all at once below
                    poses.append((n, sl.start))
                else:
                    self._values[n] = self._values[n].boxplus(dx[sl])
            if poses:
                self._boxplus_poses(dx, poses, moved=True)
            return
        else:
            for n in names:
                if n in considered:
                    continue
                sl = self._slices[n]
                value = self._values[n]
                if type(value) is Pose:
                    poses.append((n, sl.start))
                elif dx[sl].any():
                    self._values[n] = value.boxplus(dx[sl])
        if poses:
            self._boxplus_poses(dx, poses)

    def estimated_rows(self, considered: Iterable[str]) -> np.ndarray | slice:
        """The rows of P of every variable but ``considered`` (a slice when they are one block), kept for the
        same set until a variable is added, removed or moved (the UWB updates ask for the same set every
        range)."""
        key = frozenset(considered)
        plan = self._box_plan()
        cached = getattr(self, "_rows_cache", None)
        if cached is not None and cached[0] is plan and cached[1] == key:
            return cached[2]
        mask = np.ones(self._n, bool)
        mask[self.index(key)] = False
        e: np.ndarray | slice = np.flatnonzero(mask)
        if len(e) and e[-1] - e[0] + 1 == len(e):  # one block of rows: slices instead of gathers and scatters
            e = slice(int(e[0]), int(e[-1]) + 1)
        self._rows_cache = (plan, key, e)
        return e

    def _box_plan(self) -> tuple[list[tuple[str, slice, bool]], np.ndarray]:
        """(name, slot, is a Pose) of the variables in slot order, and the bounds [start_0, stop_0, start_1, ...]
        of their slots without the last stop (the end of P), for `np.logical_or.reduceat`; kept until a variable
        is added, removed or moved."""
        cached = getattr(self, "_plan", None)
        if cached is None:
            names = sorted(self._names, key=lambda n: self._slices[n].start)
            plan = [(n, self._slices[n], type(self._values[n]) is Pose) for n in names]
            bounds = np.array([b for _, sl, _ in plan for b in (sl.start, sl.stop)][:-1], np.intp)
            cached = self._plan = (plan, bounds)
        return cached

    def _boxplus_poses(self, dx: np.ndarray, poses: list[tuple[str, int]], moved: bool = False) -> None:
        """`Pose.boxplus` of many poses in one pass, the same numbers (`exp_so3_each`, one stacked product);
        poses with a zero correction keep their value (``moved``: the caller kept only poses with a nonzero one).
        The stacked result is kept: when the next update moves the same poses, still these values (values are
        replaced, never changed in place), it starts from it instead of stacking them again (the clone window
        between two updates)."""
        d = dx[np.array([start for _, start in poses])[:, None] + _SIX]
        if not moved:
            keep = np.flatnonzero(d.any(axis=1))
            if not len(keep):
                return
            if len(keep) < len(poses):
                d = d[keep]
                poses = [poses[i] for i in keep.tolist()]
        names = [n for n, _ in poses]
        vals = [self._values[n] for n in names]
        last = getattr(self, "_pose_stack", None)
        if last is not None and len(last[0]) == len(vals) and all(map(operator.is_, last[0], vals)):
            R0, p0 = last[1], last[2]
        else:
            R0, p0 = np.stack([v.R for v in vals]), np.stack([v.p for v in vals])
        R = R0 @ exp_so3_each(d[:, 0:3])
        p = p0 + d[:, 3:6]
        new = []
        for Rk, pk in zip(R, p, strict=True):  # `_fresh` written out: one small object per pose
            obj = object.__new__(Pose)
            obj.__dict__ = {"R": Rk, "p": pk}
            new.append(obj)
        self._values.update(zip(names, new, strict=True))
        self._pose_stack = (new, R, p)


_SIX = np.arange(6)


def add_probe(state: State, t_ns: int) -> str:
    """Keep the pose of the navigation variable at ``t_ns`` as a considered (Schmidt) variable ``probe/<t_ns>``:
    its value stays the filtered estimate of that time, its cross-covariances with the state stay exact (the
    paper's window states X_I, for the covariance initialisation of the anchors). Returns the name."""
    name = f"probe/{int(t_ns)}"
    if name not in state:
        nav = state.nav
        x = state.value(nav)
        J = np.zeros((6, state.dim(nav)))
        J[:, :6] = np.eye(6)
        state.augment(name, Pose(x.R, x.p), {nav: J}, considered=True, kind=Kind.PROBE, key=int(t_ns))
    return name


def reset_window(state: State, inflation: np.ndarray) -> None:
    """Re-initialise a sliding-window filter from its navigation estimate (after a detected divergence): the
    clones and landmarks are marginalised (their tracks were judged against a wrong window), the navigation
    variable keeps its estimate and its cross-covariances, its block gains the independent error ``inflation``
    (PSD: P stays PSD) and its first estimate becomes the current one (no Jacobian refers to the old one)."""
    for kind in (Kind.CLONE, Kind.LANDMARK):
        for _, n in state.of_kind(kind):
            state.remove(n)
    nav = state.nav
    sl = state.slice(nav)
    state.P[sl, sl] += inflation
    state.set_fej(nav, state.value(nav))


def remove_probes(state: State) -> None:
    for _, n in state.probes:
        state.remove(n)


def chi2_quantile(quantile: float, dof):
    """``scipy.stats.chi2.ppf(quantile, dof)`` (the same formula, bit for bit) without importing scipy.stats,
    which costs ~1.4 s per process (every Monte Carlo worker, every CLI call)."""
    return 2 * gammaincinv(np.asarray(dof) / 2, quantile)


@functools.lru_cache(maxsize=4096)
def chi2_ppf(quantile: float, dof: int) -> float:
    """Cached chi-squared quantile (the filters ask for the same few gates thousands of times)."""
    return float(chi2_quantile(quantile, dof))


def nearest_psd(A: np.ndarray) -> np.ndarray:
    """The nearest positive semi-definite matrix of each symmetrised (..., n, n) ``A``: eigenvalues clipped at 0."""
    w, V = np.linalg.eigh(0.5 * (A + np.swapaxes(A, -1, -2)))
    return (V * np.maximum(w, 0.0)[..., None, :]) @ np.swapaxes(V, -1, -2)


def covariance_upper_bound(A: np.ndarray, B: np.ndarray) -> np.ndarray:
    """The larger of two covariances: along each of their common axes (the generalised eigenvectors, where both are
    diagonal) the larger variance. It bounds both from above (C - A, C - B PSD), equals ``B`` where ``A`` <= ``B``,
    and does not depend on the coordinates' units (C(T A T', T B T') = T C(A, B) T'). A singular ``B`` is taken
    with 1e-12 of each of its variances added to it (1e-24 of A's largest where a variance is 0)."""
    A, B = 0.5 * (A + A.T), 0.5 * (B + B.T)
    try:
        L = np.linalg.cholesky(B)
    except np.linalg.LinAlgError:
        L = np.linalg.cholesky(B + np.diag(1e-12 * np.maximum(np.diag(B), 1e-12 * np.diag(A).max())))
    W = _lower_solve(L, _lower_solve(L, A).T)  # L^-1 A L^-T (A symmetric)
    s, U = np.linalg.eigh(0.5 * (W + W.T))
    M = L @ U
    return (M * np.maximum(s, 1.0)) @ M.T


def _stacked_jacobian(
    state: State, H: Mapping[str, np.ndarray], m: int
) -> tuple[slice | np.ndarray, np.ndarray]:
    """The update's Jacobian blocks as one (m, k) matrix over covariance indices ``idx`` (a slice, i.e. no copy of
    P's columns, when the variables are contiguous in the state, e.g. the MSCKF's clones)."""
    blocks = sorted(
        ((state.slice(v), np.asarray(Hb, float).reshape(m, -1)) for v, Hb in H.items()),
        key=lambda x: x[0].start,
    )
    if not blocks:
        return slice(0, 0), np.zeros((m, 0))
    if all(a[0].stop == b[0].start for a, b in zip(blocks[:-1], blocks[1:], strict=True)):
        idx: slice | np.ndarray = slice(blocks[0][0].start, blocks[-1][0].stop)
    else:
        idx = np.concatenate([np.arange(sl.start, sl.stop) for sl, _ in blocks])
    Hd = blocks[0][1] if len(blocks) == 1 else np.concatenate([Hb for _, Hb in blocks], axis=1)
    return idx, Hd


def _ranges(start: np.ndarray, length: np.ndarray) -> np.ndarray:
    """``concatenate([arange(s, s + n) for s, n in zip(start, length)])`` in three array operations."""
    total = int(length.sum())
    return np.repeat(start - (np.cumsum(length) - length), length) + np.arange(total)


@dataclass
class _Rows:
    row_nis: np.ndarray
    row_accepted: np.ndarray
    gate: float | None


def _per_row(S, r, R, PHt, chi2_gate, robust, robust_R):
    """Per-row gate and robust weights of a stacked update (see `ekf_update`); returns the kept rows' S (with
    the robust inflation on its diagonal), r, PHt and the row figures."""
    d = np.diag(S).copy()
    row_nis = r * r / d
    gate = chi2_ppf(chi2_gate, 1) if chi2_gate is not None else None
    keep = row_nis <= gate if gate is not None else np.ones(len(r), bool)
    if robust is not None:
        kind, c = robust
        s_w = d if robust_R is None else d - np.diag(R) + np.asarray(robust_R, float)
        e = np.abs(r) / np.sqrt(np.maximum(s_w, 1e-300))
        wt = robust_loss(e, kind, np.asarray(c, float))[1]
        S = S + np.diag(np.where(wt < 1.0, d / wt - d, 0.0))
    idx = np.flatnonzero(keep)
    return S[np.ix_(idx, idx)], r[idx], PHt[:, idx], _Rows(row_nis, keep, gate)


def _result(nis: float, m: int, gate: float | None, rows: _Rows | None) -> UpdateResult:
    if rows is None:
        return UpdateResult(True, nis, m, gate)
    return UpdateResult(True, nis, m, rows.gate, rows.row_nis, rows.row_accepted)


def _lower_solve(L: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``L^-1 b`` for the innovation's (C-ordered) Cholesky factor: the LAPACK call scipy's ``solve_triangular``
    makes for it (``dtrtrs`` on the Fortran-ordered transpose, transposed: the same numbers) without its ~20 us of
    checks per call; L has a positive diagonal (the Cholesky factorisation succeeded)."""
    x, info = dtrtrs(L.T, b, lower=0, trans=1)
    if info != 0:
        raise FloatingPointError(f"dtrtrs failed (info {info})")
    return x


def ekf_update(
    state: State,
    H: Mapping[str, np.ndarray],
    r: np.ndarray,
    R: np.ndarray | float,
    *,
    schmidt: Iterable[str] = (),
    chi2_gate: float | None = None,
    robust: tuple[str, float] | None = None,
    robust_R: float | np.ndarray | None = None,
    per_row: bool = False,
) -> UpdateResult:
    """The one EKF update: ``r = sum_v H[v] dx_v + n``, n ~ N(0, R).

    ``schmidt`` names variables that are *considered* but not estimated (Schmidt-Kalman filter; the state's own
    ``considered`` variables are always among them): their
    gain rows are zero, so their estimates and their own covariance block stay unchanged, while the
    cross-covariances with the estimated variables are updated (the rows of the estimated variables take the
    optimal gain's update, P_e: - P_e: H^T S^-1 H P). ``chi2_gate`` is a quantile
    (e.g. 0.95): the update is rejected when the NIS exceeds it. ``robust = (loss, c)`` with loss ``huber`` or
    ``cauchy`` (one-row updates): instead of a hard gate the innovation covariance is inflated to S / w with the
    IRLS weight w of the whitened innovation e = r / sqrt(S) (scale ``c`` in sigmas), i.e. R grows by
    (1/w - 1) S: a large residual still informs, with a bounded (Huber) or vanishing (Cauchy) influence.
    ``robust_R`` replaces R in the variance that whitens e (e.g. the per-sample noise when R is inflated for
    time-correlated errors, so that the loss keeps its scale in metres).

    ``per_row`` (m > 1 rows of independent scalar measurements, R diagonal; a stacked epoch of ranges): the gate
    and the robust loss act on each row with its marginal innovation variance S_ii — a row whose NIS r_i^2 / S_ii
    exceeds the 1-dof ``chi2_gate`` is dropped, the others update together; the robust weight w_i inflates S_ii
    to S_ii / w_i (``robust`` scale ``c`` and ``robust_R`` may then be per-row arrays). With one row the result is
    that of the scalar update, bit for bit (its row fields None).
    """
    r, R = _measurement(r, R)
    m = r.shape[0]
    idx, Hd = _stacked_jacobian(state, H, m)
    PHt = state.P[:, idx] @ Hd.T
    S = Hd @ PHt[idx, :]
    S = 0.5 * (S + S.T) + R
    rows = None
    if per_row and m > 1:
        S, r, PHt, rows = _per_row(S, r, R, PHt, chi2_gate, robust, robust_R)
        if not rows.row_accepted.any():
            return UpdateResult(False, float("nan"), 0, rows.gate, rows.row_nis, rows.row_accepted)
        m, chi2_gate, robust = int(r.shape[0]), None, None
    cho = _cholesky(S, m)
    y = _lower_solve(cho, r)
    nis = float(y @ y)
    gate = chi2_ppf(chi2_gate, m) if chi2_gate is not None else None
    if gate is not None and nis > gate:
        return UpdateResult(False, nis, m, gate)
    inflated = robust is not None and m == 1
    if inflated:
        wt = _robust_weight(robust, nis, r, S, R, robust_R)
        if wt < 1.0:
            S = S / wt
            cho = cho / np.sqrt(wt)
    # P+ = P - P H^T S^-1 H P = P - W^T W with W = L^-1 (H P), S = L L^T (the Joseph form's value for this,
    # the optimal gain: K S K^T = K H P), dx = K r = W^T L^-1 r: one triangular solve and one symmetric product
    # (BLAS syrk) instead of the gain and three products with it.
    W = _lower_solve(cho, PHt.T)  # (m, n)
    if inflated:
        y = _lower_solve(cho, r)  # with the robust inflation
    schmidt = state.considered.union(schmidt)
    if schmidt:
        _apply_schmidt(state, W, y, schmidt)
    else:
        P = state.P - W.T @ W
        np.multiply(P + P.T, 0.5, out=state.P)  # symmetric, written into the state's buffer
        state.boxplus(W.T @ y)
    return _result(nis, m, gate, rows)


def _measurement(r: np.ndarray, R: np.ndarray | float) -> tuple[np.ndarray, np.ndarray]:
    """The residual as a vector and its covariance as an (m, m) matrix (from a scalar, a row of variances or a
    matrix)."""
    r = np.asarray(r, float).reshape(-1)
    m = r.shape[0]
    R = np.atleast_2d(np.asarray(R, float))
    if R.shape == (1, 1) and m > 1:
        R = np.eye(m) * R[0, 0]
    elif R.ndim == 2 and R.shape[0] == 1 and R.shape[1] == m:
        R = np.diag(R[0])
    return r, R


def _cholesky(S: np.ndarray, m: int) -> np.ndarray:
    """The lower Cholesky factor of S; one row: the square root (what LAPACK's potrf computes), without numpy's
    wrapper."""
    if m == 1:
        if not S[0, 0] > 0.0:
            raise FloatingPointError("innovation covariance not positive definite (1 rows)")
        return np.sqrt(S)
    try:
        return np.linalg.cholesky(S)
    except np.linalg.LinAlgError as exc:
        raise FloatingPointError(f"innovation covariance not positive definite ({m} rows)") from exc


def _robust_weight(
    robust: tuple[str, float], nis: float, r: np.ndarray, S: np.ndarray, R: np.ndarray, robust_R
) -> float:
    """IRLS weight of a one-row innovation whitened by S (or by S with ``robust_R`` in place of R); the scale and
    ``robust_R`` scalars or (a `per_row` update's) arrays of the one row."""
    kind, c = robust
    e = float(np.sqrt(nis))
    if robust_R is not None:
        s_w = float(S[0, 0]) - float(R[0, 0]) + float(np.squeeze(robust_R))
        e = abs(float(r[0])) / np.sqrt(max(s_w, 1e-300))
    return float(np.squeeze(robust_loss(e, kind, c)[1]))


def _apply_schmidt(state: State, W: np.ndarray, y: np.ndarray, schmidt: set[str]) -> None:
    """Schmidt: the gain rows of the considered variables are zero, so only the rows and columns e of the
    estimated ones change, by A = W_e^T W (P_ee - K_e S K_e^T, P_ec - K_e H P_:c); the considered block stays
    as it is. The new rows e, symmetrised (P is symmetric only up to rounding, so both of its halves enter):
    0.5 (P_e: + (P_:e)^T) - A, and the block ee of that symmetrised again; one gather and one scatter of the
    columns e."""
    e = state.estimated_rows(schmidt)
    W_e = np.asfortranarray(W[:, e])  # the layout of a column gather (BLAS' rounding depends on it)
    P = state.P
    F = P[e, :].copy() if isinstance(e, slice) else P[e, :]
    F += P[:, e].T
    F *= 0.5
    F -= W_e.T @ W
    X = F[:, e]
    F[:, e] = 0.5 * (X + X.T)
    P[e, :] = F
    P[:, e] = F.T
    dx = np.zeros(state.size)
    dx[e] = W_e.T @ y
    state.boxplus(dx)


def schmidt_update(
    state: State,
    H: Mapping[str, np.ndarray],
    r: np.ndarray,
    R: np.ndarray | float,
    *,
    estimated: Iterable[str],
    **options,
) -> UpdateResult:
    """The Schmidt-Kalman update (the paper's SKF): only the ``estimated`` variables get a gain, every other
    variable is considered (its estimate and own covariance stay, its cross-covariances follow). A named view of
    the one update: `ekf_update` with ``schmidt`` = the rest of the state; ``options`` as there."""
    est = set(estimated)
    return ekf_update(state, H, r, R, schmidt=[n for n in state.names if n not in est], **options)
