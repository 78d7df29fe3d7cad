"""Real recordings with surveyed anchors, one per class of setup, converted as a user would (`convert tabular`) and
run with no config: every anchor with 200 ranges or more estimated or "not determined" with a reason; the
horizontal error of the estimated anchors at most the naive reference's (per anchor, the position alone by a
soft-L1 fit from the same ground-truth tag positions) + 0.02 m; no anchor more than 0.3 m off with a 3-dof position
NEES above 16.27 (chi2 99.9 %); honest heights (the z error within 2 sigma where the height is flagged). The same
criteria hold on each half in time of the smaller folders: recordings of the same setups never seen whole."""

import csv
import json

import numpy as np
import pytest

from uwbcal.convert.tabular import convert_tabular
from uwbcal.evaluate.evaluation import evaluate_stage
from uwbcal.pipeline.run.config import load_config
from uwbcal.pipeline.run.stages.pipeline import Pipeline

from support import naive_anchor, surveyed_half, surveyed_links

CHI2_3_999 = 16.27


def _run(data_dir, tmp_path, name, src=None):
    src = src or data_dir / "surveyed" / name
    if not src.is_dir():
        pytest.skip(f"{src} missing")
    rec = tmp_path / f"{name}.mcap"
    convert_tabular(src / "poses.tum", src / "ranges.csv", rec, src / "antennas.yaml")
    cfg = load_config(None, {"run": {"recording": str(rec), "log": False}})
    pipe = Pipeline(cfg, tmp_path / "run", evaluator=evaluate_stage)
    pipe.run(progress=lambda *_: None)
    truth = {
        r["anchor"]: np.array([float(r[k]) for k in "xyz"])
        for r in csv.DictReader(open(src / "anchors_truth.csv"))
    }
    counts: dict[str, int] = {}
    with open(src / "ranges.csv") as f:
        for r in csv.DictReader(f):
            if r["distance"] not in ("", "nan", "NaN") and float(r["distance"]) > 0:
                counts[r["anchor"]] = counts.get(r["anchor"], 0) + 1
    rows = [r for r in csv.DictReader(open(pipe.dir.file("anchors.csv"))) if r["stage"] == "refine"]
    states = json.loads(pipe.dir.file("anchor_states.json").read_text())
    metrics = json.loads(pipe.dir.file("metrics.json").read_text())
    return pipe, truth, counts, rows, states, metrics


def _naive(folder, anchors) -> np.ndarray:
    """The naive reference's horizontal errors over ``anchors``."""
    links, truth = surveyed_links(folder)
    out = []
    for a in anchors:
        xyz, d = links[a][0], links[a][1]
        out.append(float(np.hypot(*(naive_anchor(xyz[d > 0], d[d > 0]) - truth[a])[:2])))
    return np.array(out)


def _check(truth, counts, rows, states, metrics, min_ranges=200):
    undetermined = {a: v["reason"] for a, v in metrics["anchors"].items() if not v.get("determined", True)}
    est = {r["anchor"]: r for r in rows if r["x"] != ""}
    for a, n in counts.items():
        if n >= min_ranges:
            assert a in est or undetermined.get(a), f"anchor {a} ({n} ranges) neither estimated nor explained"
    eh, out = [], {}
    for a, r in est.items():
        e = np.array([float(r[k]) for k in "xyz"]) - truth[a]
        eh.append(float(np.hypot(e[0], e[1])))
        verdict = metrics["anchors"][a].get("verdict", {})
        sz = float(np.sqrt(np.asarray(states[a]["P"])[2][2]))
        if not verdict.get("height_observable", True):  # an open height: its sigma covers it (99.7 %)
            assert abs(e[2]) <= 3 * sz, (a, e[2], sz)
        out[a] = (round(eh[-1], 3), round(float(e[2]), 3), round(sz, 3))
        if np.linalg.norm(e) > 0.3:  # far off only where it says it is uncertain
            nees = float(e @ np.linalg.solve(np.asarray(states[a]["P"])[:3, :3], e))
            assert nees <= CHI2_3_999, (a, e, nees)
    print(out, undetermined)
    return np.array(eh), list(est)


def _at_most_naive(folder, name, eh, anchors):
    naive = _naive(folder, anchors)
    print(name, "ours", np.round(eh, 3), "naive", np.round(naive, 3))
    assert eh.mean() <= naive.mean() + 0.02, (eh.mean(), naive.mean())


@pytest.mark.data
@pytest.mark.parametrize(
    "name",
    ["starloc_loop-2d_s5", "inrol_filtering_state_estimation2", "rcv_seq4", "hanyang_nlos_a_case2"],
)
def test_surveyed_setups_at_least_as_good_as_the_naive_fit(data_dir, tmp_path, name):
    """A handheld rig (planar loop; an antenna pattern), a drone climbing on the spot, an outdoor RTK run with a
    clustered constellation and late ranges."""
    _, truth, counts, rows, states, metrics = _run(data_dir, tmp_path, name)
    eh, anchors = _check(truth, counts, rows, states, metrics)
    assert len(eh) >= 3
    _at_most_naive(data_dir / "surveyed" / name, name, eh, anchors)


@pytest.mark.data
@pytest.mark.parametrize("half", [0, 1])
@pytest.mark.parametrize(
    "name",
    [
        "starloc_loop-2d_s5",
        "inrol_filtering_state_estimation2",
        "rcv_seq4",
        "hanyang_nlos_a_case2",
        "cuhksz_mid",
        "mcd_ntu_night_13_tag0",
        "mcd_ntu_night_13_tag1",
    ],
)
def test_each_half_of_a_surveyed_recording(data_dir, tmp_path, name, half):
    """Generality on recordings not developed on: each half in time of a folder is another recording of its
    setup (less motion, other anchors' geometry), held to the same criteria. A half of the campus drive passes few
    of its far anchors: those it does not pin down are not determined, with their reasons (`_check`)."""
    src = data_dir / "surveyed" / name
    if not src.is_dir():
        pytest.skip(f"{src} missing")
    part = surveyed_half(src, half, tmp_path / "half")
    _, truth, counts, rows, states, metrics = _run(data_dir, tmp_path, name, part)
    eh, anchors = _check(truth, counts, rows, states, metrics)
    assert len(eh) >= (1 if name.startswith("mcd") else 2)
    _at_most_naive(part, f"{name} half {half}", eh, anchors)


@pytest.mark.data
@pytest.mark.parametrize("name", ["mcd_ntu_night_13_tag0", "mcd_ntu_night_13_tag1"])
def test_campus_vehicle_late_far_anchors(data_dir, tmp_path, name):
    pipe, truth, counts, rows, states, metrics = _run(data_dir, tmp_path, name)
    assert 'schedule = "per-anchor"' in pipe.dir.file("config.toml").read_text()
    eh, anchors = _check(truth, counts, rows, states, metrics)
    assert len(eh) >= 3 and eh.mean() <= 0.5, eh
    _at_most_naive(data_dir / "surveyed" / name, name, eh, anchors)


@pytest.fixture(scope="module")
def trolley(data_dir, tmp_path_factory):
    """cuhksz_mid run once for the module: (pipe, truth, counts, rows, states, metrics, horizontal errors)."""
    pipe, truth, counts, rows, states, metrics = _run(
        data_dir, tmp_path_factory.mktemp("cuhksz"), "cuhksz_mid"
    )
    eh, anchors = _check(truth, counts, rows, states, metrics)
    _at_most_naive(data_dir / "surveyed" / "cuhksz_mid", "cuhksz_mid", eh, anchors)
    return pipe, truth, rows, states, metrics, eh


@pytest.mark.data
@pytest.mark.xdist_group("trolley")
def test_planar_trolley_lever_arms_and_heights(trolley):
    """cuhksz_mid: 8 coplanar anchors ranged from a turning trolley with 3 tags. Plain run: the planar lever-arm
    model enters by the evidence rule (its mocap attitude spins about an in-plane axis, the arms are then estimated
    in the plane), every anchor is estimated, at most the naive fit's horizontal error + 0.02 m, max <= 0.20 m, the
    height flagged unobservable on every anchor with a sigma that covers its z error."""
    pipe, truth, rows, states, metrics, eh = trolley
    cfg = pipe.dir.file("config.toml").read_text()
    assert 'lever_arms = "planar"' in cfg
    init = json.loads(pipe.dir.file("init.json").read_text())
    arms = init["lever_arms"]
    assert arms["residual_sigma_m"] < 0.6 * arms["residual_sigma_given_m"], arms
    for lk in arms["links"].values():  # rigid rig: the arms' lengths stay within a few cm of the given ones
        assert abs(lk["length_m"] - lk["given_length_m"]) < 0.06, lk
    assert len(eh) == 8 and eh.max() <= 0.20, eh
    for a, r in ((r["anchor"], r) for r in rows):
        assert metrics["anchors"][a]["verdict"]["height_observable"] is False
        ez = float(r["z"]) - truth[a][2]
        assert abs(ez) <= float(np.sqrt(np.asarray(states[a]["P"])[2][2])), (a, ez)


@pytest.mark.data
@pytest.mark.xdist_group("trolley")
def test_planar_trolley_horizontal_goal(trolley):
    """Measured: horizontal mean 0.076 m, max 0.150 m (0.104 / 0.155 m before the installation's shared link
    offsets entered the joint fit as a prior: the anchors ranged from inside the ring traded offset against
    distance and sat 0.09-0.15 m outward; naive 0.157 / 0.249 m)."""
    eh = trolley[-1]
    assert eh.mean() <= 0.10, eh
