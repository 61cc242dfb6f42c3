"""The report channel: the ring in host memory (written here by the CPU's host function, in
the bytes and order the GPU's kernel uses; read by the channel's thread) against the
ordered io_callback, the seqlock reader under a concurrent writer, and lost reports."""

import gc
import os
import subprocess
import sys
import threading
import weakref
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxmetrics as jm
from jaxmetrics._host import _channel, _ring, _ring_send

SEEDS, STEPS, PERIOD, NUM_ENVS = 2, 24, 4, 3


def _spec() -> jm.Metrics:
    return jm.Metrics(
        terms={"speed": jm.Term(lambda x: x, reduce="max", stats=("mean", "std", "count"))},
        logged={"loss": jm.Logged(stats=("mean", "max", "count", jm.window(5)))},
    )


def _train(metrics, logger, seed, run, offset):
    def body(state, i):
        v = seed * 100.0 + i.astype(jnp.float32) ** 2 / 8.0
        state = metrics.log(state, {"loss": v})
        speed = v + jnp.arange(NUM_ENVS, dtype=jnp.float32)
        state = metrics.update(state, speed, jnp.ones(NUM_ENVS, jnp.bool_))
        return logger.emit(state, i + offset, i % PERIOD == PERIOD - 1, run=run), None

    return jax.lax.scan(body, metrics.init(NUM_ENVS), jnp.arange(STEPS))[0]


def _records(channel: str):
    metrics = _spec()
    memory = [jm.MemoryWriter() for _ in range(SEEDS)]
    logger = jm.Logger(metrics, lambda r: [memory[r]], runs=SEEDS, report_channel=channel)
    for offset in (0, STEPS):  # a second program continues the ring's sequence
        train = jax.jit(jax.vmap(lambda s, r, o=offset: _train(metrics, logger, s, r, o)))
        train(jnp.arange(SEEDS, dtype=jnp.float32), jnp.arange(SEEDS))
    logger.close()
    assert logger.report_channel.kind == channel
    # Everything but the rates, which are measured in host wall time.
    return [
        [(r.step, {t: v for t, v in r.scalars.items() if not t.endswith("/per_sec")},
          r.histograms) for r in m.records]
        for m in memory
    ]  # fmt: skip


def test_the_ring_writes_the_records_the_io_callback_writes_and_a_float64_loop_expects():
    ring, io = _records("ring"), _records("io_callback")
    assert repr(ring) == repr(io)  # same steps, tags and bits, in the same order
    ends = list(range(PERIOD - 1, STEPS, PERIOD))
    for seed, records in enumerate(ring):
        assert [step for step, _, _ in records] == ends + [e + STEPS for e in ends]
        for k, (_, scalars, _) in enumerate(records[: len(ends)]):
            steps = np.arange(k * PERIOD, (k + 1) * PERIOD, dtype=np.float64)
            loss = np.float32(100.0 * seed) + (steps**2 / 8.0).astype(np.float32)
            assert scalars["Train/loss"] == pytest.approx(loss.astype(np.float64).mean())
            assert scalars["Train/loss/count"] == PERIOD
            speeds = (loss[:, None] + np.arange(NUM_ENVS)).ravel()
            assert scalars["Episode_Metrics/speed"] == pytest.approx(speeds.mean())


def test_auto_takes_the_io_callback_on_the_cpu_and_says_why():
    logger = jm.Logger(_spec(), [jm.MemoryWriter()])
    choice = logger.report_channel
    logger.close()
    assert choice.kind == "io_callback" and "not a CUDA GPU" in choice.reason


def test_the_ring_self_test_runs_from_inside_a_trace_and_passes(monkeypatch):
    """The first `send` is traced inside the user's jit: the self-test's program runs (on a
    thread of its own), it is not staged into the program being traced."""
    monkeypatch.setattr(_channel, "_SELF_TESTS", {})
    seen = []

    @jax.jit
    def program(x):
        seen.append(_channel.self_test())
        return x + 1

    assert int(program(1)) == 2
    assert seen == [None] and _channel._SELF_TESTS == {"cpu": None}


def test_a_ring_whose_jax_internals_are_gone_is_refused_with_the_reason(monkeypatch):
    monkeypatch.setattr(_channel, "_SELF_TESTS", {})
    monkeypatch.setattr(_ring_send, "_SEND", [])

    def gone():
        raise ImportError("cannot import name 'buffer_callback' from 'jax._src'")

    monkeypatch.setattr(_ring_send, "private_jax", gone)
    logger = jm.Logger(_spec(), [jm.MemoryWriter()], report_channel="ring")
    with pytest.raises(RuntimeError, match=r"ring' does not work with JAX .*buffer_callback"):
        jax.jit(lambda s: logger.emit(s, 0, True))(logger.metrics.init(0))
    logger.close()


def test_a_ring_that_garbles_reports_fails_its_self_test(monkeypatch):
    """A round trip that delivers other words (here the host's writer flips them) is a
    failure, not a pass."""
    monkeypatch.setattr(_channel, "_SELF_TESTS", {})
    write = _ring_send.Site.write_host
    monkeypatch.setattr(_ring_send.Site, "write_host", lambda site, w: write(site, ~w))
    assert "came back as" in _channel.self_test()


def test_auto_on_a_cuda_gpu_falls_back_when_the_self_test_fails(monkeypatch):
    """Where the ring cannot be built (here: a "CUDA GPU" that has no devices), auto
    takes the io_callback and says why, naming the JAX version."""
    from jaxmetrics._host import _cuda

    class Driver:
        def version(self):
            return 13000

    monkeypatch.setattr(_channel, "_SELF_TESTS", {})
    monkeypatch.setattr(jax, "default_backend", lambda: "gpu")
    monkeypatch.setattr(_channel, "_gpu_platform", lambda: "cuda")
    monkeypatch.setattr(_cuda, "driver", Driver)
    choice = _channel.choose("auto")
    assert choice.kind == "io_callback"
    assert (
        f"fails its self-test on JAX {jax.__version__}: RuntimeError: Unknown backend"
        in choice.reason
    )


def test_bad_channel_settings_are_named():
    with pytest.raises(ValueError, match=r"report_channel=\.\.\.\) must be one of"):
        jm.Logger(_spec(), [jm.MemoryWriter()], report_channel="fast")
    with pytest.raises(ValueError, match=r"report_slots=\.\.\.\) must be an int"):
        jm.Logger(_spec(), [jm.MemoryWriter()], report_slots=0)


def test_the_reader_never_takes_a_torn_report_from_a_ring_written_concurrently():
    """A writer thread fills a 3-slot ring as fast as it can (each payload all its seq);
    the reader looks concurrently. Every report taken is whole and newer than the last,
    and taken + lost accounts for every report written."""
    words, slots, total = 64, 3, 20_000
    memory = np.zeros(_ring.ring_words(words, slots), np.uint32)
    ring = _ring.Ring(memory.ctypes.data, words, slots)
    order = np.zeros(_ring.ORDER_WORDS, np.uint32)
    done = threading.Event()

    def write():
        for seq in range(1, total + 1):
            ring.write(np.full(words, seq, np.uint32), order.ctypes.data)
        done.set()

    writer = threading.Thread(target=write)
    writer.start()
    last, lost, taken = 0, 0, []
    while True:
        finished = done.is_set()
        got = ring.take(last)
        for seq, stamp, payload in got.reports:
            assert seq > last and stamp == seq  # the only ring of its order word
            assert (np.frombuffer(payload, np.uint32) == seq).all(), f"torn report {seq}"
            taken.append(seq)
            last = seq
        lost, last = lost + got.lost, got.last
        if finished:
            break
    writer.join()
    assert taken == sorted(set(taken))
    assert last == total and len(taken) + lost == total
    assert taken and lost  # both happened: the reader raced the writer for real


def test_a_slow_consumer_loses_reports_counts_them_and_keeps_the_rest_in_order():
    """The channel's thread hands reports to a consumer that blocks: the device (here the
    CPU's host function) goes on writing the 2-slot ring, so reports are overwritten; the
    ones taken are whole and in order, and the lost ones are counted."""
    delivered = []
    gate = threading.Event()

    def deliver(values):
        gate.wait(0.05)  # a writer that blocks
        delivered.append(int(values[0]))

    channel = _channel.Channel(lambda v: None, deliver, "ring", slots=2)

    def body(c, i):
        jax.lax.cond(i % 2 == 1, lambda: channel.send(jnp.stack([i, i * i])), lambda: None)
        return c, None

    jax.jit(lambda: jax.lax.scan(body, 0, jnp.arange(40))[0])()
    jax.effects_barrier()
    channel.drain()
    lost = channel.take_lost()
    channel.close()
    assert delivered == sorted(set(delivered)) and set(delivered) <= set(range(1, 40, 2))
    assert lost > 0 and len(delivered) + lost == 20


def _reporting_every_step(slots):
    """A ring Logger of `slots` slots, its writer, and `train(state, steps)`: a jitted scan
    that logs each step's index and emits it as a record."""
    metrics = jm.Metrics(logged=["x"])
    memory = jm.MemoryWriter()
    logger = jm.Logger(metrics, [memory], report_channel="ring", report_slots=slots)

    def body(state, i):
        state = metrics.log(state, {"x": i.astype(jnp.float32)})
        return logger.emit(state, i, jnp.bool_(True)), None

    train = jax.jit(lambda state, steps: jax.lax.scan(body, state, steps)[0])
    return metrics, memory, logger, train


def test_a_logger_whose_ring_overflows_raises_at_close_naming_the_loss_and_the_fix():
    metrics, memory, logger, train = _reporting_every_step(slots=1)
    train(metrics.init(1), jnp.arange(500))
    with pytest.raises(jm.ReportsLostError, match=r"between two looks") as error:
        logger.close()
    # The remedy offered is a ring that would have held every report lost.
    assert f"report_slots={min(2**16, 1 + error.value.lost)})" in str(error.value)
    steps = [r.step for r in memory.records]
    assert steps == sorted(set(steps))
    assert all(r.scalars["Train/x"] == r.step for r in memory.records)  # each its own step
    assert error.value.lost == 500 - len(steps) > 0


def test_the_ring_sends_a_sharded_state_s_report_once_not_once_per_device(env_sharded):
    """Under automatic partitioning the report is sent from one device, as an io_callback
    is: one record, not one per device (XLA refuses a side effect with no sharding)."""
    metrics = jm.Metrics(terms={"speed": jm.Term(lambda x: x, stats=("mean", "count"))})
    memory = jm.MemoryWriter()
    logger = jm.Logger(metrics, [memory], report_channel="ring")

    def step(state, x):
        state = metrics.update(state, x, jnp.ones(8, jnp.bool_))
        return logger.emit(state, 5, True)

    x = jax.device_put(jnp.arange(8.0, dtype=jnp.float32), env_sharded)
    jax.jit(step)(metrics.init(8), x)
    logger.close()
    (record,) = memory.records
    assert (record.step, record.scalars["Episode_Metrics/speed"]) == (5, 3.5)
    assert record.scalars["Episode_Metrics/speed/count"] == 8


@pytest.mark.parametrize("slots", [1, 3, 64])
def test_the_ring_takes_every_report_across_the_wrap_of_its_32_bit_counter(slots):
    """The device counts reports in a 32-bit word: past 2^32 reports of one layout the
    counter wraps to 0, 1, ... The reader goes on taking them, in order, none lost."""
    words, start = 5, 2**32 - 4
    memory = np.zeros(_ring.ring_words(words, slots), np.uint32)
    ring = _ring.Ring(memory.ctypes.data, words, slots)
    order = np.zeros(_ring.ORDER_WORDS, np.uint32)
    memory[0] = start  # as if `start` reports had been written and taken
    last, taken, lost = start, [], 0
    for k in range(9):
        ring.write(np.full(words, k, np.uint32), order.ctypes.data)
        got = ring.take(last)
        taken += [int(np.frombuffer(p, np.uint32)[0]) for _, _, p in got.reports]
        last, lost = got.last, lost + got.lost
    assert taken == list(range(9)) and lost == 0 and last == start + 9


def test_an_idle_ring_reader_backs_off_and_a_report_brings_it_back(monkeypatch):
    """An idle reader looks less and less often (at most every IDLE_POLL_S), so idle Loggers
    cost about nothing; the first report after an idle spell is still delivered by the
    reader itself."""
    looks = []
    take = _channel.Channel.take

    def counted(channel):
        looks.append(threading.get_ident())
        return take(channel)

    monkeypatch.setattr(_channel.Channel, "take", counted)
    delivered = threading.Event()
    channel = _channel.Channel(lambda v: None, lambda v: delivered.set(), "ring")
    send = jax.jit(lambda x: jax.lax.cond(x > 0, lambda: channel.send(x), lambda: None))
    jax.block_until_ready(send(0))  # traced: the reader starts; nothing is sent
    threading.Event().wait(0.5)  # idle: nothing sent
    idle_looks = len(looks)
    # At 1 kHz that would be about 500 looks; doubling to every 32 ms makes about 20.
    assert 5 <= idle_looks <= 40
    jax.block_until_ready(send(7))
    assert delivered.wait(1.0)  # picked up by the reader's own look, no drain
    channel.close()


def test_a_closed_ring_logger_names_no_step_for_a_first_lost_report_the_ring_overwrote():
    """After close nobody reads the ring until the next close drains it: a 16-slot ring
    keeps the last 16 of 40 late reports, the first 24 were overwritten. The error counts
    all 40 and does not name the first one it could read (step 34) as the first lost (10)."""
    metrics, memory, logger, train = _reporting_every_step(slots=16)
    state = train(metrics.init(1), jnp.arange(10))
    logger.close()
    assert [r.step for r in memory.records] == list(range(10))
    train(state, jnp.arange(10, 50))
    with pytest.raises(jm.ReportsLostError) as error:
        logger.close()
    assert error.value.lost == 40
    assert "from a report the ring overwrote before the host took it on" in str(error.value)
    assert "step 34" not in str(error.value) and len(memory.records) == 10


def test_a_closed_ring_logger_is_not_kept_alive_by_the_exit_check():
    """A sweep of trainings, one ring Logger each, in one process: once closed and dropped,
    every Logger (its writers, spec and programs) goes; only its rings are checked at
    exit, weakly."""
    alive = []
    for _ in range(3):
        metrics, memory, logger, train = _reporting_every_step(slots=8)
        train(metrics.init(1), jnp.arange(4))
        logger.close()
        assert [r.step for r in memory.records] == [0, 1, 2, 3]
        alive.append(weakref.ref(logger))
        del metrics, memory, logger, train
    gc.collect()
    assert [ref() for ref in alive] == [None, None, None]


EXIT_AFTER_COLLECTED = """
import gc, jax, jax.numpy as jnp, jaxmetrics as jm
metrics = jm.Metrics(logged=["x"])
logger = jm.Logger(metrics, [jm.MemoryWriter()], report_channel="ring")

def body(state, i):
    state = metrics.log(state, {"x": i.astype(jnp.float32)})
    return logger.emit(state, i, jnp.bool_(True)), None

train = jax.jit(lambda s, steps: jax.lax.scan(body, s, steps)[0])
compiled = train.lower(metrics.init(1), jnp.arange(3)).compile()
state = compiled(metrics.init(1), jnp.arange(3))
logger.close()
del logger, train, body
gc.collect()
if RUN_AGAIN:
    jax.block_until_ready(compiled(state, jnp.arange(3, 6)))  # 3 reports to the gone Logger
print("done")
"""


@pytest.mark.parametrize("run_again", [False, True])
def test_reports_to_a_collected_ring_logger_fail_the_process_at_exit(run_again):
    script = EXIT_AFTER_COLLECTED.replace("RUN_AGAIN", str(run_again))
    env = dict(os.environ, PYTHONPATH=str(Path(__file__).resolve().parents[2]))
    out = subprocess.run(
        [sys.executable, "-c", script], capture_output=True, text=True, timeout=300, env=env
    )
    assert out.stdout.strip() == "done"
    if run_again:
        assert out.returncode == 1, out.stderr
        assert "3 in-graph report(s) reached a Logger that was closed and then garbage" in (
            out.stderr
        )
    else:
        assert out.returncode == 0, out.stderr
