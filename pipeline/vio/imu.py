"""IMU propagation of the navigation state: mean, state transition Phi and discrete noise Q over an interval.

Error state ``[dtheta, dp, dv, dbg, dba]`` with a right perturbation on ``R`` (world_from_body), world z up.
Per IMU sub-interval k (length dt_k, measurements averaged over its ends):

    R_{k+1} = R_k Exp(w_k dt),   Rm_k = R_k Exp(w_k dt / 2)   (mid-point rotation of the specific force)
    v_{k+1} = v_k + (Rm_k a_k + g) dt,   p_{k+1} = p_k + v_k dt + (Rm_k a_k + g) dt^2 / 2

with ``w = w_m - bg``, ``a = a_m - ba``. The transition over the whole interval is composed in closed form
(one 15x15 Phi per interval, so the big covariance is touched once). The orientation columns are

    Phi_tt = R_1^T R_0,  Phi_vt = -[v_1 - v_0 - g T]x R_0,  Phi_pt = -[p_1 - p_0 - v_0 T - g T^2/2]x R_0,

which is exact for the discrete scheme above. With first-estimate Jacobians (FEJ) ``R_0, v_0, p_0`` are the
first estimates of the state at the interval start (the propagated value before any update) while
``R_1, v_1, p_1`` are the new propagated estimates, as in OpenVINS; then Phi maps the 4-DoF unobservable
directions (global yaw, translation) at time 0 exactly onto those at time 1, so the filter gains no spurious
yaw/position information. Without FEJ, ``R_0, v_0, p_0`` are the current estimates.

Noise: continuous white-noise densities (gyro/acc ``*_noise_density``) enter per sub-interval with variance
``sigma^2 / dt_k`` on the averaged measurement (longer sub-intervals than the IMU period, i.e. gaps, use the
IMU period: a held measurement, which inflates the noise); the bias random walks add ``sigma_b^2 T`` to the
bias blocks. Their cross-terms with the navigation error (order sigma_b^2 T^2) are neglected; the caller keeps
intervals short (camera/range rate), where they are far below the white-noise terms.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from uwbcal.convert.calibration import parse_calibration
from uwbcal.pipeline.core.errors import InputError
from uwbcal.pipeline.core.geometry import I3, exp_jr_so3, log_so3, skew
from uwbcal.pipeline.core.state import ImuState

GRAVITY = np.array([0.0, 0.0, -9.81])
_EYE15 = np.eye(15)  # copied, never changed (np.eye costs more than a copy)


@dataclass(frozen=True)
class ImuNoise:
    """Continuous-time noise densities: gyro [rad/s/sqrt(Hz)], acc [m/s^2/sqrt(Hz)], random walks."""

    sigma_g: float
    sigma_a: float
    sigma_bg: float
    sigma_ba: float
    rate_hz: float = 200.0

    @classmethod
    def from_calibration(cls, calib: dict, source: str = "recording", inflate: float = 1.0) -> ImuNoise:
        """The IMU noise of a ``uwbcal.calibration`` mapping (validated by `convert.calibration`)."""
        c = parse_calibration(calib, f"{source}: uwbcal.calibration").imu
        if c is None:
            raise InputError(
                f"{source}: uwbcal.calibration: imu: missing; re-convert the recording with the IMU calibration "
                "(noise densities and random walks, e.g. uwbcal convert bag --calibration)"
            )
        vals = (
            c.gyroscope_noise_density,
            c.accelerometer_noise_density,
            c.gyroscope_random_walk,
            c.accelerometer_random_walk,
        )
        return cls(*(v * inflate for v in vals), rate_hz=c.rate_hz or 200.0)


@dataclass
class Propagation:
    state: ImuState  # propagated mean at the interval end
    Phi: np.ndarray  # (15, 15) error-state transition
    Q: np.ndarray  # (15, 15) discrete process noise


def imu_intervals(
    t_ns: np.ndarray, gyro: np.ndarray, acc: np.ndarray, t0_ns: int, t1_ns: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Sub-intervals of [t0, t1] at the IMU stamps: lengths dt [s] (n,) and averaged gyro/acc (n, 3).

    Measurements are linearly interpolated at t0 and t1 (held beyond the ends of the data); each sub-interval
    uses the mean of its end values (trapezoid).
    """
    if t1_ns <= t0_ns:
        return np.zeros(0), np.zeros((0, 3)), np.zeros((0, 3))
    i0 = int(np.searchsorted(t_ns, t0_ns, side="right"))
    i1 = int(np.searchsorted(t_ns, t1_ns, side="left"))
    ts = np.empty(i1 - i0 + 2, np.int64)
    ts[0], ts[-1] = t0_ns, t1_ns
    ts[1:-1] = t_ns[i0:i1]
    tf = (ts - t0_ns) * 1e-9
    n = len(t_ns)
    w = np.empty((len(ts), 3))
    a = np.empty((len(ts), 3))
    w[1:-1], a[1:-1] = gyro[i0:i1], acc[i0:i1]
    for row, t, j in ((0, t0_ns, i0), (-1, t1_ns, i1)):  # interpolate the ends, hold beyond the data
        lo, hi = min(max(j - 1, 0), n - 1), min(j, n - 1)
        t_lo = int(t_ns[lo])  # Python integers: exact differences, the same quotient as numpy's
        s = 0.0 if hi == lo else min(max((t - t_lo) / (int(t_ns[hi]) - t_lo), 0.0), 1.0)
        w[row] = (1 - s) * gyro[lo] + s * gyro[hi]
        a[row] = (1 - s) * acc[lo] + s * acc[hi]
    dt = np.diff(tf)
    wm, am = 0.5 * (w[1:] + w[:-1]), 0.5 * (a[1:] + a[:-1])
    keep = dt > 0
    if keep.all():
        return dt, wm, am
    return dt[keep], wm[keep], am[keep]


@dataclass
class _Integration:
    """The mean integrated over the sub-intervals ``dt`` (`propagate`): what the Jacobian and noise blocks use."""

    dt: np.ndarray  # (n,)
    a: np.ndarray  # (n, 3) bias-corrected acceleration
    R: np.ndarray  # (n + 1, 3, 3) orientations at the sub-interval bounds
    dRh: np.ndarray  # (n, 3, 3) half-step rotations
    Rm: np.ndarray  # (n, 3, 3) mid-interval orientations
    Jr: np.ndarray  # (n, 3, 3) right Jacobians of the full steps
    Jrh: np.ndarray  # (n, 3, 3) and of the half steps
    v: np.ndarray  # (n + 1, 3)
    p: np.ndarray  # (n + 1, 3)
    tau: np.ndarray  # (n + 1,) time since the interval start
    Rm_skew_a: np.ndarray  # (n, 3, 3) Rm [a]x


def _integrate(x: ImuState, dt: np.ndarray, gyro: np.ndarray, acc: np.ndarray) -> _Integration:
    n = dt.shape[0]
    w = gyro - x.bg
    a = acc - x.ba
    wdt = w * dt[:, None]
    wboth = np.concatenate([wdt, 0.5 * wdt])  # full and half steps in one call each (numpy overhead)
    Eboth, Jboth = exp_jr_so3(wboth)  # rotations and right Jacobians of the full and half steps
    dR, dRh = Eboth[:n], Eboth[n:]
    R = np.empty((n + 1, 3, 3))
    R[0] = x.R
    for k in range(n):
        R[k + 1] = R[k] @ dR[k]
    Rm = R[:-1] @ dRh
    f = np.einsum("kij,kj->ki", Rm, a) + GRAVITY  # world acceleration per sub-interval
    dv = f * dt[:, None]
    v = np.empty((n + 1, 3))
    v[0] = x.v
    v[1:] = x.v + np.cumsum(dv, axis=0)
    p = np.empty((n + 1, 3))
    p[0] = x.p
    p[1:] = x.p + np.cumsum(v[:-1] * dt[:, None] + 0.5 * dv * dt[:, None], axis=0)
    tau = np.concatenate([[0.0], np.cumsum(dt)])  # time since the interval start
    Jr, Jrh = Jboth[:n], Jboth[n:]
    return _Integration(dt, a, R, dRh, Rm, Jr, Jrh, v, p, tau, Rm @ skew(a))


def propagate(
    x: ImuState,
    dt: np.ndarray,
    gyro: np.ndarray,
    acc: np.ndarray,
    noise: ImuNoise,
    x_fej: ImuState | None = None,
) -> Propagation:
    """Propagate ``x`` over sub-intervals ``dt`` with measurements ``gyro``/``acc`` (see module doc).

    ``x_fej`` is the linearisation point of the start state for the orientation columns of Phi (FEJ); None
    uses ``x`` itself.
    """
    n = dt.shape[0]
    Phi = _EYE15.copy()
    Q = np.zeros((15, 15))
    if n == 0:
        return Propagation(x, Phi, Q)
    x0 = x_fej if x_fej is not None else x
    it = _integrate(x, dt, gyro, acc)
    R, v, p = it.R, it.v, it.p
    T = it.tau[-1]
    x1 = ImuState(R[-1], p[-1], v[-1], x.bg, x.ba)

    # -- orientation / velocity / position columns (FEJ-able closed form) -------------------------------------
    Phi[0:3, 0:3] = R[-1].T @ x0.R
    Phi[6:9, 0:3] = -skew(v[-1] - x0.v - GRAVITY * T) @ x0.R
    Phi[3:6, 0:3] = -skew(p[-1] - x0.p - x0.v * T - 0.5 * GRAVITY * T * T) @ x0.R
    Phi[3:6, 6:9] = T * I3
    _bias_columns(Phi, it)
    Q[0:9, 0:9] = _white_noise(it, noise)
    Q[9:12, 9:12] = noise.sigma_bg**2 * T * I3
    Q[12:15, 12:15] = noise.sigma_ba**2 * T * I3
    return Propagation(x1, Phi, Q)


def _bias_columns(Phi: np.ndarray, it: _Integration) -> None:
    """The bias columns of ``Phi`` (in place)."""
    n, dt, R, Rm = len(it.dt), it.dt, it.R, it.Rm
    dt3 = dt[:, None, None]
    C = np.zeros((n + 1, 3, 3))
    C[1:] = np.cumsum(R[1:] @ it.Jr * dt3, axis=0)
    A = -np.swapaxes(R, 1, 2) @ C  # d dtheta_k / d bg (body frame of R_k)
    Amid = np.swapaxes(it.dRh, 1, 2) @ A[:-1] - it.Jrh * (0.5 * dt)[:, None, None]
    # d dv_k / d bg and d dv_k / d ba side by side: one cumulative sum and one sum for both bias blocks
    E = np.concatenate([-(it.Rm_skew_a @ Amid) * dt3, -Rm * dt3], axis=2)
    V = np.zeros((n, 3, 6))
    V[1:] = np.cumsum(E, axis=0)[:-1]
    Phi[0:3, 9:12] = A[-1]
    Phi[6:9, 9:15] = E.sum(axis=0)
    Phi[3:6, 9:15] = (V * dt3 + 0.5 * E * dt3).sum(axis=0)


def _white_noise(it: _Integration, noise: ImuNoise) -> np.ndarray:
    """The 9x9 (orientation, position, velocity) noise of the measurements' white noise: the effect of a
    perturbation in sub-interval k on the end state, summed over k."""
    n, dt, R, v, p, Rm, Jr = len(it.dt), it.dt, it.R, it.v, it.p, it.Rm, it.Jr
    dt3 = dt[:, None, None]
    T = it.tau[-1]
    rem = T - it.tau[1:]  # time from the end of sub-interval k to the interval end
    Rk1 = R[1:]
    Ftt = R[-1].T @ Rk1  # (n, 3, 3) R_1^T R_{k+1}
    rem1 = rem[:, None]
    # the velocity and position rows of both, stacked: one skew and one product
    Fvp = -skew(
        np.concatenate(
            [v[-1] - v[1:] - GRAVITY * rem1, p[-1] - p[1:] - v[1:] * rem1 - 0.5 * GRAVITY * rem1**2]
        )
    ) @ np.concatenate([Rk1, Rk1])
    # gyro: dtheta_{k+1} = Jr dt dw; dv_{k+1} = -Rm [a]x Jrh dt^2/2 dw; dp_{k+1} = dv_{k+1} dt / 2
    gth = Jr * dt3
    gv = -(it.Rm_skew_a @ it.Jrh) * (0.5 * dt * dt)[:, None, None]
    Fg = Fvp @ np.concatenate([gth, gth])
    Gg = np.zeros((n, 9, 3))
    Gg[:, 0:3] = Ftt @ gth
    Gg[:, 6:9] = Fg[:n] + gv
    Gg[:, 3:6] = Fg[n:] + rem[:, None, None] * gv + 0.5 * dt3 * gv
    # acc: dv_{k+1} = Rm dt da; dp_{k+1} = Rm dt^2/2 da
    Ga = np.zeros((n, 9, 3))
    Ga[:, 6:9] = Rm * dt3
    Ga[:, 3:6] = Rm * (dt * rem + 0.5 * dt * dt)[:, None, None]
    dt_nom = 1.0 / noise.rate_hz
    deff = np.minimum(dt, dt_nom)
    return np.einsum("kij,klj,k->il", Gg, Gg, noise.sigma_g**2 / deff) + np.einsum(
        "kij,klj,k->il", Ga, Ga, noise.sigma_a**2 / deff
    )


def propagate_static(x: ImuState, T: float, noise: ImuNoise, x_fej: ImuState | None = None) -> Propagation:
    """Propagate ``x`` over ``T`` seconds with the zero-motion model (used while a zero-velocity update holds).

    The IMU measurements of the interval are *not* integrated: they are the zero-velocity update's measurement,
    and using them twice (propagation and update) would correlate the two. The model is R, v, biases constant,
    p += v T; the unknown residual motion is white angular rate / acceleration with the IMU's noise densities
    (continuous-time integration over T). As in `propagate`, the orientation columns of Phi are written in the
    FEJ form (``R_0, v_0, p_0`` the first estimates at the interval start, ``R_1, v_1, p_1`` the new estimates),
    so that Phi maps the 4-DoF unobservable subspace exactly; with ``x_fej = x`` they reduce to the true
    Jacobian (identity / zero).
    """
    x0 = x_fej if x_fej is not None else x
    x1 = ImuState(x.R, x.p + x.v * T, x.v, x.bg, x.ba)
    Phi = np.eye(15)
    Phi[0:3, 0:3] = x1.R.T @ x0.R
    Phi[6:9, 0:3] = -skew(x1.v - x0.v) @ x0.R
    Phi[3:6, 0:3] = -skew(x1.p - x0.p - x0.v * T) @ x0.R
    Phi[3:6, 6:9] = T * I3
    Q = np.zeros((15, 15))
    qa = noise.sigma_a**2
    Q[0:3, 0:3] = noise.sigma_g**2 * T * np.eye(3)
    Q[3:6, 3:6] = qa * T**3 / 3.0 * np.eye(3)
    Q[3:6, 6:9] = Q[6:9, 3:6] = qa * T**2 / 2.0 * np.eye(3)
    Q[6:9, 6:9] = qa * T * np.eye(3)
    Q[9:12, 9:12] = noise.sigma_bg**2 * T * I3
    Q[12:15, 12:15] = noise.sigma_ba**2 * T * I3
    return Propagation(x1, Phi, Q)


def error_between(x: ImuState, y: ImuState) -> np.ndarray:
    """Error ``dx`` with ``y = x boxplus dx`` (right perturbation on R)."""

    return np.concatenate([log_so3(x.R.T @ y.R), y.p - x.p, y.v - x.v, y.bg - x.bg, y.ba - x.ba])
