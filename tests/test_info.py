"""`uwbcal info` finds gaps, duplicate / out-of-order stamps, NaN and truncation, and reports drops."""

import numpy as np
import pytest
from typer.testing import CliRunner

from uwbcal.cli import app
from uwbcal.convert.info import recording_info, stamp_problems
from uwbcal.convert.recording import META_CALIBRATION, META_SOURCE, RecordingWriter

from support import T0


def _write(path, t_imu, gyro, ranges=None, dropped=None, **kw):
    with RecordingWriter(path, **kw) as w:
        w.write_imu_batch(t_imu, gyro, np.zeros_like(gyro))
        if ranges is not None:
            w.write_range_batch(*ranges)
        w.set_metadata(META_SOURCE, {"dataset": "test", "sequence": "s", "dropped": dropped or []})
        w.set_metadata(META_CALIBRATION, {"uwb": {"tags": {"1": {"antennas": [[0.1, 0.2, 0.3]]}}}})


def test_clean_recording_has_no_problems(tmp_path):
    t = T0 + np.arange(1000, dtype=np.int64) * 5_000_000
    _write(tmp_path / "a.mcap", t, np.zeros((1000, 3)))
    rep = recording_info(tmp_path / "a.mcap")
    assert rep.problems == []
    assert rep.topics["/imu"].count == 1000 and rep.topics["/imu"].rate_hz == pytest.approx(200.0)
    assert abs(rep.duration_s - 4.995) < 1e-9
    text = rep.render()
    assert "problems: none found" in text and "dropped during conversion: nothing" in text
    assert "uwb tag 1: antennas [[0.1, 0.2, 0.3]]" in text


def test_gap_duplicate_out_of_order_nan_and_drops(tmp_path):
    t = T0 + np.arange(1000, dtype=np.int64) * 5_000_000
    t[500:] += 1_000_000_000  # a 1 s gap
    t[100] = t[99]  # duplicate
    t[200], t[201] = t[201], t[200]  # out of order (header stamps, in writing order)
    g = np.zeros((1000, 3))
    g[300, 1] = np.nan
    rt = T0 + np.arange(10, dtype=np.int64) * 100_000_000
    rt[[4, 5]] = rt[[5, 4]]
    ranges = (rt, 1, 0, 5, np.r_[np.ones(8), np.inf, -1.0])
    drops = [{"topic": "/uwb/range", "reason": "NaN distance", "count": 3, "example": "row 17"}]
    _write(tmp_path / "b.mcap", t, g, ranges, drops)
    rep = recording_info(tmp_path / "b.mcap")
    assert rep.kinds("/imu") == {"gap", "duplicate", "out_of_order", "nan"}
    by_kind = {p.kind: p for p in rep.problems if p.topic == "/imu"}
    assert by_kind["gap"].count == 1 and "1.005 s" in str(by_kind["gap"])
    assert (
        by_kind["duplicate"].count == 1 and by_kind["out_of_order"].count == 1 and by_kind["nan"].count == 1
    )
    assert rep.kinds("/uwb/range") == {"nan", "negative_range"}
    assert rep.kinds("/uwb/range tag 1 antenna 0 anchor 5") == {"out_of_order"}
    out = CliRunner().invoke(app, ["info", str(tmp_path / "b.mcap")])
    assert out.exit_code == 0
    assert "3 x NaN distance (e.g. row 17)" in out.output and "out-of-order" in out.output


def test_truncated_recording_is_reported(tmp_path):
    n = 20000
    t = T0 + np.arange(n, dtype=np.int64) * 5_000_000
    _write(tmp_path / "full.mcap", t, np.zeros((n, 3)), chunk_size=64 * 1024)
    data = (tmp_path / "full.mcap").read_bytes()
    (tmp_path / "cut.mcap").write_bytes(data[: len(data) // 2])
    rep = recording_info(tmp_path / "cut.mcap")
    assert rep.kinds() == {"truncated"}  # the recovered prefix itself is clean
    assert 0 < rep.topics["/imu"].count < n
    assert "recovered" in rep.render()


def test_stamp_problems_on_features_and_images(tmp_path):
    path = tmp_path / "cam.mcap"
    with RecordingWriter(path) as w:
        for k in [0, 1, 2, 3, 3, 20, 21]:  # a duplicate and a gap at 20 Hz
            w.write_features(T0 + k * 50_000_000, [k], [[1.0, 2.0]])
            w.write_image("/cam0/image_raw", T0 + k * 50_000_000, np.zeros((4, 6), np.uint8))
    rep = recording_info(path)
    assert rep.kinds("/cam0/features") == {"duplicate", "gap"}
    assert rep.kinds("/cam0/image_raw") == {"duplicate", "gap"}


def test_stamp_problems_closed_form():
    t = np.array([0, 10, 20, 30, 100, 110, 110, 105], np.int64)
    got = {p.kind: p.count for p in stamp_problems("x", t)}
    assert got == {"gap": 1, "duplicate": 1, "out_of_order": 1}
    assert stamp_problems("x", np.arange(0, 100, 10)) == []


def test_info_on_garbage_exits_2_with_one_line(tmp_path):
    bad = tmp_path / "bad.mcap"
    bad.write_text("garbage")
    out = CliRunner().invoke(app, ["info", str(bad)])
    assert out.exit_code == 2
    assert "bad.mcap" in out.output and len(out.output.strip().splitlines()) == 1


def test_info_prints_the_odometry_error_model(tmp_path):
    t = T0 + np.arange(10, dtype=np.int64) * 5_000_000
    with RecordingWriter(tmp_path / "o.mcap") as w:
        w.write_imu_batch(t, np.zeros((10, 3)), np.zeros((10, 3)))
        cal = {
            "odometry": {
                "error_model": "bounded",
                "correlation_time_s": 5.0,
                "noise": {"initial_sigma_p": 0.03},
            }
        }
        w.set_metadata(META_CALIBRATION, cal)
    text = recording_info(tmp_path / "o.mcap").render()
    assert "odometry error model: bounded, correlation_time_s=5.0" in text
    assert "odometry noise: initial_sigma_p=0.03" in text
