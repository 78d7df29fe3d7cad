"""`uwbcal info`: what a recording holds and what is wrong with it."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from uwbcal.convert.calibration import parse_calibration
from uwbcal.convert.msgs import FEATURE_TRACKS, IMAGE, IMU, ODOMETRY, POINT_STAMPED, POSE_STAMPED, UWB_RANGE
from uwbcal.convert.recording import RecordingReader, TopicInfo, schema_mismatches
from uwbcal.pipeline.core.errors import InputError

ABSURD = 1e6  # no position [m], rate, acceleration or range in a recording is this large
GAP_FACTOR = 5.0  # a gap is a step longer than this many median periods


@dataclass(frozen=True)
class Problem:
    """One finding. ``kind``: gap, duplicate, out_of_order, nan, negative_range, truncated, damaged, schema, empty, calibration."""

    kind: str
    topic: str
    count: int
    text: str

    def __str__(self) -> str:
        return self.text


@dataclass
class InfoReport:
    path: Path
    topics: dict[str, TopicInfo]
    start_ns: int
    end_ns: int
    calibration: dict
    source: dict
    truth: dict | None
    problems: list[Problem] = field(default_factory=list)
    dropped: list[dict] = field(default_factory=list)

    @property
    def duration_s(self) -> float:
        return (self.end_ns - self.start_ns) * 1e-9

    def kinds(self, topic: str | None = None) -> set[str]:
        """The kinds of problems found (on ``topic``, or on any topic)."""
        return {p.kind for p in self.problems if topic is None or p.topic == topic}

    def render(self) -> str:
        lines = [
            f"recording  {self.path}",
            f"duration   {self.duration_s:.3f} s (from t = {self.start_ns} ns)",
        ]
        if self.source:
            src = self.source
            lines.append(
                f"source     {src.get('dataset', '?')} / {src.get('sequence', '?')} ({src.get('converter', '?')})"
            )
            for f in src.get("files", []):
                lines.append(f"           {f.get('path')}  sha256 {str(f.get('sha256', '?'))[:16]}")
            for topic, acc in sorted((src.get("messages") or {}).items()):
                role = acc.get("role") or "not mapped"
                lines.append(
                    f"  bag {topic} ({acc.get('type')}): {acc.get('count')} -> {role}, "
                    f"{acc.get('converted')} converted, {acc.get('dropped')} dropped"
                )
        lines += [
            "",
            f"{'topic':<24} {'type':<34} {'count':>8} {'rate Hz':>9} {'start s':>9} {'end s':>9} {'dur s':>8}",
        ]
        for name in sorted(self.topics):
            t = self.topics[name]
            lines.append(
                f"{name:<24} {t.msgtype:<34} {t.count:>8} {t.rate_hz:>9.2f} {(t.start_ns - self.start_ns) * 1e-9:>9.3f} "
                f"{(t.end_ns - self.start_ns) * 1e-9:>9.3f} {t.duration_s:>8.3f}"
            )
        lines += self._render_calibration()
        if self.truth:
            lines += ["", f"truth ({self.truth.get('kind', 'simulated')})"]
            for aid, a in self.truth.get("anchors", {}).items():
                extra = "".join(f" {k}={a[k]}" for k in ("beta", "gamma") if a.get(k) is not None)
                lines.append(f"  anchor {aid}: p={np.round(a['position'], 3).tolist()}{extra}")
            rest = {k: v for k, v in self.truth.items() if k != "anchors"}
            if rest:
                lines.append("  " + ", ".join(f"{k}={v}" for k, v in rest.items()))
        lines.append("")
        if self.source:
            if self.dropped:
                lines.append("dropped during conversion")
                for d in self.dropped:
                    ex = f" (e.g. {d['example']})" if d.get("example") else ""
                    lines.append(
                        f"  {d.get('topic', '?')}: {d.get('count', '?')} x {d.get('reason', '?')}{ex}"
                    )
            else:
                lines.append("dropped during conversion: nothing")
        lines.append("problems: none found" if not self.problems else f"problems ({len(self.problems)})")
        lines.extend(f"  - {p}" for p in self.problems)
        return "\n".join(lines)

    def _render_calibration(self) -> list[str]:
        cal = self.calibration
        if not cal:
            return ["", "calibration: none (no uwbcal.calibration metadata)"]
        if "calibration" in self.kinds(""):
            return ["", "calibration: invalid (see the problems below)"]
        lines = ["", "calibration"]
        if "imu" in cal:
            lines.append("  imu      " + ", ".join(f"{k}={v}" for k, v in cal["imu"].items()))
        for cam, c in cal.get("cameras", {}).items():
            lines.append(
                f"  {cam:<8} {c.get('distortion_model', '?')} intrinsics={c.get('intrinsics')} "
                f"distortion={c.get('distortion')} resolution={c.get('resolution')} rate_hz={c.get('rate_hz')}"
            )
            if c.get("T_imu_cam") is not None:
                T = np.asarray(c["T_imu_cam"], float)
                lines.append(f"           p_imu_cam={np.round(T[:3, 3], 4).tolist()}")
        uwb = cal.get("uwb", {})
        for tag, tc in uwb.get("tags", {}).items():
            lines.append(f"  uwb tag {tag}: antennas {tc.get('antennas')}")
        for k in ("sigma_range", "gamma_prior", "beta_prior"):
            if uwb.get(k) is not None:
                lines.append(f"  uwb {k}: {uwb[k]}")
        odo = cal.get("odometry") or {}
        if odo:
            extra = {k: v for k, v in odo.items() if k not in ("error_model", "noise")}
            lines.append(
                f"  odometry error model: {odo.get('error_model', 'drift')}"
                + "".join(f", {k}={v}" for k, v in extra.items())
            )
            if odo.get("noise"):
                lines.append(
                    "  odometry noise: " + ", ".join(f"{k}={v:.4g}" for k, v in odo["noise"].items())
                )
        if "groundtruth" in cal:
            lines.append(f"  groundtruth: {cal['groundtruth']}")
        return lines


def stamp_problems(topic: str, t: np.ndarray) -> list[Problem]:
    """Out-of-order and duplicate stamps (in writing order) and gaps longer than GAP_FACTOR median periods."""
    out: list[Problem] = []
    if len(t) < 2:
        return out
    dt = np.diff(np.asarray(t, np.int64))
    back = np.flatnonzero(dt < 0)
    dup = np.flatnonzero(dt == 0)
    if len(back):
        out.append(
            Problem(
                "out_of_order",
                topic,
                len(back),
                f"{topic}: {len(back)} out-of-order stamps "
                f"(first at {t[back[0] + 1]} ns, after {t[back[0]]} ns)",
            )
        )
    if len(dup):
        out.append(
            Problem(
                "duplicate",
                topic,
                len(dup),
                f"{topic}: {len(dup)} duplicate stamps (first at {t[dup[0]]} ns)",
            )
        )
    pos = dt[dt > 0]
    if len(pos):
        med = float(np.median(pos))
        gaps = np.flatnonzero(dt > GAP_FACTOR * med)
        if len(gaps):
            worst = int(gaps[np.argmax(dt[gaps])])
            out.append(
                Problem(
                    "gap",
                    topic,
                    len(gaps),
                    f"{topic}: {len(gaps)} gaps > {GAP_FACTOR:.0f}x the median period {med * 1e-6:.1f} ms "
                    f"(longest {dt[worst] * 1e-9:.3f} s at {t[worst]} ns)",
                )
            )
    return out


def clock_jumps(topic: str, t: np.ndarray) -> list[Problem]:
    """Stamps (in writing order) that step back by more than GAP_FACTOR median periods: a clock jump, after which
    two stretches of the topic overlap in the recording's time index (what sorting cannot repair)."""
    dt = np.diff(np.asarray(t, np.int64))
    pos = dt[dt > 0]
    if not len(pos) or dt.min() >= -GAP_FACTOR * float(np.median(pos)):
        return []
    i = int(np.argmin(dt))
    n = int((dt < 0).sum())
    return [
        Problem(
            "out_of_order",
            topic,
            n,
            f"{topic}: stamps out of order, stepping back by {-dt[i] * 1e-9:.6g} s at {t[i + 1]} ns (after "
            f"{t[i]} ns; {n} steps back in all): a clock jump, two stretches of the topic overlap in time — "
            "convert from data with monotonic stamps, or cut the recording before the jump",
        )
    ]


def nan_problems(topic: str, t: np.ndarray, *arrays: np.ndarray) -> list[Problem]:
    if len(t) == 0:
        return []
    bad = np.zeros(len(t), bool)
    for a in arrays:
        v = np.asarray(a, float).reshape(len(t), -1)
        with np.errstate(invalid="ignore"):
            bad |= ~(np.abs(v) <= ABSURD).all(axis=1)
    if not bad.any():
        return []
    n = int(bad.sum())
    return [
        Problem(
            "nan",
            topic,
            n,
            f"{topic}: {n} messages with NaN/inf or absurd (> {ABSURD:g}) values (first at {t[np.argmax(bad)]} ns)",
        )
    ]


def _range_problems(topic: str, r) -> list[Problem]:
    rng = r.read_ranges(topic, file_order=True)
    out = nan_problems(topic, rng.t_ns, rng.distance)
    links = np.stack([rng.tag, rng.antenna, rng.anchor], axis=1)
    for tag, ant, anchor in np.unique(links, axis=0).tolist():
        m = (rng.tag == tag) & (rng.antenna == ant) & (rng.anchor == anchor)
        out += stamp_problems(f"{topic} tag {tag} antenna {ant} anchor {anchor}", rng.t_ns[m])
    neg = int(np.sum(rng.distance < 0))
    if neg:
        out.append(Problem("negative_range", topic, neg, f"{topic}: {neg} negative ranges"))
    return out


def calibration_problems(r: RecordingReader, topics: dict[str, TopicInfo]) -> list[Problem]:
    """The recording's calibration against `convert.calibration` and each camera's resolution against its first
    image."""
    try:
        cal = parse_calibration(r.calibration, "uwbcal.calibration")
    except InputError as exc:
        return [
            Problem("calibration", "", 1, f"{exc}; re-convert the recording with a corrected calibration")
        ]
    out = []
    for name, c in cal.cameras.items():
        topic = f"/{name}/image_raw"
        if c.resolution is None or topic not in topics or topics[topic].msgtype != IMAGE:
            continue
        img = next((im for _, im in r.iter_images(topic)), None)
        if img is not None and [img.shape[1], img.shape[0]] != list(c.resolution):
            out.append(
                Problem(
                    "calibration",
                    topic,
                    1,
                    f"uwbcal.calibration: cameras.{name}.resolution {c.resolution[0]}x{c.resolution[1]}, but the "
                    f"images on {topic} are {img.shape[1]}x{img.shape[0]}; re-convert with this camera's calibration",
                )
            )
    return out


def recording_info(path: str | Path) -> InfoReport:
    """Topics, rates, time spans, calibration, drops and the problems found in a recording."""
    r = RecordingReader(path)
    r.verify()
    topics = r.topics()
    problems = [Problem("truncated" if "truncated" in w else "damaged", "", 0, w) for w in r.warnings]
    problems += [Problem("schema", t, topics[t].count, w) for t, w in schema_mismatches(topics).items()]
    if topics:
        start, end = r.time_span()
    else:
        start = end = 0
        problems.append(Problem("empty", "", 0, "the recording has no messages"))
    problems += calibration_problems(r, topics)
    for topic, info in sorted(topics.items()):
        if any(p.kind == "schema" and p.topic == topic for p in problems):
            continue
        if info.msgtype == UWB_RANGE:
            problems += _range_problems(topic, r)
        elif info.msgtype == IMU:
            d = r.read_imu(topic, file_order=True)
            problems += stamp_problems(topic, d.t_ns) + nan_problems(topic, d.t_ns, d.gyro, d.acc)
        elif info.msgtype in (POSE_STAMPED, ODOMETRY):
            d = (r.read_poses if info.msgtype == POSE_STAMPED else r.read_odometry)(topic, file_order=True)
            problems += stamp_problems(topic, d.t_ns) + nan_problems(topic, d.t_ns, d.p, d.q_xyzw)
        elif info.msgtype == POINT_STAMPED:
            d = r.read_positions(topic, file_order=True)
            problems += stamp_problems(topic, d.t_ns) + nan_problems(topic, d.t_ns, d.p)
        elif info.msgtype in (IMAGE, FEATURE_TRACKS):
            problems += stamp_problems(topic, r.header_stamps(topic))
    return InfoReport(
        Path(path),
        topics,
        start,
        end,
        r.calibration,
        r.source,
        r.truth,
        problems,
        list(r.source.get("dropped", [])),
    )
