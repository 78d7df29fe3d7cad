"""Experiments are seeded and reproducible, and their summary feeds `uwbcal diff`."""

import json

import polars as pl
from typer.testing import CliRunner

from cli import app

runner = CliRunner()


def test_ri_vs_lsi_reproducible_and_parallel_equal(tmp_path):
    a, b = tmp_path / "a", tmp_path / "b"
    assert runner.invoke(app, ["experiment", "ri-vs-lsi", "--runs", "3", "-o", str(a)]).exit_code == 0
    assert (
        runner.invoke(app, ["experiment", "ri-vs-lsi", "--runs", "3", "--jobs", "2", "-o", str(b)]).exit_code
        == 0
    )
    sa = json.loads((a / "summary.json").read_text())["ri-vs-lsi"]
    sb = json.loads((b / "summary.json").read_text())["ri-vs-lsi"]
    assert sa == sb and len(sa) == 18
    df = pl.read_parquet(a / "runs.parquet")
    assert df.height == 6 * 3 * 3
    for name in ("ri-vs-lsi.md", "ri-vs-lsi.csv", "ri-vs-lsi.tex", "ri_vs_lsi.png", "config.json"):
        assert (a / name).is_file()
    # the same seeds give no regression; a worsened copy does
    assert runner.invoke(app, ["diff", str(a / "summary.json"), str(b / "summary.json")]).exit_code == 0
    worse = json.loads((a / "summary.json").read_text())
    key = next(iter(worse["ri-vs-lsi"]))
    worse["ri-vs-lsi"][key] *= 1.5
    (tmp_path / "worse.json").write_text(json.dumps(worse))
    res = runner.invoke(app, ["diff", str(a / "summary.json"), str(tmp_path / "worse.json")])
    assert res.exit_code == 1 and key in res.output
