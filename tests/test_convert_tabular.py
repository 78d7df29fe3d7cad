"""Tabular converter (TUM poses + ranges CSV) and the shared source helpers."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from uwbcal.convert.recording import RangeData, RecordingReader
from uwbcal.convert.sources import Drops, clean_ranges, order_and_dedup, parse_antennas, read_tum
from uwbcal.convert.tabular import convert_tabular
from uwbcal.pipeline.core.errors import InputError

from support import T0


def _tum(path: Path, n: int = 50) -> np.ndarray:
    t = T0 / 1e9 + np.arange(n) * 0.1
    lines = ["# timestamp(s) tx ty tz qx qy qz qw"]
    for k in range(n):
        lines.append(
            f"{T0 // 10**9 + k // 10}.{(k % 10) * 100000000:09d} {k * 0.1} 0.5 1.0 0 0 0.2 0.9797958971"
        )
    path.write_text("\n".join(lines) + "\n")
    return t


def _ranges(path: Path, seconds: bool, extra: list[str] = ()) -> list[str]:
    rows = []
    for k in range(40):
        t = T0 + k * 100_000_000 + 5_000_000
        stamp = f"{t // 10**9}.{t % 10**9:09d}" if seconds else str(t)
        rows.append(f"{stamp},200,{k % 2},{100 + k % 3},{5 + 0.01 * k}")
    path.write_text("stamp,tag,antenna,anchor,distance\n" + "\n".join(rows + list(extra)) + "\n")
    return rows


@pytest.mark.parametrize("seconds", [False, True])
def test_roundtrip_and_units(tmp_path, seconds):
    _tum(tmp_path / "p.tum")
    _ranges(tmp_path / "r.csv", seconds)
    out = tmp_path / "o.mcap"
    text = convert_tabular(tmp_path / "p.tum", tmp_path / "r.csv", out)
    assert f"stamps read as {'s' if seconds else 'ns'}: the unit that puts the ranges on the poses'" in text
    rec = RecordingReader(out)
    r = rec.read_ranges()
    np.testing.assert_array_equal(
        r.t_ns, T0 + np.arange(40) * 100_000_000 + 5_000_000
    )  # exact, no float rounding
    np.testing.assert_array_equal(r.anchor, 100 + np.arange(40) % 3)
    np.testing.assert_allclose(r.distance, 5 + 0.01 * np.arange(40))
    od = rec.read_odometry()
    np.testing.assert_array_equal(od.t_ns, T0 + np.arange(50) * 100_000_000)
    np.testing.assert_allclose(od.p[:, 0], np.arange(50) * 0.1)
    np.testing.assert_allclose(np.linalg.norm(od.q_xyzw, axis=1), 1.0)
    assert rec.source["range_stamp_unit"] == ("s" if seconds else "ns")
    assert rec.calibration["uwb"]["tags"] == {"200": {"antennas": [[0.0, 0.0, 0.0], [0.0, 0.0, 0.0]]}}


def test_bad_rows_dropped_and_counted(tmp_path):
    _tum(tmp_path / "p.tum")
    rows = _ranges(tmp_path / "r.csv", False)
    t = str(T0 + 7)
    extra = [f"{t},200,0,100,nan", f"{t},200,0,101,-3", f"{t},200,0,102,5000", rows[3], rows[10]]
    _ranges(tmp_path / "r.csv", False, extra)
    # and one out-of-order row: the last line has an early stamp
    with open(tmp_path / "r.csv", "a") as f:
        f.write(f"{T0 + 1},201,0,100,4.0\n")
    yaml = tmp_path / "a.yaml"
    yaml.write_text(
        "antenna_offset: [200, 2, 0.0, -0.45, 0.0, 0.0, 0.45, 0.0,\n 201, 1, 0.1, 0.2, 0.3]\n"
        "ranging_bias: [200, -0.75, 201, -0.75]\n"
    )
    out = tmp_path / "o.mcap"
    text = convert_tabular(tmp_path / "p.tum", tmp_path / "r.csv", out, antennas=yaml)
    rec = RecordingReader(out)
    reasons = {d["reason"]: d["count"] for d in rec.source["dropped"]}
    assert reasons == {
        "distance NaN/inf": 1,
        "negative distance": 1,
        "absurd distance > 1000 m": 1,
        "duplicate stamp (kept the first)": 2,
    }
    r = rec.read_ranges()
    assert len(r) + sum(reasons.values()) == rec.source["range_rows"] == 46
    assert np.all(np.diff(r.t_ns) >= 0) and r.t_ns[0] == T0 + 1 and "out-of-order" in text
    uwb = rec.calibration["uwb"]
    assert uwb["tags"]["201"] == {"antennas": [[0.1, 0.2, 0.3]]} and uwb["gamma_prior"]["mean"] == 0.75


def test_errors(tmp_path):
    _tum(tmp_path / "p.tum")
    (tmp_path / "r.csv").write_text("t,tag,anchor,d\n1,2,3,4\n")
    with pytest.raises(
        InputError, match=r"r.csv: header: expected columns stamp,tag,antenna,anchor,distance"
    ):
        convert_tabular(tmp_path / "p.tum", tmp_path / "r.csv", tmp_path / "o.mcap")
    (tmp_path / "bad.tum").write_text("1.0 2 3\n")
    _ranges(tmp_path / "r.csv", False)
    with pytest.raises(InputError, match=r"bad.tum: line 1: 3 fields, expected 8"):
        convert_tabular(tmp_path / "bad.tum", tmp_path / "r.csv", tmp_path / "o.mcap")
    (tmp_path / "ms.csv").write_text("stamp,tag,antenna,anchor,distance\n1609059013000,200,0,100,5.0\n")
    text = convert_tabular(tmp_path / "p.tum", tmp_path / "ms.csv", tmp_path / "ms.mcap")
    assert "stamps read as ms" in text and "no overlap, the clocks differ" in text
    (tmp_path / "a.yaml").write_text("antenna_offset: [200, 2, 0.0, 0.1]\n")
    with pytest.raises(InputError, match=r"a.yaml: antenna_offset"):
        parse_antennas(tmp_path / "a.yaml")
    assert not (tmp_path / "o.mcap").exists()


def test_order_and_dedup_and_clean():
    drops = Drops()
    t = np.array([3, 1, 2, 2, 5, 4], np.int64)
    o = order_and_dedup(t, None, "/x", drops)
    np.testing.assert_array_equal(t[o], [1, 2, 3, 4, 5])
    assert drops.count("/x") == 1 and drops.notes
    r = RangeData(
        np.array([1, 1, 1, 2]),
        np.array([1, 1, 1, 1]),
        np.zeros(4, int),
        np.array([7, 8, 7, 7]),
        np.array([1.0, 2.0, 1.5, np.inf]),
    )
    d2 = Drops()
    c = clean_ranges(r, "/uwb/range", d2)
    assert len(c) == 2 and d2.count() == 2  # (1, 7) duplicate + inf


def test_tum_exact_stamps(tmp_path):
    (tmp_path / "x.tum").write_text("1403715274.30214 0 0 0 0 0 0 1\n-0.5 0 0 0 0 0 0 1\n12 0 0 0 0 0 0 1\n")
    p = read_tum(tmp_path / "x.tum")
    np.testing.assert_array_equal(p.t_ns, [1403715274302140000, -500000000, 12_000_000_000])


def _relative(path: Path, scale: int, offset_s: float = 0.0) -> None:
    """30 s of ranges at 5 Hz per link (two links) on a clock that starts at 0, in units of 1e-9 * scale s."""
    rows = []
    for k in range(300):
        t_ns = k * 100_000_000 + 3_000_000 + round(offset_s * 1e9)
        rows.append(f"{t_ns // scale},1,0,{k % 2},{5 + 0.01 * (k % 7)}")
    path.write_text("stamp,tag,antenna,anchor,distance\n" + "\n".join(rows) + "\n")


@pytest.mark.parametrize("unit,scale", [("s", 10**9), ("ms", 10**6), ("us", 10**3), ("ns", 1)])
def test_stamp_units_on_a_relative_clock(tmp_path, unit, scale):
    """Integer stamps of every unit from a clock that starts at 0 (poses relative too): the unit is the one that
    puts the ranges on the poses' span, and the summary says so; --stamp-unit gives the same."""
    poses = [f"{k * 0.05:.2f} {k * 0.01} 0 1 0 0 0 1" for k in range(640)]
    (tmp_path / "p.tum").write_text("\n".join(poses) + "\n")
    _relative(tmp_path / "r.csv", scale)
    if unit == "s":  # decimal seconds (integer seconds cannot carry 10 Hz)
        rows = [f"{k * 0.1 + 0.003:.3f},1,0,{k % 2},5.0" for k in range(300)]
        (tmp_path / "r.csv").write_text("stamp,tag,antenna,anchor,distance\n" + "\n".join(rows) + "\n")
    text = convert_tabular(tmp_path / "p.tum", tmp_path / "r.csv", tmp_path / "o.mcap")
    assert f"stamps read as {unit}: the unit that puts the ranges on the poses' time span" in text
    r = RecordingReader(tmp_path / "o.mcap").read_ranges()
    assert r.t_ns[0] == 3_000_000 and r.t_ns[-1] == 299 * 100_000_000 + 3_000_000
    text = convert_tabular(tmp_path / "p.tum", tmp_path / "r.csv", tmp_path / "o2.mcap", stamp_unit=unit)
    assert f"stamps in {unit} (--stamp-unit)" in text
    np.testing.assert_array_equal(RecordingReader(tmp_path / "o2.mcap").read_ranges().t_ns, r.t_ns)


def test_stamp_unit_by_rate_and_time_offset(tmp_path):
    """Ranges on their own relative clock (microseconds) against poses on an epoch clock: no unit overlaps, so
    the detection reads the link rate and warns with the offset that would align the starts; given that offset,
    the ranges land on the poses' clock."""
    t0 = 1_700_000_000
    poses = [f"{t0 + k * 0.05:.2f} {k * 0.01} 0 1 0 0 0 1" for k in range(640)]
    (tmp_path / "p.tum").write_text("\n".join(poses) + "\n")
    _relative(tmp_path / "r.csv", 10**3)
    text = convert_tabular(tmp_path / "p.tum", tmp_path / "r.csv", tmp_path / "o.mcap")
    assert "per-link median interval 0.2 s (5 Hz)" in text
    assert (
        "the ranges (stamps in us) span 0.003..29.903 s" in text
        and "give --time-offset 1699999999.997;" in text
    )
    text = convert_tabular(
        tmp_path / "p.tum", tmp_path / "r.csv", tmp_path / "o.mcap", time_offset=t0 - 0.2, stamp_unit="us"
    )
    assert "-0.2" not in text and "added to every range stamp (--time-offset)" in text
    r = RecordingReader(tmp_path / "o.mcap").read_ranges()
    assert r.t_ns[0] == t0 * 10**9 - 200_000_000 + 3_000_000
    with pytest.raises(InputError, match="--stamp-unit 'h'"):
        convert_tabular(tmp_path / "p.tum", tmp_path / "r.csv", tmp_path / "o.mcap", stamp_unit="h")
    with pytest.raises(InputError, match="--time-offset nan"):
        convert_tabular(tmp_path / "p.tum", tmp_path / "r.csv", tmp_path / "o.mcap", time_offset=float("nan"))
