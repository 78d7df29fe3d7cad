"""Plots: valid PNGs written atomically (no temporary files left), from plain arrays."""

from __future__ import annotations

import numpy as np
import pytest

from uwbcal.evaluate import plots as pl_

PNG = b"\x89PNG\r\n\x1a\n"


def _ok(path):
    data = path.read_bytes()
    assert data[:8] == PNG and len(data) > 5000
    assert not [p for p in path.parent.iterdir() if p.name.endswith(".part")]


def test_all_plots(tmp_path):
    rng = np.random.default_rng(0)
    t = np.linspace(0, 30, 300)
    p = np.c_[5 * np.cos(0.2 * t), 5 * np.sin(0.2 * t), 0.1 * t]
    anchors = {"1": [10, 10, 10], "2": {"position": [-5, 3, 1]}}
    _ok(
        pl_.plot_trajectory(
            tmp_path / "traj.png",
            p,
            p + rng.normal(scale=0.1, size=p.shape),
            anchors,
            {
                "lsi": np.array([[10.5, 9, 11], [-5, 3.5, 1]]),
                "ri": np.array([[10.1, 10, 10.2], [-5.1, 3, 1]]),
            },
            np.array([[10, 10.05, 10], [-5, 3, 1.05]]),
            title="demo",
        )
    )
    sig = np.full((300, 3), 0.1)
    _ok(pl_.plot_position_error(tmp_path / "perr.png", t, rng.normal(scale=0.1, size=(300, 3)), sig))
    _ok(pl_.plot_anchor_error(tmp_path / "aerr1.png", t, rng.normal(size=(300, 3)) * 0.1, sig))
    _ok(pl_.plot_anchor_error(tmp_path / "aerr.png", t, {"1": np.ones((300, 3)) * 0.1}, {"1": sig}))
    _ok(
        pl_.plot_nees(
            tmp_path / "nees.png",
            t,
            {"orientation": rng.chisquare(3, 300), "position": rng.chisquare(3, 300)},
            bounds=(0.2, 9.3),
            dof=3,
        )
    )
    _ok(
        pl_.plot_ri_vs_lsi(
            tmp_path / "rivslsi.png",
            np.array([0.0, 0.1, 0.2, 0.3]),
            {m: np.abs(rng.normal(size=(4, 20))) * k for k, m in enumerate(["lsi", "ri", "ri-robust"], 1)},
        )
    )


def test_failed_plot_leaves_no_file(tmp_path):
    with pytest.raises(ValueError):
        pl_.plot_position_error(tmp_path / "x.png", np.arange(3.0), np.zeros((4, 3)))
    assert list(tmp_path.iterdir()) == []
