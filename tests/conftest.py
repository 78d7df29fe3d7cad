import os
from pathlib import Path

import pytest

from convert.datasets import data_root


@pytest.fixture(scope="session")
def data_dir() -> Path:
    """The real data folder. Missing: skip locally, fail under CI (CI=true)."""
    root = data_root()
    if not (root / "euroc").is_dir() or not (root / "ntu_viral").is_dir():
        msg = f"real data not found at {root} (set UWBCAL_DATA)"
        if os.environ.get("CI", "").lower() == "true":
            pytest.fail(msg)
        pytest.skip(msg)
    return root
