"""The documentation stays for users and stays current: the README short, every module in the architecture page,
no dated measurements outside docs/results/, no references to files a user of the repository does not have, every
command and relative link of the user docs real."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
ARCHITECTURE = ROOT / "docs" / "architecture.md"
MAX_README_LINES = 250
DATED = re.compile(r"\b20\d\d-[01]\d-[0-3]\d\b|measured on \d")
OUTSIDE = re.compile(r"\.\./shared|DESIGN(\.md| §)|[Ii]ssue #\d")


def user_docs() -> list[Path]:
    docs = [README, *sorted((ROOT / "docs").rglob("*.md"))]
    return [p for p in docs if "results" not in p.relative_to(ROOT).parts]


def modules() -> set[str]:
    paths = [ROOT / "__init__.py", ROOT / "cli.py"]
    for folder in ("pipeline", "convert", "evaluate", "benchmarks"):
        paths += (ROOT / folder).rglob("*.py")
    return {str(p.relative_to(ROOT)) for p in paths if p.name != "__init__.py" or p.stat().st_size}


def test_the_readme_is_short():
    n = len(README.read_text().splitlines())
    assert n <= MAX_README_LINES, (
        f"README.md has {n} lines (at most {MAX_README_LINES}): move detail to docs/"
    )


def test_the_architecture_page_names_every_module_and_no_stale_one():
    text = ARCHITECTURE.read_text()
    named = set(re.findall(r"^- `([\w/]+\.py)`", text, flags=re.M))
    missing, stale = sorted(modules() - named), sorted(named - modules())
    assert not missing, f"add a line '- `path.py` — what it holds' to docs/architecture.md for {missing}"
    assert not stale, f"docs/architecture.md lists modules that no longer exist: {stale}"


@pytest.mark.parametrize("doc", user_docs(), ids=lambda p: str(p.relative_to(ROOT)))
def test_user_docs_hold_no_dates_and_no_outside_references(doc):
    bad = [
        f"{doc.name}:{i}: {line.strip()[:80]}"
        for i, line in enumerate(doc.read_text().splitlines(), 1)
        if DATED.search(line) or OUTSIDE.search(line)
    ]
    assert not bad, (
        "dated measurements belong in docs/results/; no ../shared, DESIGN or issue refs:\n" + "\n".join(bad)
    )


def test_docstrings_and_comments_hold_no_dates_and_no_outside_references():
    bad = []
    for rel in sorted(modules()):
        for i, line in enumerate((ROOT / rel).read_text().splitlines(), 1):
            if DATED.search(line) or OUTSIDE.search(line):
                bad.append(f"{rel}:{i}: {line.strip()[:80]}")
    assert not bad, "\n".join(bad)


@pytest.mark.parametrize("doc", user_docs(), ids=lambda p: str(p.relative_to(ROOT)))
def test_relative_links_resolve(doc):
    links = re.findall(r"\]\(([^)#\s]+)(?:#[^)]*)?\)", doc.read_text())
    broken = [
        t for t in links if "://" not in t and not t.startswith("mailto:") and not (doc.parent / t).exists()
    ]
    assert not broken, f"{doc.relative_to(ROOT)}: broken links {broken}"


def test_the_readme_commands_exist():
    from typer.main import get_command

    from uwbcal.cli import app

    group = get_command(app)
    blocks = re.findall(r"```(?:bash|sh|console)?\n(.*?)```", README.read_text(), flags=re.S)
    used = {m for b in blocks for m in re.findall(r"^\s*(?:\$ )?uwbcal ([a-z][\w-]*)", b, flags=re.M)}
    assert used, "the README shows no uwbcal command"
    unknown = sorted(used - set(group.commands))
    assert not unknown, f"README uses commands the CLI does not have: {unknown}"


def test_the_method_page_names_functions_that_exist():
    import importlib

    names = re.findall(
        r"`((?:pipeline|evaluate|convert)\.[\w.]+)`", (ROOT / "docs" / "method.md").read_text()
    )
    assert names
    missing = []
    for name in sorted(set(names)):
        parts = ("uwbcal." + name).split(".")
        for cut in range(len(parts), 1, -1):  # the longest importable module, then attributes
            try:
                obj = importlib.import_module(".".join(parts[:cut]))
            except ModuleNotFoundError:
                continue
            try:
                for attr in parts[cut:]:
                    obj = getattr(obj, attr)
            except AttributeError:
                missing.append(name)
            break
        else:
            missing.append(name)
    assert not missing, f"docs/method.md names functions that no longer exist (update the page): {missing}"
