"""The range-to-pose clock offset (`pipeline.uwb.clock`): found where the ranges are stamped late or early, used
only when the evidence demands it."""

from dataclasses import replace

import numpy as np
import pytest

from uwbcal.pipeline.core.series import correlated_errors_covariance
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
    scratch, on the scan's ranges) with the ranges re-stamped 40 ms past the estimate moves by 40 ms times it; `position_cov` carries
    the offset's mean squared error about the applied one (the two models weighted by their evidence) through
    it."""
    at = _windows(0.15)
    c = estimate_clock(at, FitSpec(sigma_range=0.05))
    assert set(c.shift) == set(ANCHORS)
    for a in ANCHORS:
        w0, w1 = at(c.offset_s)[a], at(c.offset_s + 0.04)[a]
        spec = FitSpec(sigma_range=0.05, max_ranges=500)  # the ranges the scan uses
        p0, p1 = (fit_anchor(w.tag_xyz, w.d, t_ns=w.t_ns, spec=spec).p for w in (w0, w1))
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


FAR_ANCHORS = {1: (np.array([0.0, 11.0, 0.5]), 0.3), 2: (np.array([5.0, 12.0, 2.0]), 0.1)}
FAR_ANCHORS |= {3: (np.array([2.0, 9.5, 1.2]), 0.2), 4: (np.array([4.0, 10.5, 1.6]), 0.0)}


def _drive(t):
    """Out along x to 50 m and back on the far side of a cluster of anchors at 2.5 m/s (a far-field drive)."""
    s = np.minimum(t, 40.0 - t) * 2.5
    return np.c_[s, 10.0 * (1.0 + np.tanh((t - 20.0) / 1.5)), np.full_like(t, 0.3)]


def _far_windows(latency_s: float, seed: int = 0):
    """windows_at(tau) of the drive's ranges, each anchor with its range offset, stamped t + latency."""
    rng = np.random.default_rng(seed)
    t = np.linspace(0.5, 39.5, 780)
    d = {
        a: np.linalg.norm(_drive(t) - p, axis=1) + g + rng.normal(0, 0.05, len(t))
        for a, (p, g) in FAR_ANCHORS.items()
    }
    stamps = t + latency_s

    def at(tau: float) -> dict:
        xyz = _drive(stamps + tau)
        ident = np.broadcast_to(np.eye(3), (len(t), 3, 3))
        ns = ((stamps + tau) * 1e9).astype(np.int64)
        return {a: InitWindow(d[a], np.zeros(3), ident, xyz, np.zeros((6, 6)), ns) for a in FAR_ANCHORS}

    return at


@pytest.mark.parametrize("seed", [0, 1])
def test_a_late_far_field_drive_with_range_offsets(seed):
    """Driving straight away from an anchor, a late range and a long one look alike: the scan frees each anchor's
    offset, and measures each anchor's noise and model again at the first scan's offset (at 0 the ranges meet the
    wrong poses and look hundreds of times noisier than they are)."""
    c = estimate_clock(_far_windows(0.2, seed), FitSpec(sigma_range=0.05))
    assert c.used and c.anchors == 4
    assert abs(c.offset_s + 0.2) < max(3 * c.sigma_s, 0.004), (c.offset_s, c.sigma_s)
    assert c.sigma_s < 0.01, c.sigma_s


@pytest.mark.parametrize("tau_s", [2.0, None])
def test_correlated_errors_covariance_is_the_quadratic_form_of_the_declared_pose_errors(tau_s):
    """`correlated_errors_covariance` against the N x N covariance written out: Gauss-Markov
    exp(-|dt| / tau) sigma_k sigma_l (bounded errors), or the earlier error's variance (a random walk of growing
    variance), through gains of two outputs."""
    rng = np.random.default_rng(3)
    n = 60
    t = np.sort(rng.uniform(0, 20, n))
    v = rng.normal(size=(n, 2, 3))
    var = 0.01 * (1 + rng.uniform(size=n)) if tau_s else np.linspace(0.001, 0.05, n)
    if tau_s:
        K = np.exp(-np.abs(t[:, None] - t[None, :]) / tau_s) * np.sqrt(np.outer(var, var))
    else:
        K = var[np.minimum.outer(np.arange(n), np.arange(n))]
    np.testing.assert_allclose(
        correlated_errors_covariance(v, var, t, tau_s), np.einsum("kl,kia,lja->ij", K, v, v), rtol=1e-10
    )


@pytest.mark.parametrize("tau_s", [2.0, None])
def test_correlated_errors_covariance_of_full_pose_covariances(tau_s):
    """The same with a full covariance per stamp (6x6, as the refinement's error map of a window's poses has):
    Gauss-Markov S_k S_l exp(-|dt| / tau) with S_k the symmetric square root, or the random walk's earlier
    covariance (growing by PSD increments)."""
    rng = np.random.default_rng(4)
    n, d = 40, 6
    t = np.sort(rng.uniform(0, 20, n))
    v = rng.normal(size=(n, 5, d))
    steps = np.array([0.01 * M @ M.T for M in rng.normal(size=(n, d, d))])
    P = np.cumsum(steps, axis=0)
    w, U = np.linalg.eigh(P)
    S = (U * np.sqrt(w)[:, None, :]) @ np.swapaxes(U, 1, 2)
    idx = np.arange(n)
    if tau_s:
        rho = np.exp(-np.abs(t[:, None] - t[None, :]) / tau_s)
        K = rho[:, :, None, None] * np.einsum("kab,lcb->klac", S, S)
    else:
        K = P[np.minimum.outer(idx, idx)]
    want = np.einsum("kia,klab,ljb->ij", v, K, v)
    np.testing.assert_allclose(correlated_errors_covariance(v, P, t, tau_s), want, rtol=1e-9)
