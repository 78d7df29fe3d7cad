"""The rerun run log: one `RunLog` per stage writes an .rrd atomically, with a blueprint.

Every stage logs through the same small object so that entity paths, timelines and styling stay consistent:
timeline `sensor_time` (timestamp, recording time in ns) on every row and `stage` (sequence, see `STAGE_INDEX`)
once a stage boundary has been logged. Long series go column-wise (`rr.send_columns`). The entity tree is fixed
by the path builders below; stages must not invent paths.

A disabled `RunLog` (path None or enabled False, i.e. `--no-log`) returns from every method at once.
"""

from __future__ import annotations

import contextlib
import functools
import os
import re
import shutil
import subprocess
import sys
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from types import TracebackType
from typing import Any

import numpy as np

from uwbcal.pipeline.core.atomic import atomic_path
from uwbcal.pipeline.core.errors import InputError
from uwbcal.pipeline.core.series import sliding_mean
from uwbcal.pipeline.core.state import chi2_quantile

APP_ID = "uwbcal"
RUN_KINDS = ("simulation", "euroc", "ntu-viral")
T_SENSOR = "sensor_time"
T_STAGE = "stage"
STAGE_INDEX = {
    "convert": 0,
    "recording": 0,
    "frontend": 1,
    "vio": 2,
    "init": 3,
    "refine": 4,
    "localize": 5,
    "evaluate": 6,
}

# -- entity paths ------------------------------------------------------------------------------------
WORLD = "world"
GT = "world/gt"  # trajectory(GT, ...) -> world/gt/{trajectory,pose}
GT_TRAJECTORY = "world/gt/trajectory"
GT_POSE = "world/gt/pose"
VIO = "world/vio"  # trajectory(VIO, ...) -> world/vio/{trajectory,pose}
VIO_POSE = "world/vio/pose"
VIO_TRAJECTORY = "world/vio/trajectory"
VIO_COV = "world/vio/cov"
FEATURES = "world/features"
CAM = "cam0"
CAM_IMAGE = "cam0/image"
CAM_TRACKS = "cam0/tracks"
FILTER = "filter"
NEES_POSE = "filter/nees_pose"
NEES_ANCHOR = "filter/nees_anchor"
SIGMA = "filter/sigma"
LOG = "log"
LOG_STAGES = "log/stages"
LOG_STAGE_INDEX = "log/stage_index"

ANCHOR_WORLD_PARTS = ("truth", "lsi", "ri", "ri-robust", "estimate", "cov")
UWB_PARTS = ("range", "residual", "nis", "nis_gate", "rejected")
_UNSAFE = re.compile(r"[^A-Za-z0-9_.\-]")
INIT_PARTS = ("cost", "fim_logdet")
ANCHOR_PARAM_PARTS = ("beta", "gamma")


def _part(x: object) -> str:
    """One entity-path part: ids with characters outside [A-Za-z0-9_.-] get them replaced by '_'."""
    return _UNSAFE.sub("_", str(x)) or "_"


def anchor_world(anchor: object, what: str) -> str:
    """`world/anchors/<id>/<what>`, what in truth, lsi, ri, ri-robust, estimate, cov."""
    return f"world/anchors/{_part(anchor)}/{what}"


def uwb(anchor: object, what: str) -> str:
    """`uwb/<id>/<what>`, what in range, residual, nis, nis_gate, rejected."""
    return f"uwb/{_part(anchor)}/{what}"


def init(method: str, what: str) -> str:
    """`init/<method>/<what>`, what in cost, fim_logdet."""
    return f"init/{_part(method)}/{what}"


def anchor_param(anchor: object, what: str) -> str:
    """`anchors/<id>/<what>`, what in beta, gamma."""
    return f"anchors/{_part(anchor)}/{what}"


# Colours (RGB) used consistently across runs: a method always has the same colour.
COLORS = {
    "truth": (230, 230, 230),
    "gt": (120, 200, 120),
    "vio": (80, 160, 255),
    "lsi": (255, 150, 40),
    "ri": (60, 120, 255),
    "ri-robust": (190, 90, 255),
    "estimate": (40, 220, 120),
    "ekf": (255, 90, 90),
    "skf": (40, 220, 120),
    "none": (160, 160, 160),
    "gate": (150, 150, 150),
    "rejected": (255, 60, 60),
    "features": (255, 230, 80),
    "world/estimate": (240, 110, 190),  # the UWB-aided trajectory (the anchor estimate itself is "estimate")
}


# 3-D markers of the initialisers (distinct shapes, explained by the legend instead of per-point labels)
MARKERS = {"lsi": "box", "ri": "sphere", "ri-robust": "cross"}
LEGEND = "legend"
NIS_UWB = "filter/nis_uwb"
VIO_NIS = "filter/vio"


def legend_markdown(methods: Sequence[str] = ("lsi", "ri", "ri-robust")) -> str:
    shape = {"box": "wireframe box", "sphere": "sphere", "cross": "cross"}
    rows = [
        "| marker | what |",
        "|---|---|",
        "| small sphere with the anchor id | true (simulated) or surveyed anchor |",
        *(
            f"| {_colour_name(m)} {shape[MARKERS.get(m, 'sphere')]} | {m.upper()} initialisation |"
            for m in methods
        ),
        "| green dot + wireframe ellipsoid | refined estimate and its 3σ ellipsoid (over time) |",
        "| green / blue / pink lines | ground truth / VIO / UWB-aided trajectories |",
    ]
    return "\n".join(rows)


def _colour_name(method: str) -> str:
    return {"lsi": "orange", "ri": "blue", "ri-robust": "purple"}.get(method, "grey")


def moving_nis(
    t_ns: Any, nis: Any, dof: int = 1, window: int = 50
) -> tuple[np.ndarray, np.ndarray, float, float]:
    """Trailing mean of `window` NIS values (time-sorted) and the 95 % two-sided bounds of such a mean,
    χ²(0.025, window·dof)/window and χ²(0.975, window·dof)/window."""

    t = np.asarray(t_ns, dtype=np.int64).reshape(-1)
    v = np.asarray(nis, dtype=np.float64).reshape(-1)
    ok = np.isfinite(v)
    t, v = t[ok], v[ok]
    o = np.argsort(t, kind="stable")
    t, v = t[o], v[o]
    if len(v) < window:
        return t[:0], v[:0], float("nan"), float("nan")
    avg = sliding_mean(v, window)
    n = window * dof
    return (
        t[window - 1 :],
        avg,
        float(chi2_quantile(0.025, n) / window),
        float(chi2_quantile(0.975, n) / window),
    )


def _ts(t_ns: Any) -> np.ndarray:
    return np.asarray(t_ns, dtype=np.int64).astype("datetime64[ns]")


def cov_to_ellipsoid(covs: np.ndarray, n_sigma: float = 3.0) -> tuple[np.ndarray, np.ndarray]:
    """Half sizes (N,3) and rotations as quaternions xyzw (N,4) of the n-sigma ellipsoids of 3x3 covariances.

    Eigenvectors form the rotation; a column is flipped where needed so that det = +1 (a proper rotation).
    """
    from scipy.spatial.transform import Rotation

    covs = np.asarray(covs, dtype=float).reshape(-1, 3, 3)
    covs = 0.5 * (covs + np.swapaxes(covs, 1, 2))
    w, v = np.linalg.eigh(covs)
    v = v.copy()
    v[:, :, 2] *= np.sign(np.linalg.det(v))[:, None]
    half = n_sigma * np.sqrt(np.clip(w, 0.0, None))
    return half, Rotation.from_matrix(v).as_quat()


@dataclass
class RrdSummary:
    """What an .rrd holds: temporal rows per entity path (no leading '/'), timelines, static rows, stores."""

    rows: dict[str, int] = field(default_factory=dict)
    timelines: set[str] = field(default_factory=set)
    timelines_by_entity: dict[str, set[str]] = field(default_factory=dict)
    static: dict[str, int] = field(default_factory=dict)
    recording_ids: list[str] = field(default_factory=list)
    application_ids: set[str] = field(default_factory=set)
    blueprints: int = 0
    blueprint_entities: list[str] = field(default_factory=list)
    blueprint_names: list[str] = field(default_factory=list)  # view and container titles


def read_rrd_summary(path: Path | str) -> RrdSummary:
    """Read an .rrd back (all recording stores) and count rows per entity path."""
    from rerun.chunk import RrdReader

    path = Path(path)
    if not path.exists():
        raise InputError(f"{path}: missing; expected a rerun .rrd file")
    reader = RrdReader(path)
    out = RrdSummary()
    for store in reader.recordings():
        out.recording_ids.append(store.recording_id)
        out.application_ids.add(store.application_id)
        for ch in reader.stream(store=store).to_chunks():
            ent = ch.entity_path.lstrip("/")
            if ent.startswith("__"):
                continue
            if ch.is_static:
                out.static[ent] = out.static.get(ent, 0) + ch.num_rows
                continue
            out.rows[ent] = out.rows.get(ent, 0) + ch.num_rows
            names = set(ch.timeline_names)
            out.timelines |= names
            out.timelines_by_entity.setdefault(ent, set()).update(names)
    bps = reader.blueprints()
    out.blueprints = len(bps)
    for store in bps:
        for ch in reader.stream(store=store).to_chunks():
            out.blueprint_entities.append(ch.entity_path)
            rb = ch.to_record_batch()
            for f in rb.schema:
                if f.name.endswith(":display_name"):
                    out.blueprint_names += [str(x) for v in rb.column(f.name).to_pylist() for x in (v or [])]
    return out


class RunLog:
    """One rerun recording written to `path` (atomically, on `close`). See the module docstring."""

    def __init__(
        self,
        path: Path | str | None,
        *,
        app_id: str = APP_ID,
        recording_id: str | None = None,
        run_kind: str = "simulation",
        enabled: bool = True,
        anchors: Iterable[object] = (),
        blueprint: bool = True,
        time_origin_ns: int | None = None,
    ) -> None:
        self.path = Path(path) if path is not None else None
        # sensor_time: real stamps (timestamp) by default; seconds from this origin (duration) when given, e.g. the
        # start of a simulated recording (whose stamps start near the epoch and would read 1970-01-01)
        self.time_origin_ns = time_origin_ns
        self._seen: set[str] = set()
        self._send_blueprint = blueprint  # stage parts of a run leave it to merge_run_logs
        self.run_kind = run_kind if run_kind in RUN_KINDS else "simulation"
        self._anchors: dict[str, None] = {_part(a): None for a in anchors}
        self._stage: int | None = None
        self._has_camera = False
        self._rec = None
        self._stack: contextlib.ExitStack | None = None
        if self.path is None or not enabled:
            return
        import rerun as rr

        self._rr = rr
        self._stack = contextlib.ExitStack()
        tmp = self._stack.enter_context(atomic_path(self.path))
        rec = rr.RecordingStream(app_id, recording_id=recording_id, send_properties=False)
        rec.set_log_time_enabled(False)
        rec.set_log_tick_enabled(False)
        rec.save(tmp)
        self._rec = rec

    # -- lifecycle -------------------------------------------------------------------------------------------
    @property
    def enabled(self) -> bool:
        """False for the no-op log: callers may skip computing what they would only log."""
        return self._rec is not None

    def __enter__(self) -> RunLog:
        return self

    def __exit__(self, exc_type: type | None, exc: BaseException | None, tb: TracebackType | None) -> None:
        self.close(keep=exc_type is None)

    def close(self, *, keep: bool | None = None) -> Path | None:
        """Send the blueprint, flush and rename the temp file to `path`.

        keep=None keeps the log unless an exception is propagating (close() called from a `finally`), so a failed
        stage never leaves an .rrd that looks whole; keep=False discards it.
        """
        if self._rec is None or self._stack is None:
            return None
        if keep is None:
            keep = sys.exc_info()[0] is None
        rec, stack = self._rec, self._stack
        self._rec, self._stack = None, None
        try:
            if keep and self._send_blueprint:
                rec.send_blueprint(self.blueprint(), make_active=True, make_default=True)
            rec.flush()
        finally:
            rec.disconnect()
        if keep:
            stack.close()
            return self.path
        stack.__exit__(RuntimeError, RuntimeError("run log discarded"), None)
        return None

    def abort(self) -> None:
        self.close(keep=False)

    # -- time --------------------------------------------------------------------------------------------------
    def _time_kw(self, t_ns: Any) -> dict:
        """``timestamp=`` (real stamps) or ``duration=`` (seconds from the time origin) for sensor_time."""
        t = np.asarray(t_ns, dtype=np.int64)
        if self.time_origin_ns is None:
            return {"timestamp": t.astype("datetime64[ns]")}
        return {"duration": (t - np.int64(self.time_origin_ns)).astype("timedelta64[ns]")}

    def _indexes(self, t_ns: np.ndarray) -> list:
        rr = self._rr
        idx = [rr.TimeColumn(T_SENSOR, **self._time_kw(np.asarray(t_ns, dtype=np.int64).reshape(-1)))]
        if self._stage is not None:
            idx.append(rr.TimeColumn(T_STAGE, sequence=np.full(len(t_ns), self._stage, dtype=np.int64)))
        return idx

    def _set_time(self, t_ns: int | None) -> None:
        if t_ns is not None:
            self._rec.set_time(T_SENSOR, **{k: v[()] for k, v in self._time_kw(int(t_ns)).items()})

    def _note(self, entity: str) -> None:
        self._seen.add(entity)
        parts = entity.split("/")
        if len(parts) >= 3 and parts[0] in ("uwb", "anchors"):
            self._anchors.setdefault(parts[1], None)
        elif len(parts) >= 4 and parts[:2] == ["world", "anchors"]:
            self._anchors.setdefault(parts[2], None)
        elif parts[0] == CAM:
            self._has_camera = True

    def stage(self, name: str, t_ns: int) -> None:
        """Stage boundary: sets the `stage` timeline and logs an event at log/stages and a step at log/stage_index."""
        if self._rec is None:
            return
        rr = self._rr
        self._stage = STAGE_INDEX.get(name, len(STAGE_INDEX))
        self._rec.set_time(T_STAGE, sequence=self._stage)
        self._set_time(t_ns)
        self._rec.log(LOG_STAGES, rr.TextLog(f"stage {self._stage}: {name}", level=rr.TextLogLevel.INFO))
        self._rec.log(LOG_STAGE_INDEX, rr.Scalars(float(self._stage)))

    def text(self, msg: str, level: str = "INFO", t_ns: int | None = None) -> None:
        if self._rec is None:
            return
        self._set_time(t_ns)
        self._rec.log(LOG, self._rr.TextLog(str(msg), level=str(level).upper()))

    # -- time series -------------------------------------------------------------------------------------------
    def _stamps(self, t_ns: Any) -> np.ndarray | None:
        """A series' stamps as int64, or None when nothing is to be logged (no recording, no stamps)."""
        if self._rec is None:
            return None
        t = np.asarray(t_ns, dtype=np.int64).reshape(-1)
        return t if len(t) else None

    def scalars(self, entity: str, t_ns: Any, values: Any, names: Sequence[str] | None = None) -> None:
        """Column-wise scalar series: values (N,) or (N,k) at t_ns (N,)."""
        if self._rec is None:
            return
        t = np.asarray(t_ns, dtype=np.int64).reshape(-1)
        v = np.asarray(values, dtype=np.float64)
        if v.shape[0] != t.shape[0]:
            raise ValueError(f"{entity}: {v.shape[0]} values for {t.shape[0]} stamps")
        if len(t) == 0:
            return
        self._note(entity)
        rr = self._rr
        self._rec.send_columns(entity, indexes=self._indexes(t), columns=rr.Scalars.columns(scalars=v))
        if names is not None:
            self._rec.log(entity, rr.SeriesLines.from_fields(names=list(names)), static=True)

    def constant(self, entity: str, t_ns: Any, values: Any, names: Sequence[str] | None = None) -> None:
        """A constant line (e.g. a chi-square gate or NEES bounds) over the span of t_ns: values scalar or (k,)."""
        t = self._stamps(t_ns)
        if t is None:
            return
        v = np.atleast_1d(np.asarray(values, dtype=np.float64))
        self.scalars(
            entity, np.array([t.min(), t.max()]), np.stack([v, v]) if v.size > 1 else np.repeat(v, 2)
        )
        colors = [COLORS["gate"]] * v.size
        self.series_static_style(entity, list(names) if names else ["gate"] * v.size, colors)

    def series_static_style(
        self, entity: str, names: Sequence[str], colors: Sequence[Any], *, points: bool = False
    ) -> None:
        if self._rec is None:
            return
        rr = self._rr
        arch = rr.SeriesPoints if points else rr.SeriesLines
        self._rec.log(entity, arch.from_fields(names=list(names), colors=list(colors)), static=True)

    # -- 3-D -----------------------------------------------------------------------------------------------------
    def points3d(
        self,
        entity: str,
        pts: Any,
        colors: Any = None,
        radii: Any = None,
        labels: Sequence[str] | None = None,
        t_ns: int | None = None,
        static: bool = False,
    ) -> None:
        if self._rec is None:
            return
        self._note(entity)
        self._set_time(t_ns)
        p = np.asarray(pts, dtype=np.float64).reshape(-1, 3)
        self._rec.log(
            entity,
            self._rr.Points3D(
                p, colors=colors, radii=radii, labels=list(labels) if labels is not None else None
            ),
            static=static,
        )

    def trajectory(
        self,
        entity: str,
        t_ns: Any,
        p: Any,
        q_xyzw: Any = None,
        static_strip: bool = True,
        color: Any = None,
        axis_length: float = 0.3,
    ) -> None:
        """`<entity>/trajectory` as one line strip + `<entity>/pose` over time (Transform3D with axes when q is
        given, else a point), column-wise so the viewer can scrub. entity: GT or VIO."""
        if self._rec is None:
            return
        rr = self._rr
        t = np.asarray(t_ns, dtype=np.int64).reshape(-1)
        p = np.asarray(p, dtype=np.float64).reshape(-1, 3)
        if len(t) == 0:
            return
        if color is None:
            color = COLORS.get(entity, COLORS.get(entity.rsplit("/", 1)[-1], COLORS["vio"]))
        strip = rr.LineStrips3D([p], colors=[color], radii=rr.Radius.ui_points(1.5))
        if static_strip:
            self._rec.log(f"{entity}/trajectory", strip, static=True)
        else:
            self._set_time(int(t[-1]))
            self._rec.log(f"{entity}/trajectory", strip)
        pose = f"{entity}/pose"
        if q_xyzw is None:
            self._rec.send_columns(pose, indexes=self._indexes(t), columns=rr.Points3D.columns(positions=p))
            self._rec.log(pose, rr.Points3D.from_fields(colors=[color], radii=[0.05]), static=True)
        else:
            q = np.asarray(q_xyzw, dtype=np.float64).reshape(-1, 4)
            cols = rr.Transform3D.columns(translation=p, quaternion=q)
            self._rec.send_columns(pose, indexes=self._indexes(t), columns=cols)
            self._rec.log(pose, rr.TransformAxes3D(axis_length), static=True)

    def ellipsoids(
        self,
        entity: str,
        centers: Any,
        covs: Any,
        n_sigma: float = 3.0,
        t_ns: int | None = None,
        colors: Any = None,
        static: bool = False,
    ) -> None:
        """n-sigma covariance ellipsoids (one batch) from 3x3 covariances."""
        if self._rec is None:
            return
        self._note(entity)
        c = np.asarray(centers, dtype=np.float64).reshape(-1, 3)
        half, quat = cov_to_ellipsoid(covs, n_sigma)
        self._set_time(t_ns)
        self._rec.log(
            entity,
            self._rr.Ellipsoids3D(
                centers=c, half_sizes=half, quaternions=quat, colors=colors, fill_mode="MajorWireframe"
            ),
            static=static,
        )

    def ellipsoid_series(
        self, entity: str, t_ns: Any, centers: Any, covs: Any, n_sigma: float = 3.0, color: Any = None
    ) -> None:
        """One n-sigma ellipsoid per stamp, column-wise (e.g. world/vio/cov from the pose covariance's p block)."""
        t = self._stamps(t_ns)
        if t is None:
            return
        rr = self._rr
        self._note(entity)
        c = np.asarray(centers, dtype=np.float64).reshape(-1, 3)
        half, quat = cov_to_ellipsoid(covs, n_sigma)
        cols = rr.Ellipsoids3D.columns(centers=c, half_sizes=half, quaternions=quat)
        self._rec.send_columns(entity, indexes=self._indexes(t), columns=cols)
        style = rr.Ellipsoids3D.from_fields(colors=[color or COLORS["vio"]], fill_mode="MajorWireframe")
        self._rec.log(entity, style, static=True)

    # -- camera ---------------------------------------------------------------------------------------------------
    def pinhole(
        self, entity: str, intrinsics: Sequence[float], resolution: Sequence[int], T_world_cam: Any = None
    ) -> None:
        """Static pinhole (fu, fv, cu, cv) at `entity` (cam0); with T_world_cam (4x4) also its static pose."""
        if self._rec is None:
            return
        rr = self._rr
        self._note(entity)
        fu, fv, cu, cv = (float(x) for x in intrinsics)
        w, h = (int(x) for x in resolution)
        if T_world_cam is not None:
            T = np.asarray(T_world_cam, dtype=np.float64)
            self._rec.log(entity, rr.Transform3D(translation=T[:3, 3], mat3x3=T[:3, :3]), static=True)
        self._rec.log(
            entity,
            rr.Pinhole(
                focal_length=[fu, fv],
                principal_point=[cu, cv],
                width=w,
                height=h,
                camera_xyz=rr.ViewCoordinates.RDF,
            ),
            static=True,
        )

    def image(self, entity: str, t_ns: int, img: np.ndarray, *, jpeg_quality: int | None = 80) -> None:
        """One camera frame; JPEG-encoded by default (a raw 752x480 EuRoC frame is 360 kB, ~25 kB as JPEG)."""
        if self._rec is None:
            return
        rr = self._rr
        self._note(entity)
        self._set_time(t_ns)
        img = np.asarray(img)
        if jpeg_quality is not None and img.dtype == np.uint8:
            import cv2

            ok, buf = cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, int(jpeg_quality)])
            if ok:
                self._rec.log(entity, rr.EncodedImage(contents=buf.tobytes(), media_type="image/jpeg"))
                return
        self._rec.log(entity, rr.Image(img))

    def tracks(self, entity: str, t_ns: int, uv: Any, ids: Any, radii: float = 2.0) -> None:
        """Feature tracks of one frame: pixel positions (M,2) coloured by track id (class ids)."""
        if self._rec is None:
            return
        rr = self._rr
        self._note(entity)
        self._set_time(t_ns)
        uv = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
        ids = np.asarray(ids, dtype=np.int64).reshape(-1)
        self._rec.log(
            entity,
            rr.Points2D(uv, class_ids=(ids % 65535).astype(np.uint16), radii=rr.Radius.ui_points(radii)),
        )

    # -- anchors: initialiser markers, estimate, legend, consistency series ------------------------------------------
    def initialiser(
        self, anchor: object, method: str, p: Any, t_ns: int | None = None, static: bool = True
    ) -> None:
        """One initialiser's anchor estimate as its own marker (no label; `legend` says which is which):
        LSI a box, RI a sphere, RI-robust a cross, each in the method's colour."""
        if self._rec is None:
            return
        rr = self._rr
        entity = anchor_world(anchor, method)
        self._note(entity)
        self._set_time(t_ns)
        c = np.asarray(p, dtype=np.float64).reshape(3)
        color = COLORS.get(method, COLORS["none"])
        marker = MARKERS.get(method, "sphere")
        # wireframe and thin lines: the markers of one anchor overlap (the estimates agree within centimetres)
        if marker == "box":
            arch = rr.Boxes3D(
                centers=[c],
                half_sizes=[[0.15] * 3],
                colors=[color],
                radii=rr.Radius.ui_points(1.5),
                fill_mode="MajorWireframe",
            )
        elif marker == "cross":
            e = 0.25 * np.eye(3)
            arch = rr.LineStrips3D(
                [[c - v, c + v] for v in e], colors=[color], radii=rr.Radius.ui_points(1.5)
            )
        else:
            arch = rr.Points3D([c], colors=[color], radii=[0.07])
        self._rec.log(entity, arch, static=static)

    def point_series(self, entity: str, t_ns: Any, p: Any, color: Any = None, radius: float = 0.05) -> None:
        """A point moving over time (e.g. an anchor estimate over refinement), column-wise."""
        t = self._stamps(t_ns)
        if t is None:
            return
        rr = self._rr
        self._note(entity)
        p = np.asarray(p, dtype=np.float64).reshape(-1, 3)
        self._rec.send_columns(entity, indexes=self._indexes(t), columns=rr.Points3D.columns(positions=p))
        self._rec.log(
            entity, rr.Points3D.from_fields(colors=[color or COLORS["estimate"]], radii=[radius]), static=True
        )

    def legend(self, methods: Sequence[str] = ("lsi", "ri", "ri-robust")) -> None:
        """A static markdown legend of the 3-D view's anchor markers (entity `legend`)."""
        if self._rec is None:
            return
        self._note(LEGEND)
        self._rec.log(
            LEGEND, self._rr.TextDocument(legend_markdown(methods), media_type="text/markdown"), static=True
        )

    # -- blueprint -------------------------------------------------------------------------------------------------
    def anchors(self) -> list[str]:
        return list(self._anchors)

    def blueprint(self):
        return make_blueprint(self.run_kind, self.anchors(), camera=self._has_camera, present=self._seen)


def _present(present: set[str] | None, prefix: str) -> bool:
    """Whether any logged entity is `prefix` or below it (everything counts as present when unknown)."""
    if present is None:
        return True
    return any(e == prefix or e.startswith(prefix + "/") for e in present)


def make_blueprint(
    run_kind: str, anchors: Sequence[str], *, camera: bool = True, present: set[str] | None = None
):
    """The layout a run opens on, built from what the run logged (`present`: entity paths; None = all):

    left, the 3-D world (anchors with markers per initialiser, trajectories, 3σ ellipsoids), the camera only when
    the run has camera data, and the marker legend; right, per-anchor range residual (with the gate as a ±σ band) and NIS tabs,
    NEES and NIS side by side each with its χ² band, σ / β / γ / VIO / init tabs, and the stage log."""
    import rerun.blueprint as rrb

    has = functools.partial(_present, present)
    rows: list = [rrb.Tabs(*_anchor_views(rrb, anchors), name="UWB residuals")]
    row_shares = [3]
    checks = _consistency_views(rrb, has)
    if checks:
        rows.append(rrb.Horizontal(*checks) if len(checks) > 1 else checks[0])
        row_shares.append(2)
    series = _series_views(rrb, has, present, anchors)
    if series:
        rows.append(rrb.Tabs(*series, name="σ, β, γ"))
        row_shares.append(2)
    rows.append(rrb.TextLogView(origin=LOG, name="log"))
    row_shares.append(1)
    right = rrb.Vertical(*rows, row_shares=row_shares)
    return rrb.Blueprint(
        rrb.Horizontal(_left_column(rrb, has, camera), right, column_shares=[3, 2]),
        rrb.BlueprintPanel(state="collapsed"),
        rrb.SelectionPanel(state="collapsed"),
        rrb.TimePanel(state="collapsed", timeline=T_SENSOR),
    )


def _left_column(rrb, has, camera: bool):
    """The 3-D world, the camera (when there is one) and the marker legend."""
    left: list = [rrb.Spatial3DView(origin=WORLD, name="world: trajectories, anchors, 3σ ellipsoids")]
    shares = [6]
    if camera:
        left.append(rrb.Spatial2DView(origin=CAM, name="cam0"))
        shares.append(3)
    if has(LEGEND):
        left.append(rrb.TextDocumentView(origin=LEGEND, name="legend"))
        shares.append(3)
    return rrb.Vertical(*left, row_shares=shares) if len(left) > 1 else left[0]


def _anchor_views(rrb, anchors: Sequence[str]) -> list:
    """Per anchor: its range residuals inside the gate band, and its NIS against the gate."""
    views = [
        rrb.Vertical(
            rrb.TimeSeriesView(
                origin=f"uwb/{a}",
                contents=[f"+ uwb/{a}/residual/**", f"+ uwb/{a}/band/**", f"+ uwb/{a}/rejected/**"],
                name=f"{a}: range residual and gate band [m]",
            ),
            rrb.TimeSeriesView(
                origin=f"uwb/{a}", contents=[f"+ uwb/{a}/nis/**", f"+ uwb/{a}/nis_gate/**"], name=f"{a}: NIS"
            ),
            name=f"anchor {a}",
        )
        for a in anchors
    ]
    return views or [rrb.TimeSeriesView(origin="uwb", name="uwb")]


def _consistency_views(rrb, has) -> list:
    """NEES of the pose (and of position / orientation) and the NIS of the UWB updates, with their chi2 bands."""
    nees = []
    if has(NEES_POSE):
        nees.append(
            rrb.TimeSeriesView(
                origin=FILTER,
                contents=[f"+ {NEES_POSE}/**", f"+ {NEES_POSE}_bounds/**"],
                name="NEES pose (6 dof)",
            )
        )
    if has(f"{FILTER}/nees_position"):
        parts = ("nees_position", "nees_position_bounds", "nees_orientation")
        nees.append(
            rrb.TimeSeriesView(
                origin=FILTER,
                contents=[f"+ {FILTER}/{p}/**" for p in parts],
                name="NEES position, orientation (3 dof)",
            )
        )
    checks = []
    if nees:
        checks.append(rrb.Tabs(*nees, name="NEES") if len(nees) > 1 else nees[0])
    if has(NIS_UWB):
        checks.append(
            rrb.TimeSeriesView(
                origin=FILTER,
                contents=[f"+ {NIS_UWB}/**", f"+ {NIS_UWB}_bounds/**"],
                name="NIS of the UWB updates",
            )
        )
    return checks


def _series_views(rrb, has, present: set[str] | None, anchors: Sequence[str]) -> list:
    """σ (metres and degrees on their own axes), β and γ per anchor, the VIO updates, the initialisers."""
    series = []
    if has(SIGMA):
        rot = sorted(
            {e for e in (present or ()) if e.startswith(SIGMA + "/") and ("deg" in e or "theta" in e)}
        )
        series.append(
            rrb.TimeSeriesView(
                origin=SIGMA, contents=[f"+ {SIGMA}/**", *(f"- {e}/**" for e in rot)], name="σ position [m]"
            )
        )
        if rot:
            series.append(
                rrb.TimeSeriesView(
                    origin=SIGMA, contents=[f"+ {e}/**" for e in rot], name="σ orientation [deg]"
                )
            )
    if anchors:
        for param, name in (("beta", "β"), ("gamma", "γ [m]")):
            contents = [f"+ anchors/{a}/{param}/**" for a in anchors]
            series.append(rrb.TimeSeriesView(origin="anchors", contents=contents, name=name))
    if has(VIO_NIS):
        series.append(rrb.TimeSeriesView(origin=VIO_NIS, name="VIO updates"))
    if has("init"):
        series.append(rrb.TimeSeriesView(origin="init", name="init cost / FIM"))
    return series


def merge_run_logs(
    parts: Sequence[Path | str], target: Path | str, run_kind: str | None = None, name: str | None = None
) -> Path | None:
    """Merge per-stage .rrd files into one recording (`target`, atomic) with ONE blueprint built from all of them.

    `rerun rrd merge` would keep every stage's blueprint (each knowing only its own stage's anchors); here the
    recordings' chunks are re-sent into one stream and the blueprint is rebuilt from the merged entity tree.
    The recording is named `name` (default: the run directory's name), so that runs opened side by side
    (`uwbcal view A B`) are told apart in the viewer.
    """
    import rerun as rr
    from rerun.chunk import RrdReader

    parts = [Path(p) for p in parts]
    if not parts:
        return None
    for p in parts:
        if not p.is_file():
            raise InputError(f"{p}: missing; re-run the stage that writes it")
    readers = [RrdReader(p) for p in parts]
    stores = [(r, st) for r in readers for st in r.recordings()]
    if not stores:
        raise InputError(f"{parts[0]}: no recording inside; re-run the stage that writes it")
    first = stores[0][1]
    chunks = [ch for r, st in stores for ch in r.stream(store=st).to_chunks()]  # entity paths only
    probe = RunLog(None, run_kind=run_kind or "simulation")
    for ch in chunks:
        probe._note(ch.entity_path.lstrip("/"))
    bp = probe.blueprint()
    # Data: rerun's own merge (re-sending chunks through a new stream lost temporal transform/point chunks).
    # Blueprint: one blueprint-only part, merged last, so the merged run opens on the layout of every stage.
    import subprocess
    import tempfile

    target = Path(target)
    with tempfile.TemporaryDirectory(prefix="uwbcal-merge-") as tdir, atomic_path(target) as tmp:
        bp_part = Path(tdir) / "blueprint.rrd"
        rec = rr.RecordingStream(first.application_id, recording_id=first.recording_id, send_properties=False)
        try:
            rec.save(bp_part, default_blueprint=bp)
            rec.send_recording_name(name or target.resolve().parent.name)
            rec.flush()
        finally:
            rec.disconnect()
        res = subprocess.run(
            [*_rerun_exe(), "rrd", "merge", *map(str, parts), str(bp_part), "-o", str(tmp)],
            capture_output=True,
            text=True,
        )
        if res.returncode != 0:
            raise RuntimeError(f"rerun rrd merge failed: {res.stderr.strip()[-400:]}")
    return target


# -- viewer --------------------------------------------------------------------------------------------------------
def _rerun_exe() -> list[str]:
    exe = Path(sys.executable).with_name("rerun")
    if exe.exists():
        return [str(exe)]
    found = shutil.which("rerun")
    return [found] if found else [sys.executable, "-m", "rerun"]


def run_rrds(run_dirs: Sequence[Path | str]) -> list[Path]:
    """run.rrd of each run dir (an .rrd path is taken as is); InputError naming the first missing one."""
    out = []
    for d in map(Path, run_dirs):
        p = d if d.suffix == ".rrd" else d / "run.rrd"
        if not p.is_file():
            raise InputError(
                f"{p}: missing; run `uwbcal run REC -o {d}` first (without --no-log), or pass a run directory"
            )
        out.append(p)
    if not out:
        raise InputError("uwbcal view: no run directory given; pass one or more RUN_DIRs")
    return out


def viewer_command(
    run_dirs: Sequence[Path | str], web: bool = False, port: int = 9090, grpc_port: int = 9876
) -> list[str]:
    """The `rerun` command that opens the runs as several recordings in one viewer (native, or served on web)."""
    cmd = [*_rerun_exe(), *map(str, run_rrds(run_dirs))]
    if web:
        cmd += [
            "--serve-web",
            "--bind",
            "127.0.0.1",
            "--web-viewer-port",
            str(port),
            "--port",
            str(grpc_port),
        ]
    return cmd


def web_url(port: int = 9090, grpc_port: int = 9876) -> str:
    """Address of the served web viewer, already pointing at the gRPC server that holds the recordings."""
    return f"http://127.0.0.1:{port}/?url=rerun%2Bhttp%3A%2F%2F127.0.0.1%3A{grpc_port}%2Fproxy"


def view_runs(run_dirs: list[Path], web: bool = False, port: int = 9090, grpc_port: int = 9876) -> None:
    """Open run.rrd of each run dir in the native viewer, or serve the web viewer on localhost (blocks)."""
    cmd = viewer_command(run_dirs, web=web, port=port, grpc_port=grpc_port)
    if web:
        print(f"rerun web viewer: {web_url(port, grpc_port)}  (Ctrl-C to stop)", flush=True)
    elif not (os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")) and sys.platform.startswith(
        "linux"
    ):
        raise InputError(
            "uwbcal view: no display (DISPLAY/WAYLAND_DISPLAY unset); use --web and open the address"
        )
    try:
        subprocess.run(cmd, check=False)
    except KeyboardInterrupt:
        pass
