"""Atomic file output: write to a temporary sibling, rename over the target only on success.

Temporary files are named ``.<name>.<pid>.<token>.part`` (`pipeline.core.errors.TEMP_RE`). They are removed on any
exception, including `Terminated` (SIGTERM, see `cli`) and KeyboardInterrupt; those of a process killed outright
(SIGKILL, power loss) are removed by the next write of the same target, or by `sweep_stale` over a directory.
Finished files get the permissions the umask gives (not mkstemp's 0600).
"""

from __future__ import annotations

import contextlib
import os
import secrets
from collections.abc import Iterator
from pathlib import Path

from uwbcal.pipeline.core.errors import TEMP_RE, InputError


def _umask() -> int:
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


FILE_MODE = 0o666 & ~_umask()


def pid_alive(pid: int) -> bool:
    if pid <= 0:
        return False
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


_LIVE: set[Path] = set()  # temporary files of this process not yet renamed or removed


def temp_path(target: Path) -> Path:
    """A fresh temporary sibling of ``target`` (not created), registered until `finish` / `discard`."""
    tmp = target.with_name(f".{target.name}.{os.getpid()}.{secrets.token_hex(4)}.part")
    _LIVE.add(tmp)
    return tmp


def discard(tmp: Path) -> None:
    """Remove a temporary file (and forget it)."""
    _LIVE.discard(tmp)
    tmp.unlink(missing_ok=True)


def discard_all() -> None:
    """Remove every temporary file this process still has: on SIGTERM / Ctrl-C the unwinding normally does it, this
    catches one created in the instant before its owner's cleanup was armed (e.g. inside a constructor)."""
    for tmp in list(_LIVE):
        with contextlib.suppress(OSError):
            discard(tmp)


def is_stale(path: Path) -> bool:
    """A temporary output whose writing process is gone."""
    m = TEMP_RE.match(path.name)
    return bool(m) and not pid_alive(int(m["pid"]))


def sweep_stale(directory: Path, recursive: bool = True) -> list[Path]:
    """Remove the temporary outputs of dead processes under ``directory``; returns what was removed."""
    directory = Path(directory)
    if not directory.is_dir():
        return []
    found = directory.rglob(".*.part") if recursive else directory.glob(".*.part")
    removed = []
    for p in sorted(found):
        if is_stale(p):
            with contextlib.suppress(OSError):
                p.unlink()
                removed.append(p)
    return removed


def check_output_file(target: Path) -> None:
    """An output file path: refuse an existing directory or non-regular file (e.g. /dev/null) up front."""
    if target.is_dir():
        raise InputError(
            f"{target}: is a directory; give a file path for the output (or remove the directory)"
        )
    if target.exists() and not target.is_file():
        raise InputError(f"{target}: exists and is not a regular file; choose another output path")


def prepare_output_file(target: str | os.PathLike) -> Path:
    """Check ``target``, create its parent and remove stale temporaries of earlier writers of it."""
    target = Path(target)
    check_output_file(target)
    target.parent.mkdir(parents=True, exist_ok=True)
    for p in target.parent.glob(f".{target.name}.*.part"):
        if is_stale(p):
            with contextlib.suppress(OSError):
                p.unlink()
    return target


def finish(tmp: Path, target: Path) -> None:
    """Give ``tmp`` the umask's permissions and rename it over ``target``."""
    os.chmod(tmp, FILE_MODE)
    check_output_file(target)  # it may have appeared meanwhile
    os.replace(tmp, target)
    _LIVE.discard(tmp)


@contextlib.contextmanager
def atomic_path(target: str | os.PathLike) -> Iterator[Path]:
    """Yield a temporary path next to ``target``; on clean exit it replaces ``target`` atomically.

    On an exception (or SIGTERM / Ctrl-C) the temporary file is removed and ``target`` is left as it was.
    """
    target = prepare_output_file(target)
    tmp_path = temp_path(target)
    fd = os.open(tmp_path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    os.close(fd)
    try:
        yield tmp_path
        finish(tmp_path, target)
    except BaseException:
        discard(tmp_path)
        raise


def write_text_atomic(target: str | os.PathLike, text: str) -> None:
    with atomic_path(target) as tmp:
        tmp.write_text(text)


def write_bytes_atomic(target: str | os.PathLike, data: bytes) -> None:
    with atomic_path(target) as tmp:
        tmp.write_bytes(data)
