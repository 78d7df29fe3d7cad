"""`uwbcal info` finds gaps, duplicate / out-of-order stamps and NaN, and reports drops."""

import numpy as np
from typer.testing import CliRunner

from cli import app
from convert.info import recording_info
from convert.recording import META_SOURCE, RecordingWriter

T0 = 1_600_000_000_000_000_000


def _write(path, t_imu, gyro, ranges=None, dropped=None):
    with RecordingWriter(path) as w:
        w.write_imu_batch(t_imu, gyro, np.zeros_like(gyro))
        if ranges is not None:
            w.write_range_batch(*ranges)
        w.set_metadata(META_SOURCE, {"dataset": "test", "sequence": "s", "dropped": dropped or []})


def test_clean_recording_has_no_problems(tmp_path):
    t = T0 + np.arange(1000, dtype=np.int64) * 5_000_000
    _write(tmp_path / "a.mcap", t, np.zeros((1000, 3)))
    rep = recording_info(tmp_path / "a.mcap")
    assert rep.problems == []
    assert rep.topics["/imu"].count == 1000
    assert abs(rep.duration_s - 4.995) < 1e-9
    assert "problems: none found" in rep.render()


def test_gap_duplicate_out_of_order_nan_and_drops(tmp_path):
    t = T0 + np.arange(1000, dtype=np.int64) * 5_000_000
    t[500:] += 1_000_000_000  # a 1 s gap
    t[100] = t[99]  # duplicate
    t[200], t[201] = t[201], t[200]  # out of order (header stamps)
    g = np.zeros((1000, 3))
    g[300, 1] = np.nan
    ranges = (T0 + np.arange(10) * 100_000_000, 1, 0, 5, np.r_[np.ones(9), -1.0])
    drops = [{"topic": "/uwb/range", "reason": "NaN distance", "count": 3, "example": "row 17"}]
    _write(tmp_path / "b.mcap", t, g, ranges, drops)
    rep = recording_info(tmp_path / "b.mcap")
    text = " | ".join(rep.problems)
    assert "gaps" in text and "1.005 s" in text
    assert "duplicate" in text and "out-of-order" in text
    assert "NaN" in text and "negative" in text
    out = CliRunner().invoke(app, ["info", str(tmp_path / "b.mcap")])
    assert out.exit_code == 0
    assert "3 x NaN distance" in out.output


def test_info_on_garbage_exits_2_with_one_line(tmp_path):
    bad = tmp_path / "bad.mcap"
    bad.write_text("garbage")
    out = CliRunner().invoke(app, ["info", str(bad)])
    assert out.exit_code == 2
    assert "bad.mcap" in out.output and len(out.output.strip().splitlines()) == 1
