"""Attitude sanity check for a carrier that moves in a plane (a planar trolley with antenna lever arms).

A ground robot's antennas stay at a fixed height over its motion plane: rotating a body-frame lever arm by the
pose attitude must keep it in that plane. If it swings out of the plane by much more than the carrier itself
leaves it, the attitude is read in the wrong convention (quaternion order, e.g. ``qw qx qy qz`` written where TUM
expects ``qx qy qz qw``) or the lever arms are given in another body frame. The check only reports (a note in the
conversion summary and the recording's source metadata); it does not rewrite the poses.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

PLANAR_RMS_M = 0.05  # the carrier leaves its best-fit plane by less than this (rms): planar motion
MIN_SPREAD_M = 0.5  # ... while spreading at least this far (rms) in the plane
MIN_LEVER_M = 0.05  # lever arms shorter than this cannot reveal the attitude
SWING_FACTOR = 3.0  # out-of-plane swing of a lever arm vs the carrier's own out-of-plane rms
MIN_SWING_M = 0.02


def _swing(q_xyzw: np.ndarray, levers: np.ndarray, n: np.ndarray) -> float:
    """Largest (over lever arms) std of the lever arm's component along the plane normal ``n``."""
    rot = Rotation.from_quat(q_xyzw)
    h = np.stack([rot.apply(lv) @ n for lv in levers], 1)  # (N, K)
    return float(h.std(0).max())


def planar_attitude_note(p: np.ndarray, q_xyzw: np.ndarray, levers: np.ndarray, source: str) -> str | None:
    """A one-line note when a planar carrier's lever arms leave its plane; ``None`` when consistent or not applicable.

    ``p`` (N, 3) positions, ``q_xyzw`` (N, 4) unit quaternions, ``levers`` (K, 3) body-frame antenna offsets.
    """
    levers = np.asarray(levers, float).reshape(-1, 3)
    levers = levers[np.linalg.norm(levers, axis=1) >= MIN_LEVER_M]
    if len(p) < 10 or len(levers) == 0:
        return None
    c = p - p.mean(0)
    _, s, vt = np.linalg.svd(c, full_matrices=False)
    rms = s / np.sqrt(len(p))
    if rms[2] > PLANAR_RMS_M or rms[1] < MIN_SPREAD_M:
        return None
    n = vt[2]
    swing = _swing(q_xyzw, levers, n)
    if swing <= max(SWING_FACTOR * rms[2], MIN_SWING_M):
        return None
    alt = _swing(q_xyzw[:, [1, 2, 3, 0]], levers, n)
    hint = (
        f"; read as qw qx qy qz they stay in it (±{alt:.3f} m)"
        if alt <= max(SWING_FACTOR * rms[2], MIN_SWING_M)
        else ""
    )
    return (
        f"{source}: the carrier moves in a plane (out-of-plane rms {rms[2]:.3f} m) but the antenna lever arms, "
        f"rotated by its attitude, swing ±{swing:.3f} m out of it{hint}: check the quaternion order (TUM is "
        "qx qy qz qw) and the frame the lever arms are given in"
    )
