"""The run directory: file names, atomic artefact I/O, checkpoints and the merged run.rrd (DESIGN §4)."""

from __future__ import annotations

import json
import pickle
from pathlib import Path
from typing import Any

import numpy as np

from convert.atomic import atomic_path, write_text_atomic
from convert.errors import InputError
from convert.recording import json_default

CONFIG = "config.toml"
METRICS = "metrics.json"
ANCHORS = "anchors.csv"
RRD = "run.rrd"
TRAJECTORY = "trajectory.npz"
LOGS = "logs"

SEGMENTS = {"init": 0, "refine": 1, "localize": 2}


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
