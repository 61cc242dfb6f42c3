"""Closes the loggers left open at interpreter exit, and says so when records are lost.

A `Logger`'s writer thread is a daemon: it dies at interpreter exit with whatever is
still queued. So every logger is registered here while open, and an exit handler closes
them in creation order. The handler is registered with the first logger, not at import:
importing jaxmetrics changes nothing in the process.

An exception raised in an exit handler is printed and the process still exits with status
0; a failed close instead prints what was lost and makes the process exit with status 1, so
that a job scheduler sees the failure. It does so without skipping anyone's exit handlers:
`os._exit(1)` in the handler would skip those registered before ours (they run after it),
for example a tracker's run finalizer. The status is set after every exit handler has run,
when the interpreter clears its modules and drops `_EXIT_STATUS`.
"""

import atexit
import itertools
import os
import sys
import weakref
from collections.abc import Callable
from typing import Protocol


class _Closable(Protocol):
    def close(self) -> None: ...


_OPEN: dict[int, _Closable] = {}
_REGISTERED: list[bool] = []


class _ExitStatus:
    """Exits the process with `status` when the interpreter drops it, after the exit
    handlers: the one point after them where Python code still runs."""

    def __init__(self, status: int):
        self.status, self.exit = status, os._exit  # kept: `os` may be cleared before us

    def __del__(self) -> None:
        self.exit(self.status)


# Holds the status while the other exit handlers run (see the module's docstring).
_EXIT_STATUS: list[_ExitStatus] = []


def register(logger: _Closable) -> None:
    """Closes `logger` at interpreter exit unless it is closed before (`forget`)."""
    if not _REGISTERED:
        atexit.register(_close_all)
        _REGISTERED.append(True)
    _OPEN[id(logger)] = logger


def forget(logger: _Closable) -> None:
    _OPEN.pop(id(logger), None)


class _Weakly:
    """A closed Logger held weakly: closed again at exit while it lives (what reached it
    after its close is raised then); once collected, `after_collected` at exit raises for
    what its programs sent it since."""

    def __init__(self, logger: _Closable, after_collected: Callable[[], None]):
        self._logger = weakref.ref(logger)
        self._after_collected = after_collected

    def close(self) -> None:
        logger = self._logger()
        if logger is None:
            self._after_collected()
        else:
            logger.close()


_WEAK_KEYS = itertools.count(-1, -1)  # never an id(): a collected Logger's id is reused


def keep_weakly(logger: _Closable, after_collected: Callable[[], None]) -> None:
    """Checks a closed `logger` at interpreter exit without keeping it alive: a sweep of
    Loggers in one process keeps none of them (their writers, spec and programs).
    `after_collected` must hold nothing of the Logger."""
    forget(logger)
    if not _REGISTERED:
        atexit.register(_close_all)
        _REGISTERED.append(True)
    _OPEN[next(_WEAK_KEYS)] = _Weakly(logger, after_collected)


def _close_all() -> None:
    failed = []
    for logger in list(_OPEN.values()):
        try:
            logger.close()
        except Exception as e:  # noqa: BLE001 (reported below)
            failed.append(e)
    if failed:
        for stream in (sys.stdout, sys.stderr):
            stream.flush()
        sys.stderr.write(
            "jaxmetrics: closing the Logger(s) at interpreter exit failed; exiting with "
            "status 1:\n" + "\n".join(f"  {type(e).__name__}: {e}" for e in failed) + "\n"
        )
        sys.stderr.flush()
        _EXIT_STATUS.append(_ExitStatus(1))
