"""Names every layer shares, each list defined once: the stages, the trajectory segments, the methods."""

from __future__ import annotations

# the staged pipeline, in run order; a stage's number (its log file 01_frontend.rrd, ...) is its
# position here + 1
STAGES = ("frontend", "vio", "init", "refine", "localize", "evaluate")
STAGE_NUMBER = {name: i + 1 for i, name in enumerate(STAGES)}

# the paper's three stretches of a run, as stored in trajectory.npz's ``segment`` column
SEGMENT_IDS = {"init": 0, "refine": 1, "localize": 2}

# anchor initialisers (paper stage 1) and refinements (paper stage 2)
INIT_METHODS = ("lsi", "ri", "ri-robust")
REFINE_METHODS = ("ekf", "skf")
