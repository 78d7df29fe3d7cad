"""`uwbcal check REC.mcap [--anchors-truth CSV]`: a recording's own consistency, before any calibration.

Without truth: per link the range statistics and outliers, the converter's negative / invalid ranges, per anchor
its visibility windows and how well the poses determine it (the information per anchor), and the stamps (order,
gaps, ranges without a pose). With truth (the recording's, or a CSV in the poses' frame): measured vs predicted
ranges per link, the anchor-id assignment that fits best (a swap is named), the lever arm given vs zero vs
mirrored vs fitted, and a range-to-pose clock-offset scan. Every problem ends in a verdict line saying what to do.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from uwbcal.evaluate import check_truth as ct
from uwbcal.evaluate.check_data import CheckData, load_check_data
from uwbcal.pipeline.core.robust import MAD_SIGMA
from uwbcal.pipeline.uwb.initializer import multilateration

OUTLIER_M = 0.5  # a range this far (and 4 MAD) from its link's running median is an outlier
OUTLIER_WINDOW = 9
WINDOW_GAP_S = 2.0  # a link silent this long (and 20 of its intervals) closes a visibility window
LEVER_TOL_M = 0.05  # a fitted lever arm closer than this to the given one is not a finding
PLANAR_M = 0.15  # a tag path this flat (std normal to its plane; 3 x a 5 cm pose error) hides a coordinate
POOR_SIGMA_M = 0.5  # an anchor whose weakest direction is determined worse than this is flagged


@dataclass
class Verdict:
    problem: str
    action: str

    def line(self) -> str:
        return f"PROBLEM {self.problem} -> {self.action}"


@dataclass
class CheckReport:
    lines: list[str] = field(default_factory=list)
    verdicts: list[Verdict] = field(default_factory=list)

    def render(self) -> str:
        tail = [v.line() for v in self.verdicts] or ["OK no problem found"]
        return "\n".join([*self.lines, "", "verdict:", *tail])


def _rel(data: CheckData, t_ns: int) -> float:
    return (t_ns - int(data.ranges.t_ns[0])) * 1e-9


# -- without truth --------------------------------------------------------------------------------------------------
def _outliers(d: np.ndarray) -> int:
    if len(d) < OUTLIER_WINDOW:
        return 0
    from numpy.lib.stride_tricks import sliding_window_view

    h = OUTLIER_WINDOW // 2
    pad = np.pad(d, h, mode="edge")
    win = sliding_window_view(pad, OUTLIER_WINDOW)
    med = np.median(win, axis=1)
    mad = MAD_SIGMA * np.median(np.abs(win - med[:, None]), axis=1)
    return int((np.abs(d - med) > np.maximum(4 * mad, OUTLIER_M)).sum())


def link_lines(data: CheckData, rep: CheckReport) -> None:
    r = data.ranges
    rep.lines += [
        "ranges per link:",
        f"  {'anchor':>6} {'tag':>5} {'ant':>3} {'n':>7} {'Hz':>6} {'min m':>7} {'median':>7} {'max m':>7} "
        f"{'outliers':>8}",
    ]
    keys = np.unique(np.column_stack([r.anchor, r.tag, r.antenna]), axis=0)
    for a, t, k in keys.tolist():
        m = (r.anchor == a) & (r.tag == t) & (r.antenna == k)
        d, ts = r.distance[m], r.t_ns[m]
        span = (ts[-1] - ts[0]) * 1e-9
        hz = (len(ts) - 1) / span if span > 0 else float("nan")
        out = _outliers(d)
        rep.lines.append(
            f"  {a:>6} {t:>5} {k:>3} {len(d):>7} {hz:>6.1f} {d.min():>7.2f} {np.median(d):>7.2f} "
            f"{d.max():>7.2f} {out:>8}"
        )
        if out > 0.05 * len(d):
            rep.verdicts.append(
                Verdict(
                    f"link anchor {a} / tag {t}: {out} of {len(d)} ranges are outliers (> {OUTLIER_M} m off the "
                    "running median)",
                    "expect NLOS on this link; the robust calibration gates them, check the anchor's line of sight",
                )
            )
    for d in data.dropped:
        rep.lines.append(f"  dropped by the converter: {d['count']} {d['reason']}")
        if "negative" in d["reason"]:
            rep.verdicts.append(
                Verdict(
                    f"{d['count']} negative ranges (dropped at conversion)",
                    "a constant offset on the radio (calibrate it: the per-link offset absorbs it); if many, "
                    "check the distance unit",
                )
            )


def visibility_lines(data: CheckData, rep: CheckReport) -> None:
    r = data.ranges
    total = (r.t_ns[-1] - r.t_ns[0]) * 1e-9
    rep.lines.append("visibility per anchor (s from the first range):")
    for a in np.unique(r.anchor).tolist():
        ts = r.t_ns[r.anchor == a]
        dt = np.diff(ts) * 1e-9
        gap = max(WINDOW_GAP_S, 20 * float(np.median(dt))) if len(dt) else WINDOW_GAP_S
        cut = np.flatnonzero(dt > gap)
        starts, ends = np.r_[ts[0], ts[cut + 1]], np.r_[ts[cut], ts[-1]]
        seen = float(np.sum(ends - starts) * 1e-9)
        wins = ", ".join(
            f"{_rel(data, s):.1f}-{_rel(data, e):.1f}" for s, e in list(zip(starts, ends, strict=True))[:6]
        )
        more = f" (+{len(starts) - 6} more)" if len(starts) > 6 else ""
        frac = seen / total if total > 0 else 1.0
        rep.lines.append(f"  anchor {a}: {len(starts)} window(s) {wins}{more}; {frac:.0%} of the recording")


def stamp_lines(data: CheckData, rep: CheckReport) -> None:
    r = data.ranges
    back = int((np.diff(data.file_order_t_ns) < 0).sum())
    dt = np.diff(r.t_ns) * 1e-9
    biggest = float(dt.max()) if len(dt) else 0.0
    rep.lines.append(
        f"stamps: ranges {len(r)} over {_rel(data, int(r.t_ns[-1])):.1f} s, {back} out of order in the file, "
        f"largest gap {biggest:.2f} s"
    )
    if back:
        rep.verdicts.append(
            Verdict(
                f"{back} range stamps step back in the file",
                "fine if the radio reports late; if large, the stamps mix two clocks: fix the export",
            )
        )
    if data.poses is None:
        return
    tp = data.poses.t_ns
    gaps = np.diff(tp) * 1e-9
    cov = data.covered(r.t_ns)
    rep.lines.append(
        f"stamps: poses ({data.poses.source}) {len(tp)} at {len(tp) / max((tp[-1] - tp[0]) * 1e-9, 1e-9):.1f} Hz, "
        f"largest gap {gaps.max() if len(gaps) else 0:.2f} s; {1 - cov.mean():.1%} of the ranges have no pose"
    )
    if cov.mean() < 0.9:
        rep.verdicts.append(
            Verdict(
                f"{1 - cov.mean():.0%} of the ranges fall outside the poses or in their gaps",
                "check that ranges and poses share a clock (convert --stamp-unit / --time-offset)",
            )
        )


def _information(x: np.ndarray, a: np.ndarray, sigma: float) -> tuple[np.ndarray, np.ndarray]:
    """Eigen-sigmas [m] and directions of the anchor position (an unknown range offset marginalised)."""
    diff = a - x
    u = diff / np.maximum(np.linalg.norm(diff, axis=1), 1e-9)[:, None]
    J = np.column_stack([-u, np.ones(len(u))]) / sigma
    F = J.T @ J
    w, V = np.linalg.eigh(F[:3, :3] - np.outer(F[:3, 3], F[3, :3]) / max(F[3, 3], 1e-12))
    return 1.0 / np.sqrt(np.maximum(w, 1e-12)), V


def excitation_lines(data: CheckData, rep: CheckReport) -> None:
    if data.poses is None:
        return
    r = data.ranges
    ok = data.covered(r.t_ns)
    x_all, _ = data.tag_positions(np.flatnonzero(ok)[:: max(1, int(ok.sum()) // 20000)])
    w, V = np.linalg.eigh(np.cov(x_all.T)) if len(x_all) > 3 else (np.zeros(3), np.eye(3))
    normal = float(np.sqrt(max(w[0], 0.0)))
    across = (
        "heights" if abs(V[2, 0]) > 0.7 else f"coordinates along ~{'xyz'[int(np.argmax(np.abs(V[:, 0])))]}"
    )
    rep.lines.append(
        f"pose excitation (the tag's spread normal to its best plane {normal:.3f} m; per anchor the sigma of its "
        "position from these poses and the range noise alone, offset free):"
    )
    if normal < PLANAR_M:
        rep.verdicts.append(
            Verdict(
                f"the tag moves in a plane (spread {normal:.3f} m normal to it): the anchors' {across} are not "
                "observable from the ranges (each has a mirror across the plane)",
                f"give the {across} from a survey (the calibration reports them as unobservable), or move the "
                "tag across the plane",
            )
        )
    for a in np.unique(r.anchor).tolist():
        idx = np.flatnonzero(ok & (r.anchor == a))
        if len(idx) < 10:
            rep.lines.append(f"  anchor {a}: {len(idx)} ranges with a pose: not determined")
            rep.verdicts.append(Verdict(f"anchor {a}: {len(idx)} ranges with a pose", "record it longer"))
            continue
        idx = idx[np.linspace(0, len(idx) - 1, min(len(idx), 5000)).astype(int)]
        x, _ = data.tag_positions(idx)
        pos = data.truth.get(a) if data.truth else None
        if pos is None:
            pos = multilateration(x, r.distance[idx])[0][:3]
        sig, V = _information(x, pos, data.sigma_range)
        spread = np.sqrt(np.linalg.eigvalsh(np.cov(x.T)))
        weak = V[:, 0]  # the direction of the least information
        axis = "xyz"[int(np.argmax(np.abs(weak)))]
        rep.lines.append(
            f"  anchor {a}: sigma {sig.min():.3f}..{sig.max():.3f} m (weakest along ~{axis}); carrier spread "
            f"{spread[0]:.2f} / {spread[1]:.2f} / {spread[2]:.2f} m"
        )
        if sig.max() > POOR_SIGMA_M:
            rep.verdicts.append(
                Verdict(
                    f"anchor {a}: poorly determined along ~{axis} (sigma {sig.max():.2f} m; the carrier's "
                    f"smallest spread {spread[0]:.2f} m)",
                    "move the carrier more around it (height changes for a planar robot), or fix that "
                    "coordinate from a survey",
                )
            )


# -- with truth -----------------------------------------------------------------------------------------------------
def fit_lines(data: CheckData, rep: CheckReport) -> list[ct.LinkFit]:
    s = ct.sample(data)
    fits = ct.predicted_vs_measured(data, s)
    rep.lines += [
        f"measured - predicted range per link (truth: {data.truth_label}, poses {data.poses.source}):",
        f"  {'anchor':>6} {'tag':>5} {'ant':>3} {'n':>7} {'median m':>9} {'MAD m':>7} {'> 1 m':>6}",
    ]
    for f in fits:
        rep.lines.append(
            f"  {f.anchor:>6} {f.tag:>5} {f.antenna:>3} {f.n:>7} {f.median_m:>9.3f} {f.mad_m:>7.3f} "
            f"{f.frac_over_1m:>6.1%}"
        )
    no_truth = sorted(set(np.unique(data.ranges.anchor).tolist()) - set(data.truth))
    if no_truth:
        rep.lines.append(f"  ranged without truth: {', '.join(map(str, no_truth))}")
    return fits


def id_lines(data: CheckData, rep: CheckReport, fits: list[ct.LinkFit]) -> CheckData:
    """The id check; returns the data with the best assignment applied when a swap is found."""
    ids = ct.anchor_ids(data)
    rep.lines.append("anchor ids (scatter of each anchor's ranges at its own truth / at the best):")
    for i, a in enumerate(ids.ranged):
        own = ids.cost[i, ids.truth_ids.index(a)] if a in data.truth else float("nan")
        b = ids.best.get(a)
        at = ids.cost[i, ids.truth_ids.index(b)] if b is not None else float("nan")
        rep.lines.append(f"  anchor {a}: {own:.3f} m at its own, best truth {b} ({at:.3f} m)")
    moved = {a for a, *_ in ids.swapped}
    for a in sorted({f.anchor for f in fits} - moved):
        mine = [f for f in fits if f.anchor == a]
        frac = sum(f.frac_over_1m * f.n for f in mine) / max(1, sum(f.n for f in mine))
        if frac > ct.MISFIT_FRAC:
            rep.verdicts.append(
                Verdict(
                    f"anchor {a}: its ranges fit no surveyed position ({frac:.0%} of them > 1 m off the "
                    "prediction, no other anchor's truth fits better)",
                    "check its survey and id, or its line of sight (NLOS throughout); leave it out of an "
                    "evaluation",
                )
            )
    if not ids.swapped:
        return data
    for a, b, there, own in ids.swapped:
        rep.verdicts.append(
            Verdict(
                f"anchor id swap: the ranges of anchor {a} fit the truth of anchor {b} (scatter {there:.3f} m "
                f"vs {own:.3f} m at its own)",
                f"fix the anchor-id map (ranged {a} is surveyed {b}) in the truth CSV or the converter's input",
            )
        )
    fixed = {a: data.truth[ids.best.get(a, a)] for a in data.truth if ids.best.get(a, a) in data.truth}
    rep.lines.append("  (the lever-arm and clock tests below use the best assignment)")
    return dataclasses.replace(data, truth=fixed)


def _finding(c: ct.LeverCheck) -> str | None:
    """The lever-arm hypothesis the ranges name instead of the given one, if any."""
    best = c.best
    ratio = ct.FITTED_BETTER if best == "fitted" else ct.BETTER
    if best == "given" or not ct.significant(c.scatter["given"], c.scatter[best], ratio):
        return None
    if best == "fitted" and np.linalg.norm(c.fitted - c.given) < LEVER_TOL_M:
        return None
    return best


def corrected_levers(data: CheckData, checks: list[ct.LeverCheck]) -> dict:
    """The lever arms for the clock scan: zero or mirrored where that is the finding (a wrong lever arm would
    otherwise pass for a clock offset; a fitted one could absorb a real clock offset, so it is not used)."""
    levers = dict(data.levers)
    for c in checks:
        if _finding(c) in ("zero", "mirrored"):
            levers[(c.tag, c.antenna)] = np.zeros(3) if _finding(c) == "zero" else -c.given
    return levers


def lever_lines(rep: CheckReport, checks: list[ct.LeverCheck], shift_s: float) -> None:
    if not checks:
        rep.lines.append("lever arms: not tested (the poses carry no attitude)")
        return
    at = f", poses shifted {shift_s:+.3f} s as the clock scan found" if shift_s else ""
    rep.lines.append(f"lever arms (scatter [m] of the ranges with each{at}):")
    for c in checks:
        cells = ", ".join(f"{k} {v:.3f}" for k, v in c.scatter.items())
        rep.lines.append(
            f"  tag {c.tag} antenna {c.antenna}: given {np.round(c.given, 3).tolist()}, fitted "
            f"{np.round(c.fitted, 3).tolist()}; {cells}"
        )
        best = _finding(c)
        if best is None:
            continue
        what = {
            "mirrored": f"lever arm of tag {c.tag} mirrored: the ranges fit {np.round(-c.given, 3).tolist()}",
            "zero": f"lever arm of tag {c.tag}: the ranges fit no lever arm better than the given one",
            "fitted": f"lever arm of tag {c.tag}: the ranges fit {np.round(c.fitted, 3).tolist()} (or a "
            "direction-dependent antenna bias mimics one)",
        }[best]
        rep.verdicts.append(
            Verdict(
                f"{what} (scatter {c.scatter[best]:.3f} m vs {c.scatter['given']:.3f} m given)",
                "check the antenna yaml's body frame and signs (the pose's body frame, not the rig's CAD frame)",
            )
        )


def clock_lines(data: CheckData, rep: CheckReport, s: ct.Sample, levers: dict) -> float:
    """The clock scan; returns the offset found (0 when none is)."""
    c = ct.clock_offset(data, s, levers)
    if c is None:
        rep.lines.append("clock offset: not tested (too few ranges with a pose)")
        return 0.0
    rep.lines.append(
        f"clock offset: best {c.best_s:+.3f} s (scatter {c.at_best:.3f} m there, {c.at_zero:.3f} m at 0; "
        f"scanned +-{ct.CLOCK_SCAN_S:g} s)"
    )
    if not c.found:
        return 0.0
    late = "late" if c.best_s < 0 else "early"
    rep.verdicts.append(
        Verdict(
            f"clock offset: the ranges are stamped {abs(c.best_s):.2f} s {late} against the poses "
            f"(scatter {c.at_best:.3f} m vs {c.at_zero:.3f} m as stamped)",
            f"reconvert with --time-offset {c.best_s:.2f}",
        )
    )
    return c.best_s


def check_recording(recording: str | Path, anchors_truth: str | Path | None = None) -> CheckReport:
    data = load_check_data(recording, anchors_truth)
    rep = CheckReport(lines=[f"check {data.path}", *(f"note: {n}" for n in data.notes)])
    link_lines(data, rep)
    visibility_lines(data, rep)
    stamp_lines(data, rep)
    excitation_lines(data, rep)
    if data.truth and data.poses is not None:
        data = id_lines(data, rep, fit_lines(data, rep))
        s = ct.sample(data, ct.CLOCK_SCAN_S)
        first = ct.lever_arms(data, s)
        shift = clock_lines(data, rep, s, corrected_levers(data, first))
        lever_lines(rep, ct.lever_arms(data, s, shift) if shift else first, shift)
    elif data.poses is not None:
        rep.lines.append("no anchor truth: id, lever-arm and clock tests skipped (give --anchors-truth CSV)")
    return rep
