"""The import layers (docs/architecture.md): folders are the layers, bottom up; a module imports its own folder
and the folders below it, never one above, and no two modules or folders import each other in a circle:

    pipeline/core -> convert -> pipeline/vio -> pipeline/uwb -> pipeline/viz -> pipeline/run
    -> pipeline/run/stages -> evaluate -> evaluate/experiments -> benchmarks, cli.py

Every import is counted, also those inside functions and under TYPE_CHECKING: a lazy import upward is still a
dependency upward. The distribution installs one name, `uwbcal` (the repository root): its package list in
pyproject.toml holds every folder of modules.
"""

from __future__ import annotations

import ast
import tomllib
from collections import defaultdict
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
FOLDERS = ("pipeline", "convert", "evaluate", "benchmarks")
LAYERS = (  # (layer, module prefixes); the longest matching prefix decides a module's layer
    ("core", ("uwbcal.pipeline.core",)),
    ("convert", ("uwbcal.convert",)),
    ("vio", ("uwbcal.pipeline.vio",)),
    ("uwb", ("uwbcal.pipeline.uwb",)),
    ("viz", ("uwbcal.pipeline.viz",)),
    ("run", ("uwbcal.pipeline.run",)),
    ("stages", ("uwbcal.pipeline.run.stages",)),
    ("evaluate", ("uwbcal.evaluate",)),
    ("experiments", ("uwbcal.evaluate.experiments",)),
    ("cli", ("uwbcal.cli", "uwbcal.benchmarks")),
)
RANK = {name: i for i, (name, _) in enumerate(LAYERS)}
# first-party imports inside functions, outside cli.py (the CLI imports its commands lazily for a fast start)
MAX_FUNCTION_LEVEL_IMPORTS = 0
MAX_FUNCTION_LINES = 80  # def line to last line, decorators not counted
MAX_CLASS_LINES = 400


def layer_of(module: str) -> str | None:
    best, best_len = None, -1
    for name, prefixes in LAYERS:
        for p in prefixes:
            if (module == p or module.startswith(p + ".")) and len(p) > best_len:
                best, best_len = name, len(p)
    return best


def project_modules(root: Path = ROOT) -> dict[str, Path]:
    mods = {"uwbcal": root / "__init__.py", "uwbcal.cli": root / "cli.py"}
    for folder in FOLDERS:
        for path in sorted((root / folder).rglob("*.py")):
            parts = ["uwbcal", *path.relative_to(root).with_suffix("").parts]
            if parts[-1] == "__init__":
                parts = parts[:-1]
            mods[".".join(parts)] = path
    return mods


def folder_of(module: str, path: Path) -> str:
    return module if path.name == "__init__.py" else module.rpartition(".")[0]


def imports_of(module: str, path: Path) -> list[tuple[int, str, bool]]:
    """(line, imported name, inside a function) for every import of the file, relative ones resolved."""
    is_pkg = path.name == "__init__.py"
    out: list[tuple[int, str, bool]] = []

    def visit(node: ast.AST, in_function: bool) -> None:
        for child in ast.iter_child_nodes(node):
            inner = in_function or isinstance(child, ast.FunctionDef | ast.AsyncFunctionDef)
            if isinstance(child, ast.Import):
                out.extend((child.lineno, a.name, in_function) for a in child.names)
            elif isinstance(child, ast.ImportFrom):
                if child.level:
                    base = module.split(".")
                    base = base if is_pkg else base[:-1]
                    base = base[: len(base) - (child.level - 1)]
                    target = ".".join(base + ([child.module] if child.module else []))
                else:
                    target = child.module or ""
                # `from pkg import module` imports the module; `from module import name` the module
                out.extend((child.lineno, f"{target}.{a.name}", in_function) for a in child.names)
            visit(child, inner)

    visit(ast.parse(path.read_text(), str(path)), False)
    return out


def resolve(target: str, mods: dict[str, Path]) -> str | None:
    """The longest prefix of an imported name that is a project module (drops imported attributes)."""
    parts = target.split(".")
    while parts and ".".join(parts) not in mods:
        parts.pop()
    return ".".join(parts) if parts else None


def dependency_graph(mods: dict[str, Path]) -> dict[str, dict[str, int]]:
    """module -> {imported project module: first line}."""
    graph: dict[str, dict[str, int]] = {}
    for module, path in mods.items():
        deps: dict[str, int] = {}
        for line, target, _ in imports_of(module, path):
            dep = resolve(target, mods)
            if dep is not None and dep != module and not module.startswith(dep + "."):
                deps.setdefault(dep, line)  # a package's own parents run first anyway
        graph[module] = deps
    return graph


def cycles(graph: dict[str, set[str] | dict[str, int]]) -> list[list[str]]:
    """The strongly connected components with more than one node (Tarjan), each sorted."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on: set[str] = set()
    found: list[list[str]] = []

    def strong(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on.add(v)
        for w in graph.get(v, ()):
            if w not in index:
                strong(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                found.append(sorted(comp))

    for v in sorted(graph):
        if v not in index:
            strong(v)
    return found


MODS = project_modules()
GRAPH = dependency_graph(MODS)


def test_every_module_has_a_layer():
    assert [m for m in MODS if m not in ("uwbcal", "uwbcal.pipeline") and layer_of(m) is None] == []


def test_no_module_imports_a_layer_above_it():
    bad = []
    for module, deps in GRAPH.items():
        own = layer_of(module)
        for dep, line in deps.items():
            target = layer_of(dep)
            if own is None or (target is not None and RANK[target] > RANK[own]):
                rel = MODS[module].relative_to(ROOT)
                bad.append(f"{rel}:{line}: {module} ({own}) imports {dep} ({target})")
    assert not bad, "upward imports:\n" + "\n".join(bad)


def test_no_import_cycle_between_modules():
    assert cycles(GRAPH) == []


def test_no_import_cycle_between_folders():
    folders: dict[str, set[str]] = defaultdict(set)
    for module, deps in GRAPH.items():
        here = folder_of(module, MODS[module])
        for dep in deps:
            there = folder_of(dep, MODS[dep])
            if there != here and not here.startswith(
                there + "."
            ):  # a folder's parent package is not a dependency
                folders[here].add(there)
    assert cycles(folders) == []


def function_level_imports() -> list[str]:
    """``file:line`` of every import statement of a project module inside a function, outside cli.py."""
    return sorted(
        {
            f"{MODS[m].relative_to(ROOT)}:{line}"
            for m in MODS
            if m != "uwbcal.cli"
            for line, target, inside in imports_of(m, MODS[m])
            if inside and resolve(target, MODS) is not None
        }
    )


def test_few_function_level_imports_of_the_project():
    lazy = function_level_imports()
    assert len(lazy) <= MAX_FUNCTION_LEVEL_IMPORTS, "\n".join(lazy)


def long_units(path: Path, rel: str) -> list[str]:
    """``rel::qualname (n lines)`` of every function over MAX_FUNCTION_LINES and class over MAX_CLASS_LINES."""
    out: list[str] = []

    def visit(node: ast.AST, prefix: str) -> None:
        for child in ast.iter_child_nodes(node):
            if isinstance(child, ast.FunctionDef | ast.AsyncFunctionDef | ast.ClassDef):
                name = f"{prefix}{child.name}"
                n = child.end_lineno - child.lineno + 1
                limit = MAX_CLASS_LINES if isinstance(child, ast.ClassDef) else MAX_FUNCTION_LINES
                if n > limit:
                    out.append(f"{rel}::{name} ({n} lines)")
                visit(child, f"{name}.")
            else:
                visit(child, prefix)

    visit(ast.parse(path.read_text(), str(path)), "")
    return out


def test_no_long_function_or_class():
    long = [u for path in MODS.values() for u in long_units(path, path.relative_to(ROOT).as_posix())]
    assert not long, (
        f"functions over {MAX_FUNCTION_LINES} / classes over {MAX_CLASS_LINES} lines:\n" + "\n".join(long)
    )


def test_the_package_list_holds_every_folder_of_modules():
    setup = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]
    assert setup["package-dir"] == {"uwbcal": "."}
    folders = {folder_of(m, p) for m, p in MODS.items()} | {"uwbcal"}
    assert sorted(setup["packages"]) == sorted(folders)
    missing_init = [f for f in folders if not (ROOT / Path(*f.split(".")[1:]) / "__init__.py").is_file()]
    assert missing_init == []


def test_the_package_data_holds_every_file_the_code_reads():
    setup = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]
    shipped = {
        path
        for package, globs in setup["package-data"].items()
        for glob in globs
        for path in (ROOT / Path(*package.split(".")[1:])).glob(glob)
    }
    data = {p for p in (ROOT / "convert" / "msg").rglob("*") if p.is_file()}
    assert data and data <= shipped, sorted(str(p.relative_to(ROOT)) for p in data - shipped)


@pytest.mark.parametrize(
    ("module", "layer"),
    [
        ("uwbcal.pipeline.core.geometry", "core"),
        ("uwbcal.convert.simulator", "convert"),
        ("uwbcal.pipeline.vio.msckf", "vio"),
        ("uwbcal.pipeline.uwb.updater", "uwb"),
        ("uwbcal.pipeline.viz.runlog", "viz"),
        ("uwbcal.pipeline.run.config", "run"),
        ("uwbcal.pipeline.run.stages.vio", "stages"),
        ("uwbcal.evaluate.experiments", "experiments"),
        ("uwbcal.cli", "cli"),
    ],
)
def test_layer_assignment(module, layer):
    assert layer_of(module) == layer


def test_the_checks_can_fail(tmp_path):
    """An upward import, a lazy import, a cycle and a long function are all seen."""
    fake = tmp_path / "geometry.py"
    fake.write_text("def f():\n    from ..vio.msckf import MsckfEstimator\n")
    assert imports_of("uwbcal.pipeline.core.geometry", fake) == [
        (2, "uwbcal.pipeline.vio.msckf.MsckfEstimator", True)
    ]
    assert RANK[layer_of("uwbcal.pipeline.vio.msckf")] > RANK[layer_of("uwbcal.pipeline.core.geometry")]
    assert cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]
    assert cycles({"a": {"b"}, "b": set()}) == []
    body = "".join(f"        x{i} = {i}\n" for i in range(80))
    fake.write_text(f"class C:\n    def short(self):\n        pass\n\n    def long(self):\n{body}")
    assert long_units(fake, "geometry.py") == ["geometry.py::C.long (81 lines)"]
