"""Closes the loggers left open at interpreter exit, and says so when records are lost.

A `Logger`'s writer thread is a daemon: it dies at interpreter exit with whatever is
still queued. So every logger is registered here while open, and an exit handler closes
them in creation order. An exception raised in an exit handler is printed and the
process still exits with status 0; a failed close instead prints what was lost and
exits with status 1, so that a job scheduler sees the failure.
"""

import atexit
import os
import sys
from typing import Protocol


class _Closable(Protocol):
    def close(self) -> None: ...


_OPEN: dict[int, _Closable] = {}


def register(logger: _Closable) -> None:
    """Closes `logger` at interpreter exit unless it is closed before (`forget`)."""
    _OPEN[id(logger)] = logger


def forget(logger: _Closable) -> None:
    _OPEN.pop(id(logger), None)


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
        os._exit(1)


atexit.register(_close_all)
