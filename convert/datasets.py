"""Where the real data lives: ``$UWBCAL_DATA``, else a ``shared/data`` folder beside the checkout (as CI lays it out)."""

from __future__ import annotations

import os
from pathlib import Path

REPO_ROOT = Path(__file__).resolve().parent.parent


def data_root() -> Path:
    env = os.environ.get("UWBCAL_DATA")
    if env:
        return Path(env)
    return (REPO_ROOT.parent / "shared" / "data").resolve()
