import os
from pathlib import Path

import pytest

from uwbcal.convert.datasets import data_root

_FALSY = {"", "0", "false", "no", "off"}


def ci() -> bool:
    """Any truthy ``CI`` value (1, true, yes, ...) means CI: missing real data fails instead of skipping."""
    return os.environ.get("CI", "").strip().lower() not in _FALSY


def pytest_collection_modifyitems(config, items):
    """Every test that uses real data (the ``data_dir`` fixture, directly or through another fixture) is marked
    ``data``, so ``-m "not data"`` selects the synthetic suite."""
    for item in items:
        if "data_dir" in getattr(item, "fixturenames", ()):
            item.add_marker(pytest.mark.data)


@pytest.fixture(scope="session")
def data_dir() -> Path:
    """The real data folder. Missing: skip locally, fail under CI (any truthy CI)."""
    root = data_root()
    if not (root / "euroc").is_dir() or not (root / "ntu_viral").is_dir():
        msg = f"real data not found at {root} (set UWBCAL_DATA)"
        if ci():
            pytest.fail(msg)
        pytest.skip(msg)
    return root


@pytest.fixture(scope="session")
def euroc_micro(data_dir, tmp_path_factory) -> tuple[Path, str]:
    """EuRoC V1_01_micro (with the V1_01_easy.csv ground truth) converted once per session: (mcap, summary)."""
    from uwbcal.convert.euroc import convert_euroc

    out = tmp_path_factory.mktemp("euroc_micro") / "v101.mcap"
    text = convert_euroc(
        data_dir / "euroc" / "V1_01_micro", out, groundtruth=data_dir / "euroc/groundtruth/V1_01_easy.csv"
    )
    return out, text


@pytest.fixture(scope="session")
def eee_01(data_dir, tmp_path_factory) -> tuple[Path, str]:
    """NTU-VIRAL eee_01 (CSV sequence folder) converted once per session: (mcap, summary)."""
    from uwbcal.convert.ntu_viral import convert_ntu_viral

    out = tmp_path_factory.mktemp("eee_01") / "eee_01.mcap"
    return out, convert_ntu_viral(data_dir / "ntu_viral" / "eee_01", out)


@pytest.fixture(scope="session")
def sim_recording(tmp_path_factory) -> Path:
    """A 45 s simulation (camera, IMU, 4 anchors, ground truth), written once per session."""
    from uwbcal.convert.simulator import SimConfig, simulate_to_file

    rec = tmp_path_factory.mktemp("sim") / "sim.mcap"
    simulate_to_file(SimConfig(duration=45.0, seed=3), rec)
    return rec


@pytest.fixture(scope="session")
def sim_run(sim_recording, tmp_path_factory) -> Path:
    """`uwbcal run --init ri --refine skf` on the session's simulation, once per session. Read-only: a test that
    re-runs stages into it works on a copy (`shutil.copytree`)."""
    from typer.testing import CliRunner

    from uwbcal.cli import app

    out = tmp_path_factory.mktemp("run") / "run"
    res = CliRunner().invoke(
        app, ["run", str(sim_recording), "-o", str(out), "--init", "ri", "--refine", "skf"]
    )
    assert res.exit_code == 0, res.output
    return out


@pytest.fixture(scope="session")
def demo_run(tmp_path_factory) -> tuple[Path, str]:
    """`uwbcal demo` (the built-in 120 s trajectory, every stage), once per session: (run dir, its output)."""
    from typer.testing import CliRunner

    from uwbcal.cli import app

    out = tmp_path_factory.mktemp("demo") / "demo"
    res = CliRunner().invoke(app, ["demo", "-o", str(out)])
    assert res.exit_code == 0, res.output
    return out, res.output
