"""Wall time of `uwbcal simulate` on the whole of EuRoC MH_01_easy (182 s; target < 15 s).

    uv run python -m uwbcal.benchmarks.simulate_mh01 [--seed 0] [--repeat 3]

Prints the time of generation (arrays) and of writing the recording, and the features per frame.
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

from uwbcal.convert.recording import RecordingReader
from uwbcal.convert.simulator import SimConfig, simulate, simulate_to_file, write_recording


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args()

    cfg = SimConfig(trajectory="MH_01_easy", seed=args.seed)
    runs = []
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "mh01.mcap"
        for _ in range(args.repeat):
            t0 = time.perf_counter()
            data = simulate(cfg)
            t1 = time.perf_counter()
            write_recording(data, out)
            t2 = time.perf_counter()
            runs.append((t1 - t0, t2 - t1))
        t0 = time.perf_counter()
        simulate_to_file(cfg, out)  # the CLI path end to end
        end_to_end = time.perf_counter() - t0
        topics = RecordingReader(out).topics()
        size_mb = out.stat().st_size / 1e6
    counts = data.features.counts
    best = min(runs, key=sum)
    print(
        json.dumps(
            {
                "case": "simulate_mh01",
                "data_seconds": round(float(data.metadata["uwbcal.truth"]["duration"]), 3),
                "simulate_s": round(best[0], 3),
                "write_s": round(best[1], 3),
                "total_s": round(sum(best), 3),
                "end_to_end_s": round(end_to_end, 3),
                "features_per_frame_mean": round(float(counts.mean()), 1),
                "features_per_frame_min": int(counts.min()),
                "landmarks": len(data.landmarks),
                "messages": {k: v.count for k, v in topics.items()},
                "file_mb": round(size_mb, 2),
            }
        )
    )


if __name__ == "__main__":
    main()
