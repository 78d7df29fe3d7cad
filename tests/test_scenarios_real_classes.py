"""Issue #28 item 7: the evidence fit (`pipeline.uwb.evidence`, the default initialiser) on the simulated
classes of real setups it is built for (`convert.scenarios`: climbing-drone, far-cluster, clock-offset,
antenna-pattern). Plain pipeline runs, 60 s of data, seeds 1-3: every anchor right or "not determined" with its
reason, the range clock offset found (within 3 sigma) and used where the ranges are late and left out where they
are not, and the 3-dof anchor position NEES inside the two-sided 95 % chi2 bounds over the seeds. The measured
figures, also over seeds 4-6, are in docs/results/2026-12-07-calibration.md."""

from __future__ import annotations

import json

import numpy as np
import pytest
from test_scenarios_calibration import _inside

from uwbcal.convert.scenarios import scenario_to_file
from uwbcal.evaluate.evaluation import evaluate_stage
from uwbcal.pipeline.run.config import load_config
from uwbcal.pipeline.run.stages.pipeline import Pipeline

SEEDS = (1, 2, 3)
DURATION = 60.0


def _runs(tmp_path_factory, name: str) -> list[dict]:
    """Plain runs of scenario ``name`` on the evidence path over `SEEDS`: per run the metrics, the range clock
    (init.json ``range_clock``) and the recording's truth."""
    out = []
    for seed in SEEDS:
        d = tmp_path_factory.mktemp(f"{name}{seed}")
        rec = d / "r.mcap"
        scenario_to_file(name, rec, seed=seed, duration=DURATION)
        over = {"run": {"recording": str(rec), "log": False}}
        pipe = Pipeline(load_config(None, over), d / "run", evaluate_stage)
        pipe.run(progress=lambda *_: None)
        init = json.loads(pipe.dir.file("init.json").read_text())
        out.append(
            {
                "metrics": json.loads(pipe.dir.file("metrics.json").read_text()),
                "clock": init.get("range_clock") or {},
                "truth": pipe.ctx.reader.truth,
            }
        )
    return out


@pytest.fixture(scope="module")
def drone(tmp_path_factory):
    return _runs(tmp_path_factory, "climbing-drone")


@pytest.fixture(scope="module")
def far(tmp_path_factory):
    return _runs(tmp_path_factory, "far-cluster")


@pytest.fixture(scope="module")
def clock(tmp_path_factory):
    return _runs(tmp_path_factory, "clock-offset")


@pytest.fixture(scope="module")
def pattern(tmp_path_factory):
    return _runs(tmp_path_factory, "antenna-pattern")


def _right_or_not_determined(runs: list[dict], max_horizontal_m: float) -> int:
    """Every anchor within ``max_horizontal_m`` horizontally or not determined with its reason; returns how many
    were determined."""
    n = 0
    for run in runs:
        for a, v in run["metrics"]["anchors"].items():
            if not v["determined"]:
                assert v["reason"], a
                continue
            assert v["error_horizontal_m"] < max_horizontal_m, (a, v["error_horizontal_m"])
            n += 1
    return n


def _nees(runs: list[dict]) -> np.ndarray:
    """The 3-dof anchor position NEES (metrics.json, at the end of the run) of every determined anchor."""
    return np.array(
        [v["nees_position"] for r in runs for v in r["metrics"]["anchors"].values() if v["determined"]]
    )


def _clock_found(runs: list[dict]) -> None:
    """The offset used and within 3 sigma of the truth (ranges stamped ``range_latency_s`` late: the poses' time
    is the range stamp minus the latency, ``offset_s`` = -latency)."""
    for r in runs:
        c, late = r["clock"], r["truth"]["range_latency_s"]
        assert c["used"], c
        assert abs(c["offset_s"] + late) < 3.0 * c["sigma_s"], (c, late)


def _clock_not_used(runs: list[dict]) -> None:
    for r in runs:
        assert "range_latency_s" not in r["truth"]
        assert not r["clock"].get("used", False), r["clock"]


# ---------------------------------------------------------------------------------------------------------------
# climbing drone: the ranges fix each anchor's horizontal distance and height, hardly its bearing
# ---------------------------------------------------------------------------------------------------------------
@pytest.mark.xdist_group("real-classes-drone")
def test_climbing_drone_anchors_right_or_not_determined(drone):
    """The weak direction is horizontal (the bearing about the climb's axis): an anchor is right within the
    not-determined gate (1 m) or not determined (an unmodelled +0.2..+0.4 m offset trades against the radial
    distance); no clock (below)."""
    assert _right_or_not_determined(drone, 1.0) >= 1
    _clock_not_used(drone)


@pytest.mark.xdist_group("real-classes-drone")
def test_climbing_drone_nees_within_chi2_bounds(drone):
    """The covariance (the evidence-weighted mixture of every range model and basin, widened to the likelihood's
    intervals) is honest where the bearing is weak."""
    assert _inside(_nees(drone))


# ---------------------------------------------------------------------------------------------------------------
# far-field cluster, ranges ~0.2 s late
# ---------------------------------------------------------------------------------------------------------------
@pytest.mark.xdist_group("real-classes-far")
def test_far_cluster_anchors_right_and_clock_found(far):
    """Anchors right within 0.5 m or not determined, the clock found within its sigma (the anchors' offsets,
    U(0, 0.3) m, leak into the scan: the estimate lags the latency by a few tens of ms)."""
    _right_or_not_determined(far, 0.5)
    _clock_found(far)


@pytest.mark.xdist_group("real-classes-far")
def test_far_cluster_nees_within_chi2_bounds(far):
    """A near-planar drive (+-0.2 m of ground undulation) picks the side of the motion plane by a Bayes factor
    that a pose error shared over 10 s makes overconfident: each side is weighted by its evidence summed over the
    range models (`evidence.basin_evidence`), and the clock offset's error moves every anchor together
    (`clock.ClockOffset.position_cov`)."""
    assert _inside(_nees(far))


# ---------------------------------------------------------------------------------------------------------------
# clock offset on a good 3-D geometry
# ---------------------------------------------------------------------------------------------------------------
@pytest.mark.xdist_group("real-classes-clock")
def test_clock_offset_found_and_anchors_right(clock):
    """On a good 3-D geometry the offset is found within 3 sigma and every anchor is right within 0.3 m."""
    _clock_found(clock)
    assert _right_or_not_determined(clock, 0.3) == 6 * len(SEEDS)


@pytest.mark.xdist_group("real-classes-clock")
def test_clock_offset_nees_within_chi2_bounds(clock):
    """The anchors' covariance carries the clock offset's error besides the ranges' own."""
    assert _inside(_nees(clock))


# ---------------------------------------------------------------------------------------------------------------
# direction-dependent antenna bias, handheld rig in a room
# ---------------------------------------------------------------------------------------------------------------
@pytest.mark.xdist_group("real-classes-pattern")
def test_antenna_pattern_anchors_right_or_not_determined(pattern):
    """A direction-dependent bias mimics a displaced anchor: right within 0.5 m or not determined."""
    assert _right_or_not_determined(pattern, 0.5) >= 1


@pytest.mark.xdist_group("real-classes-pattern")
def test_antenna_pattern_clock_not_used(pattern):
    _clock_not_used(pattern)


@pytest.mark.xdist_group("real-classes-pattern")
def test_antenna_pattern_nees_within_chi2_bounds(pattern):
    """The pattern's effect is in the covariance (`evidence.declared_errors_cov`, the simulator declaring the pattern's
    size)."""
    assert _inside(_nees(pattern))
