"""What a `Logger` raises or warns on the caller's thread, and what it keeps until then.

The writer thread cannot raise into the training loop, and a report's non-finite counts
are on the host only once its copy has landed. Both wait in a `CallerReports`: writer
failures, notices (steps that went back, env resets) and the reports whose non-finite
counts are still unchecked. The next `flush`, `wait`, `close` or `write_history`
surfaces them all at once, at a fixed point of the caller's code.
"""

import sys
import threading
import warnings
from collections.abc import Callable, Mapping, Sequence
from typing import Any, NamedTuple

import numpy as np

from .._core._tags import TagInfo
from ._transfer import Packer


class NonFiniteError(FloatingPointError):
    """Raised on the caller's thread for metrics whose nonfinite policy is "raise"."""


class ReportsLostError(RuntimeError):
    """In-graph reports were lost: the host fell more than the report ring's slots behind
    the device, which overwrote reports the host had not taken (`ring_overrun`), or they
    reached the Logger after its `close` (`after_close`).

    Attributes:
      lost: the number of reports lost since the last check.
    """

    def __init__(self, lost: int, message: str):
        self.lost = lost
        super().__init__(message)

    @classmethod
    def ring_overrun(cls, lost: int, slots: int) -> "ReportsLostError":
        # The reader queues what it takes without bound, so the writers' speed does not
        # matter: a report is lost when the device makes more than `slots` of them between
        # two looks of the reader (it looks about every millisecond, and needs the GIL).
        # A ring of `slots + lost` slots would have held every report of the same run.
        enough = min(2**16, slots + lost)
        return cls(
            lost,
            f"{lost} in-graph report(s) were lost: the device made more than {slots} "
            "report(s) between two looks of the host's reader at the report ring, and wrote "
            "them over before it took them. Report less often (a longer report_every, or "
            "fewer period ends), or give the ring room for the reports made between looks: "
            f"Logger(..., report_slots={enough}) would have held these.",
        )

    @classmethod
    def after_collected(cls, lost: int, fix: str) -> "ReportsLostError":
        return cls(
            lost,
            f"{lost} in-graph report(s) reached a Logger that was closed and then garbage "
            f"collected while a compiled program that reports to it still ran: they were not "
            f"written. {fix}",
        )

    @classmethod
    def after_close(cls, lost: int, first: tuple[int, int] | None, fix: str) -> "ReportsLostError":
        """`first`: the run and step of the first record lost (None: the ring overwrote
        it before the host took it)."""
        since = (
            ", from a report the ring overwrote before the host took it on"
            if first is None
            else f", from run {first[0]}'s record at step {first[1]} on"
        )
        return cls(
            lost,
            f"{lost} record(s) reached this Logger after its close() and were not "
            f"written{since}: it was closed while the training that reports to it "
            f"(Logger.emit or a reporting wrapper) still ran. {fix}",
        )


class WriterError(RuntimeError):
    """Every writer failure since the last check, raised together on the caller's thread.

    Attributes:
      failures: one exception per failure, in the order they happened; each message
        names the writer, the run and the step (its `__cause__` is the writer's error).
    """

    def __init__(self, failures: Sequence[BaseException]):
        self.failures = tuple(failures)
        super().__init__(
            f"{len(self.failures)} failure(s) writing records; what they did not write is "
            "lost, the rest is on disk:\n  " + "\n  ".join(str(f) for f in self.failures)
        )
        self.__cause__ = self.failures[0] if self.failures else None


class WriterTimeoutError(WriterError, TimeoutError):
    """A writer call has not returned within the `Logger`'s `timeout`: the writer thread
    is stuck, and nothing queued behind the call is written until it returns."""


class _UncheckedReport(NamedTuple):
    """A report whose non-finite counts the caller's thread has yet to check."""

    step: Any  # int, or an int array of shape () or [len(runs)]
    runs: tuple[int, ...]
    counts: Any  # packed counts, [len(runs), 2, K] (the leading axis may be absent for one)
    joined: bool  # `counts` is a flush's `Packer.joined` report, [len(runs), W] or [W]


# The modules between the user's line and `warnings.warn`: a warning names the first
# frame outside them, the line that called `flush`, `wait` or `close` (or left `with`).
_API_MODULES = frozenset({__name__, __name__.rpartition(".")[0] + "._logger"})


def _warn_at_caller(message: str) -> None:
    level, frame = 1, sys._getframe(0)
    while frame is not None and frame.f_globals.get("__name__") in _API_MODULES:
        level, frame = level + 1, frame.f_back
    warnings.warn(message, RuntimeWarning, stacklevel=level)


class CallerReports:
    """Writer errors, notices and unchecked non-finite counts, kept for the caller's thread.

    Any thread may add to it; `surface` runs on the caller's thread.

    Args:
      packer: the packer of the logger's reports.
      nonfinite: `Metrics.nonfinite` of the logger's spec.
      nonfinite_tags: the spec's `/nonfinite` tags.
    """

    def __init__(
        self,
        packer: Packer,
        nonfinite: Callable[[Mapping[str, Any]], list[tuple[TagInfo, str, int]]],
        nonfinite_tags: Sequence[str],
    ):
        self._packer, self._nonfinite, self._nonfinite_tags = packer, nonfinite, nonfinite_tags
        self._lock = threading.Lock()
        self._errors: list[BaseException] = []
        self._notices: list[str] = []
        self._unchecked: list[_UncheckedReport] = []

    def error(self, error: BaseException) -> None:
        """Keeps an error (a writer's, or a bad record's) for `surface` to raise."""
        with self._lock:
            self._errors.append(error)

    def notice(self, message: str) -> None:
        """Keeps something worth a word (nothing is lost) for `surface` to warn about."""
        with self._lock:
            self._notices.append(message)

    def check_later(
        self, step: Any, runs: tuple[int, ...], counts: Any, joined: bool = False
    ) -> None:
        """Keeps a report's packed counts (`joined`: the whole report, `Packer.joined`) for
        `surface` to check for non-finite values."""
        with self._lock:
            self._unchecked.append(_UncheckedReport(step, runs, counts, joined))

    def take_errors(self) -> list[BaseException]:
        """The errors kept so far (they are no longer kept)."""
        with self._lock:
            errors, self._errors = self._errors, []
        return errors

    def surface(self) -> None:
        """On the caller's thread: warns of the notices, applies the non-finite policy to
        the reports kept (warns for "skip", raises `NonFiniteError` for "raise"; both name
        the metric, the run and the step) and raises the writer errors (`WriterError`,
        noting the non-finite values that would have raised)."""
        with self._lock:
            notices, self._notices = self._notices, []
            unchecked, self._unchecked = self._unchecked, []
        for message in notices:
            _warn_at_caller(message)
        raising: list[str] = []
        for report in unchecked:
            for message, policy in self._nonfinite_messages(report):
                if policy == "raise":
                    raising.append(message)
                elif policy == "skip":
                    _warn_at_caller(message)
        errors = self.take_errors()
        if errors:
            error = WriterError(errors)
            if raising:
                error.add_note("Also non-finite values: " + "; ".join(raising))
            raise error
        if raising:
            raise NonFiniteError("; ".join(raising))

    def _nonfinite_messages(self, report: _UncheckedReport) -> list[tuple[str, str]]:
        """(message, policy) per metric of the report that saw non-finite values."""
        n = len(report.runs)
        counts = self._packer.parted(report.counts)[1] if report.joined else report.counts
        counts = np.reshape(np.asarray(counts), (n, 2, -1))
        steps = np.broadcast_to(np.asarray(report.step), (n,))
        out = []
        for i, run in enumerate(report.runs):
            if not self._packer.any_nonzero(counts[i], self._nonfinite_tags):
                continue
            found = self._packer.unpack(None, counts[i], self._nonfinite_tags)
            for info, policy, count in self._nonfinite(found):
                kind = "term" if info.group == "episode" else "logged value"
                message = (
                    f"step {int(steps[i])}, run {run}: {kind} {info.metric!r}: {count} "
                    f"non-finite value(s) left out or statistic(s) overflowed ({info.tag})"
                )
                out.append((message, policy))
        return out
