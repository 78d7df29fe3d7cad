"""`uwbcal calibrate`: one command from a dataset to anchors with covariance, a check and a report; and
report.html of every run."""

from __future__ import annotations

import json

import pytest
from typer.testing import CliRunner

from uwbcal.cli import app
from uwbcal.convert.simulator import SimConfig, simulate_to_file

runner = CliRunner()


@pytest.fixture(scope="module")
def sim(tmp_path_factory):
    rec = tmp_path_factory.mktemp("calibrate") / "sim.mcap"
    # long enough for the init window (a third of it) to determine every anchor: the command's output is tested
    simulate_to_file(SimConfig(duration=40.0, n_anchors=3, odometry_rate=20.0, camera=False, seed=2), rec)
    return rec


def test_calibrate_a_recording(sim, tmp_path):
    out = tmp_path / "cal"
    res = runner.invoke(app, ["calibrate", str(sim), "-o", str(out)])
    assert res.exit_code == 0, res.output
    lines = res.stdout.strip().splitlines()
    assert len(lines) == 5, res.stdout
    assert lines[0].startswith("anchors   3 estimated (0, 1, 2)") and "not determined: none" in lines[0]
    assert lines[1].startswith("sigma     0 ") and lines[2].startswith("truth     vs simulated: 3-D mean")
    assert lines[3].startswith("check     ") and str(out / "report.html") in lines[4]
    doc = json.loads((out / "anchors.json").read_text())
    assert sorted(doc["anchors"]) == ["0", "1", "2"] and len(doc["anchors"]["0"]["covariance"]) >= 5
    assert (out / "uwb_anchors.yaml").is_file() and (out / "localization.yaml").is_file()
    page = (out / "report.html").read_text()
    assert page.count("data:image/png;base64,") == 3 and "http" not in page.replace("http-equiv", "")
    assert "Recording check" in page and (out / "run" / "report.html").is_file()  # the run's own page too


def test_calibrate_refuses_what_it_cannot_read(tmp_path):
    (tmp_path / "x.txt").write_text("nothing")
    res = runner.invoke(app, ["calibrate", str(tmp_path), "-o", str(tmp_path / "o")])
    assert res.exit_code == 2 and "not a bag, EuRoC folder" in res.output
    res = runner.invoke(app, ["calibrate", "--poses", str(tmp_path / "x.txt"), "-o", str(tmp_path / "o")])
    assert res.exit_code == 2 and "--poses and --ranges go together" in res.output
