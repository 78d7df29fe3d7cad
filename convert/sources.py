"""Helpers shared by the dataset converters: provenance (sha256), drop bookkeeping, progress, CSV/TUM/yaml
readers, range cleaning and the streamed ROS1-bag loop. One implementation used by euroc, ntu_viral, tabular.
"""

from __future__ import annotations

import contextlib
import csv
import gc
import hashlib
import io
import re
import struct
import threading
from array import array
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field
from importlib import metadata as _im
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import yaml
from rosbags.serde import SerdeError

from uwbcal.convert import ros1_wire
from uwbcal.convert.bag_recovery import Recovery, open_ros1
from uwbcal.convert.recording import RangeData
from uwbcal.pipeline.core.errors import InputError
from uwbcal.pipeline.core.progress import progress

if TYPE_CHECKING:
    import polars as pl

MAX_RANGE_M = 1000.0


def converter_name() -> str:
    try:
        version = _im.version("uwbcal")
    except _im.PackageNotFoundError:
        version = "0.1.0"
    return f"uwbcal {version}"


# ---------------------------------------------------------------------------------------------------------------
# provenance
# ---------------------------------------------------------------------------------------------------------------
def sha256_file(path: str | Path, block: int = 8 << 20) -> str:
    """sha256 of a file, read in ``block``-byte pieces into one reused buffer (no fresh pages per piece)."""
    h = hashlib.sha256()
    buf = bytearray(block)
    view = memoryview(buf)
    with open(path, "rb", buffering=0) as f:
        while n := f.readinto(buf):
            h.update(view[:n])
    return h.hexdigest()


class Hasher:
    """Hashes input files in a background thread (hashlib releases the GIL) while the conversion runs."""

    def __init__(self, paths: Sequence[str | Path]) -> None:
        self.paths = [Path(p) for p in paths]
        self._result: list[dict] = []
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        self._result = [{"path": str(p), "sha256": sha256_file(p)} for p in self.paths]

    def result(self) -> list[dict]:
        self._thread.join()
        return self._result


@dataclass
class Drops:
    """Counted, reported losses: every record not converted lands here with a reason and an example."""

    entries: dict[tuple[str, str], list] = field(default_factory=dict)
    notes: list[str] = field(default_factory=list)

    def add(self, topic: str, reason: str, count: int = 1, example: object = None) -> None:
        if count <= 0:
            return
        e = self.entries.setdefault((topic, reason), [0, None])
        e[0] += int(count)
        if e[1] is None and example is not None:
            e[1] = str(example)

    def note(self, text: str) -> None:
        self.notes.append(text)

    def count(self, topic: str | None = None) -> int:
        return sum(c for (t, _), (c, _) in self.entries.items() if topic is None or t == topic)

    def as_list(self) -> list[dict]:
        return [
            {"topic": t, "reason": r, "count": c, "example": ex} for (t, r), (c, ex) in self.entries.items()
        ]


def source_metadata(dataset: str, sequence: str, files: list[dict], drops: Drops, **extra) -> dict:
    return {
        "dataset": dataset,
        "sequence": sequence,
        "files": files,
        "converter": converter_name(),
        "dropped": drops.as_list(),
        **({"notes": drops.notes} if drops.notes else {}),
        **extra,
    }


def summary(output: str | Path, counts: dict[str, int], drops: Drops, header: str) -> str:
    lines = [f"{header} -> {output}"]
    for topic in sorted(counts):
        lines.append(f"  {topic:<24} {counts[topic]:>9} messages")
    if drops.entries:
        lines.append("  dropped:")
        for d in drops.as_list():
            ex = f" (e.g. {d['example']})" if d["example"] else ""
            lines.append(f"    {d['topic']:<22} {d['count']:>9}  {d['reason']}{ex}")
    else:
        lines.append("  dropped: none")
    lines.extend(f"  note: {n}" for n in drops.notes)
    return "\n".join(lines)


# ---------------------------------------------------------------------------------------------------------------
# CSV / TUM / yaml
# ---------------------------------------------------------------------------------------------------------------
def _require_file(path: Path, what: str) -> None:
    if path.is_dir():
        raise InputError(f"{path}: a folder, not the {what}; give the file")
    if not path.is_file():
        raise InputError(f"{path}: missing {what}; check the path (or the dataset's layout)")


def read_text(path: str | Path, what: str) -> str:
    """A UTF-8 text input (a BOM is tolerated); InputError naming the file and the byte otherwise."""
    path = Path(path)
    _require_file(path, what)
    try:
        return path.read_bytes().decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        raise InputError(f"{path}: byte {exc.start}: not UTF-8 text ({what}); save it as UTF-8") from None


def read_csv_strings(path: str | Path, columns: Sequence[str] | int, *, what: str = "CSV") -> pl.DataFrame:
    """Read a CSV as strings; check the header. ``columns`` = required names, or the minimal column count
    (then the first columns are taken positionally, as for EuRoC's free-form '#timestamp [ns],...' headers)."""
    import polars as pl

    path = Path(path)
    _require_file(path, what)
    try:
        df = pl.read_csv(path, has_header=True, infer_schema_length=0, truncate_ragged_lines=False)
    except (pl.exceptions.ComputeError, pl.exceptions.NoDataError, OSError) as exc:
        ragged = _ragged_line(path)
        if ragged:
            raise InputError(f"{path}: {ragged}") from None
        first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise InputError(f"{path}: unreadable CSV ({first}); expected columns {_fmt_cols(columns)}") from None
    found = [c.strip().lstrip("\ufeff") for c in df.columns]  # a UTF-8 BOM is not part of the name
    df.columns = found
    if isinstance(columns, int):
        if len(found) < columns:
            raise InputError(
                f"{path}: header: expected {columns} columns, found {len(found)} ({','.join(found)})"
            )
        return df.select(df.columns[:columns])
    missing = [c for c in columns if c not in found]
    if missing:
        sep = next((n for c, n in (("\t", "tabs"), (";", "';'")) if len(found) == 1 and c in found[0]), None)
        hint = f"; the fields are separated by {sep}: save it with ',' between fields" if sep else ""
        raise InputError(
            f"{path}: header: expected columns {','.join(columns)}; found {','.join(found)} "
            f"(missing {','.join(missing)}){hint}"
        )
    return df.select(list(columns))


def _ragged_line(path: Path) -> str | None:
    """The first line whose field count is not the header's, and why when it can tell (a decimal comma)."""
    try:
        text = path.read_bytes().decode("utf-8")
    except (OSError, UnicodeDecodeError):
        return None
    rows = csv.reader(io.StringIO(text))
    header = next(rows, [])
    for i, row in enumerate(rows, start=2):
        if row and len(row) != len(header):
            fix = "quote or remove the extra fields"
            if len(header) == 1 and "\t" in header[0]:
                fix = "the fields are separated by tabs: save it with ',' between fields and '.' as the decimal point"
            elif len(header) == 1 and ";" in header[0]:
                fix = "the fields are separated by ';' (a decimal-comma export): save it with ',' between fields and '.' as the decimal point"
            elif len(row) > len(header) and _split_decimal(row):
                fix = "a decimal comma? write numbers with '.' as the decimal point (4.05, not 4,05)"
            return f"line {i}: {len(row)} fields, the header has {len(header)}; {fix}"
    return None


def _split_decimal(row: list[str]) -> bool:
    """Two neighbouring fields that read as one number with a decimal comma ('-3', '5' of -3,5)."""
    f = [x.strip() for x in row]
    return any(
        re.fullmatch(r"[-+]?\d+", a) and re.fullmatch(r"\d+", b) for a, b in zip(f, f[1:], strict=False)
    )


def _fmt_cols(columns: Sequence[str] | int) -> str:
    return f"{columns} numeric columns" if isinstance(columns, int) else ",".join(columns)


LINE = "_line"  # a table's column of file line numbers, where rows are not lines 2, 3, ... (TUM: no header, comments)


def _bad_row(
    path: Path, name: str, raw: pl.Series, parsed: pl.Series, what: str, df: pl.DataFrame
) -> InputError:
    bad = (parsed.is_null() & raw.is_not_null()) | raw.is_null()
    i = int(np.flatnonzero(bad.to_numpy())[0])
    line = int(df[LINE][i]) if LINE in df.columns else i + 2
    text = raw[i]
    if text is None:
        return InputError(
            f"{path}: line {line}: column '{name}': empty (a blank line?); remove the line or fill in the value"
        )
    if re.fullmatch(r"[-+]?\d+,\d+", text):
        fix = f"a decimal comma: write {text.replace(',', '.')!r}"
    else:
        fix = "fix or remove the row"
    return InputError(f"{path}: line {line}: column '{name}': {text!r} is not {what}; {fix}")


def to_float(path: Path, df: pl.DataFrame, name: str) -> np.ndarray:
    import polars as pl

    raw = df[name].str.strip_chars()
    parsed = raw.cast(pl.Float64, strict=False)
    if parsed.null_count():
        raise _bad_row(path, name, raw, parsed, "a number", df)
    return parsed.to_numpy()


def to_int(path: Path, df: pl.DataFrame, name: str) -> np.ndarray:
    import polars as pl

    raw = df[name].str.strip_chars()
    parsed = raw.cast(pl.Int64, strict=False)
    if parsed.null_count():
        raise _bad_row(path, name, raw, parsed, "an integer", df)
    return parsed.to_numpy()


STAMP_UNITS = {"s": 9, "ms": 6, "us": 3, "ns": 0}  # unit -> decimal digits to nanoseconds


@dataclass(frozen=True)
class RawStamps:
    """A stamp column as written (integer part, first nine decimals, sign), before its unit is known."""

    whole: np.ndarray  # int64, |integer part|
    frac9: np.ndarray  # int64, the fraction's first nine decimals
    sign: np.ndarray  # +1 / -1
    decimal: bool  # some stamp has a decimal point

    def fits(self, unit: str) -> bool:
        """The stamps, read in ``unit``, fit int64 nanoseconds."""
        return not len(self.whole) or int(self.whole.max()) < (2**63 - 1) // 10 ** STAMP_UNITS[unit] - 1

    def ns(self, unit: str) -> np.ndarray:
        """Exact int64 nanoseconds (no float rounding; decimals below 1 ns dropped)."""
        k = STAMP_UNITS[unit]
        return self.sign * (self.whole * 10**k + self.frac9 // 10 ** (9 - k))

    def magnitude_unit(self) -> str | None:
        """The unit by magnitude alone: integers below 1e11 or decimals -> s, integers from 1e17 -> ns."""
        top = int(self.whole.max()) if len(self.whole) else 0
        if self.decimal:
            return "s" if top < 10**11 else None
        return "s" if top < 10**11 else "ns" if top >= 10**17 else None


def parse_stamps(path: Path, df: pl.DataFrame, name: str) -> RawStamps:
    import polars as pl

    raw = df[name].str.strip_chars()
    unsigned = raw.str.strip_prefix("-")
    parts = unsigned.str.split_exact(".", 1).struct.unnest()
    whole = parts["field_0"].cast(pl.Int64, strict=False)
    frac = parts["field_1"].fill_null("0").str.pad_end(9, "0").str.slice(0, 9)
    frac_ok = frac.str.contains(r"^[0-9]{9}$")
    frac = frac.cast(pl.Int64, strict=False)
    ok = whole.is_not_null() & frac.is_not_null() & frac_ok.fill_null(False) & (whole >= 0).fill_null(False)
    if not ok.all():
        nulls = pl.Series([None] * len(raw), dtype=pl.Int64)
        raise _bad_row(path, name, raw, whole.zip_with(ok, nulls), "a time stamp", df)
    sign = np.where(raw.str.starts_with("-").to_numpy(), -1, 1)
    return RawStamps(whole.to_numpy(), frac.to_numpy(), sign, bool(raw.str.contains(".", literal=True).any()))


def to_stamps_ns(path: Path, df: pl.DataFrame, name: str) -> tuple[np.ndarray, str]:
    """Exact int64 nanoseconds from integer ns or decimal seconds (no float rounding); returns (t_ns, unit)."""
    stamps = parse_stamps(path, df, name)
    unit = magnitude_unit(path, name, stamps)
    return stamps.ns(unit), unit


def magnitude_unit(path: Path, name: str, stamps: RawStamps) -> str:
    unit = stamps.magnitude_unit()
    if unit is None:
        first = int(stamps.sign[0] * stamps.whole[0])
        raise InputError(
            f"{path}: column '{name}': stamps like {first} are neither seconds nor nanoseconds by their "
            "magnitude; give stamps in ns or s"
        )
    return unit


@dataclass
class PoseTable:
    t_ns: np.ndarray
    p: np.ndarray
    q_xyzw: np.ndarray


def read_tum(path: str | Path) -> PoseTable:
    """TUM trajectory ``t[s] x y z qx qy qz qw`` (whitespace separated, '#' comments), stamps exact."""
    import polars as pl

    path = Path(path)
    numbered = [
        (n, ln.split())
        for n, ln in enumerate(read_text(path, "TUM trajectory").splitlines(), start=1)
        if ln.strip() and not ln.lstrip().startswith("#")
    ]
    if not numbered:
        raise InputError(f"{path}: no poses; expected TUM lines 't x y z qx qy qz qw'")
    bad = next(((n, r) for n, r in numbered if len(r) != 8), None)
    if bad is not None:
        fix = "a decimal comma? write '.' as the decimal point" if any("," in f for f in bad[1]) else ""
        raise InputError(
            f"{path}: line {bad[0]}: {len(bad[1])} fields, expected 8 (t x y z qx qy qz qw)"
            + (f"; {fix}" if fix else "")
        )
    names = ["t", "x", "y", "z", "qx", "qy", "qz", "qw"]
    df = pl.DataFrame([r for _, r in numbered], schema=names, orient="row")
    df = df.with_columns(pl.Series(LINE, [n for n, _ in numbered]))
    t, _ = to_stamps_ns(path, df, "t")
    vals = np.column_stack([to_float(path, df, n) for n in names[1:]])
    return PoseTable(t, vals[:, :3], vals[:, 3:])


def normalise_quaternions(
    q: np.ndarray, topic: str, drops: Drops, tol: float = 1e-2
) -> tuple[np.ndarray, np.ndarray]:
    """Unit quaternions and a keep-mask; rows whose norm is off by more than ``tol`` are dropped (reported)."""
    n = np.linalg.norm(q, axis=1)
    keep = np.isfinite(n) & (np.abs(n - 1.0) <= tol)
    drops.add(
        topic,
        f"non-unit quaternion (|q| off by > {tol})",
        int((~keep).sum()),
        None if keep.all() else np.round(q[~keep][0], 6).tolist(),
    )
    return q / np.where(keep, n, 1.0)[:, None], keep


class _UniqueKeyLoader(yaml.SafeLoader):
    """PyYAML's safe loader, refusing a key given twice in one mapping (PyYAML keeps the last silently); merge
    keys (``<<: *base``) are YAML's own way to override and stay allowed."""

    def construct_mapping(self, node, deep=False):
        seen: set = set()
        for key_node, _ in node.value:
            if key_node.tag == "tag:yaml.org,2002:merge":
                continue
            key = self.construct_object(key_node, deep=True)
            if isinstance(key, str | int | float | bool) and key in seen:
                raise yaml.constructor.ConstructorError(
                    None, None, f"key {key!r} given twice (line {key_node.start_mark.line + 1})", None
                )
            seen.add(key)
        return super().construct_mapping(node, deep)


# YAML 1.1 (PyYAML) reads 1e-4 (no decimal point) as text; YAML 1.2, and every user, read it as a number
_UniqueKeyLoader.add_implicit_resolver(
    "tag:yaml.org,2002:float", re.compile(r"^[-+]?[0-9][0-9_]*[eE][-+]?[0-9]+$"), list("-+0123456789")
)


def _yaml_problem(exc: yaml.YAMLError) -> str:
    """A YAML error as ``line N: problem; fix``."""
    text = str(exc)
    twice = next((ln.strip() for ln in text.splitlines() if "given twice" in ln), None)
    if twice:
        return f"{twice}; give each key once"
    mark = getattr(exc, "problem_mark", None) or getattr(exc, "context_mark", None)
    problem = getattr(exc, "problem", None) or text.splitlines()[0]
    where = f"line {mark.line + 1}, column {mark.column + 1}: " if mark is not None else ""
    fix = "indent with spaces, not tabs" if "\t" in text or "tab" in problem else "fix the YAML syntax there"
    return f"{where}{problem}; {fix}"


def load_yaml(path: str | Path, what: str) -> dict:
    """YAML, tolerating OpenCV's ``%YAML:1.0`` header and ``!!opencv-matrix`` tags; a key given twice in one
    mapping is refused."""
    path = Path(path)
    text = read_text(path, what)
    lines = ["" if ln.startswith("%YAML") else ln for ln in text.splitlines()]  # line numbers kept
    text = "\n".join(lines).replace("!!opencv-matrix", "")
    try:
        data = yaml.load(text, Loader=_UniqueKeyLoader)  # noqa: S506 - a SafeLoader
    except yaml.YAMLError as exc:
        raise InputError(f"{path}: invalid YAML ({what}): {_yaml_problem(exc)}") from None
    if not isinstance(data, dict):
        raise InputError(f"{path}: expected a YAML mapping ({what})")
    return data


# ---------------------------------------------------------------------------------------------------------------
# UWB: antenna yaml and range cleaning
# ---------------------------------------------------------------------------------------------------------------
DEFAULT_GAMMA_SIGMA = 0.3
DEFAULT_BETA_PRIOR = {"mean": 1.0, "sigma": 0.05}
DEFAULT_SIGMA_RANGE = 0.1


def parse_antennas(path: str | Path) -> tuple[dict[str, dict], dict[int, float]]:
    """``antenna_offset: [tag, n, x,y,z, ... (n times), tag, n, ...]`` and ``ranging_bias: [tag, b, ...]``
    -> ({"<tag>": {"antennas": [[x,y,z], ...]}}, {tag: b})."""
    path = Path(path)
    data = load_yaml(path, "antenna yaml")
    flat = data.get("antenna_offset")
    if not isinstance(flat, list) or not flat:
        raise InputError(f"{path}: 'antenna_offset' missing or empty; expected [tag, n, x, y, z, ...]")
    tags: dict[str, dict] = {}
    i = 0
    try:
        while i < len(flat):
            tag, n = int(flat[i]), int(flat[i + 1])
            xyz = np.asarray(flat[i + 2 : i + 2 + 3 * n], float)
            if n <= 0 or xyz.size != 3 * n:
                raise ValueError(f"tag {tag}: {n} antennas need {3 * n} numbers, got {xyz.size}")
            tags[str(tag)] = {"antennas": xyz.reshape(n, 3).tolist()}
            i += 2 + 3 * n
    except (ValueError, TypeError, IndexError) as exc:
        raise InputError(
            f"{path}: antenna_offset: entry {i}: {exc}; expected [tag, n, x, y, z, ...]"
        ) from None
    bias_flat = data.get("ranging_bias") or []
    if len(bias_flat) % 2:
        raise InputError(f"{path}: ranging_bias: odd length {len(bias_flat)}; expected [tag, bias, ...]")
    bias = {int(bias_flat[k]): float(bias_flat[k + 1]) for k in range(0, len(bias_flat), 2)}
    return tags, bias


def uwb_calibration(
    tags: dict[str, dict],
    bias: dict[int, float],
    *,
    gamma_sigma: float = DEFAULT_GAMMA_SIGMA,
    sigma_range: float = DEFAULT_SIGMA_RANGE,
    beta_sigma: float | None = None,
) -> dict:
    """`uwbcal.calibration.uwb`. ranging_bias b: true = measured + b, so with d = beta*|.| + gamma, gamma ~ -b."""
    gamma_mean = -float(np.mean(list(bias.values()))) if bias else 0.0
    beta = dict(DEFAULT_BETA_PRIOR)
    if beta_sigma is not None:
        beta["sigma"] = float(beta_sigma)
    out = {
        "tags": tags,
        "sigma_range": sigma_range,
        "gamma_prior": {"mean": gamma_mean, "sigma": gamma_sigma},
        "beta_prior": beta,
    }
    if bias and len(set(bias.values())) > 1:
        out["ranging_bias_per_tag"] = {str(k): v for k, v in bias.items()}
    return out


def default_tags(tag: np.ndarray, antenna: np.ndarray) -> dict[str, dict]:
    """Zero lever arms for every (tag, antenna) seen, when no antenna yaml is given."""
    out = {}
    for t in np.unique(tag):
        n = int(antenna[tag == t].max()) + 1
        out[str(int(t))] = {"antennas": [[0.0, 0.0, 0.0]] * n}
    return out


RANGE_COLUMNS = ("stamp", "tag", "antenna", "anchor", "distance")
ID_MAX = {"tag": 2**32 - 1, "antenna": 2**8 - 1, "anchor": 2**32 - 1}  # uwbcal_msgs/UwbRange field widths


def id_problem(ids: dict[str, np.ndarray]) -> tuple[str, int] | None:
    """(field, index) of the first tag / antenna / anchor id outside its field in the recording, or None."""
    for name, v in ids.items():
        a = (
            np.asarray(v) if isinstance(v, np.ndarray) else np.asarray(v, dtype=object)
        )  # ints beyond int64 kept
        bad = (a < 0) | (a > ID_MAX[name]) if len(a) else np.zeros(0, bool)
        if bad.any():
            return name, int(np.flatnonzero(bad)[0])
    return None


def id_text(name: str, value: int) -> str:
    hi = ID_MAX[name]
    return (
        f"{name} id {value} is outside 0..{hi} (the recording stores {name} ids as uint{8 if hi == 255 else 32}); "
        f"renumber the {name}s"
    )


def read_ranges_csv(
    path: str | Path, unit_of: Callable[[RawStamps, np.ndarray], str] | None = None
) -> tuple[RangeData, str]:
    """``stamp,tag,antenna,anchor,distance``; returns the table and the stamps' unit: ``unit_of(stamps, link)``
    (``link``: an index per row of its tag, antenna, anchor), by default by magnitude (ns or s)."""
    path = Path(path)
    df = read_csv_strings(path, RANGE_COLUMNS, what="UWB range CSV")
    if df.height == 0:
        raise InputError(f"{path}: no range rows; expected columns {','.join(RANGE_COLUMNS)}")
    stamps = parse_stamps(path, df, "stamp")
    ids = {name: to_int(path, df, name) for name in ("tag", "antenna", "anchor")}
    bad = id_problem(ids)
    if bad is not None:
        name, i = bad
        raise InputError(f"{path}: line {i + 2}: column '{name}': {id_text(name, int(ids[name][i]))}")
    if unit_of is None:
        unit = magnitude_unit(path, "stamp", stamps)
    else:
        link = np.unique(np.column_stack(list(ids.values())), axis=0, return_inverse=True)[1].ravel()
        unit = unit_of(stamps, link)
    t = stamps.ns(unit)
    return RangeData(t, ids["tag"], ids["antenna"], ids["anchor"], to_float(path, df, "distance")), unit


JUMP_PERIODS = 10  # a step back of more sample periods than this in one sensor's series is a clock jump


def clock_jump(t_ns: np.ndarray, resent_are_duplicates: bool = True) -> tuple[int, float, int] | None:
    """A clock jump in one sensor's stamps, in the order written: (step back [ns], sample period [ns], stamp
    before the step) when the largest step back exceeds `JUMP_PERIODS` sample periods and more than
    `JUMP_PERIODS` later samples fall inside the span already covered (a single late sample is reordering).
    ``resent_are_duplicates``: a stamp seen before is a re-sent sample (a file's repeated rows, dropped as
    duplicates), not a step back; False for a stream, where a stretch back onto earlier stamps is a jump."""
    t_ns = np.asarray(t_ns, np.int64)
    if len(t_ns) < 2 or not (np.diff(t_ns) < 0).any():
        return None
    t1 = t_ns[np.sort(np.unique(t_ns, return_index=True)[1])] if resent_are_duplicates else t_ns
    dt = np.diff(t1)
    if not len(dt):
        return None
    i = int(np.argmin(dt))
    step = -int(dt[i])
    fwd = dt[dt > 0]
    period = float(np.median(fwd)) if len(fwd) else 0.0
    inside = int((t1[i + 1 :] < t1[: i + 1].max()).sum())
    if period > 0 and step > JUMP_PERIODS * period and inside > JUMP_PERIODS:
        return step, period, int(t1[i])
    return None


def clock_jump_text(topic: str, jump: tuple[int, float, int]) -> str:
    step, period, before = jump
    return (
        f"{topic}: out-of-order stamps: they step back by {step * 1e-9:.6g} s ({step / period:.0f} sample "
        f"periods) after t={before} ns — a clock jump, not reordering (sorting would splice two stretches of "
        "the clock together); cut the data at the jump or fix the stamps"
    )


def order_and_dedup(
    t_ns: np.ndarray, key: np.ndarray | None, topic: str, drops: Drops, series: Path | None = None
) -> np.ndarray:
    """Indices that sort by (time, key) without exact duplicates of (t, key). Out-of-order input is sorted and
    noted; duplicates are dropped (counted, the first kept). ``series``: the file of one sensor's samples (IMU,
    poses), where a `clock_jump` is refused."""
    n = len(t_ns)
    if n == 0:
        return np.zeros(0, np.int64)
    back = int((np.diff(t_ns) < 0).sum()) if n > 1 else 0
    if back:
        jump = clock_jump(t_ns) if series is not None else None
        if jump is not None:
            raise InputError(f"{series}: {clock_jump_text(topic, jump)}")
        drops.note(
            f"{topic}: {back} out-of-order stamps (stepping back by up to {-int(np.diff(t_ns).min()) * 1e-9:.6g} "
            "s); sorted by stamp"
        )
    if key is None:
        order = np.argsort(t_ns, kind="stable")
    else:
        k2 = np.asarray(key).reshape(n, -1)
        order = np.lexsort([*k2.T[::-1], t_ns])  # stable: equal (t, key) rows keep their input order
    if n < 2:
        return order
    ts = t_ns[order]
    same = ts[1:] == ts[:-1]
    if key is not None:
        ks = k2[order]
        same &= np.all(ks[1:] == ks[:-1], axis=1)
    if same.any():
        drops.add(topic, "duplicate stamp (kept the first)", int(same.sum()), f"t={int(ts[1:][same][0])}")
        order = order[np.r_[True, ~same]]
    return order


def clean_ranges(r: RangeData, topic: str, drops: Drops, max_range: float = MAX_RANGE_M) -> RangeData:
    """Drop NaN/inf, negative and absurd (> max_range) distances, sort by time, drop duplicate rows."""
    d = r.distance
    bad_nan = ~np.isfinite(d)
    bad_neg = ~bad_nan & (d < 0)
    bad_big = ~bad_nan & (d > max_range)
    for mask, reason in (
        (bad_nan, "distance NaN/inf"),
        (bad_neg, "negative distance"),
        (bad_big, f"absurd distance > {max_range:g} m"),
    ):
        if mask.any():
            i = int(np.flatnonzero(mask)[0])
            drops.add(topic, reason, int(mask.sum()), f"t={r.t_ns[i]} anchor={r.anchor[i]} d={d[i]}")
    kept = r.select(np.flatnonzero(~(bad_nan | bad_neg | bad_big)))
    key = np.column_stack([kept.tag, kept.antenna, kept.anchor])
    return kept.select(order_and_dedup(kept.t_ns, key, topic, drops))


def time_offset_ns(offset_s: float) -> int:
    if not np.isfinite(offset_s) or abs(offset_s) > 1e10:
        raise InputError(f"--time-offset {offset_s}: expected a finite number of seconds")
    return round(offset_s * 1e9)


def shift_ranges(r: RangeData, offset_s: float, drops: Drops) -> RangeData:
    """The ranges with ``offset_s`` added to their stamps (a known range-to-pose clock offset), noted."""
    if offset_s == 0.0:
        return r
    drops.note(f"ranges: {offset_s:+.6g} s added to every range stamp (--time-offset)")
    return RangeData(r.t_ns + time_offset_ns(offset_s), r.tag, r.antenna, r.anchor, r.distance)


def anchors_note(r: RangeData) -> str:
    ids, counts = np.unique(r.anchor, return_counts=True)
    tags = np.unique(r.tag)
    return (
        "anchors "
        + ", ".join(f"{a} ({c})" for a, c in zip(ids.tolist(), counts.tolist(), strict=True))
        + "; tags "
        + ", ".join(str(t) for t in tags.tolist())
    )


# ---------------------------------------------------------------------------------------------------------------
# ROS1 bags
# ---------------------------------------------------------------------------------------------------------------
class Drop(Exception):
    """Raised by a bag handler to drop one message with a reason (counted, reported)."""


class StampCheck:
    """Per output topic, in the order a converter writes: drops exact duplicate stamps (`Drop`), and counts the
    steps back in time, with the largest. ``series``: the topics of one sensor's samples (IMU, poses), whose
    stamps are kept so that `report` refuses a `clock_jump` in them, as `order_and_dedup` does for a file."""

    def __init__(self, series: tuple[str, ...] = ()) -> None:
        self.last: dict[str, int] = {}
        self.back: dict[str, list[int]] = {}  # topic -> [count, largest step back ns, stamp after it]
        self.stamps: dict[str, array] = {t: array("q") for t in series}

    def __call__(self, topic: str, t: int) -> None:
        last = self.last.get(topic)
        if last is not None:
            if t == last:
                raise Drop("duplicate stamp (kept the first)")
            if t < last:
                b = self.back.setdefault(topic, [0, 0, 0])
                b[0] += 1
                if last - t > b[1]:
                    b[1], b[2] = last - t, last
        self.last[topic] = t
        if topic in self.stamps:
            self.stamps[topic].append(t)

    def report(self, drops: Drops, source: str | Path | None = None) -> None:
        """The out-of-order stamps as notes; a clock jump in a series topic refused (InputError naming
        ``source``)."""
        for topic, (n, step, after) in self.back.items():
            t = np.frombuffer(self.stamps[topic], np.int64) if topic in self.stamps else None
            jump = clock_jump(t, resent_are_duplicates=False) if t is not None else None
            if jump is not None:
                raise InputError(f"{source}: {clock_jump_text(topic, jump)}")
            drops.note(
                f"{topic}: {n} out-of-order stamps (stamps step back by up to {step * 1e-9:.6g} s, after "
                f"{after} ns): the recording orders them by stamp"
            )


def ros1_header_stamp(raw: bytes | memoryview) -> int:
    """Header stamp of a ROS1 message that starts with std_msgs/Header (uint32 seq, uint32 sec, uint32 nsec)."""
    sec, nsec = struct.unpack_from("<II", raw, 4)
    return sec * 1_000_000_000 + nsec


@dataclass
class BagRoute:
    """How one bag topic is converted: accepted ROS1 message types and a handler(writer, conn, bag_t, raw)."""

    msgtypes: tuple[str, ...]
    handler: Callable
    out_topic: str


def open_bag(path: Path) -> tuple[Any, Recovery | None]:
    """rosbags' rosbag1 reader of ``path``, opened; a bag without its index (truncated, or a killed recorder's)
    read up to its last intact chunk like `uwbcal convert bag` does (`bag_recovery`: the `Recovery` says what
    was kept), refused when not one message could be kept."""
    from rosbags.rosbag1 import Reader
    from rosbags.rosbag1.reader import ReaderError

    reader = Reader(path)
    try:
        reader.open()
        return reader, None
    except (ReaderError, OSError, struct.error, ValueError) as exc:
        problem = " ".join(str(exc).split()) or type(exc).__name__
    reader = Reader(path)
    rec = open_ros1(reader) if path.is_file() else None
    if rec is None:
        raise InputError(
            f"{path}: unreadable ROS1 bag ({problem[:200]}); the file is truncated before its first intact chunk, "
            "corrupt or not a bag — re-export it, or run 'rosbag reindex' on it"
        )
    return reader, rec


@contextlib.contextmanager
def _gc_paused() -> Iterator[None]:
    """The cyclic garbage collector off for a bag's stream: opening the bag makes ~3 long-lived objects per
    message (its index), the messages short-lived objects and no cycles; the collections this triggered walked
    the long-lived heap for ~4 % of a conversion's CPU (perf, 1 GB EuRoC-like bag)."""
    enabled = gc.isenabled()
    gc.disable()
    try:
        yield
    finally:
        if enabled:
            gc.enable()


def stream_bag(path: Path, writer, routes: dict[str, BagRoute], drops: Drops, label: str) -> dict[str, int]:
    """Stream a ROS1 bag through ``routes`` (bounded memory: one chunk at a time). Topics without a route or
    with an unexpected message type are skipped and counted. A handler gets each message as a view into the
    chunk (`ros1_wire.messages`), valid during the call. Returns per-bag-topic message counts seen."""
    with _gc_paused():
        return _stream_bag(path, writer, routes, drops, label)


def _stream_bag(path: Path, writer, routes: dict[str, BagRoute], drops: Drops, label: str) -> dict[str, int]:
    from rosbags.rosbag1.reader import ReaderError

    reader, recovery = open_bag(path)  # its index: ~3 objects per message, the gc paused for them too
    if recovery is not None:
        drops.note(recovery.note())
    seen: dict[str, int] = {}
    try:
        use = []
        for conn in reader.connections:
            route = routes.get(conn.topic)
            if route is None:
                drops.add(conn.topic, f"topic not converted (type {conn.msgtype})", conn.msgcount)
            elif conn.msgtype not in route.msgtypes:
                drops.add(
                    conn.topic,
                    f"unexpected message type {conn.msgtype} (expected "
                    f"{' or '.join(route.msgtypes)}); skipped",
                    conn.msgcount,
                )
            else:
                use.append(conn)
        total = sum(c.msgcount for c in use)
        with progress(label, total) as advance:
            try:
                for conn, bag_t, raw in ros1_wire.messages(reader, use):
                    route = routes[conn.topic]
                    try:
                        route.handler(writer, conn, bag_t, raw)
                    except Drop as d:
                        drops.add(route.out_topic, str(d), 1, f"{conn.topic} @ bag t={bag_t}")
                    except (struct.error, ValueError, IndexError, UnicodeDecodeError, SerdeError) as exc:
                        drops.add(
                            route.out_topic,
                            f"undecodable message ({type(exc).__name__})",
                            1,
                            f"{conn.topic} @ bag t={bag_t}",
                        )
                    seen[conn.topic] = seen.get(conn.topic, 0) + 1
                    advance(1)
            except ReaderError as exc:
                raise InputError(
                    f"{path}: corrupt ROS1 bag while reading ({exc}); the file is truncated or damaged"
                ) from None
    finally:
        reader.close()
    return seen


def pose_covariance(sigma_pos: float = 0.05, sigma_rot_deg: float = 1.0) -> np.ndarray:
    """6x6 pose covariance in the nav_msgs/Odometry order (x, y, z, rot_x, rot_y, rot_z)."""
    s_rot = np.deg2rad(sigma_rot_deg)
    return np.diag([sigma_pos**2] * 3 + [s_rot**2] * 3)


def write_ranges(writer, r: RangeData, topic: str) -> None:
    writer.write_range_batch(r.t_ns, r.tag, r.antenna, r.anchor, r.distance, topic=topic)
