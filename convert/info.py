"""`uwbcal info`: what a recording holds and what is wrong with it."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .recording import (
    TOPIC_GT_POSE,
    TOPIC_GT_POSITION,
    TOPIC_IMU,
    TOPIC_ODOM,
    TOPIC_RANGE,
    RecordingReader,
    TopicInfo,
)

GAP_FACTOR = 5.0  # a gap is a step longer than this many median periods


@dataclass
class InfoReport:
    path: Path
    topics: dict[str, TopicInfo]
    duration_s: float
    calibration: dict
    source: dict
    truth: dict | None
    problems: list[str] = field(default_factory=list)
    dropped: list[dict] = field(default_factory=list)

    def render(self) -> str:
        lines = [f"recording  {self.path}", f"duration   {self.duration_s:.2f} s"]
        if self.source:
            lines.append(
                f"source     {self.source.get('dataset', '?')} / {self.source.get('sequence', '?')} "
                f"({self.source.get('converter', '?')})"
            )
        lines.append("")
        lines.append(f"{'topic':<24} {'type':<34} {'count':>8} {'rate Hz':>9} {'start s':>10} {'dur s':>8}")
        t0 = min((t.start_ns for t in self.topics.values()), default=0)
        for name in sorted(self.topics):
            t = self.topics[name]
            lines.append(
                f"{name:<24} {t.msgtype:<34} {t.count:>8} {t.rate_hz:>9.2f} "
                f"{(t.start_ns - t0) * 1e-9:>10.3f} {t.duration_s:>8.2f}"
            )
        cal = self.calibration
        if cal:
            lines.append("")
            lines.append("calibration")
            if "imu" in cal:
                imu = cal["imu"]
                lines.append("  imu      " + ", ".join(f"{k}={v}" for k, v in imu.items()))
            for cam, c in cal.get("cameras", {}).items():
                lines.append(
                    f"  {cam:<8} intrinsics={c.get('intrinsics')} distortion={c.get('distortion')} "
                    f"resolution={c.get('resolution')}"
                )
            uwb = cal.get("uwb", {})
            for tag, tc in uwb.get("tags", {}).items():
                lines.append(f"  uwb tag {tag}: antennas {tc.get('antennas')}")
            for k in ("sigma_range", "gamma_prior", "beta_prior"):
                if uwb.get(k) is not None:
                    lines.append(f"  uwb {k}: {uwb[k]}")
            if "groundtruth" in cal:
                lines.append(f"  groundtruth: {cal['groundtruth']}")
        if self.truth:
            lines.append("")
            lines.append("truth (simulation)")
            for aid, a in self.truth.get("anchors", {}).items():
                lines.append(
                    f"  anchor {aid}: p={np.round(a['position'], 3).tolist()} beta={a.get('beta')} "
                    f"gamma={a.get('gamma')}"
                )
        lines.append("")
        if self.dropped:
            lines.append("dropped during conversion")
            for d in self.dropped:
                ex = f" (e.g. {d['example']})" if d.get("example") else ""
                lines.append(f"  {d.get('topic', '?')}: {d.get('count', '?')} x {d.get('reason', '?')}{ex}")
        lines.append("problems: none found" if not self.problems else "problems")
        lines.extend(f"  - {p}" for p in self.problems)
        return "\n".join(lines)


def _stamp_problems(topic: str, t: np.ndarray) -> list[str]:
    out = []
    if len(t) < 2:
        return out
    dt = np.diff(t)
    back = int(np.sum(dt < 0))
    dup = int(np.sum(dt == 0))
    if back:
        i = int(np.argmax(dt < 0))
        out.append(f"{topic}: {back} out-of-order stamps (first at {t[i + 1]} ns)")
    if dup:
        i = int(np.argmax(dt == 0))
        out.append(f"{topic}: {dup} duplicate stamps (first at {t[i]} ns)")
    pos = dt[dt > 0]
    if len(pos):
        med = float(np.median(pos))
        gaps = np.flatnonzero(dt > GAP_FACTOR * med)
        if len(gaps):
            worst = int(gaps[np.argmax(dt[gaps])])
            out.append(
                f"{topic}: {len(gaps)} gaps > {GAP_FACTOR:.0f}x the median period {med * 1e-6:.1f} ms "
                f"(longest {dt[worst] * 1e-9:.3f} s at {t[worst]} ns)"
            )
    return out


def _nan_problem(topic: str, t: np.ndarray, *arrays: np.ndarray) -> list[str]:
    bad = np.zeros(len(t), bool)
    for a in arrays:
        bad |= ~np.isfinite(a.reshape(len(t), -1)).all(axis=1)
    if bad.any():
        return [f"{topic}: {int(bad.sum())} messages with NaN/inf values (first at {t[np.argmax(bad)]} ns)"]
    return []


def recording_info(path: str | Path) -> InfoReport:
    r = RecordingReader(path)
    topics = r.topics()
    problems = list(r.warnings)
    if topics:
        start = min(t.start_ns for t in topics.values())
        end = max(t.end_ns for t in topics.values())
    else:
        start = end = 0
        problems.append("the recording has no messages")
    if TOPIC_IMU in topics:
        imu = r.read_imu()
        problems += _stamp_problems(TOPIC_IMU, r.header_stamps(TOPIC_IMU)) + _nan_problem(
            TOPIC_IMU, imu.t_ns, imu.gyro, imu.acc
        )
    if TOPIC_RANGE in topics:
        rng = r.read_ranges()
        problems += _nan_problem(TOPIC_RANGE, rng.t_ns, rng.distance)
        for a in np.unique(rng.anchor):
            m = rng.anchor == a
            problems += _stamp_problems(f"{TOPIC_RANGE} anchor {a}", rng.t_ns[m])
        neg = int(np.sum(rng.distance < 0))
        if neg:
            problems.append(f"{TOPIC_RANGE}: {neg} negative ranges")
    for topic, reader in ((TOPIC_GT_POSE, r.read_poses), (TOPIC_ODOM, r.read_odometry)):
        if topic in topics:
            d = reader(topic)
            problems += _stamp_problems(topic, d.t_ns) + _nan_problem(topic, d.t_ns, d.p, d.q_xyzw)
    if TOPIC_GT_POSITION in topics:
        d = r.read_positions(TOPIC_GT_POSITION)
        problems += _stamp_problems(TOPIC_GT_POSITION, d.t_ns) + _nan_problem(TOPIC_GT_POSITION, d.t_ns, d.p)
    return InfoReport(
        Path(path),
        topics,
        (end - start) * 1e-9,
        r.calibration,
        r.source,
        r.truth,
        problems,
        list(r.source.get("dropped", [])),
    )
