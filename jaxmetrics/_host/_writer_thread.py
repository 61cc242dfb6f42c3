"""The `Logger`'s writer thread: one queue of jobs, run in order, and the waits on it.

Writers are slow and may hang (a network disk), so they run on a thread of their own
and the training loop only queues jobs. Three things keep that safe:

- a door: deciding "open or closed" and queueing happen under one lock, so that no job
  lands behind the last one `close` queues;
- back-pressure: at most `max_pending` report jobs wait, so a disk slower than training
  blocks `flush` instead of filling memory;
- a timeout: every writer call is timed, and whoever waits for the thread raises
  `WriterTimeoutError` once a call has been under way too long, instead of hanging.

A job that raises does not stop the thread: its error is kept for the caller's thread.
"""

import contextlib
import functools
import queue
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from typing import Any

from ._errors import CallerReports, WriterTimeoutError
from ._record import Record, Writer

Job = Callable[[], Any]


class WriterThread:
    """The thread that runs the writer jobs, in the order they were queued.

    Args:
      reports: where a failed job's error is kept.
      max_pending: report jobs that may wait before `reserved` blocks.
      timeout: seconds a writer call (`write`, `close_writers`) may take before the
        waits raise `WriterTimeoutError`; None waits forever.
    """

    def __init__(self, reports: CallerReports, max_pending: int, timeout: float | None):
        self._reports = reports
        self._timeout = None if timeout is None else float(timeout)
        self._door = threading.Lock()
        self._closed = False
        self._slots = threading.Semaphore(max_pending)
        self._queue: queue.SimpleQueue[Job | None] = queue.SimpleQueue()
        self._busy: tuple[str, float] | None = None  # the writer call under way, since
        self._thread = threading.Thread(target=self._work, name="jaxmetrics-logger", daemon=True)

    @property
    def closed(self) -> bool:
        """Whether `stop` has closed the door (the thread may still be writing)."""
        return self._closed

    def start(self) -> None:
        self._thread.start()

    def join(self, timeout: float | None = None) -> None:
        self._thread.join(timeout)

    def is_alive(self) -> bool:
        return self._thread.is_alive()

    def is_current(self) -> bool:
        """Whether the caller runs on this thread (a writer's call)."""
        return threading.current_thread() is self._thread

    def check_open(self, fn: str) -> None:
        """Raises for a closed logger, naming the `Logger` method `fn`."""
        if self._closed:
            raise RuntimeError(f"Logger.{fn}: the logger is closed; create a new Logger.")

    @contextlib.contextmanager
    def entry(self, fn: str) -> Iterator[Callable[[Job], None]]:
        """Holds the door of an open logger and yields `put(job)`, which queues a job."""
        with self._door:
            self.check_open(fn)
            yield self._queue.put

    @contextlib.contextmanager
    def entry_if_open(self) -> Iterator[Callable[[Job], None] | None]:
        """Holds the door and yields `put(job)`, or None for a closed logger (for a caller
        that must not raise: a report that reaches the host after `close`)."""
        with self._door:
            yield None if self._closed else self._queue.put

    @contextlib.contextmanager
    def reserved(self, fn: str) -> Iterator[Callable[[Job], None]]:
        """Waits for a free report slot (back-pressure) and yields `put(job)`, which
        queues the job through the door; the slot is free again once the job has run,
        or at once if the block leaves without queueing it."""
        self._wait_until(lambda t: self._slots.acquire(timeout=t), fn)
        queued = False

        def put(job: Job) -> None:
            nonlocal queued
            with self.entry(fn) as put_in_queue:
                put_in_queue(functools.partial(self._in_slot, job))
            queued = True

        try:
            yield put
        finally:
            if not queued:
                self._slots.release()

    def drain(self, fn: str, last: Job) -> None:
        """Queues `last` and waits until it has run (and everything queued before it)."""
        done = threading.Event()
        with self.entry(fn) as put:
            put(last)
            put(done.set)
        self._wait_until(done.wait, fn)

    def stop(self, *last: Job) -> bool:
        """Closes the door behind the jobs `last` and the thread's end; False if it was
        already closed."""
        with self._door:
            if self._closed:
                return False
            self._closed = True
            for job in last:
                self._queue.put(job)
            self._queue.put(None)
        return True

    def wait_stopped(self, fn: str) -> None:
        """Waits until the stopped thread has run its last job."""
        self._wait_until(lambda t: (self._thread.join(t), not self._thread.is_alive())[1], fn)

    def write(self, writers: Sequence[Writer], owner: str, record: Record) -> None:
        """Gives `record` to each writer of `owner` (a run, or the seeds summary)."""
        step = record.step
        for w in writers:
            self._call_writer(
                f"writer {w!r} of {owner} (write, step {step})",
                f"writer {w!r} of {owner} failed at step {step}",
                w.write,
                record,
            )

    def close_writers(self, writers: Sequence[Writer], owner: str) -> None:
        """Closes each writer of `owner`."""
        for w in writers:
            self._call_writer(
                f"writer {w!r} of {owner} (close)",
                f"closing writer {w!r} of {owner} failed",
                w.close,
            )

    def _call_writer(self, what: str, failed: str, fn: Callable[..., None], *args: Any) -> None:
        """A writer call, timed for `_wait_until` (`what` names it in a timeout); a failure
        is kept for the caller's thread, so that the other writers are still called. That
        includes a `SystemExit` or `KeyboardInterrupt` a writer raises: on this thread it
        stops nothing but the record, and it is named like any failure."""
        try:
            self._busy = (what, time.monotonic())
            try:
                fn(*args)
            finally:
                self._busy = None
        except BaseException as e:  # noqa: BLE001 (handed to the caller's thread)
            err = RuntimeError(f"{failed}: {e!r}")
            err.__cause__ = e
            self._reports.error(err)

    def _wait_until(self, wait: Callable[[float], bool], fn: str) -> None:
        """Calls `wait(seconds)` until it returns True; raises `WriterTimeoutError` (with
        the errors kept so far) once a writer call has been under way for longer than
        the timeout."""
        while not wait(0.05):
            busy = self._busy
            if busy is None or self._timeout is None:
                continue
            stuck = time.monotonic() - busy[1]
            if stuck > self._timeout:
                raise WriterTimeoutError(
                    [
                        TimeoutError(
                            f"Logger.{fn}: {busy[0]} has not returned for {stuck:.0f} s "
                            f"(timeout={self._timeout:g} s); what is queued behind it is not "
                            "written. Find what blocks the writer (a hung network disk?), or "
                            "pass Logger(timeout=None) to wait for ever."
                        ),
                        *self._reports.take_errors(),
                    ]
                )

    def _in_slot(self, job: Job) -> None:
        try:
            job()
        finally:
            self._slots.release()

    def _work(self) -> None:
        while True:
            job = self._queue.get()
            if job is None:
                return
            try:
                job()
            except BaseException as e:  # noqa: BLE001 (handed to the caller's thread)
                self._reports.error(e)
