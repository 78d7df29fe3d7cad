"""The run directory: file names, atomic artefact I/O (anchors.csv, odometry MCAPs, trajectory.npz), checkpoints
and the merged run.rrd."""

from __future__ import annotations

import contextlib
import csv
import fcntl
import io
import json
import os
import pickle
from collections.abc import Iterator
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from uwbcal.convert.recording import TOPIC_VIO, RecordingWriter, json_default
from uwbcal.pipeline.core.atomic import FILE_MODE, atomic_path, pid_alive, write_text_atomic
from uwbcal.pipeline.core.errors import InputError
from uwbcal.pipeline.core.names import SEGMENT_IDS
from uwbcal.pipeline.run import artefacts
from uwbcal.pipeline.viz.runlog import merge_run_logs

if TYPE_CHECKING:
    from uwbcal.pipeline.run.windows import Windows

CONFIG = "config.toml"
RESOLVED = "resolved.json"  # the recording-aware defaults of the run and why (run.resolve)
METRICS = "metrics.json"
ANCHORS = "anchors.csv"
RRD = "run.rrd"
TRAJECTORY = "trajectory.npz"
LOGS = "logs"
STAGES_JSON = "stages.json"
LOCK = ".uwbcal.lock"
# every artefact the stages write; config.toml and stages.json first: a removal (provenance.claim) cut short
# leaves neither the recording's name nor its stages
ARTEFACTS = (
    CONFIG,
    STAGES_JSON,
    RESOLVED,
    "frontend.mcap",
    "windows.json",
    "static_init.json",
    "health.json",
    "checkpoint_init.pkl",
    "vio.npz",
    "vio.mcap",
    "vio_drift.json",
    "init.pkl",
    "init.json",
    "lever_arms.pkl",
    ANCHORS,
    "checkpoint_refine.pkl",
    "refine.npz",
    "refine.mcap",
    "range_updates.npz",
    "anchor_states.json",
    "localize.npz",
    "localize.mcap",
    TRAJECTORY,
    METRICS,
    "results.md",
    "results.csv",
    "results.tex",
    "report.html",
    "recording_id.txt",
    LOGS,
    RRD,
)


def present_artefacts(path: Path) -> list[str]:
    """The artefacts present in a run directory, in `ARTEFACTS` order (other files are not the run's)."""
    return [n for n in ARTEFACTS if os.path.lexists(Path(path) / n)]


class RunDir:
    def __init__(self, path: Path) -> None:
        self.path = Path(path)

    def file(self, name: str) -> Path:
        return self.path / name

    def exists(self, name: str) -> bool:
        """Whether artefact ``name`` is there (`artefacts.present`: something else in its place is refused)."""
        return artefacts.present(self.path / name)

    def require(self, name: str, stage: str) -> Path:
        p = self.path / name
        if not artefacts.present(p):
            raise InputError(
                f"{p}: missing; run the stage that produces it before '{stage}' "
                f"(e.g. uwbcal run REC -o {self.path} --stages <earlier>,{stage})"
            )
        return p

    # -- artefacts ---------------------------------------------------------------------------------------------
    def save_json(self, name: str, data: Any) -> None:
        write_text_atomic(self.path / name, json.dumps(data, indent=2, default=json_default) + "\n")

    def load_json(self, name: str, stage: str = "this stage", schema=dict) -> Any:
        """A JSON artefact checked against ``schema`` (`artefacts.read_json`)."""
        return artefacts.read_json(self.require(name, stage), schema)

    def corrupt(self, p: Path, problem: str) -> InputError:
        return artefacts.corrupt(p, problem)

    def save_npz(self, name: str, **arrays: np.ndarray) -> None:
        with atomic_path(self.path / name) as tmp:
            with open(tmp, "wb") as f:
                np.savez_compressed(f, **arrays)

    def load_npz(self, name: str, stage: str) -> dict[str, np.ndarray]:
        """A pose history (`artefacts.read_trajectory`)."""
        return artefacts.read_trajectory(self.require(name, stage))

    def save_pickle(self, name: str, obj: Any) -> None:
        with atomic_path(self.path / name) as tmp:
            with open(tmp, "wb") as f:
                pickle.dump(obj, f, protocol=pickle.HIGHEST_PROTOCOL)

    def load_pickle(self, name: str, stage: str) -> Any:
        return artefacts.read_pickle(self.require(name, stage))

    # -- rerun logs --------------------------------------------------------------------------------------------
    def stage_rrd(self, order: int, stage: str) -> Path:
        (self.path / LOGS).mkdir(parents=True, exist_ok=True)
        return self.path / LOGS / f"{order:02d}_{stage}.rrd"

    def rrd_parts(self) -> list[Path]:
        """The per-stage logs, in stage order."""
        return sorted((self.path / LOGS).glob("*.rrd")) if (self.path / LOGS).is_dir() else []

    def merge_rrd(self, run_kind: str | None = None, server=None) -> Path | None:
        """Merge the per-stage logs into run.rrd, so a stage re-run alone still gives a complete run.rrd;
        ``server``: a `runlog_async.LogServer` to do it in (rerun is imported there already)."""

        parts = self.rrd_parts()
        if not parts:
            return None
        name = self.path.resolve().name
        if server is not None:
            return server.merge(parts, self.path / RRD, run_kind, name=name)
        return merge_run_logs(parts, self.path / RRD, run_kind, name=name)


def write_text(path: Path, text: str) -> None:
    write_text_atomic(path, text)


_HELD: dict[Path, int] = {}  # run directories this process has locked -> nesting depth


@contextlib.contextmanager
def run_lock(path: Path) -> Iterator[int | None]:
    """Hold the run directory for this process (``flock`` on ``RUN_DIR/.uwbcal.lock``, removed on release).

    A second uwbcal on the same directory is refused with the holder's pid. The kernel drops the lock of a
    process that dies (even SIGKILL), so a stale lock file of a dead pid is simply taken over; yields that pid
    (None when there was none). Re-entrant within one process (``run`` -> ``evaluate``)."""
    path = Path(path)
    if path.exists() and not path.is_dir():
        raise InputError(
            f"{path}: exists and is not a directory; choose another output directory for the run"
        )
    key = path.resolve()
    if key in _HELD:
        _HELD[key] += 1
        try:
            yield None
        finally:
            _HELD[key] -= 1
        return
    lock = path / LOCK
    created = not path.exists()
    try:
        path.mkdir(parents=True, exist_ok=True)
        while True:
            fd = os.open(lock, os.O_RDWR | os.O_CREAT, FILE_MODE)
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                holder = os.read(fd, 32).decode(errors="replace").strip() or "?"
                os.close(fd)
                raise InputError(
                    f"{path}: in use by another uwbcal run (pid {holder}); wait for it to finish or choose "
                    "another output directory"
                ) from None
            try:  # the previous holder may have removed the file between our open and flock: retry
                same = os.stat(lock).st_ino == os.fstat(fd).st_ino
            except FileNotFoundError:
                same = False
            if same:
                break
            os.close(fd)
    except OSError as exc:
        raise InputError(
            f"{path}: cannot lock the run directory ({exc.strerror}); choose a writable output directory"
        ) from None
    old = os.read(fd, 32).decode(errors="replace").strip()
    stale = int(old) if old.isdigit() and int(old) != os.getpid() and not pid_alive(int(old)) else None
    os.ftruncate(fd, 0)
    os.pwrite(fd, f"{os.getpid()}\n".encode(), 0)
    _HELD[key] = 1
    try:
        yield stale
    finally:
        del _HELD[key]
        with contextlib.suppress(OSError):
            os.unlink(lock)
        os.close(fd)
        if created:  # a run that failed before writing anything leaves no empty directory behind
            with contextlib.suppress(OSError):
                path.rmdir()


# -- artefacts the stages share ----------------------------------------------------------------------------------
ANCHOR_COLUMNS = artefacts.ANCHOR_COLUMNS


def anchor_key(a):
    """Anchor ids are ints in the recording and strings in JSON."""
    return int(a) if str(a).lstrip("-").isdigit() else a


def anchor_row(anchor, method: str, stage: str, x) -> dict:
    x = np.asarray(x, float)
    return {
        "anchor": str(anchor),
        "method": method,
        "stage": stage,
        "x": f"{x[0]:.6f}",
        "y": f"{x[1]:.6f}",
        "z": f"{x[2]:.6f}",
        "beta": f"{x[3]:.6f}",
        "gamma": f"{x[4]:.6f}",
    }


def init_summary(r) -> dict:
    """One anchor's initialisation result as written into init.json."""
    out = {
        "status": r.status,
        "x": r.x,
        "cov": r.cov,
        "iterations": r.iterations,
        "n_used": r.n_used,
        "n_rejected": r.n_rejected,
        "noise_inflation": r.noise_inflation,
        "residual_rms": r.residual_rms,
        "warnings": r.warnings,
        "costs": r.costs,
    }
    if r.fim is not None:
        out["fim"] = r.fim.summary()
    if r.verdict:
        out["verdict"] = r.verdict
        out["reason"] = r.reason
    if r.link_offsets:
        out["link_offsets_m"] = {str(k): v for k, v in r.link_offsets.items()}
    out["join_s"] = None if r.join_ns is None else r.join_ns * 1e-9
    return out


def undetermined_row(anchor, method: str, stage: str, reason: str = "") -> dict:
    """anchors.csv row of an anchor that was not determined: empty coordinates (a stage's own reason in the
    optional ``reason`` column; the initialiser's are in init.json)."""
    return {
        "anchor": str(anchor),
        "method": method,
        "stage": stage,
        **dict.fromkeys(("x", "y", "z", "beta", "gamma"), ""),
        **({"reason": reason} if reason else {}),
    }


def write_anchors(run_dir: RunDir, rows: list[dict], replace_stage: str) -> None:
    """anchors.csv: this stage's rows replace the stage's earlier rows; other stages' rows stay."""
    path = run_dir.file(ANCHORS)
    old = (
        [r for r in artefacts.read_anchor_rows(path) if r["stage"] != replace_stage]
        if artefacts.present(path)
        else []
    )
    buf = io.StringIO()
    reason = ("reason",) if any(r.get("reason") for r in old + rows) else ()
    w = csv.DictWriter(buf, fieldnames=ANCHOR_COLUMNS + reason, lineterminator="\n", extrasaction="ignore")
    w.writeheader()
    for r in old + rows:
        w.writerow(r)
    write_text(path, buf.getvalue())


def write_odometry(run_dir: RunDir, name: str, hist: dict[str, np.ndarray]) -> None:
    """A trajectory (``t_ns, p, q_xyzw, cov``) as nav_msgs/Odometry on /vio/odometry in an MCAP file."""
    cov = hist["cov"]
    # ours: [dtheta, dp]; nav_msgs/Odometry: [x, y, z, rx, ry, rz]
    perm = np.r_[3:6, 0:3]
    ros_cov = cov[:, perm][:, :, perm]
    with RecordingWriter(run_dir.file(name)) as w:
        w.write_odometry_batch(hist["t_ns"], hist["p"], hist["q_xyzw"], ros_cov, topic=TOPIC_VIO)


def assemble_trajectory(run_dir: RunDir, win: Windows) -> dict[str, np.ndarray]:
    """trajectory.npz: the estimate of each segment from the stage that owns it (VIO for what is missing)."""
    parts = []
    vio = run_dir.load_npz("vio.npz", "trajectory") if run_dir.exists("vio.npz") else None
    bounds = {
        "init": (win.start_ns, win.init_end_ns),
        "refine": (win.init_end_ns, win.refine_end_ns),
        "localize": (win.refine_end_ns, win.end_ns + 1),
    }
    for name, seg in SEGMENT_IDS.items():
        lo, hi = bounds[name]
        owner = "vio" if name == "init" else name
        src = run_dir.load_npz(f"{owner}.npz", "trajectory") if run_dir.exists(f"{owner}.npz") else vio
        if src is None:
            continue
        m = (src["t_ns"] >= lo) & (src["t_ns"] < hi)
        part = {k: v[m] for k, v in src.items()}
        part["segment"] = np.full(int(m.sum()), seg, np.int8)
        parts.append(part)
    traj = {k: np.concatenate([p[k] for p in parts]) for k in parts[0]} if parts else {}
    if traj:
        run_dir.save_npz(TRAJECTORY, **traj)
    return traj
