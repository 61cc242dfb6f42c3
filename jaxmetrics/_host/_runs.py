"""A `Logger`'s runs: their writers, made and opened, and their records, built and written.

On the writer thread `RunWriters` turns a packed report into one `Record` per run: it
unpacks the run's part (`Packer.unpack`), builds the record (`RecordBuilder`: what is
written, counter rates) and hands it to the run's writers and to the seeds summary.
Reports arrive by three jobs: `write_flush` (from `flush`), `write_run` (from `emit`) and
`write_history` (from `write_history`).
"""

import functools
import time
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import numpy as np

from .._core._tags import TagInfo
from ._errors import CallerReports
from ._history import FetchedHistory
from ._record import RecordBuilder, Writer, check_writers, close_quietly
from ._seed_run import SeedsSummaryRun
from ._transfer import Packer
from ._writer_thread import WriterThread

WritersArg = Sequence[Writer] | Callable[[int], Sequence[Writer]]

HostReport = Callable[[], Mapping[str, Any]]  # one run's report, unpacked when called


def make_writers(writers: WritersArg, runs: int, writes: bool) -> list[list[Writer]]:
    """Each run's writers: `writers` itself for one run, or the factory's per run.

    On a process that does not write (under `jax.distributed`, all but process 0) the
    factory is never called, so nothing is created, and writers already made are closed
    unused.

    Raises:
      TypeError: a list of writers for several runs, or something that is not a writer;
        what was created is closed first.
    """
    factory = callable(writers) and not isinstance(writers, Writer)
    if not writes:
        if not factory:
            assert isinstance(writers, Writer) or not callable(writers)
            close_quietly(writers if isinstance(writers, Writer) else list(writers))
        return [[] for _ in range(runs)]
    if factory:
        assert callable(writers)
        made: list[Any] = []
        try:
            for r in range(runs):
                made.append(list(writers(r)))
        except BaseException:
            close_quietly(*made)
            raise
    elif runs > 1:
        raise TypeError(
            f"Logger(runs={runs}): pass writers as a function run -> writers, e.g. "
            "lambda run: [jm.TensorBoardWriter(f'{root}/seed_{run}')], so that each run "
            "writes to its own place."
        )
    else:
        made = [writers]
    try:
        return [check_writers(ws, "Logger") for ws in made]
    except TypeError:
        close_quietly(*[ws for ws in made if isinstance(ws, list)])
        raise


class RunWriters:
    """Every run's writers, record builder and last written step, and the seeds summary.

    Everything but `open` and `resume` runs on the writer thread.

    Args:
      writers: per run, its writers (`make_writers`).
      summary: the seeds summary run.
      tags: the logger's static tag table.
      edges: histogram tag -> bin edges.
      packer: the packer of the reports.
      thread: the writer thread, which calls the writers.
      reports: where a bad record's error and notices are kept for the caller.
    """

    def __init__(
        self,
        writers: list[list[Writer]],
        summary: SeedsSummaryRun,
        tags: Sequence[TagInfo],
        edges: Mapping[str, np.ndarray],
        packer: Packer,
        thread: WriterThread,
        reports: CallerReports,
    ):
        self.runs = len(writers)
        self._writers, self._summary = writers, summary
        self._infos = {i.tag: i for i in tags}
        self._builders = [RecordBuilder(edges) for _ in range(self.runs)]
        self._written_step: list[int | None] = [None] * self.runs
        self._packer, self._thread, self._reports = packer, thread, reports

    def open(self, tags: Sequence[TagInfo], summary_tags: Sequence[TagInfo]) -> None:
        """Opens every writer with its tag table; closes them all if one fails."""
        try:
            for ws in self._writers:
                for w in ws:
                    w.open(tags)
            for w in self._summary.writers:
                w.open(summary_tags)
        except BaseException:
            close_quietly(*self._writers, self._summary.writers)
            raise

    def resume(self, wall_time: float, totals: Sequence[Mapping[str, int]], step: int) -> None:
        """Counts each run's rates from its restored counter totals; records go on from
        `step`."""
        for run in range(self.runs):
            self._builders[run].start(wall_time, totals[run])
        self._written_step = [step] * self.runs

    def write_flush(self, words: Any, step: Any, timers: dict[str, float]) -> None:
        """Writes a flush's report (`Packer.joined`, `[runs]` of them for several runs):
        every run's record at `step` (an int, or an int array of shape () or [runs])."""
        floats, counts = self._packer.parted(words)
        f = np.reshape(floats, (self.runs, -1))
        c = np.reshape(counts, (self.runs, 2, -1))
        # Stamped once the device has computed the report (the fetches above wait for
        # it), not when `flush` dispatched it: a host loop runs ahead of the device, so
        # dispatch times would make the first rates (`/per_sec`) far too high.
        wall_time = time.time()
        steps = np.broadcast_to(np.asarray(step), (self.runs,))
        for r in range(self.runs):
            host = functools.partial(self._packer.unpack, f[r], c[r])
            self.write_run(r, host, int(steps[r]), wall_time, timers)

    def write_history(self, history: FetchedHistory, wall_time: float) -> None:
        """Writes the records of a report history, in its order; rates count from
        `wall_time` on."""
        for step, r, k in history.order:
            host = functools.partial(
                self._packer.unpack, history.floats[r, k], history.counts[r, k]
            )
            try:  # one bad record (a step out of range) does not stop the others
                self.write_run(r, host, step, wall_time, {}, new_point=False)
            except Exception as e:  # noqa: BLE001 (handed to the caller's thread)
                self._reports.error(e)
        for r, kept in enumerate(history.kept):
            if kept:
                totals = self._packer.totals(history.counts[r, kept - 1], 1)[0]
                self._builders[r].start(wall_time, totals)
        self.drain_summary()

    def write_run(
        self,
        run: int,
        host: HostReport,
        step: int,
        wall_time: float,
        timers: dict[str, float],
        new_point: bool = True,
    ) -> None:
        """Writes one run's record (`new_point`: see `RecordBuilder`).

        Raises:
          ValueError: a step outside TensorBoard's int64; the record is not written.
        """
        if not 0 <= step < 2**63:
            raise ValueError(
                f"run {run}: step {step} is outside [0, 2^63) (TensorBoard's int64); the "
                "record was not written."
            )
        last = self._written_step[run]
        if last is not None and step < last:
            # The record is written (nothing is lost); charts draw back over themselves.
            self._reports.notice(
                f"run {run}: step {step} written after step {last}; steps should not "
                "decrease (charts draw back over themselves). To resume a run from an "
                "earlier step, create its writers with purge_step=<step>."
            )
        self._written_step[run] = step
        values = [(self._infos[tag], v) for tag, v in host().items()]
        record = self._builders[run](values, step, wall_time, timers, new_point=new_point)
        self._thread.write(self._writers[run], f"run {run}", record)
        self._summary.add(run, record)

    def drain_summary(self) -> None:
        """Writes the summary of the steps that some seeds have not reached."""
        self._summary.drain()

    def close_writers(self) -> None:
        """Closes every run's writers, then the summary's."""
        for run, ws in enumerate(self._writers):
            self._thread.close_writers(ws, f"run {run}")
        self._summary.close()
