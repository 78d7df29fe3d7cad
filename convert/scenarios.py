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


SCENARIOS: dict[str, Scenario] = {
    s.name: s
    for s in (
        Scenario("planar", "ground trolley, 3 tags in a plane, 8 anchors at one height", _planar),
        Scenario(
            "large-area", "campus drive over ~400 m, 150 m range, anchors ranged late or briefly", _large_area
        ),
        Scenario("per-link", "3 tags x 6 anchors, an offset of 0.1-0.5 m per link", _per_link),
        Scenario("nlos", "6 anchors, the links of two carry 30 % positive NLOS junk", _nlos),
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
