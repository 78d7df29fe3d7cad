"""`uwbcal export --format anchors-json|anchors-yaml|tum` on a tabular run (no ground truth): the anchors read back
equal the run's anchor_states.json; TUM export of the estimate alone."""

from __future__ import annotations

import json

import numpy as np
import pytest
import yaml
from typer.testing import CliRunner

from uwbcal.cli import app
from uwbcal.evaluate.anchors_export import load_anchors, parameter_names
from uwbcal.evaluate.export import load_run_trajectory

ANCHORS = np.array([[4.0, 3.0, 0.5], [-4.0, 3.0, 2.5], [-4.0, -3.0, 1.0], [4.0, -3.0, 2.0]])
T0_S = 1_000_000_000


def _motion(t):
    return np.c_[3 * np.cos(0.3 * t), 2 * np.sin(0.6 * t), 1.2 + 0.5 * np.sin(0.2 * t)]


@pytest.fixture(scope="module")
def tabular_run(tmp_path_factory):
    """A TUM + ranges CSV input converted and run through every stage (no ground truth, no rerun log)."""
    d = tmp_path_factory.mktemp("tab")
    t = np.arange(0, 30, 0.05)
    p, yaw = _motion(t), 0.3 * t
    q = np.c_[np.zeros((len(t), 2)), np.sin(yaw / 2), np.cos(yaw / 2)]
    (d / "poses.tum").write_text(
        "".join(f"{T0_S + ti:.6f} " + " ".join(repr(float(v)) for v in (*pi, *qi)) + "\n" for ti, pi, qi in zip(t, p, q, strict=True))
    )  # fmt: skip
    rng = np.random.default_rng(1)
    rows = ["stamp,tag,antenna,anchor,distance"]
    for ti in np.arange(0, 30, 0.1):
        pi = _motion(np.array([ti]))[0]
        for a, pa in enumerate(ANCHORS):
            rows.append(
                f"{T0_S + ti + 0.01 * a:.6f},0,0,{a},{float(np.linalg.norm(pa - pi) + 0.1 * rng.normal())!r}"
            )
    (d / "ranges.csv").write_text("\n".join(rows) + "\n")
    r = CliRunner()
    res = r.invoke(app, ["convert", "tabular", "--poses", str(d / "poses.tum"), "--ranges", str(d / "ranges.csv"),
                         "-o", str(d / "rec.mcap")])  # fmt: skip
    assert res.exit_code == 0, res.output
    res = r.invoke(app, ["run", str(d / "rec.mcap"), "-o", str(d / "run"), "--no-log"])
    assert res.exit_code == 0, res.output
    return d / "run"


def test_anchors_json_reads_back_equal_to_anchor_states(tabular_run, tmp_path):
    res = CliRunner().invoke(
        app, ["export", str(tabular_run), "--format", "anchors-json", "-o", str(tmp_path)]
    )
    assert res.exit_code == 0, res.output
    doc = json.loads((tmp_path / "anchors.json").read_text())
    states = json.loads((tabular_run / "anchor_states.json").read_text())
    assert set(doc["anchors"]) == set(states) and doc["stage"] == "refine"
    assert doc["method"] == "ri-robust+skf" or "+" in doc["method"]
    for a, s in states.items():
        got = doc["anchors"][a]
        assert got["x"] == s["x"] and got["covariance"] == s["P"]  # exact: JSON floats round-trip
        assert got["position"] == s["x"][:3] and [got["beta"], got["gamma"]] == s["x"][3:5]
        assert got["noise_inflation"] == s["noise_inflation"]
        np.testing.assert_array_equal(got["sigma"], np.sqrt(np.diag(s["P"])))


def test_anchors_yaml_reads_back_equal_to_anchor_states(tabular_run, tmp_path):
    res = CliRunner().invoke(
        app, ["export", str(tabular_run), "--format", "anchors-yaml", "-o", str(tmp_path)]
    )
    assert res.exit_code == 0, res.output
    states = json.loads((tabular_run / "anchor_states.json").read_text())
    uvio = yaml.safe_load((tmp_path / "uwb_anchors.yaml").read_text())
    by_id = {str(a["id"]): a for a in uvio["anchors"]}
    for a, s in states.items():
        got = by_id[a]
        assert got["p_AinG"] == s["x"][:3] and [got["beta"], got["gamma"]] == s["x"][3:5]
        assert got["cov"] == s["P"] and got["names"] == ["x", "y", "z", "beta", "gamma"]
    loc = yaml.safe_load((tmp_path / "localization.yaml").read_text())["/**"]["ros__parameters"]
    ids = [str(i) for i in loc["anchor_ids"]]
    assert sorted(ids) == sorted(states)
    pos = np.reshape(loc["anchor_positions"], (-1, 3))
    for i, a in enumerate(ids):
        assert pos[i].tolist() == states[a]["x"][:3]
        assert [loc["anchor_beta"][i], loc["anchor_gamma"][i]] == states[a]["x"][3:5]


def test_tum_export_of_a_tabular_run_without_ground_truth(tabular_run, tmp_path):
    res = CliRunner().invoke(app, ["export", str(tabular_run), "--format", "tum", "-o", str(tmp_path)])
    assert res.exit_code == 0, res.output
    assert "no ground truth" in res.output and not (tmp_path / "groundtruth.tum").exists()
    tr = load_run_trajectory(tabular_run)
    rows = [ln.split() for ln in (tmp_path / "estimate.tum").read_text().splitlines()]
    assert len(rows) == len(tr.t_ns) and all(len(r) == 8 for r in rows)
    vals = np.array([[float(v) for v in r[1:]] for r in rows])
    np.testing.assert_array_equal(vals[:, :3], tr.p)
    np.testing.assert_array_equal(vals[:, 3:], tr.q_xyzw)
    assert rows[0][0] == f"{tr.t_ns[0] // 10**9}.{tr.t_ns[0] % 10**9:09d}"
    # the estimate follows the input poses (real stamps, seconds since the epoch)
    assert abs(float(rows[0][0]) - T0_S) < 31


def test_per_link_states_and_errors(tmp_path):
    run = tmp_path / "run"
    run.mkdir()
    (run / "config.toml").write_text('[uwb]\ninit_method = "ri"\nrefine_method = "ekf"\n')
    x = [1.0, 2.0, 3.0, 0.9, -0.3, 1.01, 0.2]
    P = np.diag([0.1, 0.2, 0.3, 0.01, 0.02, 0.03, 0.04]).tolist()
    (run / "anchor_states.json").write_text(json.dumps({"7": {"x": x, "P": P, "links": ["t0a0", "t0a1"]}}))
    doc = load_anchors(run)
    a = doc["anchors"]["7"]
    assert a["beta"] == {"t0a0": 0.9, "t0a1": 1.01} and a["gamma"] == {"t0a0": -0.3, "t0a1": 0.2}
    assert a["covariance"] == P and doc["method"] == "ri+ekf"
    res = CliRunner().invoke(app, ["export", str(run), "--format", "anchors-yaml", "-o", str(tmp_path / "o")])
    assert res.exit_code == 0, res.output
    assert "anchor_beta" not in (tmp_path / "o" / "localization.yaml").read_text()
    assert parameter_names({}, 5) == ["x", "y", "z", "beta", "gamma"]
    (run / "anchor_states.json").write_text(json.dumps({"7": {"x": x[:4], "P": P}}))
    res = CliRunner().invoke(app, ["export", str(run), "--format", "anchors-json", "-o", str(tmp_path / "o")])
    assert res.exit_code == 2 and "anchor 7" in res.output and len(res.output.strip().splitlines()) == 1
    res = CliRunner().invoke(app, ["export", str(run), "--format", "kml", "-o", str(tmp_path / "o")])
    assert res.exit_code == 2 and "unsupported" in res.output
