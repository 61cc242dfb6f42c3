"""Host-side timers: wall seconds spent inside `with logger.timer(name):`, per flush period."""

import contextlib
import threading
import time
from collections.abc import Iterator


class Timers:
    """Totals of named timers since the last `take`; a timer once used reports 0.0 in
    periods where it did not run (a real zero, not a gap)."""

    def __init__(self):
        self._lock = threading.Lock()
        self._totals: dict[str, float] = {}

    @contextlib.contextmanager
    def measure(self, key: str) -> Iterator[None]:
        start = time.perf_counter()
        try:
            yield
        finally:
            elapsed = time.perf_counter() - start
            with self._lock:
                self._totals[key] = self._totals.get(key, 0.0) + elapsed

    def take(self) -> dict[str, float]:
        """The totals since the last call, and a restart from zero."""
        with self._lock:
            out = dict(self._totals)
            self._totals = dict.fromkeys(out, 0.0)
        return out
