"""Issue #14 on the simulated setup classes (`convert.scenarios`), plain pipeline runs with no config: anchors
right or honestly "not determined", heights flagged where the motion is planar, per-link offsets recovered."""

from __future__ import annotations

import json

import numpy as np
import pytest

from uwbcal.convert.recording import RecordingReader
from uwbcal.convert.scenarios import PLANAR_ANCHORS, scenario_to_file
from uwbcal.evaluate.evaluation import evaluate_stage
from uwbcal.pipeline.run.config import load_config
from uwbcal.pipeline.run.stages.pipeline import Pipeline


def _run(tmp_path, name, schedule=None, **kw):
    rec = tmp_path / f"{name}.mcap"
    scenario_to_file(name, rec, seed=1, **kw)
    run = {"recording": str(rec), "log": False} | ({"schedule": schedule} if schedule else {})
    cfg = load_config(None, {"run": run})
    pipe = Pipeline(cfg, tmp_path / "run", evaluator=evaluate_stage)
    pipe.run(progress=lambda *_: None)
    metrics = json.loads(pipe.dir.file("metrics.json").read_text())
    init = json.loads(pipe.dir.file("init.json").read_text())
    return pipe, metrics, init["methods"][init["chosen"]]


def test_planar_height_flagged_and_honest(tmp_path):
    # 20 s of a drifting odometry: the first third pins few anchors down, so each joins on its own data
    pipe, m, init = _run(tmp_path, "planar", schedule="per-anchor", duration=20.0)
    anchors = m["anchors"]
    assert len(anchors) == 8 and sum(v["determined"] for v in anchors.values()) >= 4
    for a, v in anchors.items():
        if not v["determined"]:  # honestly: with its reason
            assert v["reason"], a
            continue
        assert not v["verdict"]["model"]["model"].startswith(
            "link"
        )  # 3 tags, one offset: no spurious per-link
        assert v["z_error_sigmas"] <= 2.0, (a, v["z_error_sigmas"])
        assert v["error_horizontal_m"] < 1.0
    assert "schedule" in pipe.dir.file("config.toml").read_text()


def test_planar_nees_within_chi2_bounds(tmp_path):
    """Planar ground robot, CI-sized: the trolley with its 3 in-plane tags and 4 of the scenario's coplanar
    anchors (one at each corner), ranged at 5 Hz per link for 60 s, plain runs over 3 fixed seeds. Every anchor
    right or not determined with its reason, its height flagged unobservable with an honest sigma_z (|z error|
    <= sigma_z), and the horizontal (2-dof) anchor NEES inside the two-sided 95 % chi2 bounds (measured: 1.05 in
    [1.03, 3.28] over 12 anchors; 1.00 with the direction jackknife the declared errors' floor replaced:
    conservative on this class)."""
    corners = [PLANAR_ANCHORS[i] for i in (0, 2, 4, 6)]
    nees_h = []
    for seed in (1, 2, 3):
        d = tmp_path / f"planar{seed}"
        d.mkdir()
        rec = d / "r.mcap"
        scenario_to_file("planar", rec, seed=seed, duration=60.0, uwb_rate=5.0, anchors=corners)
        pipe = Pipeline(
            load_config(None, {"run": {"recording": str(rec), "log": False}}), d / "run", evaluate_stage
        )
        pipe.run(progress=lambda *_: None)
        m = json.loads(pipe.dir.file("metrics.json").read_text())
        states = json.loads(pipe.dir.file("anchor_states.json").read_text())
        init = json.loads(pipe.dir.file("init.json").read_text())
        truth = pipe.ctx.reader.truth["anchors"]
        _right_or_not_determined([m], 1.0)
        for a, v in m["anchors"].items():
            if not v["determined"]:
                continue
            assert v["verdict"]["height_observable"] is False, a
            assert v["z_error_sigmas"] <= 1.0, (a, v["z_error_sigmas"])
            x, P = np.asarray(states[a]["x"], float), np.asarray(states[a]["P"], float)
            # the range updates leave an unobservable height alone: as uncertain after refinement as at init
            assert P[2, 2] == pytest.approx(init["methods"][init["chosen"]][a]["cov"][2][2], rel=1e-9), a
            e = x[:2] - np.asarray(truth[a]["position"], float)[:2]
            nees_h.append(float(e @ np.linalg.solve(P[:2, :2], e)))
    assert len(nees_h) >= 9 and _inside(np.array(nees_h), dof=2)


def test_per_link_offsets_recovered(tmp_path):
    pipe, m, init = _run(tmp_path, "per-link", duration=60.0)
    truth = RecordingReader(pipe.config.run.recording).truth
    off = {}
    for lk in truth["links"]:
        off.setdefault(str(lk["anchor"]), {})[lk["tag"]] = lk["gamma"]
    n_checked = 0
    for a, r in init.items():
        if r["status"] not in ("ok", "warning") or "link_offsets_m" not in r:
            continue
        est = {int(k) // 256: v for k, v in r["link_offsets_m"].items()}
        t = off[a]
        mean = np.mean(list(t.values()))
        for tag, v in est.items():
            assert abs(v - (t[tag] - mean)) < 0.05, (a, tag, v, t[tag] - mean)
        n_checked += 1
    assert n_checked >= 1  # per-link where the data support it (auto)
    assert m["anchor_truth"]["error_horizontal_m"]["mean"] < 0.4


@pytest.mark.parametrize("name", ["nlos"])
def test_anchors_right_or_not_determined(tmp_path, name):
    pipe, m, init = _run(tmp_path, name, duration=60.0)
    for a, v in m["anchors"].items():
        if not v["determined"]:
            assert v["reason"], a
            continue
        assert v["error_horizontal_m"] < 1.0, (a, v["error_horizontal_m"])
    assert m["anchor_truth"]["error_horizontal_m"]["mean"] < 0.5


def _monte_carlo(tmp_path, name, seeds, uwb=None, **kw):
    """Plain runs of scenario ``name`` over fixed seeds. Returns (join NEES, final NEES, metrics per run): the
    3-dof anchor position NEES of every anchor at the moment it joins the filter (`add_initialised_anchors`:
    the initialiser's estimate with the covariance and cross-covariances refinement starts from; anchors
    joining later are left out) and at the end of the run (metrics.json ``anchors.<id>.nees_position``)."""
    from uwbcal.pipeline.uwb.updater import add_initialised_anchors, anchor_var

    joined, final, runs = [], [], []
    for seed in seeds:
        d = tmp_path / f"{name}{seed}"
        d.mkdir()
        rec = d / "r.mcap"
        scenario_to_file(name, rec, seed=seed, **kw)
        over = {"run": {"recording": str(rec), "log": False}} | ({"uwb": uwb} if uwb else {})
        pipe = Pipeline(load_config(None, over), d / "run", evaluate_stage)
        pipe.run(progress=lambda *_: None)
        cfg, cal = pipe.config, pipe.ctx.reader.calibration
        truth = pipe.ctx.reader.truth["anchors"]
        results = pipe.dir.load_pickle("init.pkl", "init")[cfg.uwb.init_method]
        est = pipe.dir.load_pickle("checkpoint_init.pkl", "init")
        now = {a: r for a, r in results.items() if r.ok and r.join_ns is None}
        add_initialised_anchors(est.state, now, cfg.uwb, cal, getattr(est, "pose_correlation_s", None))
        for a, r in now.items():
            e = r.x[:3] - np.asarray(truth[str(a)]["position"], float)
            joined.append(float(e @ np.linalg.solve(est.state.cov(anchor_var(a))[:3, :3], e)))
        m = json.loads(pipe.dir.file("metrics.json").read_text())
        final += [v["nees_position"] for v in m["anchors"].values() if v["determined"]]
        runs.append(m)
    return np.array(joined), np.array(final), runs


def _inside(vals: np.ndarray, dof: int = 3) -> bool:
    """The mean of ``vals`` (n NEES of ``dof`` dof) inside the two-sided 95 % chi2 bounds of such a mean."""
    from scipy.stats import chi2

    n = len(vals)
    lo, hi = chi2.ppf([0.025, 0.975], dof * n) / n
    print(f"ANEES {np.mean(vals):.2f} in [{lo:.2f}, {hi:.2f}] over {n}")
    return bool(lo < np.mean(vals) < hi)


def _inside_open(final: np.ndarray, runs) -> bool:
    """`_inside` over anchors of 3 dof, an open height counting 2 (its sigma is the prior's: the horizontal NEES
    is what its position claims)."""
    from scipy.stats import chi2

    dofs = np.array(
        [
            2 if not v["verdict"].get("height_observable", True) else 3
            for m in runs
            for v in m["anchors"].values()
            if v["determined"]
        ]
    )
    n = len(final)
    lo, hi = chi2.ppf([0.025, 0.975], int(dofs.sum())) / n
    print(f"NEES mean {np.mean(final):.2f} in [{lo:.2f}, {hi:.2f}] over {n} (dof {dofs.sum()})")
    return bool(lo < np.mean(final) < hi)


def _right_or_not_determined(runs, max_horizontal_m):
    for m in runs:
        for a, v in m["anchors"].items():
            if not v["determined"]:
                assert v["reason"], a
            else:
                assert v["error_horizontal_m"] < max_horizontal_m, (a, v["error_horizontal_m"])


def test_per_link_nees_within_chi2_bounds(tmp_path):
    """Per-link offsets, entering by the evidence rule (the links' offsets differ) on every anchor: over 3 fixed
    seeds x 6 anchors (each fitted from all its ranges: the scenario's poses have a bounded error) the anchor position
    NEES at the end lies inside the two-sided 95 % chi2 bounds."""
    joined, final, runs = _monte_carlo(tmp_path, "per-link", (1, 2, 3), duration=60.0)
    assert len(final) == 18
    for seed, m in zip((1, 2, 3), runs, strict=True):
        # per-link offsets wherever the links' true offsets spread over twice the range noise (0.1 m); where they
        # spread less the simpler model may win, its covariance carrying what it leaves out (the NEES below)
        spread = {}
        for lk in RecordingReader(tmp_path / f"per-link{seed}" / "r.mcap").truth["links"]:
            spread.setdefault(str(lk["anchor"]), []).append(lk["offset"])
        for a, v in m["anchors"].items():
            if v["determined"] and np.ptp(spread[a]) > 0.2:
                assert v["verdict"]["model"]["model"].startswith("link"), (seed, a, v["verdict"]["model"])
    assert _inside(final), final.mean()
    _right_or_not_determined(runs, 0.3)


def test_large_area_nees_within_chi2_bounds(tmp_path):
    """Campus drive (ranges up to 150 m, anchors ranged late or for 12 s): every anchor right or not determined
    with a reason (the brief one is), and the anchor position NEES at the end inside the chi2 bounds."""
    joined, final, runs = _monte_carlo(tmp_path, "large-area", (1, 2))
    assert len(final) >= 12 and _inside_open(final, runs)
    _right_or_not_determined(runs, 1.0)
    assert all(
        not m["anchors"]["9"]["determined"] or m["anchors"]["9"]["error_horizontal_m"] < 1.0 for m in runs
    )


@pytest.fixture(scope="module")
def nlos_runs(tmp_path_factory):
    """30 % NLOS junk on two anchors' links, robust initialisation (the real-data default; on simulated
    recordings auto means the paper's plain RI), 3 fixed seeds: (join NEES, final NEES, metrics per run)."""
    return _monte_carlo(
        tmp_path_factory.mktemp("nlos"), "nlos", (1, 2, 3), uwb={"init_method": "ri-robust"}, duration=60.0
    )


def test_nlos_join_nees_within_chi2_bounds(tmp_path):
    """Anchors right or not determined, and the initial covariances the anchors join the filter with are honest
    (position NEES inside the chi2 bounds over 3 seeds). A drifting odometry: the anchors are initialised from the
    first window and join the refinement at its start (with bounded poses each is fitted from all its ranges)."""
    uwb = {"init_method": "ri-robust"}
    joined, final, runs = _monte_carlo(
        tmp_path, "nlos", (1, 2, 3), uwb=uwb, duration=60.0, odometry_error="drift"
    )
    assert len(joined) >= 9 and _inside(joined)
    _right_or_not_determined(runs, 1.0)


def test_nlos_final_nees_within_chi2_bounds(nlos_runs):
    """After refinement with the robust update (Cauchy) the anchor position NEES stays inside the chi2 bounds:
    the NLOS anchors carry their robust fit's sandwich variance factor (`robust_noise_factor`, ~3.5 here, 1 on
    the clean anchors) into the refinement. Without it: ANEES 5.25 over these 18 (bounds [1.98, 4.23])."""
    joined, final, runs = nlos_runs
    assert len(final) >= 15 and _inside(final)
