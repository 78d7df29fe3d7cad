"""Generic input -> recording: any odometry as a TUM file plus UWB ranges as CSV.

``--poses`` TUM ``t[s] x y z qx qy qz qw`` -> /odometry (with a configured pose covariance), ``--ranges``
``stamp,tag,antenna,anchor,distance`` (stamps in s, ms, us or ns: given, or the unit that puts them on the poses'
time span, else the one that gives a plausible UWB rate) -> /uwb/range, optional antenna
yaml in the NTU-VIRAL format -> ``uwbcal.calibration.uwb``, optional surveyed anchors ``anchor,x,y,z`` (same
frame as the poses) -> ``uwbcal.truth`` (kind "surveyed", see `convert.anchor_truth`).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from uwbcal.convert.anchor_truth import read_anchor_truth, truth_note, truth_record
from uwbcal.convert.attitude_check import planar_attitude_note
from uwbcal.convert.ntu_viral import find_antennas
from uwbcal.convert.recording import (
    META_CALIBRATION,
    META_SOURCE,
    META_TRUTH,
    TOPIC_ODOM,
    TOPIC_RANGE,
    RangeData,
    RecordingWriter,
)
from uwbcal.convert.sources import (
    MAX_RANGE_M,
    STAMP_UNITS,
    Drops,
    Hasher,
    RawStamps,
    anchors_note,
    clean_ranges,
    default_tags,
    normalise_quaternions,
    order_and_dedup,
    parse_antennas,
    pose_covariance,
    read_ranges_csv,
    read_tum,
    shift_ranges,
    source_metadata,
    summary,
    time_offset_ns,
    write_ranges,
)
from uwbcal.pipeline.core.errors import InputError
from uwbcal.pipeline.core.progress import progress

STATED_BIAS_SIGMA = 0.05  # [m] a ranging bias the antenna file states is known to a few centimetres
MAX_POSITION_M = 1e5  # a pose farther than 100 km from the origin is a unit error or garbage
TYPICAL_LINK_INTERVAL_S = (
    0.04  # per-link UWB rates are 1-1000 Hz: one unit puts the median within 31x of 25 Hz
)


@dataclass
class RangeStampUnit:
    """Chooses the unit of the range stamps (given, or detected) and says why (``reason``, after the call; and
    ``warning`` when the ranges miss the poses' time span in that unit)."""

    path: Path
    pose_span_ns: tuple[int, int]
    given: str | None = None
    offset_ns: int = 0
    reason: str = ""
    warning: str = ""

    def __call__(self, stamps: RawStamps, link: np.ndarray) -> str:
        units = [u for u in STAMP_UNITS if stamps.fits(u)]
        if self.given is not None:
            if self.given not in STAMP_UNITS:
                raise InputError(f"--stamp-unit {self.given!r}: expected one of {', '.join(STAMP_UNITS)}")
            if self.given not in units:
                raise InputError(f"{self.path}: stamps too large for {self.given} (int64 nanoseconds)")
            self._check_overlap(stamps, self.given)
            self.reason = f"stamps in {self.given} (--stamp-unit)"
            return self.given
        overlap = {u: self._overlap(stamps, u) for u in units}
        best = max(overlap, key=overlap.get) if overlap else None
        if best is not None and overlap[best] > 0:
            self.reason = (
                f"stamps read as {best}: the unit that puts the ranges on the poses' time span "
                f"({overlap[best]:.0%} overlap)"
            )
            return best
        unit, dt = self._by_rate(stamps, link, units)
        self.reason = f"stamps read as {unit}: per-link median interval {dt:.3g} s ({1 / dt:.3g} Hz)"
        self._check_overlap(stamps, unit)
        return unit

    def _span(self, stamps: RawStamps, unit: str) -> tuple[int, int]:
        t = stamps.ns(unit) + self.offset_ns
        return int(t.min()), int(t.max())

    def _overlap(self, stamps: RawStamps, unit: str) -> float:
        """Intersection over union of the ranges' and the poses' time spans."""
        (a, b), (c, d) = self._span(stamps, unit), self.pose_span_ns
        inter, union = min(b, d) - max(a, c), max(b, d) - min(a, c)
        return inter / union if inter > 0 and union > 0 else 0.0

    def _by_rate(self, stamps: RawStamps, link: np.ndarray, units: list[str]) -> tuple[str, float]:
        t = stamps.ns("ns")  # the raw numbers: only their spacing counts
        o = np.lexsort([t, link])
        dt = np.diff(t[o]).astype(float)
        dt = dt[(np.diff(link[o]) == 0) & (dt > 0)]
        step = float(np.median(dt)) if len(dt) else 1.0
        scale = {u: 10.0 ** (STAMP_UNITS[u] - 9) for u in units}
        unit = min(units, key=lambda u: abs(np.log10(step * scale[u] / TYPICAL_LINK_INTERVAL_S)))
        return unit, step * scale[unit]

    def _check_overlap(self, stamps: RawStamps, unit: str) -> None:
        (a, b), (c, d) = self._span(stamps, unit), self.pose_span_ns
        if b < c or a > d:
            self.warning = (
                f"the ranges (stamps in {unit}) span {a * 1e-9:.3f}..{b * 1e-9:.3f} s, the poses "
                f"{c * 1e-9:.3f}..{d * 1e-9:.3f} s: no overlap, the clocks differ (nothing to calibrate). If both "
                f"start with the recording, give --time-offset {_seconds(c - a + self.offset_ns)}; or check "
                "--stamp-unit"
            )


def _seconds(t_ns: int) -> str:
    return f"{t_ns * 1e-9:.6f}".rstrip("0").rstrip(".")


def _usable_poses(poses: Path, drops: Drops) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The TUM trajectory's usable poses (finite, plausible, unit quaternion) in time order without duplicates:
    stamps, positions, quaternions; the others dropped and counted."""
    pt = read_tum(poses)
    q, ok = normalise_quaternions(pt.q_xyzw, TOPIC_ODOM, drops)
    fin = np.isfinite(pt.p).all(1)
    drops.add(TOPIC_ODOM, "non-finite position", int((~fin).sum()))
    with np.errstate(invalid="ignore"):
        absurd = fin & ~(np.abs(pt.p) <= MAX_POSITION_M).all(1)
    if absurd.any():
        i = int(np.flatnonzero(absurd)[0])
        drops.add(
            TOPIC_ODOM, f"implausible position (> {MAX_POSITION_M:g} m)", int(absurd.sum()), f"record {i + 1}"
        )
    idx = np.flatnonzero(ok & fin & ~absurd)
    if len(idx) == 0:
        raise InputError(
            f"{poses}: none of the {len(pt.t_ns)} poses is usable (non-finite, absurd or non-unit quaternion); "
            "fix the trajectory"
        )
    o = idx[order_and_dedup(pt.t_ns[idx], None, TOPIC_ODOM, drops, Path(poses))]
    return pt.t_ns[o], pt.p[o], q[o]


def _usable_ranges(
    ranges: Path,
    t_pose: np.ndarray,
    stamp_unit: str | None,
    time_offset: float,
    max_range: float,
    drops: Drops,
) -> tuple[RangeData, int, str]:
    """The ranges CSV read (stamp unit chosen against the poses' span, shifted by ``time_offset``) and cleaned;
    also its number of rows and the unit."""
    chooser = RangeStampUnit(
        ranges, (int(t_pose[0]), int(t_pose[-1])), stamp_unit, time_offset_ns(time_offset)
    )
    raw, unit = read_ranges_csv(ranges, chooser)
    raw = shift_ranges(raw, time_offset, drops)
    n_rows = len(raw)
    r = clean_ranges(raw, TOPIC_RANGE, drops, max_range)
    if len(r) == 0:
        why = "; ".join(f"{d['count']} {d['reason']}" for d in drops.as_list() if d["topic"] == TOPIC_RANGE)
        raise InputError(
            f"{ranges}: all {n_rows} range rows dropped ({why}); nothing to calibrate — fix the file"
        )
    drops.note(f"{ranges.name}: {n_rows} rows, {chooser.reason}; " + anchors_note(r))
    if chooser.warning:
        drops.note(chooser.warning)
    return r, n_rows, unit


def _uwb_calibration(
    antenna_file: Path | None, r: RangeData, p: np.ndarray, q: np.ndarray, poses: Path, drops: Drops
) -> dict:
    """The calibration's uwb section: what the files state, nothing more (tags and antennas from the antenna
    file, else zero lever arms from the ranges; a stated ranging_bias as the offset prior); the range noise and the
    priors of the hardware class are the run's (`uwb` config). With antennas, the note on attitudes a planar
    trajectory leaves unobserved."""
    if antenna_file is None:
        return {"tags": default_tags(r.tag, r.antenna)}
    tags, bias = parse_antennas(antenna_file)
    uwb: dict = {"tags": tags}
    if bias:
        uwb["gamma_prior"] = {"mean": -float(np.mean(list(bias.values()))), "sigma": STATED_BIAS_SIGMA}
        drops.note(f"{antenna_file}: ranging_bias: range offset prior {uwb['gamma_prior']['mean']:+.3f} m")
    if antenna_file is not None:
        levers = [a for t in parse_antennas(antenna_file)[0].values() for a in t.get("antennas", [])]
        note = planar_attitude_note(p, q, np.asarray(levers, float), str(poses))
        if note:
            drops.note(note)
    return uwb


def convert_tabular(
    poses: str | Path,
    ranges: str | Path,
    output: str | Path,
    antennas: str | Path | None = None,
    *,
    anchors_truth: str | Path | None = None,
    sigma_pos: float = 0.05,
    sigma_rot_deg: float = 1.0,
    max_range: float = MAX_RANGE_M,
    pose_error: str = "bounded",
    stamp_unit: str | None = None,
    time_offset: float = 0.0,
) -> str:
    """Convert a TUM trajectory and a ranges CSV into one recording; returns a human summary.

    ``anchors_truth``: a surveyed ``anchor,x,y,z`` CSV in the poses' frame, written as ``uwbcal.truth``
    (``{"kind": "surveyed", "anchors": {id: {"position"}}, "anchors_frame": "odometry", "anchors_file"}``) so that
    ``uwbcal evaluate`` reports anchor errors against it.

    ``pose_error`` is declared as the calibration's ``odometry.error_model``: ``bounded`` (default) for poses in
    the world frame the anchors are calibrated in (ground truth, a SLAM output with a map: their error stays
    near the message covariance), ``drift`` for a dead-reckoning odometry whose error grows with distance.

    ``stamp_unit`` (s, ms, us, ns) of the range stamps; None detects it (and the summary says how).
    ``time_offset`` [s] is added to every range stamp: a known range-to-pose clock offset (ranges stamped 0.2 s
    late: -0.2), applied before the unit detection compares the clocks.
    """
    if pose_error not in ("bounded", "drift"):
        raise InputError(f"--pose-error {pose_error!r}: expected bounded or drift")

    poses, ranges = Path(poses), Path(ranges)
    drops = Drops()
    t_pose, p, q = _usable_poses(poses, drops)

    r, n_rows, unit = _usable_ranges(ranges, t_pose, stamp_unit, time_offset, max_range, drops)
    antenna_file = find_antennas(ranges, Path(antennas)) if antennas is not None else None
    uwb = _uwb_calibration(antenna_file, r, p, q, poses, drops)
    truth = None
    if anchors_truth is not None:
        anchors_truth = Path(anchors_truth)
        truth = truth_record(read_anchor_truth(anchors_truth), "surveyed", anchors_truth, frame="odometry")
        drops.note(truth_note(truth["anchors"], r.anchor, anchors_truth))
    files = [poses, ranges] + ([antenna_file] if antenna_file else [])
    hasher = Hasher(files)
    with RecordingWriter(output) as w, progress("tabular", len(t_pose) + len(r)) as advance:
        w.write_odometry_batch(t_pose, p, q, cov6=pose_covariance(sigma_pos, sigma_rot_deg), topic=TOPIC_ODOM)
        advance(len(t_pose))
        write_ranges(w, r, TOPIC_RANGE)
        advance(len(r))
        w.set_metadata(
            META_CALIBRATION,
            {"uwb": uwb, "odometry": {"error_model": pose_error, "source": f"tabular {poses.name}"}},
        )
        if truth is not None:
            w.set_metadata(META_TRUTH, truth)
        w.set_metadata(
            META_SOURCE,
            source_metadata(
                "tabular",
                poses.stem,
                hasher.result(),
                drops,
                format="tum+csv",
                range_rows=n_rows,
                range_stamp_unit=unit,
                odometry_covariance={
                    "sigma_pos_m": sigma_pos,
                    "sigma_rot_deg": sigma_rot_deg,
                    "order": "x y z rot_x rot_y rot_z",
                },
            ),
        )
        counts = dict(w.counts)
    return summary(output, counts, drops, f"tabular {poses.name} + {ranges.name}")
