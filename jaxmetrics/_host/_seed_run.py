"""The cross-seed summary as one more run of a `Logger`: its checks, writers and records.

`_seed_statistics` computes the summary; this is where it meets the Logger. `Logger(runs=N,
seeds_summary=[writers])` is checked before any run's writers are made, and on the writer
thread `SeedsSummaryRun` takes every seed's record and writes each summary record that
is complete to the summary writers.
"""

from collections.abc import Sequence
from typing import Any

from .._core._tags import TagInfo
from ._record import Record, Writer, check_writers, close_quietly
from ._seed_statistics import SeedsSummary, summary_tags
from ._writer_thread import WriterThread

_OWNER = "the seeds summary"


def summary_run_tags(
    seeds_summary: Sequence[Writer] | None, runs: int, tags: Sequence[TagInfo]
) -> tuple[TagInfo, ...]:
    """The summary run's tag table (empty without a summary), from the seeds' `tags`.

    Raises:
      ValueError: a summary of fewer than two runs, or summary tags that clash; the
        summary writers are closed first.
    """
    if seeds_summary is None:
        return ()
    if runs < 2:
        close_quietly(seeds_summary)
        raise ValueError(
            f"Logger(runs={runs}, seeds_summary=...): a summary across seeds "
            "needs runs >= 2 (vmapped seeds)."
        )
    try:
        return summary_tags(tags)
    except ValueError:
        close_quietly(seeds_summary)
        raise


def summary_writers(
    seeds_summary: Sequence[Writer] | None, writes: bool, run_writers: Sequence[Sequence[Any]]
) -> list[Writer]:
    """The summary writers, checked: none without a summary, nor on a process that does not
    write (its summary writers are closed unused).

    Raises:
      TypeError: `seeds_summary` is not a list of writers; every writer is closed first.
    """
    if seeds_summary is None:
        return []
    if not writes:
        close_quietly(seeds_summary)
        return []
    try:
        return check_writers(seeds_summary, "Logger(seeds_summary=...)")
    except TypeError:
        close_quietly(*run_writers, seeds_summary)
        raise


class SeedsSummaryRun:
    """On the writer thread: the seeds' records in, the summary records out to `writers`.

    Args:
      writers: the summary writers (none: no summary is made).
      tags: the summary run's tag table (`summary_run_tags`).
      runs: the number of seeds.
      thread: the writer thread that calls the writers.
    """

    def __init__(
        self, writers: list[Writer], tags: Sequence[TagInfo], runs: int, thread: WriterThread
    ):
        self.writers = writers
        self._summary = SeedsSummary(tags, runs) if writers else None
        self._thread = thread

    def add(self, run: int, record: Record) -> None:
        """Takes one seed's record; writes the summary records it completes."""
        if self._summary is not None:
            self._write(self._summary.add(run, record))

    def drain(self) -> None:
        """Writes the summary of the steps that some seeds have not reached."""
        if self._summary is not None:
            self._write(self._summary.drain())

    def close(self) -> None:
        self._thread.close_writers(self.writers, _OWNER)

    def _write(self, summaries: list[Record]) -> None:
        for summary in summaries:
            self._thread.write(self.writers, _OWNER, summary)
