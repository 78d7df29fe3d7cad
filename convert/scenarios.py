"""Simulator scenarios, one per class of real setup, so that tests do not lean on one dataset.

``uwbcal simulate --scenario NAME`` and, from Python::

    from uwbcal.convert.scenarios import SCENARIOS, scenario_config, simulate_scenario
    cfg = scenario_config("planar", seed=3, duration=60)      # a SimConfig; any SimConfig field can be overridden
    data = simulate_scenario("nlos", seed=1)                    # SimData (arrays, nothing written)
    simulate_to_file(cfg, "planar.mcap")                        # convert.simulator: the recording

Every scenario is ranges plus poses by default (``camera=False``, ``/odometry`` at 20 Hz with a *bounded* error,
as the real recordings of these classes come: SLAM with a map, GNSS/INS or surveyed ground truth; a Gauss-Markov
error of 5 cm / 0.5 deg with a 5 s correlation time, declared as ``odometry.error_model = "bounded"``;
``odometry_error="drift"`` gives dead-reckoning odometry drifting as the odometry filter models it;
``camera=True`` adds feature tracks for the MSCKF). The truth (``uwbcal.truth``) holds
the anchors, per-link offsets and NLOS rates (``links``) and the visibility windows. Scenarios:

- ``planar``: a ground trolley (`trajectory.planar_trajectory`, IMU at 0.3 m, yaw only) with 3 tags whose lever
  arms keep them in that plane, 8 anchors all at one height (1.5 m) around the 7 m x 5 m area: the anchor
  heights are not observable from the ranges (mirror ambiguity across the tag plane).
- ``large-area``: a campus drive (`trajectory.campus_trajectory`, 260 s, ~390 m x 125 m, 4 m/s) with 10 anchors
  spread over ~450 m at -2..11 m above the road, ranges only within 150 m (so 100+ m ranges are common), one
  anchor ranged only in a brief 12 s window and two only near the end of the run (beyond reach of the block).
- ``per-link``: the 3-D figure-8 with 3 tags and 6 anchors, beta 1, every (anchor, tag) link with its own offset
  drawn from U(0.1, 0.5) m (`link_gamma_offset`), anchor gamma 0.
- ``nlos``: the 3-D figure-8 with 6 anchors where the links of anchors 1 and 4 carry 30 % NLOS junk (positive
  Exp bias, mean 1.5 m) and the others none.

The classes of real recordings the evidence fit (`pipeline.uwb.evidence`) is built for, each with
beta 1 and the offsets real hardware has, their calibration declaring no offset or scale prior (as a converted
real recording does):

- ``climbing-drone``: a quadrotor climbing and descending on the spot (`trajectory.climb_trajectory`, 100 s,
  height 0.1-1.9 m, ~0.2 m horizontal extent) amid 4 anchors at the corners of a 2 m x 2 m square at 0.6-1.1 m,
  each with a constant offset of +0.2..+0.4 m (drawn per seed): the ranges fix each anchor's horizontal distance
  and height but hardly its bearing (a weak *horizontal* direction).
- ``far-cluster``: an outdoor ground platform (`trajectory.far_field_trajectory`, 60 s at 2.5 m/s, nearly planar)
  driving out to ~55 m from a 5 m x 2 m cluster of 4 anchors at 0.5-2 m and back past it ~11 m away, with
  RTK-like poses (bounded error 3 cm / 0.3 deg, 10 s correlation) and the ranges stamped 0.16-0.22 s late
  (``range_latency_s``, drawn per seed).
- ``clock-offset``: the 3-D figure-8 with 6 anchors around it, the ranges stamped 0.1-0.2 s late (drawn per seed).
- ``antenna-pattern``: a handheld rig carried around a room (`trajectory.handheld_trajectory`: a walk at up to
  1 m/s, the rig at 0.9-1.7 m, turning, panning and tilting) with 8 anchors outside its volume (4 corners and 4
  walls of a 9 m x 7 m room, at 0.3-2.7 m), every range biased by its anchor's antenna pattern
  b0 + b1 cos(az - phi) + b2 sin(el) (``antenna_pattern``: b0, b1 from U(0.05, 0.15) m, |b2| from U(0.05, 0.15) m
  with a random sign, phi uniform; drawn per seed).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, fields
from pathlib import Path

import numpy as np

from uwbcal.convert.simulator import SimConfig, SimData, simulate, simulate_to_file, stream
from uwbcal.pipeline.core.errors import InputError

ODOMETRY_RATE = 20.0

# planar trolley: 3 tags in the IMU's horizontal plane (IMU x is up), ~0.3 m apart
PLANAR_TAGS = [[0.0, -0.14, -0.07], [0.0, 0.14, -0.07], [0.0, 0.15, 0.2]]
PLANAR_ANCHORS = [
    [-4.5, 2.5, 1.5],
    [0.0, 2.6, 1.5],
    [4.4, 2.4, 1.5],
    [4.5, -1.2, 1.5],
    [4.3, -5.0, 1.5],
    [0.1, -5.1, 1.5],
    [-4.4, -4.9, 1.5],
    [-4.6, -1.3, 1.5],
]
# campus: the block spans x -2..190, y 0..124; the final leg runs east along y ~ 0 to x ~ 388
CAMPUS_ANCHORS = [
    [-20.0, -25.0, 3.0],
    [95.0, -30.0, 8.0],
    [200.0, 25.0, 1.0],
    [215.0, 140.0, 11.0],
    [95.0, 150.0, 5.0],
    [-30.0, 130.0, -2.0],
    [90.0, 60.0, 6.0],
    [330.0, -30.0, 4.0],  # ~140 m beyond the block's east edge: ranged from the final leg only
    [400.0, 35.0, 9.0],  # the far end: late
    [150.0, 95.0, 2.0],  # visible only in a brief window (12 s)
]
CAMPUS_BRIEF = {9: [(100.0, 112.0)]}
PER_LINK_TAGS = [[0.05, 0.0, 0.1], [0.05, 0.3, -0.1], [0.05, -0.3, -0.1]]
NLOS_ANCHORS = (1, 4)
# a quadrotor's constellation: the corners of a 2 m x 2 m square, 0.6-1.1 m high, the drone near its centre
DRONE_ANCHORS = [[-1.0, -1.0, 0.6], [1.0, -1.0, 0.9], [1.0, 1.0, 1.1], [-1.0, 1.0, 0.75]]
# a clustered outdoor constellation: 5 m x 2 m, 0.5-2 m high, the platform starting 4 m from its edge
CLUSTER_ANCHORS = [[-2.5, -1.0, 0.5], [2.5, -1.0, 1.5], [2.5, 1.0, 2.0], [-2.5, 1.0, 1.0]]
# a motion-capture room around the handheld rig's ~6 m x 4.5 m loop: 4 corners and 4 walls
ROOM_ANCHORS = [
    [-4.5, -3.5, 0.3],
    [4.5, -3.5, 2.6],
    [4.5, 3.5, 0.5],
    [-4.5, 3.5, 2.7],
    [0.2, -3.6, 1.8],
    [4.6, 0.1, 1.2],
    [-0.1, 3.6, 2.2],
    [-4.6, -0.2, 0.9],
]


@dataclass(frozen=True)
class Scenario:
    name: str
    summary: str
    build: Callable[[int], dict]  # seed -> SimConfig fields


def _planar(seed: int) -> dict:
    return dict(
        trajectory="planar",
        anchors=PLANAR_ANCHORS,
        tags=PLANAR_TAGS,
        uwb_rate=20.0,
        beta=1.0,
        gamma=0.2,
    )


def _large_area(seed: int) -> dict:
    return dict(
        trajectory="campus",
        anchors=CAMPUS_ANCHORS,
        uwb_rate=10.0,
        max_range=150.0,
        visibility=CAMPUS_BRIEF,
        beta=1.0,
        gamma=0.1,
    )


def _per_link(seed: int) -> dict:
    rng = stream(seed, "scenario/per-link")
    return dict(
        n_anchors=6,
        tags=PER_LINK_TAGS,
        beta=1.0,
        gamma=0.0,
        link_gamma_offset=rng.uniform(0.1, 0.5, (6, len(PER_LINK_TAGS))).tolist(),
    )


def _nlos(seed: int) -> dict:
    rate = np.zeros((6, 1))
    rate[list(NLOS_ANCHORS)] = 0.3
    return dict(n_anchors=6, beta=1.0, gamma=0.1, link_nlos_rate=rate.tolist(), nlos_bias_mean=1.5)


def _climbing_drone(seed: int) -> dict:
    rng = stream(seed, "scenario/climbing-drone")
    return dict(
        trajectory="climb",
        anchors=DRONE_ANCHORS,
        beta=1.0,
        gamma=rng.uniform(0.2, 0.4, len(DRONE_ANCHORS)).tolist(),
        declared_priors=False,
    )


def _far_cluster(seed: int) -> dict:
    rng = stream(seed, "scenario/far-cluster")
    return dict(
        trajectory="far-field",
        anchors=CLUSTER_ANCHORS,
        beta=1.0,
        gamma=rng.uniform(0.0, 0.3, len(CLUSTER_ANCHORS)).tolist(),
        range_latency_s=float(rng.uniform(0.16, 0.22)),
        odometry_sigma_p=0.03,
        odometry_sigma_theta_deg=0.3,
        odometry_correlation_s=10.0,
        declared_priors=False,
    )


def _clock_offset(seed: int) -> dict:
    rng = stream(seed, "scenario/clock-offset")
    return dict(
        n_anchors=6, beta=1.0, gamma=0.1, range_latency_s=float(rng.uniform(0.1, 0.2)), declared_priors=False
    )


def _antenna_pattern(seed: int) -> dict:
    rng = stream(seed, "scenario/antenna-pattern")
    n = len(ROOM_ANCHORS)
    b2 = rng.uniform(0.05, 0.15, n) * rng.choice([-1.0, 1.0], n)
    pattern = np.column_stack(
        [rng.uniform(0.05, 0.15, n), rng.uniform(0.05, 0.15, n), rng.uniform(0, 360, n), b2]
    )
    return dict(
        trajectory="handheld",
        anchors=ROOM_ANCHORS,
        beta=1.0,
        gamma=0.0,
        antenna_pattern=pattern.tolist(),
        declared_priors=False,
    )


SCENARIOS: dict[str, Scenario] = {
    s.name: s
    for s in (
        Scenario("planar", "ground trolley, 3 tags in a plane, 8 anchors at one height", _planar),
        Scenario(
            "large-area", "campus drive over ~400 m, 150 m range, anchors ranged late or briefly", _large_area
        ),
        Scenario("per-link", "3 tags x 6 anchors, an offset of 0.1-0.5 m per link", _per_link),
        Scenario("nlos", "6 anchors, the links of two carry 30 % positive NLOS junk", _nlos),
        Scenario(
            "climbing-drone",
            "a drone climbing on the spot amid 4 anchors of a 2 m square, offsets +0.2..+0.4 m",
            _climbing_drone,
        ),
        Scenario(
            "far-cluster",
            "outdoor drive out to ~55 m from a 5 m x 2 m cluster of 4 anchors, RTK-like poses, ranges ~0.2 s late",
            _far_cluster,
        ),
        Scenario(
            "clock-offset", "the 3-D figure-8 with 6 anchors, ranges stamped 0.1-0.2 s late", _clock_offset
        ),
        Scenario(
            "antenna-pattern",
            "a handheld rig in a room with 8 anchors, each with a direction-dependent range bias",
            _antenna_pattern,
        ),
    )
}


def scenario_config(name: str, *, seed: int = 0, **overrides) -> SimConfig:
    """The scenario's `SimConfig` (ranges + odometry, no camera unless ``camera=True``); ``overrides`` are any
    SimConfig fields (``duration``, ``odometry_rate``, ``uwb_rate``, ``link_gamma_offset``, ...)."""
    if name not in SCENARIOS:
        raise InputError(f"--scenario {name!r}: unknown; choose one of {', '.join(SCENARIOS)}")
    known = {f.name for f in fields(SimConfig)}
    bad = sorted(set(overrides) - known)
    if bad:
        raise InputError(f"scenario {name}: unknown setting(s) {', '.join(bad)}; SimConfig fields only")
    cfg = dict(camera=False, odometry_rate=ODOMETRY_RATE, odometry_error="bounded", seed=seed, scenario=name)
    cfg.update(SCENARIOS[name].build(seed))
    cfg.update(overrides)
    if not cfg["camera"]:  # no tracks: a sparse room (the automatic density probe costs ~20 s at 400 m)
        cfg.setdefault("landmark_density", 0.05)
    return SimConfig(**cfg)


def simulate_scenario(name: str, *, seed: int = 0, **overrides) -> SimData:
    """The scenario's streams as arrays (see `scenario_config`); a few seconds without the camera."""
    return simulate(scenario_config(name, seed=seed, **overrides))


def scenario_to_file(name: str, output: str | Path, *, seed: int = 0, **overrides) -> str:
    """Simulate the scenario into a recording; returns the simulator's summary."""
    cfg = scenario_config(name, seed=seed, **overrides)
    return f"scenario {name}: {SCENARIOS[name].summary}\n" + simulate_to_file(cfg, output)
