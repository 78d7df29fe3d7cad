"""Planar-carrier attitude check (issue #14): lever arms rotated by a planar robot's attitude must stay in its
plane; a quaternion written in the wrong order (qw first) or a lever arm in another frame makes them swing out."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from uwbcal.convert.attitude_check import planar_attitude_note
from uwbcal.convert.tabular import convert_tabular

LEVERS = np.array([[-0.07, -0.14, 0.0], [0.2, 0.15, 0.0]])


def _track(n=400, z_down=True, seed=0):
    """A trolley on a loop at 0.96 m with yaw following the path; body z down (mocap rigid body) or up."""
    s = np.linspace(0, 2 * np.pi, n)
    p = np.c_[3 * np.cos(s), 2 * np.sin(s), 0.96 + np.random.default_rng(seed).normal(0, 0.003, n)]
    yaw = np.arctan2(2 * np.cos(s), -3 * np.sin(s))
    rot = Rotation.from_euler("z", yaw[:, None])
    if z_down:
        rot = rot * Rotation.from_rotvec([np.pi, 0, 0])
    return p, rot.as_quat()  # xyzw


@pytest.mark.parametrize("z_down", [False, True])
def test_consistent_attitude_is_quiet(z_down):
    p, q = _track(z_down=z_down)
    assert planar_attitude_note(p, q, LEVERS, "p.tum") is None


def test_wrong_quaternion_order_is_named():
    p, q = _track(z_down=True)
    wxyz = q[:, [3, 0, 1, 2]]  # what a "qw qx qy qz" file read as TUM's "qx qy qz qw" yields
    note = planar_attitude_note(p, wxyz, LEVERS, "p.tum")
    assert note is not None and note.startswith("p.tum:") and "qw qx qy qz" in note


def test_not_applicable():
    p, q = _track()
    wxyz = q[:, [3, 0, 1, 2]]
    assert planar_attitude_note(p, wxyz, np.zeros((2, 3)), "p.tum") is None  # no lever arm: nothing to check
    p3 = p.copy()
    p3[:, 2] += 0.5 * np.sin(np.linspace(0, 20, len(p)))  # 3-D motion: no verdict
    assert planar_attitude_note(p3, wxyz, LEVERS, "p.tum") is None


def test_note_reaches_the_conversion_summary(tmp_path):
    p, q = _track(z_down=True)
    t = 1_700_000_000 + np.arange(len(p)) * 0.1
    wxyz = q[:, [3, 0, 1, 2]]
    rows = [
        f"{a:.3f} {b[0]:.4f} {b[1]:.4f} {b[2]:.4f} " + " ".join(f"{v:.6f}" for v in c)
        for a, b, c in zip(t, p, wxyz, strict=True)
    ]
    (tmp_path / "p.tum").write_text("\n".join(rows) + "\n")
    ranges = [f"{int((t[k] + 0.05) * 1e9)},0,{k % 2},1,{4 + 0.01 * (k % 7)}" for k in range(len(t) - 1)]
    (tmp_path / "r.csv").write_text("stamp,tag,antenna,anchor,distance\n" + "\n".join(ranges) + "\n")
    (tmp_path / "a.yaml").write_text("antenna_offset: [0, 2, -0.07, -0.14, 0.0,  0.2, 0.15, 0.0]\n")
    text = convert_tabular(tmp_path / "p.tum", tmp_path / "r.csv", tmp_path / "o.mcap", tmp_path / "a.yaml")
    assert "swing" in text and "qw qx qy qz" in text


def test_cuhksz_mid_attitude_is_flagged(data_dir, tmp_path):
    """The planar trolley (surveyed/SOURCES.md): its mocap quaternions, read in TUM order, swing the 0.15 m lever
    arms about ±0.1 m out of the motion plane; read with w first they stay within millimetres."""
    src = data_dir / "surveyed" / "cuhksz_mid"
    if not src.is_dir():
        pytest.skip(f"{src} missing")
    text = convert_tabular(src / "poses.tum", src / "ranges.csv", tmp_path / "c.mcap", src / "antennas.yaml")
    assert "swing" in text and "qw qx qy qz" in text
