"""`uwbcal check`: each simulated data-preparation fault named in its verdict (and none on the clean recording),
the no-truth statistics, and a real surveyed set."""

from __future__ import annotations

import pytest
from check_faults import fault_recording
from typer.testing import CliRunner

from uwbcal.cli import app
from uwbcal.evaluate.check import check_recording

runner = CliRunner()


@pytest.fixture(scope="module")
def faults(tmp_path_factory):
    root = tmp_path_factory.mktemp("check-faults")
    return {
        f: fault_recording(f, root / f"{f}.mcap", duration=25.0) for f in ("none", "swap", "mirror", "clock")
    }


def _verdicts(path) -> list[str]:
    return check_recording(path).render().split("verdict:\n")[1].splitlines()


def test_clean_recording_has_no_problem(faults):
    text = check_recording(faults["none"]).render()
    assert text.endswith("OK no problem found"), text
    for part in (
        "ranges per link:",
        "visibility per anchor",
        "stamps: ranges",
        "pose excitation",
        "anchor ids",
    ):
        assert part in text


def test_swapped_anchor_ids_are_named(faults):
    v = _verdicts(faults["swap"])
    assert len(v) == 2 and all("anchor id swap" in x for x in v), v
    assert "ranges of anchor 1 fit the truth of anchor 2" in v[0] and "ranged 2 is surveyed 1" in v[1]


def test_mirrored_lever_arm_is_named(faults):
    v = _verdicts(faults["mirror"])
    assert len(v) == 1 and "lever arm of tag 1 mirrored: the ranges fit [0.3, 0.2, 0.1]" in v[0], v


def test_clock_offset_is_named_with_its_fix(faults):
    v = _verdicts(faults["clock"])
    assert len(v) == 1 and "ranges are stamped 0.2" in v[0] and "s late" in v[0], v
    fix = float(v[0].split("--time-offset ")[1])
    assert fix == pytest.approx(-0.2, abs=0.03)


def test_cli_check(faults, tmp_path):
    res = runner.invoke(app, ["check", str(faults["clock"])])
    assert res.exit_code == 0 and "PROBLEM clock offset" in res.output, res.output
    res = runner.invoke(app, ["check", str(tmp_path / "missing.mcap")])
    assert res.exit_code == 2 and "missing.mcap: no such recording" in res.output


@pytest.mark.data
def test_surveyed_rcv_clock_offset(data_dir, tmp_path):
    """RCV seq4: ranges ~0.09 s late against the poses (its SOURCES.md): the scan finds them late."""
    from uwbcal.convert.tabular import convert_tabular

    src = data_dir / "surveyed" / "rcv_seq4"
    if not src.is_dir():
        pytest.skip(f"{src} missing")
    rec = tmp_path / "rcv.mcap"
    convert_tabular(
        src / "poses.tum",
        src / "ranges.csv",
        rec,
        src / "antennas.yaml",
        anchors_truth=src / "anchors_truth.csv",
    )
    v = [x for x in check_recording(rec).render().splitlines() if x.startswith("PROBLEM clock offset")]
    assert len(v) == 1 and "s late" in v[0], v
    assert -0.15 < float(v[0].split("--time-offset ")[1]) < -0.03


def test_an_anchor_fitting_no_survey_is_named(faults, tmp_path):
    """A truth CSV (in the poses' frame) with anchor 3 surveyed 8 m off: named as fitting no survey, no swap."""
    from uwbcal.convert.recording import RecordingReader

    truth = RecordingReader(faults["none"]).truth["anchors"]
    rows = ["anchor,x,y,z"]
    for a, v in truth.items():
        x, y, z = v["position"]
        rows.append(f"{a},{x + (8.0 if a == '3' else 0.0)},{y},{z}")
    (tmp_path / "truth.csv").write_text("\n".join(rows) + "\n")
    v = check_recording(faults["none"], tmp_path / "truth.csv").render().split("verdict:\n")[1].splitlines()
    assert any("anchor 3: its ranges fit no surveyed position" in x for x in v), v
    assert not any("swap" in x for x in v), v
