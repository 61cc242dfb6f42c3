"""The `Logger`: the API over the host flush, `emit`, report histories and the writer thread.

A value's way from `flush` to a writer, one module a step:
1. `_programs`: the jitted report program computes and resets the period, and packs the
   report into one array (`_transfer.Packer`); `flush` starts its copy to the host;
2. `_writer_thread`: the job that writes it is queued for the writer thread;
3. `_runs`: unpacks each run's part and builds its `Record` (`_record.RecordBuilder`);
4. the run's writers get the record, and `_seed_run` the seeds summary's.
`emit` enters at step 2 through `_emit_in_graph` and `_emit_receiver` (host); `write_history`
through `_history`. What goes wrong on the way surfaces on the caller's thread (`_errors`).
"""

import functools
import time
from collections.abc import Sequence
from contextlib import AbstractContextManager
from typing import Any

import jax
import jax.numpy as jnp

from .._core import _tags
from .._core._count import Count
from .._core._metrics import Metrics
from .._core._metrics_state import MetricsState
from .._core._spec import check_name
from .._core._tags import TagInfo
from .._core._validate import is_int
from . import _channel, _close_at_exit, _history
from ._call_checks import check_settings, check_state, check_step, is_traced, scalar_args
from ._emit_in_graph import InGraphEmit
from ._emit_receiver import CLOSE_AFTER_TRAINING, EmitReceiver, LateRecords, WrapperPeriod
from ._emit_receiver import unreported as unreported_steps
from ._errors import CallerReports
from ._errors import NonFiniteError as NonFiniteError
from ._errors import ReportsLostError as ReportsLostError
from ._errors import WriterError as WriterError
from ._errors import WriterTimeoutError as WriterTimeoutError
from ._history import History
from ._programs import report_programs, tag_table
from ._record import Writer
from ._runs import RunWriters, WritersArg, make_writers
from ._seed_run import SeedsSummaryRun, summary_run_tags, summary_writers
from ._timer import Timers
from ._writer_thread import WriterThread


class Logger(AbstractContextManager):
    """Writes a `Metrics` state's reports to several writers, without stalling the device.

    Host-loop mode: `state = logger.flush(state, step)` once per iteration. It runs a
    jitted `compute` + `reset_period`, starts an asynchronous device -> host copy of the
    (small) report and hands it to the logger's writer thread, then returns the reset
    state at once; the writer thread turns the report into one `Record` per run and
    gives it to every writer, in flush order. `close()` (or leaving a `with` block)
    drains everything in order and closes the writers; `wait()` drains without closing.

    Fully-jitted mode (PureJaxRL style): `state = logger.emit(state, step, when, run=i)`
    inside the jitted function writes the same records, sent to the host under `lax.cond`
    only where `when` is true (the period ends), and works under `vmap` over seeds, each
    seed to its own run. On a CUDA GPU the report is written by the device into a ring
    in host memory that a thread of the logger reads (no host round trip on the steps
    that report nothing); elsewhere it goes through an ordered `io_callback`
    (`report_channel`). Without a callback: `state, history =
    logger.record(state, history, step, when)` keeps the packed reports in an in-graph
    buffer (`history_init(capacity)`) returned with the jitted call's result, and
    `logger.write_history(history)` writes them afterwards (plain JAX: persistent
    compilation cache, `vmap` and sharding with no special rule).

    Cross-seed summary: with `runs > 1` and `seeds_summary=[writers]`, one more run gets,
    per scalar tag `T` and step, the mean across seeds under `T` itself and
    `T/seeds_std`, `/seeds_min`, `/seeds_max`, `/seeds_iqm`, `/seeds_ci_lower`,
    `/seeds_ci_upper` and `/seeds_count` (see `summary_tags`).

    What each record holds, beyond the spec's tags (`Metrics.tags`):

    - `Counters/<c>/per_sec`: counter growth per second of host wall time between two
      records of the run (so from the second record on);
    - `<timer_prefix>/<name>`: seconds spent in `with logger.timer(name):` since the last
      flush (0.0 once a timer has run before; host flushes only);
    - `<metric>/histogram/underflow|overflow`: values outside the histogram range;
    - `<metric>/running` with `include_running`.

    Empty statistics (NaN: no episode in the period) are left out, never written as 0; a
    period's `/count` (and `/sum`) of 0 is a true value and is written. `/nonfinite` and
    histogram under/overflow counts are written from their first non-zero value on, so
    that healthy runs are not cluttered with rows of zeros.

    Non-finite values (policy "skip" warns with a `RuntimeWarning` attributed to the
    caller's line, "raise" raises `NonFiniteError`; both name the metric, the run and the
    step; "propagate" is silent) surface on the caller's thread at a fixed point: a
    flush's are checked by the *next* `flush` or by `wait()`/`close()`; emitted ones by
    the next `flush`, `wait()` or `close()` after the jitted call. Writer errors surface
    the same way, all of them at once (`WriterError`, naming writer, run and step).

    A `flush` that raises has done nothing: it did not queue its report and the state
    you passed still holds the period, so catching the error and flushing that state
    again later counts every episode once (the next record covers both periods). A
    `flush` that returns has queued its report: `wait()` or `close()` writes it, also
    when another thread closes the logger meanwhile.

    A writer call that does not return within `timeout` seconds (a hung network disk)
    makes `flush` (once `max_pending` reports wait), `wait` and `close` raise
    `WriterTimeoutError` instead of hanging; at interpreter exit the open loggers are
    closed, and if that fails the process prints what was lost and exits with status 1.

    Attributes:
      metrics: the spec.
      runs: the number of runs.
      tags: the static tag table handed to the writers (the spec's tags plus the
        logger's: per_sec, histogram under/overflow, running); timer tags come on top.
      report_nbytes: bytes of the report the last `flush` copied device -> host.
      emit_calls: reports received from `emit` (one per period end, whatever the
        number of vmapped seeds in it).
      report_channel: the channel in-graph reports take (`kind` "ring" or "io_callback")
        and why (`reason`); decided when an emit is first traced.
      summary_tags: the tag table of the seeds summary run (empty without one).

    Args:
      metrics: the spec whose states are flushed.
      writers: the writers of the run (`runs=1`), or a function `run -> writers` called
        once per run here, e.g. `lambda run: [TensorBoardWriter(f"{root}/seed_{run}")]`.
        Writers are created (and their paths checked) before training starts.
      runs: number of runs. With `runs > 1`, `flush` takes states with a leading
        `[runs]` axis (e.g. `vmap`-ed seeds) and `emit` needs `run=`.
      include_running: also report running episodes (`Metrics.compute`).
      timer_prefix: tag prefix of the timers.
      max_pending: flushes that may wait for the writer thread before `flush` blocks
        (back-pressure when the disk is slower than training).
      timeout: seconds one writer call (`open`, `write`, `close`) may take before the
        calls that wait for the writer thread raise `WriterTimeoutError`; None waits
        forever.
      seeds_summary: writers of the cross-seed summary run (e.g.
        `[TensorBoardWriter(f"{root}/seeds_summary")]`, or `per_seed(...).seeds_summary()`
        of the W&B and MLflow writers); needs `runs >= 2`. None (the default): no
        summary. Per step, over the seeds whose value is finite there: mean, sample std
        (ddof 1), min, max, interquartile mean (rliable's `trim_mean(x, 0.25)`), the
        Student-t 95% interval of the mean (`mean -/+ t(0.975, n-1) std / sqrt(n)`) and
        that number of seeds. Scalar statistics, counts and counters are summarized;
        histograms, window contents, `/nonfinite` and under/overflow counts and timers
        are not. A step's summary is written once every seed has written that step or
        a later one (and at `wait`/`close`/`write_history` for the rest).
      report_channel: how `emit` and the reporting wrappers send reports to the host:
        "auto" (the default) takes the ring on CUDA GPUs where it is tested and the
        ordered `io_callback` elsewhere; "ring" (CUDA GPUs and the CPU) or
        "io_callback" force one. Both give the same records, in the same order.
      report_slots: the ring's slots: how many reports the host may fall behind the
        device before one is lost (the loss is counted, and `flush`, `wait` and `close`
        raise `ReportsLostError` naming it).

    Examples:
      >>> import jax.numpy as jnp, jaxmetrics as jm
      >>> metrics = jm.Metrics(logged=["loss"], counters=["updates"])
      >>> memory = jm.MemoryWriter()
      >>> state = metrics.init(num_envs=1)
      >>> with jm.Logger(metrics, [memory]) as logger:
      ...     for it in range(3):
      ...         with logger.timer("update"):
      ...             state = metrics.log(state, {"loss": jnp.float32(it)})
      ...             state = metrics.increment(state, "updates")
      ...         state = logger.flush(state, step=it)
      >>> [r.scalars["Train/loss"] for r in memory.records]
      [0.0, 1.0, 2.0]
      >>> memory.records[-1].scalars["Counters/updates"]
      3
    """

    def __init__(
        self,
        metrics: Metrics,
        writers: WritersArg,
        *,
        runs: int = 1,
        include_running: bool = False,
        timer_prefix: str = "Timers",
        max_pending: int = 8,
        timeout: float | None = 120.0,
        seeds_summary: Sequence[Writer] | None = None,
        report_channel: str = "auto",
        report_slots: int = _channel.DEFAULT_SLOTS,
    ):
        if not isinstance(metrics, Metrics):
            raise TypeError(f"Logger: metrics must be a jaxmetrics.Metrics, got {metrics!r}.")
        check_settings(runs, max_pending, timeout, timer_prefix)
        _channel.check_settings(report_channel, report_slots)
        self.metrics = metrics
        self.runs = int(runs)
        self.include_running = bool(include_running)
        self.tags: tuple[TagInfo, ...] = tag_table(metrics, self.include_running)
        _tags.check_unique((i.tag, _tags.origin(i)) for i in self.tags)
        self.summary_tags = summary_run_tags(seeds_summary, self.runs, self.tags)
        # Under jax.distributed every process runs the same program; process 0 writes.
        self.writes = jax.process_index() == 0
        run_writers = make_writers(writers, self.runs, self.writes)
        summary = summary_writers(seeds_summary, self.writes, run_writers)

        self._programs = report_programs(metrics, self.runs, self.include_running)
        packer, compute = self._programs.packer, self._programs.compute
        nonfinite_tags = [i.tag for i in metrics.tags if i.stat == "nonfinite"]
        self._reports = CallerReports(packer, metrics.nonfinite, nonfinite_tags)
        self._thread = WriterThread(self._reports, max_pending, timeout)
        edges = {
            i.tag: metrics.histogram_edges(i.tag) for i in metrics.tags if i.stat == "histogram"
        }
        summary_run = SeedsSummaryRun(summary, self.summary_tags, self.runs, self._thread)
        self._runs = RunWriters(
            run_writers, summary_run, self.tags, edges, packer, self._thread, self._reports
        )
        # Records that reach this Logger after `close`: the exit handler raises them.
        self._late = LateRecords(functools.partial(_close_at_exit.register, self))
        self._emitted = EmitReceiver(
            self.runs,
            packer,
            metrics.tags,
            self._runs.write_run,
            self._thread,
            self._reports,
            self._late,
        )
        self._channel = _channel.Channel(
            self._emitted,
            self._emitted.receive,
            report_channel,
            report_slots,
            on_error=self._reports.error,
            on_lost=self._ring_overwritten,
        )
        send = self._channel.send
        self._emit = InGraphEmit(compute, metrics.reset_period, send)
        # The reporting wrappers' emit: no run argument, seeds by their vmapped position.
        self._wrapper_emit = InGraphEmit(
            compute, metrics.reset_period, send, runs_by_position=self.runs
        )
        self._history_id = _history.layout_id(metrics.config_id, self.include_running)
        self._wrapper_periods: set[WrapperPeriod] = set()  # of the reporting wrappers traced
        # The reporting wrapper whose reports this Logger takes: its steps are that
        # training's env steps, which another training's would go back over.
        self._wrapper: object | None = None
        self._timer_prefix = timer_prefix
        self._timer_tags: set[str] = set()
        self._timers = Timers()
        self._last_step: int | None = None  # the last host-int step flushed (all runs)
        # Set by a `close` on the writer thread, which can neither wait nor raise: the
        # next `close` raises what was deferred.
        self._closed_by_writer = False
        self.report_nbytes = 0
        self._runs.open(self.tags, self.summary_tags)
        self._thread.start()
        # Daemon threads die at interpreter exit: drain whatever is queued first.
        _close_at_exit.register(self)

    @property
    def emit_calls(self) -> int:
        """Reports received from `emit` (one per period end, all vmapped seeds in it)."""
        return self._emitted.calls

    @property
    def closed(self) -> bool:
        """Whether `close()` has been called (by any thread)."""
        return self._thread.closed

    @property
    def report_channel(self) -> _channel.Choice:
        """The channel in-graph reports take, and why (see the class docstring)."""
        return self._channel.choice

    def _surface(self) -> None:
        """Raises on the caller's thread what the writer thread and the channel kept."""
        self._reports.surface()
        if lost := self._channel.take_lost():
            raise ReportsLostError.ring_overrun(lost, self._channel.slots)

    # ------------------------------------------------------------------ host loop

    def flush(self, state: MetricsState, step: Any) -> MetricsState:
        """Writes the state's report (asynchronously) and returns the state for the next
        period (`reset_period`). Its record comes after those the programs dispatched before
        it emitted: where `emit` was traced, `flush` first waits for those programs.

        Args:
          state: a state of this logger's spec; with `runs > 1`, with a leading
            `[runs]` axis.
          step: the x-axis value: an int, or an int array (scalar, or `[runs]`); a device
            array is fetched by the writer thread, not here.

        Returns:
          The reset state. Only the period statistics are new arrays; running episodes,
          counters, windows and EMAs are the very arrays of `state` (nothing is copied).

        Raises:
          NonFiniteError: a metric with policy "raise" saw non-finite values in an
            earlier flush.
          WriterError: writers failed since the last check.
          WriterTimeoutError: the writer thread is stuck in a writer call.
          ReportsLostError: in-graph reports were lost since the last check (the host
            fell more than `report_slots` reports behind the device).
          RuntimeError: the logger is closed.

        When it raises, the flush has done nothing (see the class docstring).
        """
        self._thread.check_open("flush")
        if is_traced(state):
            raise TypeError(
                "Logger.flush is a host call and cannot run inside jit/vmap/scan; inside "
                "a jitted training loop use logger.emit(state, step, when)."
            )
        check_state(state, self.runs)
        check_step(step, self.runs, self._last_step)
        # What earlier flushes left to report is raised before this one acts.
        self._surface()
        with self._thread.reserved("flush") as put:
            words, finished, logged = self._programs.report_and_reset(state)
            words.copy_to_host_async()
            timers = self._timers.take()
            with self._channel.in_order():
                put(functools.partial(self._runs.write_flush, words, step, timers))
        self.report_nbytes = words.nbytes
        if is_int(step):
            self._last_step = int(step)
        self._reports.check_later(step, tuple(range(self.runs)), words, joined=True)
        return state._replace(finished=finished, logged=logged)

    def timer(self, name: str) -> AbstractContextManager[None]:
        """`with logger.timer("rollout"): ...` adds the block's wall time to the tag
        `<timer_prefix>/rollout` of the next flush.

        JAX dispatches asynchronously: to time device work, block on its result inside
        the block (`jax.block_until_ready`).
        """
        check_name(name, "Logger.timer")
        tag = _tags.timer(self._timer_prefix, name)
        if tag not in self._timer_tags:
            _tags.check_unique(
                [(i.tag, f"tag {i.tag!r}") for i in self.tags]
                + [(t, f"timer {t!r}") for t in sorted(self._timer_tags)]
                + [(tag, f"timer {name!r}")]
            )
            self._timer_tags.add(tag)
        return self._timers.measure(tag)

    def resume(self, state: MetricsState, step: int) -> None:
        """Continues a run restored from a checkpoint: call it once, before the first
        `flush`, with the restored state and the step it was saved at.

        Counters' `/per_sec` then start from the restored totals (the first record has
        a rate, measured from this call), and flushes must not go below `step`. Create
        the writers with `purge_step=step + 1` (or the first step the resumed run will
        write), so earlier records past the checkpoint are dropped, not drawn twice.
        Checkpoint the state that `flush` returned, so that the periods line up.

        Args:
          state: the restored state (with a leading `[runs]` axis when `runs > 1`).
          step: the step of the checkpoint.
        """
        self._thread.check_open("resume")
        check_state(state, self.runs)
        if not is_int(step) or not 0 <= step < 2**63:
            raise ValueError(f"Logger.resume: step must be an int in [0, 2^63), got {step!r}.")
        words, _, _ = self._programs.report_and_reset(state)
        packer = self._programs.packer
        totals = packer.totals(packer.parted(words)[1], self.runs)
        now = time.time()
        with self._thread.entry("resume"):
            self._runs.resume(now, totals, int(step))
            self._last_step = int(step)

    def wait(self) -> None:
        """Blocks until everything flushed or emitted so far is written.

        Raises what was deferred (see the class docstring).
        """
        self._thread.check_open("wait")
        jax.effects_barrier()
        self._channel.drain()
        self._thread.drain("wait", self._runs.drain_summary)
        self._surface()

    def close(self) -> None:
        """Drains everything in order, closes the writers and stops the writer thread.

        Idempotent, and it returns only once everything is written: a `close` called
        while another thread's `close` drains waits for it (that one raises what was
        deferred). Raises what was deferred, after the writers are closed.

        What a reporting wrapper (`jmb.wrap(..., logger=)`, `jm.wrap_step(..., logger=)`)
        left unreported is said here, with a `RuntimeWarning`: the host sees its steps at
        period ends only, so the env steps after its last record are counted where the
        trainer's total is known (Brax's `ppo.train` and `sac.train`: "the last K of the T
        env steps ... are in no record", with a `report_every` that loses none); their
        episodes are not known on the host. Elsewhere it says so only when the wrapper
        wrote no record at all: a loop of your own holds its final state, and
        `flush` reports the steps after the last record from it.

        Close the Logger after the training that reports to it has returned. Records that
        reach it after `close` (a training still running) are not written: the training
        goes on, the first is logged at once (logger "jaxmetrics"), and the next `close`
        (at the latest, the one at interpreter exit, which then exits with status 1)
        raises `ReportsLostError` with their number and the step of the first.

        A writer may call `close` from its `write` or `close` (a writer that decides to
        stop): on the writer thread, which cannot wait for itself, it closes the door and
        returns at once, raising nothing. The records queued before it are still written
        and then the writers closed, once that writer call returns; reports that come
        later are counted as above, and the next `close` on another thread (the `with`
        block's, or the one at interpreter exit) waits for the writer thread and raises
        what was deferred.
        """
        on_writer = self._thread.is_current()
        if not self._thread.closed:
            if not on_writer:
                # Emits still in flight land before the door closes. (On the writer
                # thread, the barrier would hold it until the training that reports has
                # ended, writing nothing meanwhile: the writer asked to stop now.)
                jax.effects_barrier()
            self._channel.close()
            for message in unreported_steps(
                self._wrapper_periods, self._emitted.calls, self._emitted.wrapper_steps
            ):
                self._reports.notice(message)
            if self._thread.stop(self._runs.drain_summary, self._runs.close_writers):
                if on_writer:
                    # The thread writes what is queued and closes the writers once this
                    # writer call returns; the Logger stays registered for the exit
                    # handler until a close on another thread has raised what is deferred.
                    self._closed_by_writer = True
                    return
                # Registered until the writer thread has stopped: if the thread that
                # closes is a daemon and the interpreter exits meanwhile, the exit handler
                # waits for the rest. A Logger whose reports take the ring stays checked
                # at exit, weakly, for what the device writes there after this close
                # (`_stay_checked`).
                self._thread.wait_stopped("close")
                self._stay_checked()
                self._surface()
                return
        # Closed before, or by another thread's close meanwhile.
        if not on_writer:
            self._close_again()

    def _stay_checked(self) -> None:
        """After a close: a Logger whose reports take the ring stays checked at exit for
        reports its programs send later, weakly, so that a sweep of Loggers keeps none of
        them alive; once it is collected, its rings alone are checked (`unread_check`).
        Any other is forgotten."""
        if not self._channel.in_use:
            _close_at_exit.forget(self)
            return
        unread = self._channel.unread_check()

        def after_collected() -> None:
            if lost := unread():
                raise ReportsLostError.after_collected(lost, CLOSE_AFTER_TRAINING)

        _close_at_exit.keep_weakly(self, after_collected)

    def _ring_overwritten(self) -> None:
        """The ring lost reports (the channel's thread): after `close`, they are late
        records, and where they come first the first late record has no step."""
        if self._thread.closed:
            self._late.overwritten()

    def _close_again(self) -> None:
        """`close` of a closed Logger: waits for the writer thread, raises what a writer's
        close deferred, then the records that reached the Logger after its close."""
        self._thread.wait_stopped("close")
        if self._closed_by_writer:
            self._closed_by_writer = False
            # Before the late records are taken: if this raises, they stay counted, and
            # the Logger registered for the exit handler.
            self._surface()
            self._stay_checked()
        jax.effects_barrier()
        self._channel.drain()  # the ring's reports since the first close: late
        late, first = self._late.take()
        late += self._channel.take_lost()
        if late:
            _close_at_exit.forget(self)
            raise ReportsLostError.after_close(late, first, CLOSE_AFTER_TRAINING)

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ------------------------------------------------------------------ in-graph

    def emit(self, state: MetricsState, step: Any, when: Any, *, run: Any = None) -> MetricsState:
        """In-graph flush for training loops inside one `jit`: where `when` is true, the
        report goes to the writers (through `report_channel`) and the period resets.

        Pure and jittable; a no-op (no callback, no host traffic) where `when` is false.
        Under `vmap` over seeds, pass each seed's run index as `run` (vmapped alongside,
        e.g. `jax.vmap(train)(keys, jnp.arange(runs))`): one callback per period end
        carries every seed, and each goes to its own run's writers. `when` may differ
        between seeds. Inside a function that `jax.grad` differentiates, the report is a
        side effect of the forward pass: it carries the primal values, and the gradient
        is the one without the emit (see `Metrics`).

        Args:
          state: the state (per seed, under vmap).
          step: int scalar, the x-axis value.
          when: bool scalar: whether this is a period end.
          run: int scalar run index in `[0, runs)`; may be left out when `runs == 1`.

        Returns:
          The state, reset where `when` is true.

        Examples:
          >>> import jax, jax.numpy as jnp, jaxmetrics as jm
          >>> metrics = jm.Metrics(logged=["x"])
          >>> memory = [jm.MemoryWriter() for _ in range(2)]
          >>> logger = jm.Logger(metrics, lambda run: [memory[run]], runs=2)
          >>> def train(seed, run):
          ...     def body(state, i):
          ...         state = metrics.log(state, {"x": seed * 10.0 + i.astype(jnp.float32)})
          ...         return logger.emit(state, i, i % 2 == 1, run=run), None
          ...     return jax.lax.scan(body, metrics.init(1), jnp.arange(4))[0]
          >>> _ = jax.jit(jax.vmap(train))(jnp.arange(2.0), jnp.arange(2))
          >>> logger.close()
          >>> [(r.step, r.scalars["Train/x"]) for r in memory[1].records]
          [(1, 10.5), (3, 12.5)]
        """
        self._thread.check_open("emit")
        if run is None:
            if self.runs != 1:
                raise TypeError(f"Logger(runs={self.runs}).emit needs run=<run index>.")
            run = jnp.zeros((), jnp.int32)
        step, run, when = scalar_args("Logger.emit", step=step, run=run, when=when)
        return self._emit(state, step, when, run)

    def emit_from_wrapper(
        self,
        state: MetricsState,
        step: Count,
        when: jax.Array,
        period: WrapperPeriod,
        source: object,
    ) -> MetricsState:
        """The reporting wrappers' in-graph emit (`_wrapper_reporter.ReportSink`), not for user
        code: the step is an exact `Count` (env steps pass 2^31 in long runs), and under
        `vmap` each seed's position on the vmapped axis is its run. `period` is kept to
        say, at `close`, what the wrapper left unreported. `source` is the wrapper's
        reporter: a Logger takes the reports of one (trace time)."""
        if self._thread.closed:
            raise RuntimeError(
                "the Logger given to a reporting wrapper (jmb.wrap, jmp.wrap, "
                "jm.wrap_step(..., logger=)) is closed; give the wrapper an open Logger "
                "(create a new one for each training)."
            )
        if self._wrapper is None:
            self._wrapper = source
        elif self._wrapper is not source:
            raise ValueError(
                "this Logger already takes the reports of another reporting wrapper (jmb.wrap, "
                "jmp.wrap, jm.wrap_step(..., logger=)): an earlier training's, as each "
                "ppo.train builds its env anew. This training's records would go on from that "
                "one's last step, while its own steps (Brax's progress) start from 0 again. "
                "Create a new Logger for each training: jm.Logger(metrics, writers), with "
                "writers of a directory of its own."
            )
        state = self._wrapper_emit(state, step, when, jnp.zeros((), jnp.int32))
        self._wrapper_periods.add(period)  # traced: it reports unless never run
        return state

    # ------------------------------------------------------------------ report history

    def history_init(self, capacity: int) -> History:
        """An empty report history of `capacity` records, for `record` (pure; call it
        inside or outside `jit`, per seed under `vmap`).

        Args:
          capacity: the most period ends it keeps, a Python int >= 1 (it fixes the
            buffer's shape): at least the number of periods the jitted call ends.

        Raises:
          ValueError: for a capacity that is not an int >= 1.
        """
        self._thread.check_open("history_init")
        return _history.init(self._programs.packer, capacity, self._history_id)

    def record(
        self, state: MetricsState, history: History, step: Any, when: Any
    ) -> tuple[MetricsState, History]:
        """In-graph flush into a report history, without a host callback: where `when` is
        true, the report and `step` go into the next slot of `history` and the period
        resets. After the jitted call, `write_history` writes the records.

        Pure and jittable, plain JAX (no callback, no custom batching rule): it works
        under `vmap` over seeds (one history per seed; `run` is its position on the
        vmapped axis) and with sharded states, and a program using it goes into JAX's
        persistent compilation cache. Under `vmap` with a batched `when`, JAX computes the
        report on every call (a `switch` becomes a select), so call `record` at period
        ends, as `emit`.

        A full history (more period ends than its capacity) keeps nothing more: the
        period is then *not* reset, so the returned state still holds every episode
        since the last record kept (a `flush` of it reports them), and `write_history`
        raises after writing what it holds.

        Args:
          state: the state (per seed, under vmap).
          history: from `history_init` of this logger (per seed, under vmap).
          step: int scalar, the x-axis value (exact to 64 bits with `jax_enable_x64`).
          when: bool scalar: whether this is a period end.

        Returns:
          `(state, history)`: the state, reset where a record was kept, and the history.

        Examples:
          >>> import jax, jax.numpy as jnp, jaxmetrics as jm
          >>> metrics = jm.Metrics(logged=["x"])
          >>> memory = [jm.MemoryWriter() for _ in range(2)]
          >>> logger = jm.Logger(metrics, lambda run: [memory[run]], runs=2)
          >>> def train(seed):
          ...     def body(carry, i):
          ...         state, history = carry
          ...         state = metrics.log(state, {"x": seed * 10.0 + i.astype(jnp.float32)})
          ...         return logger.record(state, history, i, i % 2 == 1), None
          ...     carry = (metrics.init(1), logger.history_init(capacity=2))
          ...     return jax.lax.scan(body, carry, jnp.arange(4))[0]
          >>> state, history = jax.jit(jax.vmap(train))(jnp.arange(2.0))
          >>> logger.write_history(history)
          >>> logger.close()
          >>> [(r.step, r.scalars["Train/x"]) for r in memory[1].records]
          [(1, 10.5), (3, 12.5)]
        """
        self._thread.check_open("record")
        step, when = scalar_args("Logger.record", step=step, when=when)
        if not isinstance(state, MetricsState):
            raise TypeError(f"Logger.record: expected a MetricsState, got {type(state).__name__}.")
        _history.check(history, self._history_id, self._programs.packer, (), "Logger.record")
        compute, reset = self._programs.compute, self.metrics.reset_period
        return _history.record(compute, reset, state, history, step, when)

    def write_history(self, history: History) -> None:
        """Writes every record of a report history (`record`), in order, per run: each
        run's records in the order its periods ended, the runs interleaved by step.

        Like `flush`, it returns once the records are queued for the writer thread
        (`wait()` or `close()` writes them), and what earlier calls left to report is
        raised before it acts. A record's `wall_time` is when this call ran, and records
        from a history have no `Counters/<c>/per_sec` (no host clock ran between them);
        the rates of later flushes and emits count from this call.

        Args:
          history: the history the jitted call returned (with a leading `[runs]` axis
            when `runs > 1`).

        Raises:
          ValueError: a history of another logger's spec, of the wrong shape, or one
            that overflowed: more period ends than its capacity. Then the records it
            holds are queued first (they are written), and the error names how many
            period ends were not kept and the capacity that holds them all.
          TypeError: not a `History`, or called inside `jit`.
          NonFiniteError, WriterError, WriterTimeoutError: as for `flush`, from earlier
            calls.
          RuntimeError: the logger is closed.
        """
        self._thread.check_open("write_history")
        if is_traced(history):
            raise TypeError(
                "Logger.write_history is a host call: return the history from the jitted "
                "function and write it after the call."
            )
        lead = () if self.runs == 1 else (self.runs,)
        packer = self._programs.packer
        _history.check(history, self._history_id, packer, lead, "Logger.write_history")
        self._reports.surface()
        fetched = _history.fetch(history, self.runs)
        wall_time = time.time()
        with self._channel.in_order(), self._thread.entry("write_history") as put:
            put(functools.partial(self._runs.write_history, fetched, wall_time))
        for step, run, slot in fetched.order:
            self._reports.check_later(step, (run,), fetched.counts[run, slot])
        _history.check_overflow(fetched)
