"""The range-to-pose clock offset (`pipeline.uwb.clock`): found where the ranges are stamped late or early, used
only when the evidence demands it."""

from dataclasses import replace

import numpy as np
import pytest

from uwbcal.pipeline.uwb.clock import estimate_clock
from uwbcal.pipeline.uwb.evidence import FitSpec, fit_anchor
from uwbcal.pipeline.uwb.window import InitWindow

ANCHORS = {1: np.array([5.0, 4.0, 2.0]), 2: np.array([-4.0, 6.0, 0.5]), 3: np.array([0.0, -6.0, 2.5])}


def _path(t):
    return np.c_[4 * np.cos(t / 4), 3 * np.sin(t / 3), 1.2 + 0.6 * np.sin(t / 2)]  # ~1.5 m/s


def _windows(latency_s: float, seed: int = 0):
    """windows_at(tau) of ranges measured at t and stamped t + latency (the poses are exact)."""
    rng = np.random.default_rng(seed)
    t = np.linspace(1.0, 119.0, 2400)
    d = {a: np.linalg.norm(_path(t) - p, axis=1) + rng.normal(0, 0.05, len(t)) for a, p in ANCHORS.items()}
    stamps = t + latency_s

    def at(tau: float) -> dict:
        xyz = _path(stamps + tau)
        n = len(t)
        ident = np.broadcast_to(np.eye(3), (n, 3, 3))
        return {
            a: InitWindow(
                d[a], np.zeros(3), ident, xyz, np.zeros((6, 6)), ((stamps + tau) * 1e9).astype(np.int64)
            )
            for a in ANCHORS
        }

    return at


@pytest.mark.parametrize("latency", [0.15, -0.08])
def test_clock_offset_found_and_used(latency):
    c = estimate_clock(_windows(latency), FitSpec(sigma_range=0.05))
    assert c.used and c.anchors == 3
    assert abs(c.offset_s + latency) < max(3 * c.sigma_s, 0.005), (c.offset_s, c.sigma_s)


def test_no_offset_is_not_used():
    c = estimate_clock(_windows(0.0, seed=1), FitSpec(sigma_range=0.05))
    assert not c.used and c.applied_s == 0.0
    assert abs(c.offset_s) < 0.02


def test_the_offsets_error_reaches_the_anchors_covariance():
    """``shift`` is each anchor's displacement per second of offset: an anchor fitted (`fit_anchor`, from
    scratch) with the ranges re-stamped 40 ms past the estimate moves by 40 ms times it; `position_cov` carries
    the offset's mean squared error about the applied one (the two models weighted by their evidence) through
    it."""
    at = _windows(0.15)
    c = estimate_clock(at, FitSpec(sigma_range=0.05))
    assert set(c.shift) == set(ANCHORS)
    for a in ANCHORS:
        w0, w1 = at(c.offset_s)[a], at(c.offset_s + 0.04)[a]
        p0, p1 = (fit_anchor(w.tag_xyz, w.d, t_ns=w.t_ns, spec=FitSpec(sigma_range=0.05)).p for w in (w0, w1))
        g = np.asarray(c.shift[a])
        assert np.linalg.norm(g) > 0.5  # ~1.5 m/s of carrier: tenths of a metre per second
        np.testing.assert_allclose(p1 - p0, 0.04 * g, atol=0.15 * np.linalg.norm(0.04 * g) + 1e-3)
        p1 = 1.0 / (1.0 + np.exp(-c.log_bayes))  # the offset's posterior probability (~1 here)
        expect = (1 - p1) * c.offset_s**2 + p1 * c.sigma_s**2
        np.testing.assert_allclose(c.position_cov(a), expect * np.outer(g, g), rtol=1e-9)
        doubtful = replace(c, used=False, log_bayes=0.0)  # even odds, left out: half its squared error
        expect = 0.5 * (c.sigma_s**2 + c.offset_s**2)
        np.testing.assert_allclose(doubtful.position_cov(a), expect * np.outer(g, g), rtol=1e-9)
    assert not np.any(c.position_cov("no such anchor"))
