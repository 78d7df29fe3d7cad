"""SO(3) and quaternion helpers, vectorised over a leading axis where it matters.

Conventions used across uwbcal:
- ``R`` is world_from_body (``R_WB``): ``p_W = R @ p_B + t``.
- Quaternions are Hamilton, stored ``(x, y, z, w)`` as in ROS messages.
- Rotation errors are right (body-frame) perturbations: ``R = R_hat @ Exp(dtheta)``.
"""

from __future__ import annotations

import math

import numpy as np

_EPS = 1e-10
I3 = np.eye(3)  # read-only: the hot paths add it, never change it (np.eye costs a call each time)
I3.flags.writeable = False


def norms(v: np.ndarray) -> np.ndarray:
    """``np.linalg.norm(v, axis=-1)`` of a real array by its own expression, without its wrapper (hot paths)."""
    return np.sqrt(np.add.reduce(v * v, axis=-1))


def skew(v: np.ndarray) -> np.ndarray:
    """Skew-symmetric matrix(es) of vector(s) ``v`` with shape (3,) or (N, 3)."""
    v = np.asarray(v, dtype=float)
    if v.shape == (3,):  # one vector (the propagation's Phi blocks): one array from Python floats
        x, y, z = v.tolist()
        return np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])
    out = np.zeros(v.shape[:-1] + (3, 3))
    out[..., 0, 1] = -v[..., 2]
    out[..., 0, 2] = v[..., 1]
    out[..., 1, 0] = v[..., 2]
    out[..., 1, 2] = -v[..., 0]
    out[..., 2, 0] = -v[..., 1]
    out[..., 2, 1] = v[..., 0]
    return out


def exp_so3(w: np.ndarray) -> np.ndarray:
    """Rodrigues' formula for (3,) or (N, 3) rotation vectors."""
    w = np.asarray(w, dtype=float)
    if w.shape == (3,):  # the filter's hot path: scalar arithmetic beats broadcasting on one vector
        return _exp_so3_one(float(w[0]), float(w[1]), float(w[2]))
    theta = np.linalg.norm(w, axis=-1)[..., None, None]
    K = skew(w)
    small = theta < 1e-7
    th = np.where(small, 1.0, theta)
    a = np.where(small, 1.0 - theta**2 / 6.0, np.sin(th) / th)
    b = np.where(small, 0.5 - theta**2 / 24.0, (1.0 - np.cos(th)) / th**2)
    return np.eye(3) + a * K + b * (K @ K)


def _exp_so3_one(x: float, y: float, z: float) -> np.ndarray:
    t2 = x * x + y * y + z * z
    if t2 < 1e-14:
        a, b = 1.0 - t2 / 6.0, 0.5 - t2 / 24.0
    else:
        t = math.sqrt(t2)
        a, b = math.sin(t) / t, (1.0 - math.cos(t)) / t2
    return np.array(
        [
            [1.0 - b * (y * y + z * z), b * x * y - a * z, b * x * z + a * y],
            [b * x * y + a * z, 1.0 - b * (x * x + z * z), b * y * z - a * x],
            [b * x * z - a * y, b * y * z + a * x, 1.0 - b * (x * x + y * y)],
        ]
    )


def exp_so3_each(w: np.ndarray) -> np.ndarray:
    """``exp_so3`` of each row of ``w`` (N, 3) with the numbers of the one-vector path (`exp_so3` of a (3,)
    vector), bit for bit: the same expressions in the same order, elementwise over the rows, and ``math``'s sine
    and cosine (numpy's vectorised ones may differ in the last bit). For updating many poses at once."""
    x, y, z = w[:, 0], w[:, 1], w[:, 2]
    xx, yy, zz = x * x, y * y, z * z
    t2 = xx + yy + zz
    a_, b_ = [], []  # Python lists, one array each at the end (item assignment into numpy costs more)
    for s2 in t2.tolist():
        if s2 < 1e-14:
            a_.append(1.0 - s2 / 6.0)
            b_.append(0.5 - s2 / 24.0)
        else:
            t = math.sqrt(s2)
            a_.append(math.sin(t) / t)
            b_.append((1.0 - math.cos(t)) / s2)
    a, b = np.array(a_), np.array(b_)
    bx, by = b * x, b * y
    bxy, bxz, byz = bx * y, bx * z, by * z  # b x y etc., evaluated left to right as in `_exp_so3_one`
    ax, ay, az = a * x, a * y, a * z
    out = np.empty((len(t2), 3, 3))
    out[:, 0, 0] = 1.0 - b * (yy + zz)
    out[:, 0, 1] = bxy - az
    out[:, 0, 2] = bxz + ay
    out[:, 1, 0] = bxy + az
    out[:, 1, 1] = 1.0 - b * (xx + zz)
    out[:, 1, 2] = byz - ax
    out[:, 2, 0] = bxz - ay
    out[:, 2, 1] = byz + ax
    out[:, 2, 2] = 1.0 - b * (xx + yy)
    return out


def log_so3(R: np.ndarray) -> np.ndarray:
    """Rotation vector(s) of (3, 3) or (N, 3, 3) rotation matrices (robust near 0 and pi)."""
    R = np.asarray(R, dtype=float)
    single = R.ndim == 2
    R = R.reshape(-1, 3, 3)
    q = rot_to_quat(R)
    # q = (x, y, z, w); keep w >= 0 so that the angle is in [0, pi]
    q = np.where(q[:, 3:4] < 0, -q, q)
    vn = np.linalg.norm(q[:, :3], axis=1)
    angle = 2.0 * np.arctan2(vn, q[:, 3])
    scale = np.where(vn < _EPS, 2.0 / np.maximum(q[:, 3], _EPS), angle / np.maximum(vn, _EPS))
    out = q[:, :3] * scale[:, None]
    return out[0] if single else out


def jr_so3(w: np.ndarray) -> np.ndarray:
    """Right Jacobian of SO(3): Exp(w + dw) ~= Exp(w) Exp(Jr(w) dw)."""
    w = np.asarray(w, dtype=float)
    theta = np.linalg.norm(w, axis=-1)[..., None, None]
    K = skew(w)
    small = theta < 1e-5
    th = np.where(small, 1.0, theta)
    a = np.where(small, 0.5 - theta**2 / 24.0, (1.0 - np.cos(th)) / th**2)
    b = np.where(small, 1.0 / 6.0 - theta**2 / 120.0, (th - np.sin(th)) / th**3)
    return np.eye(3) - a * K + b * (K @ K)


def exp_jr_so3(w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(exp_so3(w), jr_so3(w))`` for (N, 3) rotation vectors with the norm, the skew matrices, their square and
    the sine and cosine computed once (the IMU propagation needs both for every sample); the same numbers as the
    two functions."""
    w = np.asarray(w, dtype=float)
    theta = norms(w)[..., None, None]
    K = skew(w)
    KK = K @ K
    small_e, small_j = theta < 1e-7, theta < 1e-5  # small_e implies small_j
    # one argument for the sine and cosine: theta wherever either function uses its closed form (theta >= 1e-7)
    th = np.where(small_e, 1.0, theta) if small_j.any() else theta
    sin, cos = np.sin(th), np.cos(th)
    one_m_cos_th2 = (1.0 - cos) / th**2
    eye = I3
    if small_j.any():  # the series near zero where the closed forms lose digits
        t2 = theta**2
        a = np.where(small_e, 1.0 - t2 / 6.0, sin / th)
        b = np.where(small_e, 0.5 - t2 / 24.0, one_m_cos_th2)
        R = eye + a * K + b * KK
        a = np.where(small_j, 0.5 - t2 / 24.0, one_m_cos_th2)
        b = np.where(small_j, 1.0 / 6.0 - t2 / 120.0, (th - sin) / th**3)
        return R, eye - a * K + b * KK
    R = eye + (sin / th) * K + one_m_cos_th2 * KK
    return R, eye - one_m_cos_th2 * K + ((th - sin) / th**3) * KK


def jr_inv_so3(w: np.ndarray) -> np.ndarray:
    """Inverse of the right Jacobian of SO(3)."""
    w = np.asarray(w, dtype=float)
    theta = np.linalg.norm(w, axis=-1)[..., None, None]
    K = skew(w)
    small = theta < 1e-5
    th = np.where(small, 1.0, theta)
    c = np.where(
        small, 1.0 / 12.0 + theta**2 / 720.0, 1.0 / th**2 - (1.0 + np.cos(th)) / (2.0 * th * np.sin(th))
    )
    return np.eye(3) + 0.5 * K + c * (K @ K)


def quat_to_rot(q: np.ndarray) -> np.ndarray:
    """(x, y, z, w) quaternion(s) -> rotation matrix(es). Normalises the input."""
    q = np.asarray(q, dtype=float)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    x, y, z, w = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    R = np.empty(q.shape[:-1] + (3, 3))
    R[..., 0, 0] = 1 - 2 * (y * y + z * z)
    R[..., 0, 1] = 2 * (x * y - z * w)
    R[..., 0, 2] = 2 * (x * z + y * w)
    R[..., 1, 0] = 2 * (x * y + z * w)
    R[..., 1, 1] = 1 - 2 * (x * x + z * z)
    R[..., 1, 2] = 2 * (y * z - x * w)
    R[..., 2, 0] = 2 * (x * z - y * w)
    R[..., 2, 1] = 2 * (y * z + x * w)
    R[..., 2, 2] = 1 - 2 * (x * x + y * y)
    return R


def rot_to_quat(R: np.ndarray) -> np.ndarray:
    """Rotation matrix(es) -> (x, y, z, w) unit quaternion(s) with w >= 0 (Shepperd's method)."""
    R = np.asarray(R, dtype=float)
    single = R.ndim == 2
    R = R.reshape(-1, 3, 3)
    tr = np.trace(R, axis1=1, axis2=2)
    diag = np.stack([R[:, 0, 0], R[:, 1, 1], R[:, 2, 2], tr], axis=1)
    k = np.argmax(diag, axis=1)
    q = np.empty((R.shape[0], 4))
    # case w largest
    m = k == 3
    s = np.sqrt(np.maximum(1.0 + tr[m], _EPS)) * 2
    q[m] = np.stack(
        [
            (R[m, 2, 1] - R[m, 1, 2]) / s,
            (R[m, 0, 2] - R[m, 2, 0]) / s,
            (R[m, 1, 0] - R[m, 0, 1]) / s,
            0.25 * s,
        ],
        axis=1,
    )
    m = k == 0
    s = np.sqrt(np.maximum(1.0 + R[m, 0, 0] - R[m, 1, 1] - R[m, 2, 2], _EPS)) * 2
    q[m] = np.stack(
        [
            0.25 * s,
            (R[m, 0, 1] + R[m, 1, 0]) / s,
            (R[m, 0, 2] + R[m, 2, 0]) / s,
            (R[m, 2, 1] - R[m, 1, 2]) / s,
        ],
        axis=1,
    )
    m = k == 1
    s = np.sqrt(np.maximum(1.0 + R[m, 1, 1] - R[m, 0, 0] - R[m, 2, 2], _EPS)) * 2
    q[m] = np.stack(
        [
            (R[m, 0, 1] + R[m, 1, 0]) / s,
            0.25 * s,
            (R[m, 1, 2] + R[m, 2, 1]) / s,
            (R[m, 0, 2] - R[m, 2, 0]) / s,
        ],
        axis=1,
    )
    m = k == 2
    s = np.sqrt(np.maximum(1.0 + R[m, 2, 2] - R[m, 0, 0] - R[m, 1, 1], _EPS)) * 2
    q[m] = np.stack(
        [
            (R[m, 0, 2] + R[m, 2, 0]) / s,
            (R[m, 1, 2] + R[m, 2, 1]) / s,
            0.25 * s,
            (R[m, 1, 0] - R[m, 0, 1]) / s,
        ],
        axis=1,
    )
    q = np.where(q[:, 3:4] < 0, -q, q)
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    return q[0] if single else q


def quat_slerp(q0: np.ndarray, q1: np.ndarray, s: np.ndarray) -> np.ndarray:
    """Spherical interpolation between (N, 4) quaternion arrays with fractions s (N,)."""
    q0 = np.asarray(q0, float)
    q1 = np.asarray(q1, float)
    s = np.asarray(s, float)[..., None]
    dot = np.sum(q0 * q1, axis=-1, keepdims=True)
    q1 = np.where(dot < 0, -q1, q1)
    dot = np.abs(dot)
    theta = np.arccos(np.clip(dot, -1.0, 1.0))
    small = theta < 1e-6
    sin_t = np.where(small, 1.0, np.sin(theta))
    w0 = np.where(small, 1.0 - s, np.sin((1.0 - s) * theta) / sin_t)
    w1 = np.where(small, s, np.sin(s * theta) / sin_t)
    q = w0 * q0 + w1 * q1
    return q / np.linalg.norm(q, axis=-1, keepdims=True)


# ---------------------------------------------------------------------------------------------------------------
# SE(3): poses (R, p), twists [w, u] (rotation first, like the error ordering)
# ---------------------------------------------------------------------------------------------------------------
def log_so3_one(R: np.ndarray) -> np.ndarray:
    """SO(3) log of one matrix in scalar arithmetic (`log_so3` is vectorised and slower on one matrix)."""
    c = 0.5 * (R[0, 0] + R[1, 1] + R[2, 2] - 1.0)
    if c < -0.99:  # near pi the axis needs the symmetric part
        return log_so3(R)
    v = 0.5 * np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    s = math.sqrt(v @ v)
    theta = math.atan2(s, c)
    return v * (theta / s if s > 1e-12 else 1.0 + theta * theta / 6.0)


def exp_so3_rodrigues(w: np.ndarray) -> np.ndarray:
    """Rodrigues' formula in matrix form for one (3,) vector (the odometry filter's arithmetic)."""
    th2 = float(w @ w)
    K = skew(w)
    if th2 < 1e-14:
        return np.eye(3) + K + 0.5 * K @ K
    th = math.sqrt(th2)
    return np.eye(3) + (math.sin(th) / th) * K + ((1.0 - math.cos(th)) / th2) * (K @ K)


def left_jacobian_so3(w: np.ndarray, inverse: bool = False) -> np.ndarray:
    """SO(3) left Jacobian V(w) (= Jr(-w)) or its inverse: the SE(3) translation map p = V u."""
    th2 = float(w @ w)
    K = skew(w)
    th = math.sqrt(th2)
    if inverse:
        c = (
            1.0 / 12.0 + th2 / 720.0
            if th < 1e-4
            else 1.0 / th2 - (1.0 + math.cos(th)) / (2.0 * th * math.sin(th))
        )
        return np.eye(3) - 0.5 * K + c * (K @ K)
    if th < 1e-4:
        a, b = 0.5 - th2 / 24.0, 1.0 / 6.0 - th2 / 120.0
    else:
        a, b = (1.0 - math.cos(th)) / th2, (th - math.sin(th)) / (th2 * th)
    return np.eye(3) + a * K + b * (K @ K)


def se3_log(R: np.ndarray, p: np.ndarray) -> np.ndarray:
    """Twist ``[w, u]`` with ``Exp([w, u]) = (R, p)`` (rotation first, like our error ordering)."""
    w = log_so3_one(R)
    return np.concatenate([w, left_jacobian_so3(w, inverse=True) @ p])


def se3_exp(xi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    w, u = xi[0:3], xi[3:6]
    return exp_so3_rodrigues(w), left_jacobian_so3(w) @ u


def se3_interpolate(
    R0: np.ndarray, p0: np.ndarray, R1: np.ndarray, p1: np.ndarray, s: float
) -> tuple[np.ndarray, np.ndarray]:
    """``T0 Exp(s Log(T0^-1 T1))`` (constant-twist interpolation)."""
    dR, dp = relative(R0, p0, R1, p1)
    Rs, ps = se3_exp(s * se3_log(dR, dp))
    return R0 @ Rs, p0 + R0 @ ps


def relative(R0: np.ndarray, p0: np.ndarray, R1: np.ndarray, p1: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``T0^-1 T1``."""
    return R0.T @ R1, R0.T @ (p1 - p0)


def compose(R: np.ndarray, p: np.ndarray, dR: np.ndarray, dp: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``T dT``."""
    return R @ dR, p + R @ dp


def compose_jacobians(R: np.ndarray, dR: np.ndarray, dp: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Error Jacobians of ``T_new = T dT`` w.r.t. the pose error of T and the increment noise ``[n_theta, n_p]``
    (``dR = dR_hat Exp(n_theta)``, ``dp = dp_hat + n_p``): ``dx_new = F dx + G n``."""
    F = np.eye(6)
    F[0:3, 0:3] = dR.T
    F[3:6, 0:3] = -R @ skew(dp)
    G = np.zeros((6, 6))
    G[0:3, 0:3] = np.eye(3)
    G[3:6, 3:6] = R
    return F, G
