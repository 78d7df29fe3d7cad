"""Simulator scenarios: each produces the geometry it promises (coplanarity, visibility, per-link offsets, NLOS)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.stats import binom
from typer.testing import CliRunner

from uwbcal.cli import app
from uwbcal.convert.recording import RecordingReader
from uwbcal.convert.scenarios import CAMPUS_BRIEF, NLOS_ANCHORS, SCENARIOS, scenario_config, simulate_scenario
from uwbcal.convert.simulator import NS, antenna_bias, rel_seconds
from uwbcal.pipeline.core.errors import InputError


def _tag_positions(data) -> np.ndarray:
    """The tags when each range was measured (its stamp minus the latency)."""
    r, cfg = data.ranges, data.config
    s = data.trajectory.evaluate(rel_seconds(data.trajectory, r.t_ns - round(cfg.range_latency_s * NS)))
    arms = cfg.lever_arms()[r.tag - cfg.tag_id]
    return s.p + np.einsum("nij,nj->ni", s.R, arms)


def _check_model(data) -> np.ndarray:
    """The ranges follow d = beta (|tag - anchor| + n) + gamma_link (+ NLOS); returns d - beta |.| - gamma_link."""
    r = data.ranges
    true = np.linalg.norm(_tag_positions(data) - data.anchors[r.anchor], axis=1)
    np.testing.assert_allclose(true, r.true_distance, atol=1e-9)
    gamma = {(lk["anchor"], lk["tag"]): lk["gamma"] for lk in data.metadata["uwbcal.truth"]["links"]}
    g = np.array([gamma[(a, t)] for a, t in zip(r.anchor.tolist(), r.tag.tolist(), strict=True)])
    beta = data.beta[r.anchor]
    return r.distance - beta * true - g


def test_planar_tags_and_anchors_coplanar():
    data = simulate_scenario("planar", duration=30.0)
    tags = _tag_positions(data)
    assert np.ptp(tags[:, 2]) < 1e-6  # every tag stays in one horizontal plane
    assert np.ptp(data.anchors[:, 2]) == 0.0 and abs(data.anchors[0, 2] - tags[0, 2]) > 0.5
    assert len(np.unique(data.ranges.tag)) == 3 and len(data.anchors) == 8
    # the mirror anchor (reflected across the tag plane) explains every range equally well
    mirror = data.anchors.copy()
    mirror[:, 2] = 2 * tags[0, 2] - mirror[:, 2]
    d_mirror = np.linalg.norm(tags - mirror[data.ranges.anchor], axis=1)
    np.testing.assert_allclose(d_mirror, data.ranges.true_distance, atol=1e-6)
    res = _check_model(data)
    assert abs(res.std() - data.config.sigma_range) < 0.01
    cfg = scenario_config("planar")
    assert cfg.camera is False and cfg.odometry_rate and data.odometry is not None


def test_large_area_visibility_windows_and_long_ranges():
    data = simulate_scenario("large-area")
    r, cfg = data.ranges, data.config
    t = rel_seconds(data.trajectory, r.t_ns)
    T = t.max()
    assert r.true_distance.max() <= cfg.max_range and np.mean(r.true_distance > 100.0) > 0.1
    span = {
        a: (t[r.anchor == a].min(), t[r.anchor == a].max(), int((r.anchor == a).sum())) for a in range(10)
    }
    ((brief, (lo, hi)),) = ((a, w[0]) for a, w in CAMPUS_BRIEF.items())
    assert lo <= span[brief][0] and span[brief][1] <= hi and span[brief][2] > 50  # brief: only in its window
    late = [a for a, (first, _, _) in span.items() if first > 0.75 * T]
    assert late, span  # at least one anchor first ranged in the last quarter
    assert all(n > 0 for _, _, n in span.values())
    heights = data.anchors[:, 2]
    assert (
        heights.min() < 0 < 10 < heights.max() and np.ptp(data.groundtruth.p[:, 2]) < 1.0
    )  # near-planar road
    assert abs(_check_model(data).std() - cfg.sigma_range) < 0.01
    truth = data.metadata["uwbcal.truth"]
    assert truth["visibility"] == {str(brief): [[lo, hi]]} and truth["scenario"] == "large-area"


def test_per_link_offsets():
    data = simulate_scenario("per-link", duration=40.0, seed=2)
    links = data.metadata["uwbcal.truth"]["links"]
    assert len(links) == 6 * 3
    off = np.array([lk["offset"] for lk in links])
    assert np.all((off >= 0.1) & (off <= 0.5)) and len(np.unique(off.round(6))) == len(off)
    res = _check_model(data)  # the residual after each link's own gamma is plain noise ...
    sigma = data.config.sigma_range
    for lk in links:
        sel = (data.ranges.anchor == lk["anchor"]) & (data.ranges.tag == lk["tag"])
        assert sel.sum() == lk["ranges"] > 100
        assert abs(res[sel].mean()) < 4 * sigma / np.sqrt(sel.sum())
    # ... while one gamma per anchor leaves the tags' offsets apart by more than the noise
    per_anchor = np.array([[lk["offset"] for lk in links if lk["anchor"] == a] for a in range(6)])
    assert np.ptp(per_anchor, axis=1).min() > 0.0 and np.ptp(per_anchor, axis=1).max() > 0.1
    other = simulate_scenario("per-link", duration=40.0, seed=3).metadata["uwbcal.truth"]["links"]
    assert [lk["offset"] for lk in other] != off.tolist()  # drawn per seed


def test_nlos_fraction_on_some_links():
    data = simulate_scenario("nlos", duration=60.0)
    r = data.ranges
    for a in range(6):
        sel = r.anchor == a
        k, n = int(r.nlos[sel].sum()), int(sel.sum())
        if a in NLOS_ANCHORS:
            lo, hi = binom.ppf([0.0005, 0.9995], n, 0.3)
            assert lo <= k <= hi
        else:
            assert k == 0
    res = _check_model(data)
    assert abs(res[~r.nlos].std() - data.config.sigma_range) < 0.01
    junk = res[r.nlos]
    assert np.mean(junk > 0) > 0.9 and abs(junk.mean() - 1.5) < 0.3  # positive, mean ~ nlos_bias_mean
    truth = {(lk["anchor"]): lk for lk in data.metadata["uwbcal.truth"]["links"]}
    assert truth[1]["nlos_rate"] == 0.3 and truth[0]["nlos_rate"] == 0.0 and truth[1]["nlos_count"] > 0


def test_cli_scenario_recording(tmp_path):
    out = tmp_path / "s.mcap"
    res = CliRunner().invoke(
        app, ["simulate", "--scenario", "per-link", "--duration", "8", "--seed", "5", "-o", str(out)]
    )
    assert res.exit_code == 0, res.output
    rec = RecordingReader(out)
    truth, cal = rec.truth, rec.calibration
    assert truth["scenario"] == "per-link" and truth["kind"] == "simulated" and len(truth["links"]) == 18
    assert sorted(cal["uwb"]["tags"]) == ["1", "2", "3"] and "cameras" not in cal
    r = rec.read_ranges()
    assert set(np.unique(r.tag).tolist()) == {1, 2, 3} and len(rec.read_odometry().t_ns) > 100
    expect = scenario_config("per-link", seed=5).link_gamma_offset
    got = [[lk["offset"] for lk in truth["links"] if lk["anchor"] == a] for a in range(6)]
    np.testing.assert_allclose(got, expect)
    bad = CliRunner().invoke(app, ["simulate", "--scenario", "planar", "--anchors", "3", "-o", str(out)])
    assert bad.exit_code == 2 and "fixes its anchors" in bad.output


def test_scenario_errors():
    with pytest.raises(
        InputError, match="unknown; choose one of planar, large-area, per-link, nlos, climbing-drone"
    ):
        scenario_config("hilly")
    with pytest.raises(InputError, match="unknown setting"):
        scenario_config("nlos", colour="red")
    assert set(SCENARIOS) == {
        "planar",
        "large-area",
        "per-link",
        "nlos",
        "climbing-drone",
        "far-cluster",
        "clock-offset",
        "antenna-pattern",
    }


def test_climbing_drone_climbs_on_the_spot():
    data = simulate_scenario("climbing-drone", duration=60.0, seed=2)
    tags, p = _tag_positions(data), data.groundtruth.p
    assert np.ptp(p[:, 0]) < 0.3 and np.ptp(p[:, 1]) < 0.3 and p[:, 2].min() < 0.2 and p[:, 2].max() > 1.8
    a = data.anchors
    assert np.allclose(np.abs(a[:, :2]), 1.0) and 0.6 <= a[:, 2].min() and a[:, 2].max() <= 1.1
    g = data.gamma
    assert np.all((g >= 0.2) & (g <= 0.4)) and len(np.unique(g)) == 4 and np.all(data.beta == 1.0)
    res = _check_model(data)
    assert abs(res.std() - data.config.sigma_range) < 0.01 and abs(res.mean()) < 0.01
    assert np.all(np.abs(tags[:, :2]) < 0.5)  # well inside the square


def test_far_cluster_latency_on_the_range_stamps_only():
    data = simulate_scenario("far-cluster", duration=60.0, seed=1)
    cfg, r = data.config, data.ranges
    assert 0.16 <= cfg.range_latency_s <= 0.22
    assert data.metadata["uwbcal.truth"]["range_latency_s"] == cfg.range_latency_s
    res = _check_model(data)  # the model holds at the measurement times (stamp - latency) ...
    assert abs(res.std() - cfg.sigma_range) < 0.01
    late = np.linalg.norm(
        data.trajectory.evaluate(rel_seconds(data.trajectory, r.t_ns)).p - data.anchors[r.anchor], axis=1
    )
    assert np.std(r.distance - late - data.gamma[r.anchor]) > 2 * cfg.sigma_range  # ... not at the stamps
    assert r.t_ns.max() <= data.groundtruth.t_ns[-1] and r.true_distance.max() > 50.0
    np.testing.assert_array_equal(data.odometry.t_ns, data.groundtruth.t_ns[::10])  # poses on time
    assert np.ptp(data.anchors[:, 0]) == 5.0 and np.ptp(data.anchors[:, 1]) == 2.0


def test_clock_offset_and_antenna_pattern():
    clock = simulate_scenario("clock-offset", duration=30.0, seed=3)
    assert 0.1 <= clock.config.range_latency_s <= 0.2 and abs(_check_model(clock).std() - 0.1) < 0.01
    data = simulate_scenario("antenna-pattern", duration=60.0, seed=1)
    pat = np.asarray(data.config.antenna_pattern)
    assert pat.shape == (8, 4) and np.all((pat[:, :2] >= 0.05) & (pat[:, :2] <= 0.15))
    assert np.all((np.abs(pat[:, 3]) >= 0.05) & (np.abs(pat[:, 3]) <= 0.15))
    assert data.metadata["uwbcal.truth"]["antenna_pattern"] == pat.tolist()
    r, tags = data.ranges, _tag_positions(data)
    res = _check_model(data)
    bias = antenna_bias(pat[r.anchor], tags - data.anchors[r.anchor])
    assert abs((res - bias).std() - data.config.sigma_range) < 0.01  # the pattern is all that is added
    for a in range(8):  # and it varies with the direction of arrival
        assert np.ptp(bias[r.anchor == a]) > 0.02
    lo, hi = tags.min(axis=0), tags.max(axis=0)
    outside = (data.anchors[:, :2] < lo[:2]) | (data.anchors[:, :2] > hi[:2])
    assert np.all(outside.any(axis=1))
