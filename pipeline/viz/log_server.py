"""Rerun logging off the critical path: the run's `RunLog`s live in one helper process.

A `LogServer` starts a helper process (fork) that imports rerun (and pyarrow's pandas bridge, ~2.5 s of imports
together) while the first stage computes. `LogServer.open` returns an `AsyncRunLog`: the same methods as
`RunLog`, each call pickled at once (the arrays are snapshotted) and queued to the helper, which replays it on a
real `RunLog`. ``close`` waits until the helper has written that stage's .rrd (atomically, as `RunLog` does), so
the files are complete when a stage returns. A log call that fails in the helper does not stop the run (as with
the in-process log inside the filters): the first failure per stage is reported as a warning at ``close``.

Without a usable process start (e.g. inside a daemonic worker), `open_run_log` falls back to the in-process
`RunLog`.
"""

from __future__ import annotations

import itertools
import logging
import multiprocessing as mp
import pickle
import queue
import sys
from pathlib import Path
from types import TracebackType
from typing import Any

from uwbcal.pipeline.viz.runlog import RunLog, merge_run_logs

_log = logging.getLogger(__name__)
_REPLY_TIMEOUT_S = 600.0


def _warm_up() -> None:
    """The imports a first log call would pay for: rerun, and pyarrow's pandas bridge (first string array)."""
    import rerun as rr

    rr.TextLog("warm-up")


def _serve(requests, replies) -> None:  # pragma: no cover (runs in the helper process)

    _warm_up()
    logs: dict[int, RunLog] = {}
    errors: dict[int, str] = {}
    while True:
        msg = pickle.loads(requests.get())
        op, lid = msg[0], msg[1]
        if op == "stop":
            for log in logs.values():
                log.close(keep=False)
            replies.put(("stopped", None, None))
            return
        if op == "open":
            try:
                logs[lid] = RunLog(msg[2], **msg[3])
            except Exception as exc:  # reported at close
                errors.setdefault(lid, f"open: {exc!r}")
        elif op == "call":
            log = logs.get(lid)
            if log is not None:
                try:
                    getattr(log, msg[2])(*msg[3], **msg[4])
                except Exception as exc:
                    errors.setdefault(lid, f"{msg[2]}: {exc!r}")
        elif op == "merge":
            try:
                path = merge_run_logs(*msg[2], **msg[3])
                replies.put((lid, None if path is None else str(path), None))
            except Exception as exc:
                replies.put((lid, None, f"merge: {exc!r}"))
        elif op == "close":
            log = logs.pop(lid, None)
            try:
                path = log.close(keep=msg[2]) if log is not None else None
                replies.put((lid, None if path is None else str(path), errors.pop(lid, None)))
            except Exception as exc:
                replies.put((lid, None, f"close: {exc!r}"))


class LogServer:
    """The helper process and its request / reply queues (one per pipeline run)."""

    def __init__(self) -> None:
        # fork: no re-import of the parent's __main__ (spawn would re-run an unguarded user script) and no
        # second numpy import; the helper only runs `_serve`
        ctx = mp.get_context("fork")
        self._requests = ctx.Queue()
        self._replies = ctx.Queue()
        self._proc = ctx.Process(
            target=_serve, args=(self._requests, self._replies), name="uwbcal-runlog", daemon=True
        )
        self._proc.start()
        self._ids = itertools.count()

    def send(self, msg: tuple) -> None:
        # pickled here, so the arrays are copied now (the queue's feeder thread sends them later)
        self._requests.put(pickle.dumps(msg, protocol=pickle.HIGHEST_PROTOCOL))

    def reply(self, lid: int) -> tuple:
        while True:
            try:
                got = self._replies.get(timeout=_REPLY_TIMEOUT_S)
            except queue.Empty:
                raise RuntimeError("rerun logging helper did not answer (timeout)") from None
            if got[0] == lid:
                return got
            if not self._proc.is_alive():
                raise RuntimeError(f"rerun logging helper exited (code {self._proc.exitcode})")

    def open(self, path: Path | str, **kwargs: Any) -> AsyncRunLog:
        lid = next(self._ids)
        self.send(("open", lid, str(path), kwargs))
        return AsyncRunLog(self, lid, Path(path), kwargs)

    def merge(self, parts: list[Path], target: Path, run_kind: str | None, **kwargs: Any) -> Path | None:
        """`runlog.merge_run_logs` in the helper (rerun is imported there already); raises what it raised."""
        lid = next(self._ids)
        self.send(("merge", lid, ([str(p) for p in parts], str(target), run_kind), kwargs))
        _, path, error = self.reply(lid)
        if error:
            raise RuntimeError(f"{target}: merging the stage logs failed: {error}")
        return None if path is None else Path(path)

    def stop(self) -> None:
        if self._proc.is_alive():
            try:
                self.send(("stop", -1))
                self.reply("stopped")
            except (RuntimeError, OSError, ValueError):
                pass
            self._proc.join(timeout=30)
            if self._proc.is_alive():
                self._proc.kill()
                self._proc.join()
        self._requests.close()
        self._replies.close()


class AsyncRunLog:
    """A `RunLog` whose calls run in the `LogServer`'s helper process (see the module docstring)."""

    def __init__(self, server: LogServer, lid: int, path: Path, options: dict[str, Any]) -> None:
        self._server = server
        self._id = lid
        self.path = path
        self._open = True
        # the RunLog's settings stay readable here (anything else not starting with "_" is a forwarded call)
        self.run_kind = options.get("run_kind", "simulation")
        self.time_origin_ns = options.get("time_origin_ns")

    @property
    def enabled(self) -> bool:
        return self._open

    def __getattr__(self, name: str):
        if name.startswith("_"):
            raise AttributeError(name)

        def call(*args: Any, **kwargs: Any) -> None:
            if self._open:
                self._server.send(("call", self._id, name, args, kwargs))

        return call

    def __enter__(self) -> AsyncRunLog:
        return self

    def __exit__(self, exc_type: type | None, exc: BaseException | None, tb: TracebackType | None) -> None:
        self.close(keep=exc_type is None)

    def close(self, *, keep: bool | None = None) -> Path | None:
        """Wait until the helper has written (keep) or discarded the stage's .rrd; see `RunLog.close`."""
        if not self._open:
            return None
        if keep is None:
            keep = sys.exc_info()[0] is None
        self._open = False
        self._server.send(("close", self._id, keep))
        _, path, error = self._server.reply(self._id)
        if error:
            _log.warning("%s: rerun logging: %s", self.path, error)
        return None if path is None else Path(path)

    def abort(self) -> None:
        self.close(keep=False)


def start_log_server() -> LogServer | None:
    """A helper process for the run's logs, or None where none can be started (daemonic worker processes)."""
    if mp.current_process().daemon:
        return None
    try:
        return LogServer()
    except (OSError, RuntimeError, ValueError) as exc:
        _log.warning("rerun logging in-process (no helper process: %s)", exc)
        return None
