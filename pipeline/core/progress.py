"""Progress bars for long loops (converters, frontend, simulator)."""

from __future__ import annotations

import contextlib
import sys
from collections.abc import Callable, Iterator


@contextlib.contextmanager
def progress(description: str, total: float | None) -> Iterator[Callable[[float], None]]:
    """A rich progress bar on stderr (disabled when stderr is not a TTY); yields ``advance(n)``."""
    from rich.console import Console
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn

    console = Console(stderr=True)
    with Progress(
        TextColumn("{task.description}"),
        BarColumn(),
        MofNCompleteColumn(),
        TimeRemainingColumn(),
        console=console,
        disable=not sys.stderr.isatty(),
        transient=True,
    ) as bar:
        task = bar.add_task(description, total=total)
        pending = [0.0]

        def advance(n: float = 1) -> None:
            pending[0] += n
            if pending[0] >= 256:  # rich redraw costs more than a message conversion
                bar.advance(task, pending[0])
                pending[0] = 0.0

        yield advance
        bar.advance(task, pending[0])
