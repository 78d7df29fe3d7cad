"""Property tests (hypothesis) of the text readers at the edges: TUM trajectories, range CSVs, TOML configs.

Each reader, on any input, either returns data that round-trips exactly or raises `InputError` naming the file;
never another exception (which the CLI would report as a bug)."""

from __future__ import annotations

import tempfile
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from uwbcal.convert.sources import ID_MAX, read_ranges_csv, read_tum
from uwbcal.evaluate.export import tum_text
from uwbcal.pipeline.core.errors import InputError
from uwbcal.pipeline.run.config import load_config

SETTINGS = settings(
    max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)

finite = st.floats(min_value=-1e4, max_value=1e4, allow_nan=False, allow_infinity=False)
stamps = st.lists(st.integers(min_value=0, max_value=2**62), min_size=1, max_size=30, unique=True)


def _write(data: str | bytes, suffix: str) -> Path:
    f = tempfile.NamedTemporaryFile("wb", suffix=suffix, delete=False)  # noqa: SIM115
    f.write(data.encode() if isinstance(data, str) else data)
    f.close()
    return Path(f.name)


@SETTINGS
@given(t=stamps, data=st.data())
def test_tum_round_trip_is_exact(t, data):
    n = len(t)
    p = np.array(data.draw(st.lists(st.tuples(finite, finite, finite), min_size=n, max_size=n)))
    q = np.array(data.draw(st.lists(st.tuples(finite, finite, finite, finite), min_size=n, max_size=n)))
    path = _write(tum_text(np.array(t, np.int64), p, q), ".tum")
    try:
        got = read_tum(path)
    finally:
        path.unlink()
    np.testing.assert_array_equal(got.t_ns, t)  # exact nanoseconds through decimal seconds
    np.testing.assert_array_equal(got.p, p)
    np.testing.assert_array_equal(got.q_xyzw, q)


@SETTINGS
@given(text=st.one_of(st.text(max_size=300), st.binary(max_size=300)))
def test_tum_reader_on_anything_returns_or_names_the_file(text):
    path = _write(text, ".tum")
    try:
        got = read_tum(path)
        assert len(got.t_ns) == len(got.p) == len(got.q_xyzw) > 0
    except InputError as exc:
        assert str(path) in str(exc)
    finally:
        path.unlink()


ids = {k: st.integers(min_value=0, max_value=v) for k, v in ID_MAX.items()}


@SETTINGS
@given(
    rows=st.lists(
        st.tuples(
            st.integers(min_value=10**17, max_value=2**62),
            ids["tag"],
            ids["antenna"],
            ids["anchor"],
            st.floats(min_value=0, max_value=1e3, allow_nan=False),
        ),
        min_size=1,
        max_size=30,
    )
)
def test_ranges_csv_round_trip_keeps_full_id_range(rows):
    text = "stamp,tag,antenna,anchor,distance\n" + "".join(
        f"{a},{b},{c},{d},{e!r}\n" for a, b, c, d, e in rows
    )
    path = _write(text, ".csv")
    try:
        r, unit = read_ranges_csv(path)
    finally:
        path.unlink()
    assert unit == "ns"
    cols = list(zip(*rows, strict=True))
    for got, want in zip((r.t_ns, r.tag, r.antenna, r.anchor, r.distance), cols, strict=True):
        np.testing.assert_array_equal(got, want)


@SETTINGS
@given(
    col=st.sampled_from(["tag", "antenna", "anchor"]),
    value=st.one_of(st.integers(max_value=-1), st.integers(min_value=2**32, max_value=2**63 - 1)),
)
def test_ranges_csv_ids_out_of_range_are_refused(col, value):
    row = {"stamp": 10**18, "tag": 1, "antenna": 0, "anchor": 3, "distance": 2.5}
    row[col] = value if not (col == "antenna" and value >= 2**32) else 256
    text = "stamp,tag,antenna,anchor,distance\n" + ",".join(str(v) for v in row.values()) + "\n"
    path = _write(text, ".csv")
    try:
        with pytest.raises(InputError, match=f"{path}: line 2: column '{col}'"):
            read_ranges_csv(path)
    finally:
        path.unlink()


@SETTINGS
@given(data=st.one_of(st.binary(max_size=400), st.text(max_size=400)))
def test_ranges_csv_on_anything_returns_or_names_the_file(data):
    path = _write(data, ".csv")
    try:
        r, _ = read_ranges_csv(path)
        assert len(r.t_ns) == len(r.distance) > 0
    except InputError as exc:
        assert str(path) in str(exc)
    finally:
        path.unlink()


toml_values = st.one_of(
    st.integers(min_value=-(2**63), max_value=2**63 - 1).map(str),
    st.floats().map(
        lambda x: (
            "nan" if x != x else ("inf" if x == float("inf") else ("-inf" if x == -float("inf") else repr(x)))
        )
    ),
    st.sampled_from(['"10"', "true", "false", '"ri"', "[1, 2]", '"auto"', "{}"]),
)
keys = st.sampled_from(
    [
        ("run", "init_window_s"),
        ("run", "refine_window_s"),
        ("run", "log"),
        ("uwb", "sigma_range"),
        ("uwb", "min_ranges"),
        ("uwb", "init_method"),
        ("uwb", "chi2_quantile"),
        ("vio", "max_clones"),
        ("odometry", "sigma_p_per_sqrt_m"),
        ("uwb", "nonexistent"),
    ]
)


@SETTINGS
@given(entries=st.lists(st.tuples(keys, toml_values), min_size=1, max_size=4, unique_by=lambda e: e[0]))
def test_config_is_strict_finite_or_names_the_file(entries):
    sections: dict[str, list[str]] = {}
    for (sec, key), value in entries:
        sections.setdefault(sec, []).append(f"{key} = {value}")
    text = "".join(f"[{sec}]\n" + "\n".join(lines) + "\n" for sec, lines in sections.items())
    path = _write(text, ".toml")
    try:
        cfg = load_config(path)
    except InputError as exc:
        assert str(path) in str(exc) and "\n" not in str(exc)
        return
    finally:
        path.unlink()
    for (sec, key), value in entries:  # accepted: the value is exactly what the file says, of the key's type
        got = getattr(getattr(cfg, sec), key)
        assert not isinstance(got, str) or value.strip('"') == got
        if isinstance(got, float):
            assert np.isfinite(got) and float(value) == got


@SETTINGS
@given(text=st.one_of(st.text(max_size=200), st.binary(max_size=200)))
def test_config_on_anything_returns_or_names_the_file(text):
    path = _write(text, ".toml")
    try:
        load_config(path)
    except InputError as exc:
        assert str(path) in str(exc)
    finally:
        path.unlink()
