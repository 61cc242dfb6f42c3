"""The host side of `Logger.emit`: one callback's reports, split by run and queued.

The in-graph emit (`_emit_in_graph`) makes one ordered `io_callback` per period end, carrying
every vmapped seed's packed report, step, `when` and run index. `EmitReceiver` keeps the
seeds whose period ended and queues one writer job per record. A reporting wrapper's
steps are env steps, which start again where a wrapper is stepped from a fresh state;
`EnvStepsContinuation` carries them on from the run's last record.

A report that reaches a closed Logger (closed while the jitted training still runs) is
counted, not written, and the receiver returns normally: an exception raised in a host
callback ends the training with XLA's opaque `CpuCallback error`, and the training's own
result is worth more than its metrics. The loss is logged at once and raised by the
Logger's next `close` (at the latest, at interpreter exit).
"""

import functools
import logging
import threading
import time
from collections.abc import Callable, Collection, Sequence
from typing import Any, NamedTuple

import numpy as np

from .._core._count import Count, to_int
from .._core._tags import TagInfo
from ._errors import CallerReports
from ._runs import HostReport
from ._transfer import Packer
from ._writer_thread import WriterThread

# How long the writer thread lets an emit's callback finish before writing its records.
_CALLBACK_GRACE_S = 0.005

_log = logging.getLogger("jaxmetrics")

CLOSE_AFTER_TRAINING = (
    "Close the Logger after the training returns (a `with jm.Logger(...) as logger:` block "
    "around ppo.train, or logger.close() after it)."
)


class WrapperPeriod(NamedTuple):
    """A reporting wrapper's period, as traced: what `close` needs to say what it left
    unreported."""

    env_steps: int  # the period, in env steps over all envs and devices
    batch: int  # env steps over all envs and devices in one step of the batch
    planned: int | None  # the env steps the trainer runs to its end, where known


def unreported(
    periods: Collection[WrapperPeriod], calls: int, wrapper_steps: Sequence[int | None]
) -> list[str]:
    """What `close` says of the env steps a reporting wrapper left unreported.

    The host sees a wrapper's steps at its period ends only: the steps after the last one
    stay on the device with the trainer's final env state. Where the trainer's number of
    env steps is known (Brax's `ppo.train` and `sac.train`, read when the env step is
    traced), each run whose records end before it is told how many env steps are in no
    record; elsewhere only a wrapper that wrote no record at all is (a loop of one's own
    holds its final state, and the steps after its last record with it).
    """
    if not periods:
        return []
    every = " or ".join(f"{p:,}" for p in sorted({p.env_steps for p in periods}))
    why = (
        f"it reports every {every} env steps over all envs (report_every, rounded up to whole "
        "steps of the batch; by default 100 steps of the batch)"
    )
    planned = {p.planned for p in periods} - {None}
    if not planned:
        if calls:
            return []
        return [
            f"a reporting wrapper was traced but wrote no record: {why}, so a training that "
            "ran ended before the first period did, and its episodes were not reported. "
            "Pass a report_every of at most the training's env steps."
        ]
    total = max(p for p in planned if p is not None)
    batch = max(p.batch for p in periods)
    period = max(p.env_steps for p in periods)
    fix = f"Pass a report_every that divides {total:,}"
    if total % batch == 0 and total >= batch:
        fix += f", e.g. {_divisor(total, batch, period):,}"
    fix += "."
    notices = []
    for run, last in enumerate(wrapper_steps):
        if last is not None and last >= total:
            continue
        who = f"run {run}: " if len(wrapper_steps) > 1 else ""
        runs_to_end = f"{total:,} env steps Brax's trainer runs (to its end)"
        if last is None:
            lost = f"wrote no record: none of the {runs_to_end} is in one"
        else:
            lost = (
                f"wrote its last record at env step {last:,}: the last {total - last:,} of "
                f"the {runs_to_end} are in no record"
            )
        notices.append(
            f"{who}a reporting wrapper {lost}, nor are the episodes that ended in them (how "
            f"many, the host cannot know): {why}, and the trainer keeps its final env state "
            "to itself, so the steps after the last period end never reach the host (seeing "
            f"them would take a host round trip per step). {fix}"
        )
    return notices


def _divisor(total: int, batch: int, period: int) -> int:
    """The largest multiple of `batch` that divides `total` and is at most `period` (at
    least `batch`)."""
    steps = total // batch
    return batch * next(d for d in range(min(period // batch, steps), 0, -1) if steps % d == 0)


def _shifted(host: HostReport, tag: str, offset: int) -> dict[str, Any]:
    """The host report with the count `tag` raised by `offset`."""
    values = dict(host())
    values[tag] = values[tag] + offset
    return values


class EnvStepsContinuation:
    """A reporting wrapper's step and env-step count, continued where they start again.

    Brax's PPO hands its env resets the last env state, and the wrapper carries its
    statistics and count through them. A wrapper stepped from a fresh state again (a
    trainer that resets its envs without handing the state over, or `wrapped.init` called
    again in a loop of one's own) restarts them, and its next record would go back in
    steps. The record's step and `Counters/env_steps` continue from the run's last record
    instead, with a notice: the steps between that record and the restart, if any, are
    not counted. (A second training on the same Logger is refused at trace time.)

    Args:
      runs: the number of runs.
      env_steps_tag: the tag of the env-step counter's total (None: a spec with no
        terms, which no reporting wrapper uses).
      reports: where the notice of a reset is kept for the caller's thread.
    """

    def __init__(self, runs: int, env_steps_tag: str | None, reports: CallerReports):
        self._tag, self._reports = env_steps_tag, reports
        # Per run, the last env-step count and the offset that continues the count
        # after a reset (the step of the run's last record: both added up).
        self._raw: list[int | None] = [None] * runs
        self._offset = [0] * runs

    def peek(self, run: int, raw: int) -> int:
        """The step `step` would give, without taking the record in (a record that reached
        a closed Logger is named by the step it would have had)."""
        last = self._raw[run]
        restarted = last if last is not None and raw <= last else 0
        return self._offset[run] + restarted + raw

    def step(self, run: int, raw: int) -> int:
        """The record's step, from the wrapper's `raw` step."""
        last = self._raw[run]
        if last is not None and raw <= last:
            self._offset[run] += last
            self._reports.notice(
                f"run {run}: the reporting wrapper's env steps started again after its record "
                f"at step {self._offset[run]}: its envs were reset by a trainer that does not "
                "hand it their last state (Brax's ppo.train does, and its resets lose "
                "nothing), or it was stepped from a fresh state again (wrapped.init). Records "
                "go on from that step; windows and EMAs restarted, and what the envs did "
                "between that record and the restart, if anything, is in no record"
            )
        self._raw[run] = raw
        return self._offset[run] + raw

    def host(self, run: int, host: HostReport) -> HostReport:
        """The host report of the record `step` last continued, its env steps continued."""
        offset = self._offset[run]
        if offset == 0:
            return host
        assert self._tag is not None, "a reporting wrapper's spec counts env steps"
        return functools.partial(_shifted, host, self._tag, offset)


_OVERWRITTEN = (-1, -1)
"""`LateRecords`' first record when the ring overwrote it: no run or step to name."""


class LateRecords:
    """The records that reached the Logger after its `close`: counted, never written.

    Args:
      on_first: called (with the log message) at the first one, on the thread that
        received it.
    """

    def __init__(self, on_first: Callable[[], None]):
        self._on_first = on_first
        self._lock = threading.Lock()
        self._count = 0
        self._first: tuple[int, int] | None = None  # (run, step) of the first

    def add(self, run: int, step: int, from_wrapper: bool) -> None:
        with self._lock:
            self._count += 1
            first = self._first is None
            if first:
                self._first = (run, step)
        if first:
            source = (
                "a reporting wrapper (jmb.wrap, jmp.wrap, jm.wrap_step(..., logger=))"
                if from_wrapper
                else "Logger.emit"
            )
            _log.warning(
                "jaxmetrics: the Logger that %s reports to was closed while the training "
                "still runs: its record of run %d at step %d and every later one are not "
                "written (the training goes on). They are counted, and the Logger's next "
                "close() (at the latest, at interpreter exit) raises ReportsLostError with "
                "the number. %s",
                source,
                run,
                step,
                CLOSE_AFTER_TRAINING,
            )
            self._on_first()

    def overwritten(self) -> None:
        """The report ring lost reports to this closed Logger before the host took them
        (counted by the channel): where that comes before any late record, the first
        record lost has no step to name, and the one taken after it must not be named
        first."""
        with self._lock:
            first = self._count == 0 and self._first is None
            if first:
                self._first = _OVERWRITTEN
        if first:
            _log.warning(
                "jaxmetrics: the Logger that Logger.emit or a reporting wrapper reports to "
                "was closed while the training still runs: its report ring was overwritten "
                "before the host took the reports; they and every later one are not written "
                "(the training goes on). The Logger's next close() raises ReportsLostError "
                "with the number. %s",
                CLOSE_AFTER_TRAINING,
            )
            self._on_first()

    def take(self) -> tuple[int, tuple[int, int] | None]:
        """(count, (run, step) of the first) since the last call; None for the first when
        the ring overwrote it, or when there was none."""
        with self._lock:
            first = None if self._first == _OVERWRITTEN else self._first
            taken = (self._count, first)
            self._count, self._first = 0, None
        return taken


class EmitReceiver:
    """The emit's host callback `(packed, step, when, run) -> None`.

    Every argument has the same leading batch axes (none when not vmapped). A step that
    is a `Count` comes from a reporting wrapper and is continued across env resets.

    Args:
      runs: the number of runs.
      packer: the packer of the reports.
      tags: the spec's tag table (`Metrics.tags`).
      write_run: the writer-thread job that writes one run's record.
      thread: the writer thread.
      reports: where a bad run index, a reset's notice and the reports' non-finite
        counts are kept for the caller's thread.
      late: where the records that reach a closed Logger are counted.

    Attributes:
      calls: callbacks received.
      wrapper_steps: per run, the step of the last record of a reporting wrapper (None:
        none yet).
    """

    def __init__(
        self,
        runs: int,
        packer: Packer,
        tags: Sequence[TagInfo],
        write_run: Callable[..., None],
        thread: WriterThread,
        reports: CallerReports,
        late: LateRecords,
    ):
        self._runs, self._packer, self._write_run = runs, packer, write_run
        self._thread, self._reports, self._late = thread, reports, late
        env_steps = [i.tag for i in tags if i.group == "counter" and i.metric == "env_steps"]
        self._continuation = EnvStepsContinuation(runs, next(iter(env_steps), None), reports)
        self.calls = 0
        self.wrapper_steps: list[int | None] = [None] * runs

    def __call__(self, packed: tuple[Any, Any], step: Any, when: Any, run: Any) -> None:
        """The `io_callback`'s host function: the device waits until it returns."""
        self._receive(packed, step, when, run, grace=True)

    def receive(self, packed: tuple[Any, Any], step: Any, when: Any, run: Any) -> None:
        """The report ring's delivery (on the channel's thread: the device does not wait)."""
        self._receive(packed, step, when, run, grace=False)

    def _receive(
        self, packed: tuple[Any, Any], step: Any, when: Any, run: Any, grace: bool
    ) -> None:
        wall_time = time.time()
        from_wrapper = isinstance(step, Count)
        if from_wrapper:  # env steps, exact
            step = to_int(step)
        unvmapped = np.ndim(when) == 0
        # io_callback hands over jax Arrays: one copy to numpy here, not a device
        # dispatch per statistic when the writer thread unpacks them.
        n = int(np.size(when))
        floats = np.reshape(np.asarray(packed[0]), (n, -1))
        counts = np.reshape(np.asarray(packed[1]), (n, 2, -1))
        step, when, run = (np.reshape(np.asarray(a), (n,)) for a in (step, when, run))
        with self._thread.entry_if_open() as put:
            if put is None:  # closed: counted, and the training goes on
                for i in np.flatnonzero(when):
                    r, s = int(run[i]), int(step[i])
                    if from_wrapper and 0 <= r < self._runs:
                        s = self._continuation.peek(r, s)
                    self._late.add(r, s, from_wrapper)
                return
            self.calls += 1
            if from_wrapper and unvmapped and self._runs > 1:
                # A wrapper reports under vmap with one run per seed; unvmapped, every
                # record would go to run 0. (After close() such records are counted as
                # lost above, as any other: an error stored then would never be raised.)
                self._reports.error(
                    ValueError(
                        f"a reporting wrapper's Logger has runs={self._runs}, but the wrapper "
                        "is not vmapped over seeds, so its reports were not written (each "
                        "would have gone to run 0). Create the Logger with runs=1, or vmap "
                        f"the training over {self._runs} seeds."
                    )
                )
                return
            queued = False
            for i in np.flatnonzero(when):
                r, s = int(run[i]), int(step[i])
                if not 0 <= r < self._runs:
                    self._reports.error(
                        ValueError(f"Logger.emit: run index {r} is outside [0, {self._runs}).")
                    )
                    continue
                host = functools.partial(self._packer.unpack, floats[i], counts[i])
                if from_wrapper:
                    s, host = self._continuation.step(r, s), self._continuation.host(r, host)
                    self.wrapper_steps[r] = s
                self._reports.check_later(s, (r,), counts[i])
                if grace and not queued:
                    # The device waits for this callback, and JAX still runs Python after
                    # it returns; a writer thread woken now would hold the GIL through a
                    # record's Python and keep the device idle meanwhile. It first
                    # sleeps, so that the callback returns alone.
                    put(functools.partial(time.sleep, _CALLBACK_GRACE_S))
                    queued = True
                put(functools.partial(self._write_run, r, host, s, wall_time, {}))
