"""The host side of `Logger.emit`: one callback's reports, split by run and queued.

The in-graph emit (`_emit_in_graph`) makes one ordered `io_callback` per period end, carrying
every vmapped seed's packed report, step, `when` and run index. `EmitReceiver` keeps the
seeds whose period ended and queues one writer job per record. A reporting wrapper's
steps are env steps, which start again where a wrapper is stepped from a fresh state;
`EnvStepsContinuation` carries them on from the run's last record.
"""

import functools
import time
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

from .._core._count import Count, to_int
from .._core._tags import TagInfo
from ._errors import CallerReports
from ._runs import HostReport
from ._transfer import Packer
from ._writer_thread import WriterThread

# How long the writer thread lets an emit's callback finish before writing its records.
_CALLBACK_GRACE_S = 0.005


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

    def __call__(self, run: int, raw: int, host: HostReport) -> tuple[int, HostReport]:
        """The record's step and host report, from the wrapper's `raw` step."""
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
        offset = self._offset[run]
        if offset == 0:
            return raw, host
        assert self._tag is not None, "a reporting wrapper's spec counts env steps"
        return offset + raw, functools.partial(_shifted, host, self._tag, offset)


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

    Attributes:
      calls: callbacks received.
    """

    def __init__(
        self,
        runs: int,
        packer: Packer,
        tags: Sequence[TagInfo],
        write_run: Callable[..., None],
        thread: WriterThread,
        reports: CallerReports,
    ):
        self._runs, self._packer, self._write_run = runs, packer, write_run
        self._thread, self._reports = thread, reports
        env_steps = [i.tag for i in tags if i.group == "counter" and i.metric == "env_steps"]
        self._continuation = EnvStepsContinuation(runs, next(iter(env_steps), None), reports)
        self.calls = 0

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
        # io_callback hands over jax Arrays: one copy to numpy here, not a device
        # dispatch per statistic when the writer thread unpacks them.
        if from_wrapper and np.ndim(when) == 0 and self._runs > 1:
            self.calls += 1
            # A wrapper reports under vmap with one run per seed; unvmapped, every record
            # would go to run 0.
            self._reports.error(
                ValueError(
                    f"a reporting wrapper's Logger has runs={self._runs}, but the wrapper is "
                    "not vmapped over seeds, so its reports were not written (each would have "
                    "gone to run 0). Create the Logger with runs=1, or vmap the training over "
                    f"{self._runs} seeds."
                )
            )
            return
        n = int(np.size(when))
        floats = np.reshape(np.asarray(packed[0]), (n, -1))
        counts = np.reshape(np.asarray(packed[1]), (n, 2, -1))
        step, when, run = (np.reshape(np.asarray(a), (n,)) for a in (step, when, run))
        # Raised inside the jitted call that emitted, the only place left to say it.
        with self._thread.entry("emit") as put:
            self.calls += 1
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
                    s, host = self._continuation(r, s, host)
                self._reports.check_later(s, (r,), counts[i])
                if grace and not queued:
                    # The device waits for this callback, and JAX still runs Python after
                    # it returns; a writer thread woken now would hold the GIL through a
                    # record's Python and keep the device idle meanwhile. It first
                    # sleeps, so that the callback returns alone.
                    put(functools.partial(time.sleep, _CALLBACK_GRACE_S))
                    queued = True
                put(functools.partial(self._write_run, r, host, s, wall_time, {}))
