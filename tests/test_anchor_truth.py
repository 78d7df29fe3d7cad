"""Surveyed anchor truth: convert tabular / NTU-VIRAL -> uwbcal.truth -> anchor metrics (closed forms)."""

from __future__ import annotations

import json
import shutil
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
from scipy.stats import chi2
from typer.testing import CliRunner

from uwbcal.cli import app
from uwbcal.convert.anchor_truth import read_anchor_truth
from uwbcal.convert.ntu_viral import convert_ntu_viral
from uwbcal.convert.recording import RecordingReader
from uwbcal.convert.tabular import convert_tabular
from uwbcal.evaluate.anchor_report import AnchorReference, anchor_metrics, read_run_anchors
from uwbcal.evaluate.evaluation import render_metrics
from uwbcal.evaluate.metrics import anchor_errors, inter_anchor_distance_errors
from uwbcal.pipeline.core.errors import InputError
from uwbcal.pipeline.run import rundir as rd
from uwbcal.pipeline.run.stages.refine import _weak_after_refine

from support import T0

TRUTH = {"0": [0.0, 0.0, 1.0], "1": [4.0, 0.0, 1.0], "2": [4.0, 3.0, 1.0], "3": [0.0, 3.0, 2.0]}


def _inputs(d: Path) -> tuple[Path, Path]:
    poses, ranges = d / "p.tum", d / "r.csv"
    poses.write_text("".join(f"{1_700_000_000 + 0.1 * k:.1f} {0.1 * k} 1 0 0 0 0 1\n" for k in range(30)))
    rows = [f"{T0 + k * 50_000_000},1,0,{k % 4},{3 + 0.01 * k}" for k in range(60)]
    ranges.write_text("stamp,tag,antenna,anchor,distance\n" + "\n".join(rows) + "\n")
    return poses, ranges


def _truth_csv(path: Path, rows: dict[str, list[float]] = TRUTH, header: str = "anchor,x,y,z") -> Path:
    path.write_text(header + "\n" + "".join(f"{a},{x},{y},{z}\n" for a, (x, y, z) in rows.items()))
    return path


def test_tabular_truth_round_trip(tmp_path):
    poses, ranges = _inputs(tmp_path)
    truth = _truth_csv(tmp_path / "anchors_truth.csv", {**TRUTH, "9": [1.5, -2.25, 0.125]})
    out = tmp_path / "o.mcap"
    text = convert_tabular(poses, ranges, out, anchors_truth=truth)
    t = RecordingReader(out).truth
    assert t["kind"] == "surveyed" and t["anchors_frame"] == "odometry"
    assert t["anchors_file"]["path"] == str(truth) and len(t["anchors_file"]["sha256"]) == 64
    assert {a: v["position"] for a, v in t["anchors"].items()} == {**TRUTH, "9": [1.5, -2.25, 0.125]}
    assert "truth for 5 anchors; truth without ranges: 9" in text
    # without the option the recording has no truth
    convert_tabular(poses, ranges, tmp_path / "n.mcap")
    assert RecordingReader(tmp_path / "n.mcap").truth is None


@pytest.mark.parametrize(
    ("content", "message"),
    [
        ("anchor,x,y\n0,1,2\n", "header: expected columns anchor,x,y,z"),
        ("anchor,x,y,z\n0,1,2,3\n1,1,two,3\n", "line 3: column 'y': 'two' is not a number"),
        ("anchor,x,y,z\n0,1,2,3\n0,1,2,4\n", "lines [2, 3]: anchor 0 listed 2 times"),
        ("anchor,x,y,z\n", "no anchor rows"),
        ("anchor,x,y,z\n0,1,inf,3\n", "line 2: anchor 0: non-finite position"),
        ("anchor,x,y,z\nA,1,2,3\n", "line 2: column 'anchor': 'A' is not an integer"),
    ],
)
def test_bad_truth_csv_exits_2_with_one_line(tmp_path, content, message):
    poses, ranges = _inputs(tmp_path)
    bad = tmp_path / "bad.csv"
    bad.write_text(content)
    args = ["convert", "tabular", "--poses", str(poses), "--ranges", str(ranges)]
    res = CliRunner().invoke(app, [*args, "--anchors-truth", str(bad), "-o", str(tmp_path / "o.mcap")])
    assert res.exit_code == 2
    lines = res.output.strip().splitlines()
    assert len(lines) == 1 and str(bad) in lines[0] and message in lines[0], res.output
    assert not (tmp_path / "o.mcap").exists()


def test_site_column(tmp_path):
    f = tmp_path / "pub.csv"
    f.write_text("site,anchor,x,y,z\neee,100,1,2,3\neee,101,4,5,6\nnya,100,7,8,9\n")
    assert read_anchor_truth(f, site="nya") == {"100": {"position": [7.0, 8.0, 9.0]}}
    assert set(read_anchor_truth(f, site="eee")) == {"100", "101"}
    with pytest.raises(InputError, match="several sites"):
        read_anchor_truth(f)
    with pytest.raises(InputError, match="no rows for site 'sbs'"):
        read_anchor_truth(f, site="sbs")


def test_ntu_folder_published_truth(tmp_path):
    root = tmp_path / "ntu"
    seq = root / "eee_07"
    seq.mkdir(parents=True)
    (seq / "uwb_ranges.csv").write_text(
        "stamp,tag,antenna,anchor,distance\n"
        + "".join(f"{T0 + k},200,0,{100 + k % 2},5.0\n" for k in range(10))
    )
    (root / "published_anchors.csv").write_text(
        "site,anchor,x,y,z\neee,100,1,2,3\neee,101,4,5,6\nnya,100,0,0,0\n"
    )
    convert_ntu_viral(seq, tmp_path / "o.mcap")
    t = RecordingReader(tmp_path / "o.mcap").truth
    assert t["kind"] == "published" and t["anchors_frame"] == "slict"  # no SLICT poses in this folder
    assert t["anchors"] == {"100": {"position": [1.0, 2.0, 3.0]}, "101": {"position": [4.0, 5.0, 6.0]}}
    # an explicit file wins; a bad explicit file is an error, a found file without the site only a note
    other = _truth_csv(tmp_path / "mine.csv", {"100": [0.5, 0.5, 0.5]})
    convert_ntu_viral(seq, tmp_path / "m.mcap", anchors_truth=other)
    assert RecordingReader(tmp_path / "m.mcap").truth["anchors"] == {"100": {"position": [0.5, 0.5, 0.5]}}
    shutil.move(seq, root / "sbs_01")
    text = convert_ntu_viral(root / "sbs_01", tmp_path / "s.mcap")
    assert RecordingReader(tmp_path / "s.mcap").truth is None and "no rows for site 'sbs'" in text


# ---------------------------------------------------------------------------------------------------------------
# metrics: closed forms
# ---------------------------------------------------------------------------------------------------------------
def test_errors_and_distances_closed_form():
    est = {k: list(v) for k, v in TRUTH.items()}
    est["0"] = [0.3, 0.4, 2.2]  # off by (0.3, 0.4, 1.2): 3-D 1.3, horizontal 0.5
    ae = anchor_errors(est, TRUTH)
    assert ae.per_anchor["0"]["error_m"] == pytest.approx(1.3)
    assert ae.per_anchor["0"]["error_horizontal_m"] == pytest.approx(0.5)
    assert ae.mean_m == pytest.approx(1.3 / 4) and ae.max_m == pytest.approx(1.3)
    assert ae.mean_horizontal_m == pytest.approx(0.5 / 4) and ae.max_horizontal_m == pytest.approx(0.5)
    d = inter_anchor_distance_errors(est, TRUTH)
    assert len(d.per_pair) == 6
    # pair 0-1: |(3.7, -0.4, -1.2)| - 4; pair 1-2 unchanged
    assert d.per_pair["0-1"] == pytest.approx(np.sqrt(3.7**2 + 0.4**2 + 1.2**2) - 4.0)
    assert d.per_pair["1-2"] == pytest.approx(0.0, abs=1e-12)
    e01 = np.sqrt(3.7**2 + 0.4**2 + 1.2**2) - 4.0
    e02 = np.sqrt(3.7**2 + 2.6**2 + 1.2**2) - 5.0
    e03 = np.sqrt(0.3**2 + 2.6**2 + 0.2**2) - np.sqrt(9 + 1)
    assert d.mean_abs_m == pytest.approx((abs(e01) + abs(e02) + abs(e03)) / 6)
    assert d.max_abs_m == pytest.approx(max(abs(e01), abs(e02), abs(e03)))


def test_distances_are_frame_free():
    rng = np.random.default_rng(3)
    T = np.asarray(list(TRUTH.values()))
    E = T + rng.normal(0, 0.05, T.shape)
    q = np.linalg.qr(rng.normal(size=(3, 3)))[0]  # any rotation or reflection
    moved = E @ q.T + [10.0, -4.0, 2.0]
    a = inter_anchor_distance_errors(dict(zip(TRUTH, E, strict=True)), TRUTH)
    b = inter_anchor_distance_errors(dict(zip(TRUTH, moved, strict=True)), TRUTH)
    assert b.per_pair == pytest.approx(a.per_pair, abs=1e-12)
    assert anchor_errors(dict(zip(TRUTH, moved, strict=True)), TRUTH).mean_m > 1.0


def _run_dir(d: Path) -> Path:
    d.mkdir()
    rows = [
        "anchor,method,stage,x,y,z,beta,gamma,reason",
        "0,ri,init,0.1,0.0,1.0,1.0,0.0,",
        "1,ri,init,4.0,0.2,1.0,1.0,0.0,",
        "2,ri,init,,,,,,never observable: ranged only from one point",
        "0,ri+skf,refine,0.1,0.0,1.0,1.0,0.1,",
        "1,ri+skf,refine,4.0,0.2,1.0,1.0,0.1,",
    ]
    (d / "anchors.csv").write_text("\n".join(rows) + "\n")
    P0 = np.diag([0.01, 0.04, 0.25, 1e-4, 1e-2])
    states = {
        "0": {"x": [0.1, 0.0, 1.0, 1.0, 0.1], "P": P0.tolist()},
        "1": {"x": [4.0, 0.2, 1.0, 1.0, 0.1], "P": P0.tolist()},
    }
    (d / "anchor_states.json").write_text(json.dumps(states))
    init = {
        "chosen": "ri",
        "methods": {
            "ri": {
                "0": {"status": "ok", "x": [0.1, 0.0, 1.0, 1.0, 0.0], "cov": P0.tolist()},
                "1": {"status": "ok", "x": [4.0, 0.2, 1.0, 1.0, 0.0], "cov": P0.tolist()},
                "2": {"status": "refused", "warnings": ["rank-deficient FIM"]},
                "3": {"status": "skipped", "warnings": ["12 ranges, too few"]},
            }
        },
    }
    (d / "init.json").write_text(json.dumps(init))
    return d


def test_report_undetermined_nees_and_render(tmp_path):
    run = read_run_anchors(_run_dir(tmp_path / "run"), "ri")
    assert set(run.estimates) == {"0", "1"} and run.estimates["0"]["method"] == "ri+skf"
    assert (
        run.undetermined["2"]["reason"] == "never observable: ranged only from one point"
    )  # the csv's reason
    assert run.undetermined["3"]["reason"] == "skipped; 12 ranges, too few"  # from init.json
    ref = AnchorReference(
        {k: {"position": v} for k, v in TRUTH.items()}, "surveyed", "surveyed (t.csv)", True
    )
    anchors, top, warns = anchor_metrics(run, ref)
    # NEES of the position: e^T P^-1 e with diagonal P, by hand
    assert anchors["0"]["nees_position"] == pytest.approx(0.1**2 / 0.01)
    assert anchors["1"]["nees_position"] == pytest.approx(0.2**2 / 0.04)
    n = top["nees_anchor_position"]
    assert n["mean"] == pytest.approx((1.0 + 1.0) / 2) and n["dof"] == 3 and n["n_runs"] == 2
    assert n["bounds"] == pytest.approx([chi2.ppf(0.025, 6) / 2, chi2.ppf(0.975, 6) / 2])
    assert anchors["1"]["sigma_xyz"] == pytest.approx([0.1, 0.2, 0.5])
    assert anchors["1"]["z_error_sigmas"] == pytest.approx(0.0)
    assert anchors["2"] == {
        "determined": False,
        "reason": "never observable: ranged only from one point",
        "method": "ri",
    }
    assert "error_m" not in anchors["3"] and "nees" not in anchors["0"]  # no beta/gamma truth: no 5-dof NEES
    at = top["anchor_truth"]
    assert at["n_estimated"] == 2 and at["n_truth"] == 4 and at["missing"] == []
    assert at["not_determined"] == ["2", "3"]  # the ids: each reason once, in anchors[<id>].reason
    assert at["error_3d_m"] == pytest.approx({"mean": 0.15, "max": 0.2})
    assert at["error_horizontal_m"] == pytest.approx({"mean": 0.15, "max": 0.2})
    d = at["inter_anchor_distance_error_m"]
    # estimated 0-1 distance |(3.9, 0.2, 0)| against the true 4.0
    assert d["pairs"] == 1 and d["per_pair"]["0-1"] == pytest.approx(np.hypot(3.9, 0.2) - 4.0)
    assert d["max_abs"] == d["mean_abs"] == pytest.approx(4.0 - np.hypot(3.9, 0.2))
    assert top["anchor_error_m"] == pytest.approx(0.15) and not warns
    text = render_metrics({"anchors": anchors, **top, "warnings": warns})
    assert "anchor 2 not determined: never observable" in text and "not determined: skipped" in text
    assert "horizontal mean 0.150 m, max 0.200 m (2 of 4)" in text and "1 pairs" in text


def test_nees_in_the_filters_gauge_errors_after_the_fitted_alignment(tmp_path):
    """A static-initialised run: errors (and sigmas) after the trajectory's fitted alignment, the NEES of the
    states the evaluator passes in the filter's gauge (here the fitted frame shifted by 0.1 m in y): by hand."""
    from uwbcal.evaluate.align import Alignment
    from uwbcal.evaluate.anchor_report import aligned_anchors

    run = read_run_anchors(_run_dir(tmp_path / "run"), "ri")
    ref = AnchorReference({k: {"position": v} for k, v in TRUTH.items()}, "simulated", "simulated", True)
    gauge = aligned_anchors(run, Alignment(t=np.array([0.0, -0.1, 0.0]))).states
    anchors, top, _ = anchor_metrics(run, ref, gauge)
    fitted = anchor_metrics(run, ref)[0]
    assert anchors["0"]["error_xyz"] == pytest.approx([0.1, 0.0, 0.0])  # errors: the fitted frame's
    assert anchors["1"]["error_m"] == fitted["1"]["error_m"] == pytest.approx(0.2)
    # NEES: e = (0.1, -0.1, 0) and (0, 0.1, 0) under diag(0.01, 0.04, 0.25)
    assert anchors["0"]["nees_position"] == pytest.approx(1.0 + 0.01 / 0.04)
    assert anchors["1"]["nees_position"] == pytest.approx(0.01 / 0.04)
    assert top["nees_anchor_position"]["mean"] == pytest.approx((1.25 + 0.25) / 2)
    # 5 dof with the simulated truth's beta = 1, gamma = 0: + (0.1)^2 / 1e-2 for gamma
    assert anchors["0"]["nees"] == pytest.approx(1.25 + 1.0)


def test_report_truth_in_another_frame_is_frame_free_only(tmp_path):
    run = read_run_anchors(_run_dir(tmp_path / "run"), "ri")
    ref = AnchorReference({k: {"position": v} for k, v in TRUTH.items()}, "published", "published", False)
    anchors, top, warns = anchor_metrics(run, ref)
    assert "error_m" not in anchors["0"] and "anchor_error_m" not in top and "nees_anchor_position" not in top
    assert (
        "inter_anchor_distance_error_m" in top["anchor_truth"] and "only inter-anchor distances" in warns[0]
    )


@pytest.mark.data
def test_surveyed_real_truth_round_trip(data_dir, tmp_path):
    d = data_dir / "surveyed" / "cuhksz_mid"
    out = tmp_path / "mid.mcap"
    text = convert_tabular(
        d / "poses.tum", d / "ranges.csv", out, d / "antennas.yaml", anchors_truth=d / "anchors_truth.csv"
    )
    t = RecordingReader(out).truth
    assert t["kind"] == "surveyed" and set(t["anchors"]) == {str(a) for a in range(8)}
    assert t["anchors"]["0"]["position"] == [-3.4203, 3.0053, 1.0442]
    assert "anchors_truth.csv: truth for 8 anchors" in text and "without" not in text.split("truth for")[1]


@pytest.mark.data
def test_ntu_folder_carries_published_truth(data_dir, tmp_path):
    out = tmp_path / "nya.mcap"
    convert_ntu_viral(data_dir / "ntu_viral" / "nya_01", out)
    t = RecordingReader(out).truth
    assert t["kind"] == "published" and t["anchors_frame"] == "odometry"  # SLICT poses: the anchors' frame
    assert t["anchors"]["101"]["position"] == [-8.43474, -1.66775, 1.11005] and len(t["anchors"]) == 3


def test_undetermined_reason_stated_once(tmp_path):
    d = _run_dir(tmp_path / "run")
    init = json.loads((d / "init.json").read_text())
    why = "horizontal sigma 1.52 m > 1 m"
    init["methods"]["ri"]["3"] = {
        "status": "not determined",
        "reason": why,
        "warnings": [f"3: not determined: {why}"],
    }
    (d / "init.json").write_text(json.dumps(init))
    assert read_run_anchors(d, "ri").undetermined["3"]["reason"] == why


def test_an_anchor_refinement_leaves_weak_is_not_determined_with_its_reason(tmp_path):
    """The init's gate on the covariance the run reports: an anchor whose horizontal sigma after refinement is
    above max_sigma_horizontal_m gets an empty refine row with the reason, which metrics.json states."""
    d = _run_dir(tmp_path / "run")
    states = json.loads((d / "anchor_states.json").read_text())
    P = np.diag([0.01, 1.0, 0.25, 1e-4, 1e-2])
    P[0, 1] = P[1, 0] = 0.09  # the weak direction leans towards x
    states["1"]["P"] = P.tolist()
    warns: list[str] = []
    logged = []
    log = SimpleNamespace(text=lambda msg, level="INFO", t_ns=None: logged.append((msg, level, t_ns)))
    weak = _weak_after_refine(states, 0.9, warns, log, 7_000)
    lam, V = np.linalg.eigh(P[:2, :2])
    assert (
        set(weak) == {"1"}
        and set(states) == {"0"}
        and warns == [f"refine: anchor 1 not determined: {weak['1']}"]
    )
    assert logged == [(warns[0], "WARN", 7_000)]  # the viewer's log says it beside the anchor's last state
    assert (
        f"sigma {np.sqrt(lam[-1]):.2f} m > 0.9 m" in weak["1"]
        and f"({V[0, -1]:.2f}, {V[1, -1]:.2f})" in weak["1"]
    )
    (d / "anchor_states.json").write_text(json.dumps(states))
    rows = [rd.anchor_row("0", "ri+skf", "refine", states["0"]["x"])]
    rd.write_anchors(rd.RunDir(d), rows + [rd.undetermined_row("1", "ri+skf", "refine", weak["1"])], "refine")
    assert (d / "anchors.csv").read_text().splitlines()[0].endswith(",gamma,reason")
    run = read_run_anchors(d, "ri")
    assert set(run.estimates) == {"0"} and run.undetermined["1"]["reason"] == weak["1"]
    (tmp_path / "plain").mkdir()
    rd.write_anchors(
        rd.RunDir(tmp_path / "plain"), rows + [rd.undetermined_row("1", "ri+skf", "refine")], "refine"
    )
    assert (tmp_path / "plain" / "anchors.csv").read_text().startswith(",".join(rd.ANCHOR_COLUMNS) + "\n")


def _own_frame_run(tmp_path: Path, static: bool) -> tuple[Path, np.ndarray, np.ndarray]:
    """A run whose trajectory and anchors are the truth seen from a frame turned by 0.7 rad of yaw and shifted
    (a static initialiser's own frame) when ``static``, else the truth's frame; anchors 0.1 m off in x."""
    from uwbcal.convert.anchor_truth import truth_record
    from uwbcal.convert.recording import RecordingWriter
    from uwbcal.pipeline.core.geometry import exp_so3, rot_to_quat

    t = T0 + np.arange(0, 10_000_000_001, 20_000_000, dtype=np.int64)
    s = (t - t[0]) * 1e-9
    p_gt = np.c_[2 * np.cos(0.6 * s), 1.5 * np.sin(0.6 * s), 1.0 + 0.2 * np.sin(s)]
    R_gt = exp_so3(np.c_[0.05 * np.sin(s), 0.02 * s, 0.6 * s])
    rec = tmp_path / "rec.mcap"
    with RecordingWriter(rec) as w:
        w.write_pose_batch(t, p_gt, rot_to_quat(R_gt))
        anchors = {a: {"position": v} for a, v in TRUTH.items()}
        w.set_metadata("uwbcal.truth", truth_record(anchors, "surveyed", frame="world"))
    yaw, shift = (0.7, np.array([3.0, -2.0, 0.5])) if static else (0.0, np.zeros(3))
    Rz = exp_so3(np.array([0.0, 0.0, yaw]))
    to_own = lambda p: (np.asarray(p) - shift) @ Rz  # noqa: E731  (Rz^T (p - shift))
    run = tmp_path / "run"
    run.mkdir()
    q_est = rot_to_quat(Rz.T @ R_gt)
    np.savez(run / "trajectory.npz", t_ns=t, p=to_own(p_gt), q_xyzw=q_est, segment=np.zeros(len(t), np.int64))
    (run / "config.toml").write_text(f'[run]\nrecording = "{rec}"\n[uwb]\ninit_method = "ri"\n')
    est = {a: to_own(np.asarray(v) + [0.1, 0.0, 0.0]) for a, v in TRUTH.items()}
    rows = [f"{a},ri,init,{x},{y},{z},1.0,0.0," for a, (x, y, z) in est.items()]
    (run / "anchors.csv").write_text("anchor,method,stage,x,y,z,beta,gamma,reason\n" + "\n".join(rows) + "\n")
    if static:
        (run / "static_init.json").write_text("{}")
    return run, Rz, shift


@pytest.mark.parametrize("static", [True, False])
def test_anchors_get_the_trajectorys_alignment_in_a_static_initialisers_frame(tmp_path, static):
    """Surveyed truth, a run in its own frame (known yaw + translation): the anchors are reported in the truth's
    frame with the trajectory's alignment, their error the 0.1 m put in; a run in the truth's frame (started from
    ground truth) is compared as it is, whatever alignment its trajectory gets."""
    from uwbcal.evaluate.evaluation import evaluate_run

    run, _, _ = _own_frame_run(tmp_path, static)
    m = evaluate_run(run)
    assert m["alignment"] == ("posyaw" if static else "se3")
    assert m["prmse_m"]["all"] == pytest.approx(0.0, abs=1e-6)
    assert m["anchor_error_m"] == pytest.approx(0.1, abs=1e-6)
    for a, v in TRUTH.items():
        assert m["anchors"][a]["estimate"] == pytest.approx(np.asarray(v) + [0.1, 0.0, 0.0], abs=1e-6)
        assert m["anchors"][a]["error_xyz"] == pytest.approx([0.1, 0.0, 0.0], abs=1e-6)
    assert ("anchor_alignment" in m) == static
