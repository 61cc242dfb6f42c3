"""The `Logger`: in-graph compute + reset, an async copy, a writer thread, and the errors.

`Logger.flush` dispatches one jitted `compute` + `reset_period` (only the reduced report
crosses to the host, never O(num_envs)), starts the report's device -> host copy and
queues it for the writer thread; it returns the reset state without waiting for the
device or the disk. `Logger.emit` is the same path for training loops inside one `jit`.
The writer thread turns reports into `Record`s (`_report`) and hands them to the writers;
what goes wrong there, and the non-finite policy, surface on the caller's thread.
"""

import atexit
import functools
import heapq
import os
import queue
import sys
import threading
import time
import warnings
from collections.abc import Callable, Mapping, Sequence
from contextlib import AbstractContextManager
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from . import _history, _tags
from ._count import Count, to_int
from ._emit import InGraphEmit
from ._history import History
from ._metrics import Metrics
from ._programs import report_programs, tag_table
from ._report import Record, RecordBuilder, Writer, check_writers
from ._seeds import SeedsSummary, summary_tags
from ._spec import check_name
from ._state import MetricsState
from ._tags import TagInfo
from ._timer import Timers
from ._validate import is_int, is_number

WritersArg = Sequence[Writer] | Callable[[int], Sequence[Writer]]


def _unused(writers: WritersArg, runs: int) -> list[list[Writer]]:
    """Writers of a process other than 0: a factory is never called (nothing is created);
    writers already made are closed unused."""
    if not callable(writers) or isinstance(writers, Writer):
        _close_quietly([list(writers)] if not isinstance(writers, Writer) else [[writers]])
    return [[] for _ in range(runs)]


def _writer_list(writers: Any) -> list[Any]:
    """`writers` as a list for `_close_quietly` (a lone writer or a non-list as one)."""
    if isinstance(writers, Writer) or not isinstance(writers, Sequence):
        return [writers]
    return list(writers)


def _close_quietly(writers: Sequence[Sequence[Any]]) -> None:
    """Closes what was created before a construction error (that error is what matters)."""
    for ws in writers:
        for w in ws:
            close = getattr(w, "close", None)
            if callable(close):
                try:
                    close()
                except Exception:  # noqa: BLE001, S110
                    pass


class NonFiniteError(FloatingPointError):
    """Raised on the caller's thread for metrics whose nonfinite policy is "raise"."""


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


def _scalars(where: str, **args: Any) -> tuple[jax.Array, ...]:
    """The in-graph arguments as scalar arrays: `when` a bool, the others ints."""
    out = []
    for name, v in args.items():
        v = jnp.asarray(v)
        ok = v.dtype == jnp.bool_ if name == "when" else jnp.issubdtype(v.dtype, jnp.integer)
        if not ok or v.shape != ():
            kind = "a bool" if name == "when" else "an int"
            raise TypeError(f"{where}: {name} must be {kind} scalar, got {v.dtype}{list(v.shape)}.")
        out.append(v)
    return tuple(out)


# How long the writer thread lets an emit's callback finish before writing its records.
_CALLBACK_GRACE_S = 0.005

# Loggers not yet closed, closed together at interpreter exit (in creation order).
_OPEN: dict[int, "Logger"] = {}


def _close_all_at_exit() -> None:
    """Closes every open logger; if any loses records, says so and exits with status 1
    (an exception in an exit handler would be printed and the process would exit 0)."""
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


atexit.register(_close_all_at_exit)


def _shifted(host: Callable[[], Mapping[str, Any]], tag: str, offset: int) -> dict[str, Any]:
    """The host report with the count `tag` raised by `offset`."""
    values = dict(host())
    values[tag] = values[tag] + offset
    return values


class _PendingNonFinite(NamedTuple):
    """A report whose non-finite counts the caller's thread has yet to check."""

    step: Any  # int, or an int array of shape () or [len(runs)]
    runs: tuple[int, ...]
    counts: Any  # packed counts, [len(runs), 2, K] (the leading axis may be absent for one)


def _warn_at_caller(message: str) -> None:
    """A `RuntimeWarning` attributed to the first frame outside this module: the line that
    called `flush`, `wait` or `close` (or left the `with` block)."""
    level, frame = 1, sys._getframe(0)
    while frame is not None and frame.f_code.co_filename == __file__:
        level, frame = level + 1, frame.f_back
    warnings.warn(message, RuntimeWarning, stacklevel=level)


class Logger(AbstractContextManager):
    """Writes a `Metrics` state's reports to several writers, without stalling the device.

    Host-loop mode: `state = logger.flush(state, step)` once per iteration. It runs a
    jitted `compute` + `reset_period`, starts an asynchronous device -> host copy of the
    (small) report and hands it to the logger's writer thread, then returns the reset
    state at once; the writer thread turns the report into one `Record` per run and
    gives it to every writer, in flush order. `close()` (or leaving a `with` block)
    drains everything in order and closes the writers; `wait()` drains without closing.

    Fully-jitted mode (PureJaxRL style): `state = logger.emit(state, step, when, run=i)`
    inside the jitted function writes the same records through an ordered `io_callback`
    under `lax.cond`, only where `when` is true (the period ends), and works under `vmap`
    over seeds, each seed to its own run. Without a callback: `state, history =
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
      emit_calls: host callbacks received from `emit` (one per period end, whatever the
        number of vmapped seeds in it).
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
    ):
        if not isinstance(metrics, Metrics):
            raise TypeError(f"Logger: metrics must be a jaxmetrics.Metrics, got {metrics!r}.")
        if not is_int(runs) or runs < 1:
            raise ValueError(f"Logger: runs must be an int >= 1, got {runs!r}.")
        if not is_int(max_pending) or max_pending < 1:
            raise ValueError(f"Logger: max_pending must be an int >= 1, got {max_pending!r}.")
        if timeout is not None and (not is_number(timeout) or not timeout > 0):
            raise ValueError(f"Logger: timeout must be seconds > 0 or None, got {timeout!r}.")
        check_name(timer_prefix, "Logger(timer_prefix=...)")
        self.metrics = metrics
        self.runs = int(runs)
        self.tags: tuple[TagInfo, ...] = tag_table(metrics, include_running)
        _tags.check_unique((i.tag, _tags.origin(i)) for i in self.tags)
        self.summary_tags: tuple[TagInfo, ...] = ()
        if seeds_summary is not None:
            if self.runs < 2:
                _close_quietly([_writer_list(seeds_summary)])
                raise ValueError(
                    f"Logger(runs={self.runs}, seeds_summary=...): a summary across seeds "
                    "needs runs >= 2 (vmapped seeds)."
                )
            try:
                self.summary_tags = summary_tags(self.tags)
            except ValueError:
                _close_quietly([_writer_list(seeds_summary)])
                raise
        self._timer_prefix = timer_prefix
        self._timer_tags: set[str] = set()
        # Under jax.distributed every process runs the same program; process 0 writes.
        self.writes = jax.process_index() == 0
        self._writers = (
            self._make_writers(writers, self.runs) if self.writes else _unused(writers, self.runs)
        )
        self._summary_writers: list[Writer] = []
        if seeds_summary is not None and not self.writes:
            _close_quietly([_writer_list(seeds_summary)])
        elif seeds_summary is not None:
            try:
                self._summary_writers = check_writers(seeds_summary, "Logger(seeds_summary=...)")
            except TypeError:
                _close_quietly([*self._writers, _writer_list(seeds_summary)])
                raise
        self._summary = (
            SeedsSummary(self.summary_tags, self.runs) if self._summary_writers else None
        )
        self._infos = {i.tag: i for i in self.tags}
        edges = {
            i.tag: metrics.histogram_edges(i.tag) for i in metrics.tags if i.stat == "histogram"
        }
        self._builders = [RecordBuilder(edges) for _ in range(self.runs)]
        self._nonfinite_tags = [i.tag for i in metrics.tags if i.stat == "nonfinite"]

        self._programs = report_programs(metrics, self.runs, bool(include_running))
        self._packer, compute = self._programs.packer, self._programs.compute
        self._emit = InGraphEmit(compute, metrics.reset_period, self._on_emit)
        # The reporting wrappers' emit: no run argument, seeds by their vmapped position.
        self._wrapper_emit = InGraphEmit(
            compute, metrics.reset_period, self._on_emit, runs_by_position=self.runs
        )
        self.include_running = bool(include_running)
        # Per run, a reporting wrapper's last env-step count and the offset that continues
        # the count after the trainer resets the envs (its last record's step: both added).
        self._wrapper_raw: list[int | None] = [None] * self.runs
        self._wrapper_offset = [0] * self.runs
        # Written records worth a word (steps that went back): warnings, not errors.
        self._notices: list[str] = []
        self._env_steps_tag = _tags.tag(metrics._counter_prefix, "env_steps", "total")
        self._compute = compute
        self._layout_id = _history.layout_id(metrics.config_id, include_running)
        self._timers = Timers()
        self._timeout = None if timeout is None else float(timeout)
        self._lock = threading.Lock()
        # Held while deciding "open or closed" and queueing: nothing lands behind close.
        self._door = threading.Lock()
        self._busy: tuple[str, float] | None = None  # the writer call under way, since
        self._last_step: int | None = None  # the last host-int step flushed (all runs)
        self._written_step: list[int | None] = [None] * self.runs  # on the writer thread
        self._errors: list[BaseException] = []
        self._unchecked: list[_PendingNonFinite] = []
        self._slots = threading.Semaphore(max_pending)
        self._queue: queue.SimpleQueue[Callable[[], None] | None] = queue.SimpleQueue()
        self._closed = False
        self.emit_calls = 0
        self.report_nbytes = 0
        try:
            for ws in self._writers:
                for w in ws:
                    w.open(self.tags)
            for w in self._summary_writers:
                w.open(self.summary_tags)
        except BaseException:
            _close_quietly([*self._writers, self._summary_writers])
            raise
        self._thread = threading.Thread(target=self._work, name="jaxmetrics-logger", daemon=True)
        self._thread.start()
        # Daemon threads die at interpreter exit: drain whatever is queued first.
        _OPEN[id(self)] = self

    @staticmethod
    def _make_writers(writers: WritersArg, runs: int) -> list[list[Writer]]:
        if callable(writers) and not isinstance(writers, Writer):
            made: list[list[Any]] = []
            try:
                for r in range(runs):
                    made.append(list(writers(r)))
            except BaseException:
                _close_quietly(made)
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
            _close_quietly([ws for ws in made if isinstance(ws, list)])
            raise

    # ------------------------------------------------------------------ host loop

    def flush(self, state: MetricsState, step: Any) -> MetricsState:
        """Writes the state's report (asynchronously) and returns the state for the next
        period (`reset_period`).

        Args:
          state: a state of this logger's spec; with `runs > 1`, with a leading
            `[runs]` axis.
          step: the x-axis value: an int, or an int array (scalar, or `[runs]`); a device
            array is fetched by the writer thread, not here.

        Returns:
          The reset state. Only the report streams are new arrays; running episodes and
          counters are the very arrays of `state` (no copy of O(num_envs) data).

        Raises:
          NonFiniteError: a metric with policy "raise" saw non-finite values in an
            earlier flush.
          WriterError: writers failed since the last check.
          WriterTimeoutError: the writer thread is stuck in a writer call.
          RuntimeError: the logger is closed.
          When it raises, the flush has done nothing (see the class docstring).
        """
        self._check_open("flush")
        if any(isinstance(x, jax.core.Tracer) for x in jax.tree.leaves(state)):
            raise TypeError(
                "Logger.flush is a host call and cannot run inside jit/vmap/scan; inside "
                "a jitted training loop use logger.emit(state, step, when)."
            )
        self._check_leading(state)
        self._check_step(step)
        # What earlier flushes left to report is raised before this one acts.
        self._surface(self._take_unchecked())
        self._await(lambda t: self._slots.acquire(timeout=t), "flush")
        try:
            (floats, counts), finished, logged = self._report_and_reset(state)
            floats.copy_to_host_async()
            counts.copy_to_host_async()
            with self._door:
                self._check_open("flush")
                timers = self._timers.take()
                self._queue.put(functools.partial(self._write_flush, floats, counts, step, timers))
        except BaseException:
            self._slots.release()
            raise
        self.report_nbytes = floats.nbytes + counts.nbytes
        if is_int(step):
            self._last_step = int(step)
        with self._lock:
            self._unchecked.append(_PendingNonFinite(step, tuple(range(self.runs)), counts))
        return state._replace(finished=finished, logged=logged)

    def _report_and_reset(self, state: MetricsState) -> Any:
        """Dispatches the jitted flush program for the state's layout: `((floats, counts),
        finished, logged)`, the packed report and the reset statistics."""
        return self._programs.report_and_reset(state)

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
        self._check_open("resume")
        self._check_leading(state)
        if not is_int(step) or not 0 <= step < 2**63:
            raise ValueError(f"Logger.resume: step must be an int in [0, 2^63), got {step!r}.")
        totals = self._packer.totals(self._report_and_reset(state)[0][1], self.runs)
        now = time.time()
        with self._door:
            self._check_open("resume")
            for run in range(self.runs):
                self._builders[run].start(now, totals[run])
            self._last_step = int(step)
            self._written_step = [int(step)] * self.runs

    def wait(self) -> None:
        """Blocks until everything flushed or emitted so far is written.

        Raises what was deferred (see the class docstring).
        """
        self._check_open("wait")
        jax.effects_barrier()
        done = threading.Event()
        with self._door:
            self._check_open("wait")
            self._queue.put(self._drain_summary)
            self._queue.put(done.set)
        self._await(done.wait, "wait")
        self._surface(self._take_unchecked())

    def close(self) -> None:
        """Drains everything in order, closes the writers and stops the writer thread.

        Idempotent. Raises what was deferred, after the writers are closed.
        """
        if self._closed:
            return
        jax.effects_barrier()  # emits still in flight land before the door closes
        with self._door:
            if self._closed:
                return
            self._closed = True
            self._queue.put(self._drain_summary)
            self._queue.put(self._close_writers)
            self._queue.put(None)
        _OPEN.pop(id(self), None)
        self._await(lambda t: (self._thread.join(t), not self._thread.is_alive())[1], "close")
        self._surface(self._take_unchecked())

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ------------------------------------------------------------------ in-graph

    def emit(self, state: MetricsState, step: Any, when: Any, *, run: Any = None) -> MetricsState:
        """In-graph flush for training loops inside one `jit`: where `when` is true, the
        report goes to the writers (ordered `io_callback`) and the period resets.

        Pure and jittable; a no-op (no callback, no host traffic) where `when` is false.
        Under `vmap` over seeds, pass each seed's run index as `run` (vmapped alongside,
        e.g. `jax.vmap(train)(keys, jnp.arange(runs))`): one callback per period end
        carries every seed, and each goes to its own run's writers. `when` may differ
        between seeds.

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
        self._check_open("emit")
        if run is None:
            if self.runs != 1:
                raise TypeError(f"Logger(runs={self.runs}).emit needs run=<run index>.")
            run = jnp.zeros((), jnp.int32)
        step, run, when = _scalars("Logger.emit", step=step, run=run, when=when)
        return self._emit(state, step, when, run)

    def _emit_from_wrapper(self, state: MetricsState, step: Count, when: jax.Array) -> MetricsState:
        """`emit` for a reporting wrapper (`_reporting.Reporter`): the step is an exact
        `Count` (env steps pass 2^31 in long runs), and under `vmap` each seed's position
        on the vmapped axis is its run."""
        self._check_open("emit")
        return self._wrapper_emit(state, step, when, jnp.zeros((), jnp.int32))

    def _on_emit(
        self, packed: tuple[np.ndarray, np.ndarray], step: Any, when: Any, run: Any
    ) -> None:
        wall_time = time.time()
        from_wrapper = isinstance(step, Count)
        if from_wrapper:  # env steps, exact
            step = to_int(step)
        # io_callback hands over jax Arrays: one copy to numpy here, not a device
        # dispatch per statistic when the writer thread unpacks them.
        n = int(np.size(when))
        floats = np.reshape(np.asarray(packed[0]), (n, -1))
        counts = np.reshape(np.asarray(packed[1]), (n, 2, -1))
        step, when, run = (np.reshape(np.asarray(a), (n,)) for a in (step, when, run))
        with self._door, self._lock:
            if self._closed:
                # Raised inside the jitted call that emitted, the only place left to say it.
                raise RuntimeError("Logger.emit: the logger is closed; create a new Logger.")
            self.emit_calls += 1
            queued = False
            for i in np.flatnonzero(when):
                r, s = int(run[i]), int(step[i])
                if not 0 <= r < self.runs:
                    self._errors.append(
                        ValueError(f"Logger.emit: run index {r} is outside [0, {self.runs}).")
                    )
                    continue
                host = functools.partial(self._packer.unpack, floats[i], counts[i])
                if from_wrapper:
                    s, host = self._continued(r, s, host)
                self._unchecked.append(_PendingNonFinite(s, (r,), counts[i]))
                if not queued:
                    # The device waits for this callback, and JAX still runs Python after
                    # it returns; a writer thread woken now would hold the GIL through a
                    # record's Python (TensorBoard's is milliseconds) and keep the device
                    # idle meanwhile. It first sleeps, so that the callback returns alone.
                    self._queue.put(functools.partial(time.sleep, _CALLBACK_GRACE_S))
                    queued = True
                self._queue.put(functools.partial(self._write_run, r, host, s, wall_time, {}))

    def _continued(
        self, run: int, raw: int, host: Callable[[], Mapping[str, Any]]
    ) -> tuple[int, Callable[[], Mapping[str, Any]]]:
        """A reporting wrapper's step and host report, continued across env resets.

        A trainer that resets its envs (Brax's `num_resets_per_eval`) restarts the
        wrapper's statistics and env-step count; its next record would go back in steps.
        The record's step and `Counters/env_steps` continue from the run's last record
        instead: the steps between that record and the reset are not counted (none when
        the period divides the steps between resets)."""
        last = self._wrapper_raw[run]
        if last is not None and raw <= last:
            self._wrapper_offset[run] += last
            self._notices.append(
                f"run {run}: the envs were reset after step {self._wrapper_offset[run]} (e.g. "
                "Brax's num_resets_per_eval): windows and EMAs restarted, and episodes ended "
                "since that record were not reported; records go on from that step"
            )
        self._wrapper_raw[run] = raw
        offset = self._wrapper_offset[run]
        if offset == 0:
            return raw, host
        return offset + raw, functools.partial(_shifted, host, self._env_steps_tag, offset)

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
        self._check_open("history_init")
        if not is_int(capacity) or capacity < 1:
            raise ValueError(
                f"Logger.history_init: capacity must be an int >= 1 (the period ends the "
                f"jitted call records), got {capacity!r}."
            )
        return _history.init(self._packer, int(capacity), self._layout_id)

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
        self._check_open("record")
        step, when = _scalars("Logger.record", step=step, when=when)
        if not isinstance(state, MetricsState):
            raise TypeError(f"Logger.record: expected a MetricsState, got {type(state).__name__}.")
        _history.check(history, self._layout_id, self._packer, (), "Logger.record")
        return _history.record(self._compute, self.metrics.reset_period, state, history, step, when)

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
        self._check_open("write_history")
        if any(isinstance(x, jax.core.Tracer) for x in jax.tree.leaves(history)):
            raise TypeError(
                "Logger.write_history is a host call: return the history from the jitted "
                "function and write it after the call."
            )
        lead = () if self.runs == 1 else (self.runs,)
        _history.check(history, self._layout_id, self._packer, lead, "Logger.write_history")
        self._surface(self._take_unchecked())
        floats, counts, hi, lo, ends = jax.device_get(
            (history.floats, history.counts, history.steps.hi, history.steps.lo, history.ends)
        )
        capacity = history.floats.shape[-2]
        floats = np.reshape(floats, (self.runs, capacity, -1))
        counts = np.reshape(counts, (self.runs, capacity, 2, -1))
        steps = np.reshape(to_int(Count(hi, lo)), (self.runs, capacity))
        ends = np.reshape(ends, (self.runs,))
        kept = np.minimum(ends, capacity)
        # Each run's records in their order, the runs interleaved by step.
        order = list(
            heapq.merge(
                *[[(int(steps[r, k]), r, k) for k in range(int(kept[r]))] for r in range(self.runs)]
            )
        )
        wall_time = time.time()
        with self._door:
            self._check_open("write_history")
            self._queue.put(
                functools.partial(self._write_history, order, floats, counts, kept, wall_time)
            )
        with self._lock:
            self._unchecked += [_PendingNonFinite(s, (r,), counts[r, k]) for s, r, k in order]
        over = [(r, int(ends[r])) for r in range(self.runs) if ends[r] > capacity]
        if over:
            shown = ", ".join(f"run {r}: {n} period ends" for r, n in over)
            raise ValueError(
                f"Logger.write_history: the history overflowed ({shown}; capacity "
                f"{capacity}): the {capacity} records it holds per run are written, the "
                "period ends past them were not kept (the state returned with it still "
                "holds those periods: flush it to report them). Create the history with "
                f"logger.history_init({max(n for _, n in over)}) or more."
            )

    def _write_history(
        self,
        order: Sequence[tuple[int, int, int]],
        floats: np.ndarray,
        counts: np.ndarray,
        kept: np.ndarray,
        wall_time: float,
    ) -> None:
        for step, r, k in order:
            host = functools.partial(self._packer.unpack, floats[r, k], counts[r, k])
            try:  # one bad record (a step out of range) does not stop the others
                self._write_run(r, host, step, wall_time, {}, new_point=False)
            except Exception as e:  # noqa: BLE001 (handed to the caller's thread)
                with self._lock:
                    self._errors.append(e)
        for r in range(self.runs):
            if kept[r]:
                totals = self._packer.totals(counts[r, kept[r] - 1], 1)[0]
                self._builders[r].start(wall_time, totals)
        self._drain_summary()

    # ------------------------------------------------------------------ writer thread

    def _work(self) -> None:
        while True:
            job = self._queue.get()
            if job is None:
                return
            try:
                job()
            except BaseException as e:  # noqa: BLE001 (handed to the caller's thread)
                with self._lock:
                    self._errors.append(e)

    def _write_flush(self, floats: jax.Array, counts: jax.Array, step: Any, timers: dict) -> None:
        try:
            f = np.reshape(np.asarray(floats), (self.runs, -1))
            c = np.reshape(np.asarray(counts), (self.runs, 2, -1))
            # Stamped once the device has computed the report (the fetches above wait for
            # it), not when `flush` dispatched it: a host loop runs ahead of the device, so
            # dispatch times would make the first rates (`/per_sec`) far too high.
            wall_time = time.time()
            steps = np.broadcast_to(np.asarray(step), (self.runs,))
            for r in range(self.runs):
                host = functools.partial(self._packer.unpack, f[r], c[r])
                self._write_run(r, host, int(steps[r]), wall_time, timers)
        finally:
            self._slots.release()

    def _write_run(
        self,
        run: int,
        host: Callable[[], Mapping[str, Any]],
        step: int,
        wall_time: float,
        timers: dict,
        new_point: bool = True,
    ) -> None:
        if not 0 <= step < 2**63:
            raise ValueError(
                f"run {run}: step {step} is outside [0, 2^63) (TensorBoard's int64); the "
                "record was not written."
            )
        last = self._written_step[run]
        if last is not None and step < last:
            # The record is written (nothing is lost); charts draw back over themselves.
            with self._lock:
                self._notices.append(
                    f"run {run}: step {step} written after step {last}; steps should not "
                    "decrease (charts draw back over themselves). To resume a run from an "
                    "earlier step, create its writers with purge_step=<step>."
                )
        self._written_step[run] = step
        values = [(self._infos[tag], v) for tag, v in host().items()]
        record = self._builders[run](values, step, wall_time, timers, new_point=new_point)
        self._write_to(self._writers[run], f"run {run}", record)
        if self._summary is not None:
            for summary in self._summary.add(run, record):
                self._write_to(self._summary_writers, "the seeds summary", summary)

    def _write_to(self, writers: Sequence[Writer], run: str, record: Record) -> None:
        """Gives `record` to each writer; a failure is kept for the caller's thread and
        the other writers still get the record."""
        step = record.step
        for w in writers:
            try:
                self._call(f"writer {w!r} of {run} (write, step {step})", w.write, record)
            except Exception as e:  # noqa: BLE001 (handed to the caller's thread)
                err = RuntimeError(f"writer {w!r} of {run} failed at step {step}: {e!r}")
                err.__cause__ = e
                with self._lock:
                    self._errors.append(err)

    def _drain_summary(self) -> None:
        """Writes the summary of the steps that some seeds have not reached."""
        if self._summary is not None:
            for summary in self._summary.drain():
                self._write_to(self._summary_writers, "the seeds summary", summary)

    def _close_writers(self) -> None:
        named = [(f"run {run}", ws) for run, ws in enumerate(self._writers)]
        for run, ws in [*named, ("the seeds summary", self._summary_writers)]:
            for w in ws:
                try:
                    self._call(f"writer {w!r} of {run} (close)", w.close)
                except Exception as e:  # noqa: BLE001 (handed to the caller's thread)
                    err = RuntimeError(f"closing writer {w!r} of {run} failed: {e!r}")
                    err.__cause__ = e
                    with self._lock:
                        self._errors.append(err)

    def _call(self, what: str, fn: Callable[..., None], *args: Any) -> None:
        """A writer call, timed for `_await`."""
        self._busy = (what, time.monotonic())
        try:
            fn(*args)
        finally:
            self._busy = None

    def _await(self, wait: Callable[[float], bool], fn: str) -> None:
        """Calls `wait(seconds)` until it returns True; raises `WriterTimeoutError` once
        a writer call has been under way for longer than the timeout."""
        while not wait(0.05):
            busy = self._busy
            if busy is None or self._timeout is None:
                continue
            stuck = time.monotonic() - busy[1]
            if stuck > self._timeout:
                with self._lock:
                    errors, self._errors = self._errors, []
                raise WriterTimeoutError(
                    [
                        TimeoutError(
                            f"Logger.{fn}: {busy[0]} has not returned for {stuck:.0f} s "
                            f"(timeout={self._timeout:g} s); what is queued behind it is not "
                            "written. Find what blocks the writer (a hung network disk?), or "
                            "pass Logger(timeout=None) to wait for ever."
                        ),
                        *errors,
                    ]
                )

    # ------------------------------------------------------------------ checks

    def _check_open(self, fn: str) -> None:
        if self._closed:
            raise RuntimeError(f"Logger.{fn}: the logger is closed; create a new Logger.")

    def _check_leading(self, state: Any) -> None:
        if not isinstance(state, MetricsState):
            raise TypeError(f"Logger.flush: expected a MetricsState, got {type(state).__name__}.")
        # A leaf and its own axes (counters [C], logged [R], finished [shards, R]).
        leaves = (
            (None if state.counters is None else state.counters.lo, 1),
            (None if state.logged is None else state.logged.mean, 1),
            (None if state.finished is None else state.finished.mean, 2),
        )
        found = next(((x, own) for x, own in leaves if x is not None), None)
        if found is None:
            return
        leaf, own = found
        lead = tuple(leaf.shape[:-own])
        want = () if self.runs == 1 else (self.runs,)
        if lead != want:
            hint = (
                f"for {lead[0]} vmapped seeds create Logger(..., runs={lead[0]})"
                if self.runs == 1 and len(lead) == 1
                else f"pass the states of all {self.runs} runs stacked on a leading axis"
            )
            raise ValueError(
                f"Logger(runs={self.runs}).flush: the state has leading axes {lead}, "
                f"expected {want}; {hint}."
            )

    def _check_step(self, step: Any) -> None:
        ok = is_int(step)
        if not ok and hasattr(step, "dtype") and hasattr(step, "shape"):
            ok = jnp.issubdtype(step.dtype, jnp.integer) and tuple(step.shape) in ((), (self.runs,))
        if not ok:
            raise TypeError(
                f"Logger.flush: step must be an int (or an int array of shape () or "
                f"({self.runs},)), got {step!r}."
            )
        if not is_int(step):
            return  # a device array: checked on the writer thread
        if not 0 <= step < 2**63:
            raise ValueError(
                f"Logger.flush: step must be in [0, 2^63) (TensorBoard stores int64), got {step}."
            )
        last = self._last_step
        if last is not None and step < last:
            raise ValueError(
                f"Logger.flush: step {step} after step {last}; steps must not decrease (charts "
                "would draw back over themselves). To resume a run from an earlier step, "
                "create a new Logger whose writers have purge_step=<step>."
            )

    def _take_unchecked(self) -> list[_PendingNonFinite]:
        with self._lock:
            out, self._unchecked = self._unchecked, []
        return out

    def _surface(self, pending: Sequence[_PendingNonFinite]) -> None:
        """Applies the non-finite policy to earlier reports on the caller's thread (warns
        for "skip", raises `NonFiniteError` for "raise") and raises what was deferred."""
        with self._lock:
            notices, self._notices = self._notices, []
        for message in notices:
            _warn_at_caller(message)
        raising: list[str] = []
        for check in pending:
            n = len(check.runs)
            counts = np.reshape(np.asarray(check.counts), (n, 2, -1))
            steps = np.broadcast_to(np.asarray(check.step), (n,))
            for i, run in enumerate(check.runs):
                if not self._packer.any_nonzero(counts[i], self._nonfinite_tags):
                    continue
                found = self._packer.unpack(None, counts[i], self._nonfinite_tags)
                for info, policy, count in self.metrics.nonfinite(found):
                    kind = "term" if info.group == "episode" else "logged value"
                    message = (
                        f"step {int(steps[i])}, run {run}: {kind} {info.metric!r}: {count} "
                        f"non-finite value(s) left out or statistic(s) overflowed ({info.tag})"
                    )
                    if policy == "raise":
                        raising.append(message)
                    elif policy == "skip":
                        _warn_at_caller(message)
        with self._lock:
            errors, self._errors = self._errors, []
        if errors:
            error = WriterError(errors)
            if raising:
                error.add_note("Also non-finite values: " + "; ".join(raising))
            raise error
        if raising:
            raise NonFiniteError("; ".join(raising))
