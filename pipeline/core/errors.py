"""Errors that the CLI turns into a one-line message and exit code 2, and the wording of OS errors."""

from __future__ import annotations

import errno
import re
from pathlib import Path


class InputError(Exception):
    """Bad input or bad usage: names the file/record and what to do. Never a bug in uwbcal."""


class EstimateFailed(Exception):  # noqa: N818 - a result, not a bug
    """An estimator's health check failed (a diverged VIO): the CLI prints the one-line message, exit 3."""


class Terminated(BaseException):  # noqa: N818 - like KeyboardInterrupt: not an Exception, unwinds everything
    """SIGTERM received: unwind (temporary outputs are removed on the way) and exit 143."""


# A temporary output (pipeline.core.atomic): ".<name>.<pid>.<token>.part" next to the target <name>.
TEMP_RE = re.compile(r"^\.(?P<name>.+)\.(?P<pid>\d+)\.(?P<token>[A-Za-z0-9_]+)\.part$")

_ADVICE = {
    errno.EACCES: "permission denied; choose a location you can write/read or fix its permissions",
    errno.EPERM: "operation not permitted; choose another location or fix its permissions",
    errno.EROFS: "read-only file system; write the output elsewhere",
    errno.ENOSPC: "no space left on the device; free space or write the output elsewhere",
    errno.EDQUOT: "disk quota exceeded; free space or write the output elsewhere",
    errno.EEXIST: "already exists and is in the way; remove it or choose another path",
    errno.EISDIR: "is a directory; give a file path (or remove the directory)",
    errno.ENOTDIR: "a component of the path is not a directory; check the path",
    errno.ENOENT: "no such file or directory; check the path",
    errno.ENAMETOOLONG: "file name too long; choose a shorter path",
    errno.ELOOP: "too many symbolic links; check the path",
    errno.EMFILE: "too many open files; raise the limit (ulimit -n)",
    errno.EIO: "input/output error; check the device",
}


def user_path(path: str | Path) -> Path:
    """The path the user gave for a temporary output ``.<name>.<pid>.<token>.part`` (else ``path``)."""
    p = Path(path)
    m = TEMP_RE.match(p.name)
    return p.with_name(m["name"]) if m else p


def os_error_message(exc: OSError) -> str:
    """One line for an OS error: the user's path (never a temporary file), the problem, what to do."""
    where = exc.filename if exc.filename is not None else exc.filename2
    advice = _ADVICE.get(exc.errno or -1) or f"{(exc.strerror or str(exc)).lower()}; check the path"
    return f"{user_path(where)}: {advice}" if where is not None else f"{exc.strerror or exc}; {advice}"
