"""The import layers (docs/architecture.md), bottom up; a module may import its own layer and those below:

    foundation (pipeline/core)  ->  convert (recording format, converters, simulator)
    ->  estimation (pipeline: state, filters, initialisers, run log)  ->  stages (pipeline/stages, run, rundir)
    ->  evaluate  ->  cli (cli.py, the demo, benchmarks)

Every import is checked, also those inside functions and under TYPE_CHECKING: a lazy import upward is still a
dependency upward.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("pipeline", "convert", "evaluate", "benchmarks")
# (layer, module prefixes); the longest matching prefix decides a module's layer
LAYERS = (
    ("foundation", ("pipeline.core",)),
    ("convert", ("convert",)),
    ("estimation", ("pipeline",)),
    ("stages", ("pipeline.stages", "pipeline.run", "pipeline.rundir", "pipeline.provenance")),
    ("evaluate", ("evaluate",)),
    ("cli", ("cli", "pipeline.demo", "benchmarks")),
)
RANK = {name: i for i, (name, _) in enumerate(LAYERS)}


def layer_of(module: str) -> str | None:
    best, best_len = None, -1
    for name, prefixes in LAYERS:
        for p in prefixes:
            if (module == p or module.startswith(p + ".")) and len(p) > best_len:
                best, best_len = name, len(p)
    return best


def project_modules() -> dict[str, Path]:
    mods = {"cli": ROOT / "cli.py"}
    for pkg in PACKAGES:
        for path in sorted((ROOT / pkg).rglob("*.py")):
            parts = list(path.relative_to(ROOT).with_suffix("").parts)
            if parts[-1] == "__init__":
                parts = parts[:-1]
            mods[".".join(parts)] = path
    return mods


def imports_of(module: str, path: Path) -> list[tuple[int, str]]:
    """(line, imported module) for every import of the file, relative ones resolved."""
    is_pkg = path.name == "__init__.py"
    out = []
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            out += [(node.lineno, a.name) for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = module.split(".")
                base = base if is_pkg else base[:-1]
                base = base[: len(base) - (node.level - 1)]
                target = ".".join(base + ([node.module] if node.module else []))
            else:
                target = node.module or ""
            # `from pkg import module` imports the module
            out += [(node.lineno, f"{target}.{a.name}") for a in node.names]
    return out


def upward_imports() -> list[str]:
    mods = project_modules()
    bad = []
    for module, path in mods.items():
        own = layer_of(module)
        assert own is not None, f"{module}: in no layer; add it to LAYERS"
        for line, target in imports_of(module, path):
            # the longest prefix of the target that is a project module (drops imported names)
            parts = target.split(".")
            while parts and ".".join(parts) not in mods:
                parts.pop()
            if not parts:
                continue
            dep = layer_of(".".join(parts))
            if dep is not None and RANK[dep] > RANK[own]:
                rel = path.relative_to(ROOT)
                bad.append(f"{rel}:{line}: {module} ({own}) imports {'.'.join(parts)} ({dep})")
    return bad


def test_no_module_imports_a_layer_above_it():
    bad = upward_imports()
    assert not bad, "upward imports:\n" + "\n".join(bad)


@pytest.mark.parametrize(
    ("module", "layer"),
    [
        ("pipeline.core.geometry", "foundation"),
        ("convert.simulator", "convert"),
        ("pipeline.msckf", "estimation"),
        ("pipeline.stages.vio", "stages"),
        ("pipeline.run", "stages"),
        ("evaluate.experiments", "evaluate"),
        ("cli", "cli"),
    ],
)
def test_layer_assignment(module, layer):
    assert layer_of(module) == layer


def test_the_check_sees_an_upward_import(tmp_path, monkeypatch):
    """The test can fail: a foundation module importing the estimation layer is reported."""
    fake = tmp_path / "geometry.py"
    fake.write_text("from ..msckf import MsckfEstimator\n")
    found = imports_of("pipeline.core.geometry", fake)
    assert found == [(1, "pipeline.msckf.MsckfEstimator")]
    assert RANK[layer_of("pipeline.msckf")] > RANK[layer_of("pipeline.core.geometry")]
