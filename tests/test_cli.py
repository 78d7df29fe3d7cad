"""Every command through the CLI: one good input (exit 0, the output it promises) and one bad input (exit 2, a
single line on stderr naming the problem). The large fault-injection table is tests/test_faults.py."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
from typer.testing import CliRunner

from uwbcal.cli import app
from uwbcal.convert.recording import RecordingReader

runner = CliRunner()
COMMANDS = (
    "demo",
    "simulate",
    "convert",
    "info",
    "run",
    "evaluate",
    "export",
    "experiment",
    "diff",
    "view",
    "bench",
)


def _ok(args: list[str]):
    res = runner.invoke(app, [str(a) for a in args])
    assert res.exit_code == 0, res.output
    return res


def _bad(args: list[str], *words: str):
    """Exit 2 with exactly one line on stderr, starting ``error:`` and containing every word."""
    res = runner.invoke(app, [str(a) for a in args])
    assert res.exit_code == 2, res.output
    err = res.stderr.strip()
    assert len(err.splitlines()) == 1 and err.startswith("error:"), err
    for w in words:
        assert w in err, (w, err)
    return err


def test_help_lists_every_command():
    res = _ok(["--help"])
    for cmd in COMMANDS:
        assert cmd in res.output


def test_demo(demo_run, tmp_path):
    out, text = demo_run  # conftest: `uwbcal demo -o DIR` exited 0
    assert "results (metrics.json):" in text and f"uwbcal view {out}" in text
    m = json.loads((out / "metrics.json").read_text())
    assert len(m["anchors"]) == 4 and (out / "run.rrd").stat().st_size > 0
    (tmp_path / "file").write_text("x")
    _bad(["demo", "-o", tmp_path / "file" / "demo"], "file")


def test_simulate(tmp_path):
    out = tmp_path / "s.mcap"
    res = _ok(
        ["simulate", "-o", out, "--duration", "5", "--anchors", "2", "--no-camera", "--odometry-rate", "20"]
    )
    rd = RecordingReader(out)
    assert set(np.unique(rd.read_ranges().anchor)) == {0, 1} and len(rd.read_odometry().t_ns) > 90
    assert str(out) in res.output or "s.mcap" in res.output
    _bad(["simulate", "-o", tmp_path / "b.mcap", "--duration", "5", "--nlos-rate", "2"], "nlos_rate")
    assert not (tmp_path / "b.mcap").exists()


def test_convert_euroc(tmp_path):
    from uwbcal.benchmarks.convert_bag import write_euroc_bag

    bag = tmp_path / "e.bag"
    content = write_euroc_bag(bag, duration_s=0.2, width=8, height=6, gt=None, record=True)
    _ok(["convert", "euroc", bag, "-o", tmp_path / "e.mcap"])
    assert RecordingReader(tmp_path / "e.mcap").topics()["/imu"].count == len(content.imu_t)
    (tmp_path / "e.txt").write_text("x")
    _bad(["convert", "euroc", tmp_path / "e.txt", "-o", tmp_path / "x.mcap"], "e.txt", ".bag")
    assert not (tmp_path / "x.mcap").exists()


def test_convert_ntu_viral(tmp_path):
    seq = tmp_path / "eee_99"
    seq.mkdir()
    rows = [
        f"{1_600_000_000_000_000_000 + k * 50_000_000},200,{k % 2},{100 + k % 3},{5 + 0.01 * k}"
        for k in range(30)
    ]
    (seq / "uwb_ranges.csv").write_text("stamp,tag,antenna,anchor,distance\n" + "\n".join(rows) + "\n")
    (tmp_path / "uwb_antennas.yaml").write_text(
        "antenna_offset: [200,2, 0.0,-0.45,0.0,  0.0,0.45,0.0]\nranging_bias: [200, -0.75]\n"
    )
    _ok(["convert", "ntu-viral", seq, "-o", tmp_path / "n.mcap"])
    assert len(RecordingReader(tmp_path / "n.mcap").read_ranges()) == 30
    (tmp_path / "empty").mkdir()
    _bad(["convert", "ntu-viral", tmp_path / "empty", "-o", tmp_path / "x.mcap"], "uwb_ranges.csv")


def test_convert_tabular(tmp_path):
    t0 = 1_600_000_000
    (tmp_path / "p.tum").write_text("".join(f"{t0 + 0.1 * k:.1f} {0.1 * k} 0 1 0 0 0 1\n" for k in range(30)))
    ranges = "".join(f"{(t0 + 0.1 * k) * 1e9:.0f},200,0,100,{5 + 0.01 * k}\n" for k in range(1, 20))
    (tmp_path / "r.csv").write_text("stamp,tag,antenna,anchor,distance\n" + ranges)
    _ok(
        [
            "convert",
            "tabular",
            "--poses",
            tmp_path / "p.tum",
            "--ranges",
            tmp_path / "r.csv",
            "-o",
            tmp_path / "t.mcap",
        ]
    )
    assert len(RecordingReader(tmp_path / "t.mcap").read_ranges()) == 19
    (tmp_path / "bad.csv").write_text("time,range\n1,2\n")
    _bad(
        [
            "convert",
            "tabular",
            "--poses",
            tmp_path / "p.tum",
            "--ranges",
            tmp_path / "bad.csv",
            "-o",
            tmp_path / "x.mcap",
        ],
        "bad.csv",
    )


def test_info(sim_recording, tmp_path):
    res = _ok(["info", sim_recording])
    assert "/uwb" in res.output and "/imu" in res.output
    (tmp_path / "g.mcap").write_bytes(b"nope")
    _bad(["info", tmp_path / "g.mcap"], "g.mcap")


def test_run(sim_run, tmp_path):
    assert (sim_run / "metrics.json").is_file()  # the session's run (conftest) exited 0
    _bad(["run", tmp_path / "missing.mcap", "-o", tmp_path / "r"], "missing.mcap")
    assert not (tmp_path / "r").exists()


def test_evaluate(sim_run, tmp_path):
    run = Path(shutil.copytree(sim_run, tmp_path / "run"))
    res = _ok(["evaluate", run, "--align", "se3"])
    assert "prmse" in res.output.lower() and (run / "results.md").is_file()
    (tmp_path / "not_a_run").mkdir()
    _bad(["evaluate", tmp_path / "not_a_run"], "not_a_run")


def test_export(sim_run, tmp_path):
    _ok(["export", sim_run, "-o", tmp_path / "tum"])
    est = np.loadtxt(tmp_path / "tum" / "estimate.tum")
    with np.load(sim_run / "trajectory.npz") as z:
        assert len(est) == len(z["t_ns"]) and np.allclose(est[:, 1:4], z["p"], atol=1e-6)
    _bad(["export", sim_run, "-o", tmp_path / "x", "--format", "csv"], "--format csv")


def test_experiment(tmp_path):
    out = tmp_path / "exp"
    _ok(["experiment", "ri-vs-lsi", "--runs", "1", "-o", out])
    summary = json.loads((out / "summary.json").read_text())
    assert summary["runs"] == 1
    _bad(["experiment", "ri-vs-lsi", "--runs", "1", "-o", tmp_path / "x", "--param", "nope=1"], "nope")


def test_diff(tmp_path):
    a = tmp_path / "a.json"
    a.write_text(json.dumps({"prmse_m": 0.2}))
    assert "OK" in _ok(["diff", a, a]).output
    _bad(["diff", a, tmp_path / "missing.json"], "missing.json")


def test_view(sim_run, tmp_path, monkeypatch):
    """No viewer is spawned: the command it would run is captured."""

    from uwbcal.pipeline.viz import runlog

    calls = []
    monkeypatch.setattr(runlog.subprocess, "run", lambda cmd, **kw: calls.append(cmd))
    monkeypatch.setenv("DISPLAY", ":99")
    _ok(["view", sim_run])
    assert len(calls) == 1 and str(sim_run / "run.rrd") in calls[0]
    _ok(["view", sim_run, "--web"])
    assert "--serve-web" in calls[1] and "127.0.0.1" in calls[1]
    (tmp_path / "norrd").mkdir()
    _bad(["view", tmp_path / "norrd"], "run.rrd", "missing")
    assert len(calls) == 2


def test_bench(tmp_path):
    out = tmp_path / "b.json"
    res = _ok(["bench", "--quick", "--cases", "calibration", "-o", out])
    doc = json.loads(out.read_text())
    assert doc["quick"] and [r["case"] for r in doc["results"]] == ["calibration"] and doc["results"][0]["ok"]
    assert "calibration" in res.output
    _bad(["bench", "--quick", "--cases", "nope"], "nope")


def test_numerical_warnings_become_a_note(capsys):
    """A numpy RuntimeWarning inside a command reaches the user as one note naming where it arose, not raw."""
    import typer

    from uwbcal.cli import _guard

    @_guard
    def noisy() -> None:
        np.array([0.0]) / np.array([0.0])
        np.array([1.0]) / np.array([0.0])

    try:
        noisy()
    except typer.Exit:
        pass
    err = capsys.readouterr().err.splitlines()
    assert len(err) == 2 and all(e.startswith("note: a numerical step produced NaN/inf (") for e in err)
    assert "tests/test_cli.py:" in err[0] and "RuntimeWarning" not in "".join(err)
