"""The run directory: file names, atomic artefact I/O (anchors.csv, odometry MCAPs, trajectory.npz), checkpoints
and the merged run.rrd (DESIGN §4)."""

from __future__ import annotations

import csv
import io
import json
import pickle
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from convert.recording import TOPIC_VIO, RecordingWriter, json_default
from pipeline.core.atomic import atomic_path, write_text_atomic
from pipeline.core.errors import InputError
from pipeline.core.names import SEGMENT_IDS

if TYPE_CHECKING:
    from .windows import Windows

CONFIG = "config.toml"
METRICS = "metrics.json"
ANCHORS = "anchors.csv"
RRD = "run.rrd"
TRAJECTORY = "trajectory.npz"
LOGS = "logs"


class RunDir:
    def __init__(self, path: Path) -> None:
        self.path = Path(path)

    def file(self, name: str) -> Path:
        return self.path / name

    def exists(self, name: str) -> bool:
        return (self.path / name).exists()

    def require(self, name: str, stage: str) -> Path:
        p = self.path / name
        if not p.exists():
            raise InputError(
                f"{p}: missing; run the stage that produces it before '{stage}' "
                f"(e.g. uwbcal run REC -o {self.path} --stages <earlier>,{stage})"
            )
        return p

    # -- artefacts ---------------------------------------------------------------------------------------------
    def save_json(self, name: str, data: Any) -> None:
        write_text_atomic(self.path / name, json.dumps(data, indent=2, default=json_default) + "\n")

    def load_json(self, name: str) -> Any:
        return json.loads((self.path / name).read_text())

    def save_npz(self, name: str, **arrays: np.ndarray) -> None:
        with atomic_path(self.path / name) as tmp:
            with open(tmp, "wb") as f:
                np.savez_compressed(f, **arrays)

    def load_npz(self, name: str, stage: str) -> dict[str, np.ndarray]:
        with np.load(self.require(name, stage), allow_pickle=False) as z:
            return {k: z[k] for k in z.files}

    def save_pickle(self, name: str, obj: Any) -> None:
        with atomic_path(self.path / name) as tmp:
            with open(tmp, "wb") as f:
                pickle.dump(obj, f, protocol=pickle.HIGHEST_PROTOCOL)

    def load_pickle(self, name: str, stage: str) -> Any:
        with open(self.require(name, stage), "rb") as f:
            return pickle.load(f)

    # -- rerun logs --------------------------------------------------------------------------------------------
    def stage_rrd(self, order: int, stage: str) -> Path:
        (self.path / LOGS).mkdir(parents=True, exist_ok=True)
        return self.path / LOGS / f"{order:02d}_{stage}.rrd"

    def merge_rrd(self, run_kind: str | None = None) -> Path | None:
        """Merge the per-stage logs into run.rrd, so a stage re-run alone still gives a complete run.rrd."""
        from .runlog import merge_run_logs

        parts = sorted((self.path / LOGS).glob("*.rrd")) if (self.path / LOGS).is_dir() else []
        return (
            merge_run_logs(parts, self.path / RRD, run_kind, name=self.path.resolve().name) if parts else None
        )


def write_text(path: Path, text: str) -> None:
    write_text_atomic(path, text)


# -- artefacts the stages share ----------------------------------------------------------------------------------
ANCHOR_COLUMNS = ["anchor", "method", "stage", "x", "y", "z", "beta", "gamma"]


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
    return out


def write_anchors(run_dir: RunDir, rows: list[dict], replace_stage: str) -> None:
    """anchors.csv: this stage's rows replace the stage's earlier rows; other stages' rows stay."""
    path = run_dir.file(ANCHORS)
    old = []
    if path.exists():
        with open(path, newline="") as f:
            old = [r for r in csv.DictReader(f) if r["stage"] != replace_stage]
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=ANCHOR_COLUMNS, lineterminator="\n")
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
