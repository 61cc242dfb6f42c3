"""What the Logger and its writers guarantee when things go wrong: races with `close`,
failing, stuck and full-disk writers, crashes at exit, resumes into the same files.

Each test reproduced its defect before the fix (the stress loops included)."""

import json
import os
import subprocess
import sys
import textwrap
import threading
import time

import jax
import jax.numpy as jnp
import pytest
from jax.experimental import io_callback
from tensorboard.backend.event_processing import event_accumulator as ea

import jaxmetrics as jm

METRICS = jm.Metrics(logged=["x"], counters=["u"])


def _state(value: float, inc: int = 1):
    return METRICS.increment(METRICS.log(METRICS.init(0), {"x": value}), "u", inc)


def _jsonl(path):
    with open(path) as f:
        return [json.loads(line) for line in f]


def _tb_steps(logdir, tag="Train/x"):
    acc = ea.EventAccumulator(str(logdir), size_guidance={ea.SCALARS: 0})
    acc.Reload()
    return [(e.step, e.value) for e in acc.Scalars(tag)]


class _Failing:
    """A writer that fails on the steps it is given."""

    def __init__(self, name, fail_steps):
        self.name, self.fail_steps, self.written = name, set(fail_steps), []

    def __repr__(self):
        return f"_Failing({self.name!r})"

    def open(self, tags):
        pass

    def write(self, record):
        if record.step in self.fail_steps:
            raise OSError(f"{self.name} cannot write step {record.step}")
        self.written.append(record.step)

    def close(self):
        pass


class _Gated:
    """A writer whose writes block until `gate` is set (a hung network disk)."""

    def __init__(self):
        self.gate, self.written = threading.Event(), []

    def open(self, tags):
        pass

    def write(self, record):
        self.gate.wait()
        self.written.append(record.step)

    def close(self):
        pass


def test_close_racing_a_flush_never_loses_a_flush_that_returned():
    # close() while another thread was inside flush() lost that returned flush (149 of
    # 150 trials): it was queued behind the writer thread's stop.
    lost = []
    for trial in range(40):
        memory = jm.MemoryWriter()
        logger = jm.Logger(METRICS, [memory])
        returned, started = [], threading.Event()

        def flusher(logger=logger, returned=returned, started=started):
            state = _state(1.0)
            for step in range(10_000):
                started.set()
                try:
                    state = logger.flush(state, step)
                except RuntimeError:
                    return  # closed: that flush did nothing
                returned.append(step)

        t = threading.Thread(target=flusher)
        t.start()
        started.wait()
        time.sleep(0.002 * (trial % 5))
        logger.close()
        t.join()
        written = [r.step for r in memory.records]
        if written != returned:
            lost.append((trial, sorted(set(returned) - set(written))))
    assert lost == []


class _Slow:
    """A writer that takes `seconds` per record."""

    def __init__(self, seconds):
        self.seconds, self.written = seconds, []

    def open(self, tags):
        pass

    def write(self, record):
        time.sleep(self.seconds)
        self.written.append(record.step)

    def close(self):
        pass


def test_a_close_racing_another_close_returns_only_once_everything_is_written():
    # The second close() returned at once with 0 of 5 records written.
    slow = _Slow(0.05)
    logger = jm.Logger(METRICS, [slow])
    for step in range(5):
        logger.flush(_state(float(step)), step)
    other = threading.Thread(target=logger.close)
    other.start()
    while not logger._thread.closed:  # the other close holds the door
        time.sleep(0.001)
    logger.close()
    assert slow.written == [0, 1, 2, 3, 4]
    other.join()


def _within(seconds, fn):
    """`fn()`'s result, or its exception; fails the test if it has not returned within
    `seconds` (a deadlock)."""
    out = []

    def run():
        try:
            out.append((True, fn()))
        except BaseException as e:  # noqa: BLE001 (raised on the test's thread)
            out.append((False, e))

    t = threading.Thread(target=run, daemon=True)
    t.start()
    t.join(seconds)
    assert out, f"{fn} did not return within {seconds} s"
    ok, value = out[0]
    if not ok:
        raise value
    return value


class _ClosesItsLogger(jm.MemoryWriter):
    """A writer that decides to stop: writing `step`, it closes its Logger (from the writer
    thread), and again when it is closed itself. It writes once `gate` is set."""

    def __init__(self, step):
        super().__init__()
        self.step, self.logger, self.gate = step, None, threading.Event()
        self.closed_logger, self.close_raised, self.closes = threading.Event(), [], 0

    def write(self, record):
        self.gate.wait()
        super().write(record)
        if record.step == self.step:
            self._close_logger()
            self.closed_logger.set()

    def close(self):
        self.closes += 1
        self._close_logger()

    def _close_logger(self):
        try:
            self.logger.close()
        except BaseException as e:  # noqa: BLE001 (the test asserts there is none)
            self.close_raised.append(e)


def test_close_from_a_writers_write_returns_and_the_records_queued_before_are_written():
    # close() in a writer's write raised "RuntimeError: cannot join current thread" (the
    # writer thread waited for itself), and the next close() raised nothing, not even
    # the other writer's failure.
    stopping, failing = _ClosesItsLogger(step=1), _Failing("f", {3})
    logger = jm.Logger(METRICS, [stopping, failing])
    stopping.logger = logger
    for step in range(5):  # all queued before the writer closes the Logger
        logger.flush(_state(float(step)), step)
    stopping.gate.set()
    assert stopping.closed_logger.wait(30), "close() from the writer thread did not return"
    assert stopping.close_raised == []
    assert logger.closed
    with pytest.raises(RuntimeError, match="the logger is closed"):
        logger.flush(_state(5.0), 5)
    # The next close waits for the records queued before and raises what was kept.
    with pytest.raises(jm.WriterError) as err:
        _within(30, logger.close)
    assert [str(f).split(":")[0] for f in err.value.failures] == [
        "writer _Failing('f') of run 0 failed at step 3"
    ]
    assert [(r.step, r.scalars["Train/x"]) for r in stopping.records] == [
        (s, float(s)) for s in range(5)
    ]
    assert failing.written == [0, 1, 2, 4]
    assert stopping.closes == 1 and stopping.close_raised == []
    assert _within(30, logger.close) is None  # nothing left to raise


@pytest.mark.parametrize("channel", ["io_callback", "ring"])
def test_close_from_a_writer_mid_training_counts_every_later_emit_as_lost(channel):
    # A writer stops the Logger while the jitted training still emits: the records queued
    # before its close are written, and each later one is counted, once.
    steps, stop_at = 20, 2
    stopping = _ClosesItsLogger(step=stop_at)
    stopping.gate.set()
    logger = jm.Logger(METRICS, [stopping], report_channel=channel)
    stopping.logger = logger

    def wait_for_the_writers_close():
        stopping.closed_logger.wait(30)

    def train(state):
        def body(state, i):
            # The training goes on only once the writer has closed the Logger (its
            # reports of steps 0 to stop_at are sent before).
            jax.lax.cond(
                i == stop_at + 1,
                lambda: io_callback(wait_for_the_writers_close, None, ordered=True),
                lambda: None,
            )
            state = METRICS.log(state, {"x": i.astype(jnp.float32)})
            return logger.emit(state, i, jnp.bool_(True)), None

        return jax.lax.scan(body, state, jnp.arange(steps))[0]

    jax.block_until_ready(_within(60, lambda: jax.jit(train)(METRICS.init(0))))
    assert stopping.closed_logger.is_set() and stopping.close_raised == []
    with pytest.raises(jm.ReportsLostError, match=f"from run 0's record at step {stop_at + 1} on"):
        _within(30, logger.close)
    written = [(r.step, r.scalars["Train/x"]) for r in stopping.records]
    assert written == [(s, float(s)) for s in range(stop_at + 1)]
    assert _within(30, logger.close) is None
    assert stopping.closes == 1 and stopping.close_raised == []


def test_a_daemon_thread_closing_at_exit_still_gets_every_record_written(tmp_path):
    # The process exited 0 with 1 of 5 records: the exit handler had already forgotten
    # the logger that the daemon thread was closing.
    path = tmp_path / "m.jsonl"
    script = textwrap.dedent(
        f"""
        import threading, time
        import jaxmetrics as jm

        class Slow(jm.JsonlWriter):
            def write(self, record):
                time.sleep(0.1)
                super().write(record)

        metrics = jm.Metrics(logged=["x"])
        logger = jm.Logger(metrics, [Slow({str(path)!r})])
        for step in range(5):
            logger.flush(metrics.log(metrics.init(0), {{"x": float(step)}}), step)
        threading.Thread(target=logger.close, daemon=True).start()
        time.sleep(0.05)
        """
    )
    out = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True)
    assert out.returncode == 0, out.stderr
    assert [d["step"] for d in _jsonl(path)] == [0, 1, 2, 3, 4]


def test_every_writer_error_reaches_the_caller_naming_writer_run_and_step():
    # 6 failures once surfaced as 1 (the first), the rest vanished.
    a, b, gated = _Failing("a", {1, 2, 3}), _Failing("b", {1, 2, 3}), _Gated()
    logger = jm.Logger(
        METRICS, lambda run: [gated, a, b] if run == 0 else [jm.MemoryWriter()], runs=2
    )
    for step in range(4):  # all queued before the first write: one check sees every failure
        logger.flush(_seeds(step), step)
    gated.gate.set()
    with pytest.raises(jm.WriterError) as err:
        logger.wait()
    failures = [str(f) for f in err.value.failures]
    want = [f"writer _Failing({n!r}) of run 0 failed at step {s}" for s in (1, 2, 3) for n in "ab"]
    assert [f.split(":")[0] for f in failures] == want
    assert isinstance(err.value.failures[0].__cause__, OSError)
    assert a.written == b.written == [0]
    logger.close()  # nothing left to raise


def _seeds(step):
    """The states of two vmapped seeds."""
    return jax.vmap(lambda v: _state(v))(jnp.full((2,), step, jnp.float32))


def test_a_flush_raising_a_held_over_writer_error_does_not_count_its_period_twice():
    # The raising flush had queued its own report but the caller never got the reset
    # state: flushing that state again wrote the period twice.
    failing = _Failing("f", {0})
    memory = jm.MemoryWriter()
    logger = jm.Logger(METRICS, [failing, memory])
    state = logger.flush(_state(1.0), 0)
    state = METRICS.log(state, {"x": 5.0})
    time.sleep(0.2)  # let the writer thread fail on step 0
    with pytest.raises(jm.WriterError, match=r"writer _Failing\('f'\) of run 0 failed at step 0"):
        logger.flush(state, 1)
    logger.flush(state, 1)
    logger.close()
    counts = [
        (r.step, r.scalars["Train/x/count"], r.scalars.get("Train/x")) for r in memory.records
    ]
    assert counts == [(0, 1, 1.0), (1, 1, 5.0)]


def test_a_stuck_writer_raises_a_timeout_instead_of_hanging():
    gated = _Gated()
    logger = jm.Logger(METRICS, [gated], max_pending=2, timeout=0.5)
    state = logger.flush(_state(1.0), 0)  # the writer thread blocks in it
    state = logger.flush(state, 1)  # queued: the last pending slot
    t0 = time.monotonic()
    with pytest.raises(jm.WriterTimeoutError, match=r"\(write, step 0\) has not returned for"):
        logger.flush(state, 2)
    with pytest.raises(jm.WriterTimeoutError, match=r"Logger.wait: .*timeout=0.5 s"):
        logger.wait()
    with pytest.raises(jm.WriterTimeoutError, match=r"Logger.close: "):
        logger.close()
    assert time.monotonic() - t0 < 10
    gated.gate.set()  # the disk comes back: the thread drains and stops
    logger._thread.join(10)
    assert not logger._thread.is_alive()
    assert gated.written == [0, 1]


def _run_child(script, *args, timeout=120):
    env = dict(os.environ, JAX_PLATFORMS="cpu")
    return subprocess.run(
        [sys.executable, "-c", textwrap.dedent(script), *args],
        capture_output=True,
        text=True,
        timeout=timeout,
        env=env,
    )


_CHILD_HEAD = """
    import sys, threading, jax.numpy as jnp, jaxmetrics as jm
    m = jm.Metrics(logged=["x"])
"""


def test_exit_status_1_runs_every_other_exit_handler_and_import_registers_none():
    # The status used to be set by os._exit(1) inside jaxmetrics' handler, which skipped the
    # handlers registered before it (they run after it), e.g. a tracker's run finalizer.
    out = _run_child(
        """
    import atexit, sys
    import jax.numpy as jnp  # JAX registers exit handlers of its own
    atexit.register(print, "registered before the import", flush=True)
    before = atexit._ncallbacks()
    import jaxmetrics as jm
    assert atexit._ncallbacks() == before, "importing jaxmetrics registered an exit handler"
    atexit.register(print, "registered after the import", flush=True)
    class Failing:
        def open(self, tags): pass
        def write(self, record): raise OSError("disk gone")
        def close(self): pass
    m = jm.Metrics(logged=["x"])
    logger = jm.Logger(m, [Failing()])
    atexit.register(print, "registered after the Logger", flush=True)
    logger.flush(m.log(m.init(0), {"x": 1.0}), 7)
    """
    )
    assert out.returncode == 1, out.stderr
    assert out.stdout.splitlines() == [
        "registered after the Logger",
        "registered after the import",
        "registered before the import",
    ]
    assert "OSError('disk gone')" in out.stderr and "exiting with status 1" in out.stderr


def test_records_lost_at_interpreter_exit_give_exit_status_1_and_say_so():
    # A writer error at exit printed "Exception ignored in atexit callback" and exited 0;
    # a stuck writer hung the exit.
    failing = _run_child(
        _CHILD_HEAD
        + """
    class Failing:
        def open(self, tags): pass
        def write(self, record): raise OSError("disk gone")
        def close(self): pass
        def __repr__(self): return "Failing()"
    logger = jm.Logger(m, [Failing()])
    logger.flush(m.log(m.init(0), {"x": 1.0}), 7)
    print("flushed", flush=True)
    """
    )
    assert failing.returncode == 1, failing.stderr
    assert "flushed" in failing.stdout
    assert "writer Failing() of run 0 failed at step 7: OSError('disk gone')" in failing.stderr
    stuck = _run_child(
        _CHILD_HEAD
        + """
    class Stuck:
        def open(self, tags): pass
        def write(self, record): threading.Event().wait()
        def close(self): pass
    logger = jm.Logger(m, [Stuck()], timeout=1)
    logger.flush(m.log(m.init(0), {"x": 1.0}), 7)
    """,
        timeout=60,
    )
    assert stuck.returncode == 1, stuck.stderr
    assert "WriterTimeoutError" in stuck.stderr and "step 7" in stuck.stderr
    # A record written at a step lower than the last is no loss: exit status 0, or the
    # user's own (it used to be reported as lost and the process ended with status 1).
    for tail, status in (("", 0), ("sys.exit(3)", 3)):
        back = _run_child(
            _CHILD_HEAD
            + f"""
    logger = jm.Logger(m, [jm.MemoryWriter()])
    state = logger.flush(m.log(m.init(0), {{"x": 1.0}}), 7)
    logger.flush(state, jnp.asarray(3, jnp.int32))
    {tail}
    """
        )
        assert back.returncode == status, back.stderr
        assert "step 3 written after step 7" in back.stderr
        assert "lost" not in back.stderr and "status 1" not in back.stderr
    clean = _run_child(
        _CHILD_HEAD
        + """
    logger = jm.Logger(m, [jm.MemoryWriter()])
    logger.flush(m.log(m.init(0), {"x": 1.0}), 7)
    """
    )
    assert clean.returncode == 0 and clean.stderr.count("jaxmetrics") == 0, clean.stderr


_FULL_DISK = """
    import json, os, resource, signal, sys
    import jax.numpy as jnp, jaxmetrics as jm
    signal.signal(signal.SIGXFSZ, signal.SIG_IGN)  # a write past the limit fails with EFBIG
    root = sys.argv[1]
    m = jm.Metrics(logged=["x"])
    jsonl, tb = jm.JsonlWriter(os.path.join(root, "m.jsonl")), jm.TensorBoardWriter(os.path.join(root, "tb"))
    logger = jm.Logger(m, [jsonl, tb])
    state, step, failed = m.init(0), 0, []
    def flush():
        global state, step
        state = logger.flush(m.log(state, {"x": float(step)}), step)
        try:
            logger.wait()
        except jm.WriterError as e:
            failed.extend(str(f) for f in e.failures)
        step += 1
    def event_file():
        d = os.path.join(root, "tb")
        return os.path.join(d, os.listdir(d)[0])
    for _ in range(3):
        flush()
    _, hard = resource.getrlimit(resource.RLIMIT_FSIZE)
    for path in (jsonl.path, event_file()):
        # The disk fills: 10 more bytes fit, a record is cut part-way.
        resource.setrlimit(resource.RLIMIT_FSIZE, (os.path.getsize(path) + 10, hard))
        flush()
        resource.setrlimit(resource.RLIMIT_FSIZE, (hard, hard))  # space is freed
        flush()
    logger.close()
    print(json.dumps(failed))
"""


def test_a_disk_that_fills_and_frees_leaves_every_other_record_readable(tmp_path):
    # Writes after the disk freed up again used to be unreadable in TensorBoard, and the
    # JSONL file merged two records into one line.
    child = _run_child(_FULL_DISK, str(tmp_path))
    assert child.returncode == 0, child.stderr
    failed = json.loads(child.stdout.strip().splitlines()[-1])
    lost = {"JsonlWriter": set(), "TensorBoardWriter": set()}
    for f in failed:
        kind = "JsonlWriter" if "JsonlWriter" in f else "TensorBoardWriter"
        lost[kind].add(int(f.split(" failed at step ")[1].split(":")[0]))
    assert lost["JsonlWriter"] and lost["TensorBoardWriter"]  # both were cut part-way
    everything = set(range(7))
    js = [(d["step"], d["scalars"]["Train/x"]) for d in _jsonl(tmp_path / "m.jsonl")]
    assert js == [(s, float(s)) for s in sorted(everything - lost["JsonlWriter"])]
    tb = _tb_steps(tmp_path / "tb")
    assert tb == [(s, float(s)) for s in sorted(everything - lost["TensorBoardWriter"])]


def test_resuming_into_a_crash_cut_jsonl_file_repairs_it_and_purges_later_steps(tmp_path):
    path = tmp_path / "m.jsonl"
    with jm.Logger(METRICS, [jm.JsonlWriter(path)]) as logger:
        for step in range(0, 800, 100):
            logger.flush(_state(float(step)), step)
    with open(path, "ab") as f:
        f.write(b'{"step":800,"wall_ti')  # the crash cut this line
    # Resumed from a checkpoint at step 500: steps 600.. are written again.
    with jm.Logger(METRICS, [jm.JsonlWriter(path, purge_step=600)]) as logger:
        logger.resume(_state(0.0, inc=6), 500)
        for step in range(600, 1000, 100):
            logger.flush(_state(step + 0.5), step)
    records = _jsonl(path)
    assert [(d["step"], d["scalars"]["Train/x"]) for d in records] == [
        *((s, float(s)) for s in range(0, 600, 100)),
        *((s, s + 0.5) for s in range(600, 1000, 100)),
    ]
    # per_sec continues from the restored counters: present on the first resumed record.
    assert "Counters/u/per_sec" in records[6]["scalars"]
    # A resumed writer without purge_step keeps every line, still repaired.
    with open(path, "ab") as f:
        f.write(b'{"ste')
    jm.JsonlWriter(path).close()
    assert len(_jsonl(path)) == 10


def test_resuming_tensorboard_with_purge_step_draws_no_zigzag(tmp_path):
    logdir = tmp_path / "tb"
    with jm.Logger(METRICS, [jm.TensorBoardWriter(logdir)]) as logger:
        for step in range(0, 900, 100):
            logger.flush(_state(float(step)), step)
    with jm.Logger(METRICS, [jm.TensorBoardWriter(logdir, purge_step=600)]) as logger:
        logger.resume(_state(0.0), 500)
        for step in range(600, 1000, 100):
            logger.flush(_state(step + 0.5), step)
    assert _tb_steps(logdir) == [
        *((s, float(s)) for s in range(0, 600, 100)),
        *((s, s + 0.5) for s in range(600, 1000, 100)),
    ]


def test_steps_out_of_int64_or_going_back_are_refused():
    memory = jm.MemoryWriter()
    with jm.Logger(METRICS, [memory]) as logger:
        with pytest.raises(ValueError, match=r"step must be in \[0, 2\^63\)"):
            logger.flush(_state(1.0), 2**63)
        state = logger.flush(_state(1.0), 10)
        with pytest.raises(ValueError, match=r"step 9 after step 10; .* purge_step"):
            logger.flush(state, 9)
        logger.flush(state, 10)  # equal steps are allowed
        # A device step is checked on the writer thread and reported at the next call.
        logger.flush(state, jnp.asarray(3, jnp.int32))
        # It is written, so it is no loss: a warning, not a WriterError.
        with pytest.warns(RuntimeWarning, match=r"run 0: step 3 written after step 10"):
            logger.wait()
    assert [r.step for r in memory.records] == [10, 10, 3]


class _Exiting:
    """A writer that raises `exc` on every write (a library calling sys.exit, Ctrl-C)."""

    def __init__(self, exc):
        self.exc = exc

    def __repr__(self):
        return "_Exiting()"

    def open(self, tags):
        pass

    def write(self, record):
        raise self.exc

    def close(self):
        pass


@pytest.mark.parametrize("exc", [SystemExit(7), KeyboardInterrupt()])
def test_a_writer_raising_systemexit_is_named_and_the_writers_after_it_still_write(exc):
    # It was listed as "7" (or an empty line) with no writer, run or step, and the writers
    # after it skipped that record.
    memory = jm.MemoryWriter()
    logger = jm.Logger(METRICS, [_Exiting(exc), memory])
    logger.flush(_state(1.0), 3)
    with pytest.raises(jm.WriterError) as error:
        logger.close()
    assert [r.step for r in memory.records] == [3]
    (failure,) = error.value.failures
    assert f"writer _Exiting() of run 0 failed at step 3: {exc!r}" in str(failure)
