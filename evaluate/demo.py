"""`uwbcal demo`: simulate the built-in trajectory, run every stage, evaluate, print the results."""

from __future__ import annotations

from pathlib import Path

from uwbcal.convert.simulator import SimConfig, simulate_to_file
from uwbcal.evaluate.evaluation import evaluate_stage
from uwbcal.pipeline.run.config import load_config
from uwbcal.pipeline.run.stages.pipeline import Pipeline


def run_demo(output: Path, seed: int = 0, duration: float | None = None) -> str:
    output = Path(output)
    output.mkdir(parents=True, exist_ok=True)
    recording = output / "recording.mcap"
    print(simulate_to_file(SimConfig(trajectory=None, seed=seed, duration=duration), recording))
    cfg = load_config(None, {"run": {"recording": str(recording.resolve())}})
    pipe = Pipeline(cfg, output, evaluate_stage)
    pipe.run(overwrite=True)  # the demo's directory holds its own recording, simulated anew
    text = pipe.results_text
    lines = [
        "",
        "results (metrics.json):",
        text,
        "",
        f"run directory: {output}  (config.toml, anchors.csv, metrics.json, run.rrd)",
        f"replay: uwbcal view {output} [--web]",
    ]
    return "\n".join(lines)
