"""Records of one Logger reach the writers in program order, whatever the channel: a host
`flush` after a jitted chunk that emitted comes after the emit's record (and before the
records of chunks dispatched after it), and emits of several payload layouts in one program
come out in the order the program sent them, not grouped by layout. The ring's merge by its
channel-wide stamp is also tested on hand-written ring memory: a report whose stamp was
taken but whose slot is not yet whole holds back the later ones, and one that was
overwritten does not stall the rest."""

import threading
import warnings

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxmetrics as jm
from jaxmetrics._host import _channel, _ring

CHANNELS = ["ring", "io_callback"]


class _OrderLog:
    """A writer that appends `(run, step)` of each record to a list shared by every run:
    the order in which the Logger handed records to its writers, across runs."""

    def __init__(self, log: list[tuple[int, int]], run: int):
        self.log, self.run = log, run

    def open(self, tags):
        pass

    def write(self, record):
        self.log.append((self.run, record.step))

    def close(self):
        pass


def _inversions(order: list) -> int:
    return sum(a > b for a, b in zip(order, order[1:]))


@pytest.mark.parametrize("channel", CHANNELS)
@pytest.mark.parametrize("flushed", ["the chunk's state", "another state"])
def test_a_flush_after_a_chunk_that_emitted_comes_after_its_records(channel, flushed):
    """100 chunks, each a jitted scan that emits at its middle step (and, by a random
    schedule, at other steps), followed by a host flush: the records come in the order
    the host loop made them, whether the flushed state is the chunk's result or another
    one (no data dependence: program order is the order of dispatch)."""
    rng = np.random.default_rng(0 if flushed == "another state" else 1)
    metrics = jm.Metrics(logged=["x"])
    memory = jm.MemoryWriter()
    logger = jm.Logger(metrics, [memory], report_channel=channel, report_slots=256)
    steps_per_chunk = 10

    def body(state, xs):
        i, when = xs
        state = metrics.log(state, {"x": i.astype(jnp.float32)})
        return logger.emit(state, i, when), None

    chunk = jax.jit(lambda state, i, when: jax.lax.scan(body, state, (i, when))[0])
    state, other = metrics.init(1), metrics.init(1)
    expected = []
    # Warnings are the symptom counted here (a record drawn back), not an error.
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        for k in range(100):
            first = k * steps_per_chunk
            when = rng.random(steps_per_chunk - 1) < 0.2
            when[steps_per_chunk // 2] = True
            state = chunk(state, first + jnp.arange(steps_per_chunk - 1), jnp.asarray(when))
            expected += [first + int(j) for j in np.flatnonzero(when)]
            flush_step = first + steps_per_chunk - 1
            if flushed == "the chunk's state":
                state = logger.flush(state, flush_step)
            else:
                other = logger.flush(metrics.log(other, {"x": jnp.float32(k)}), flush_step)
            expected.append(flush_step)
        logger.close()
    backwards = [w for w in caught if "steps should not decrease" in str(w.message)]
    steps = [r.step for r in memory.records]
    assert _inversions(steps) == 0, f"{_inversions(steps)} records written out of order"
    assert steps == expected and not backwards


@pytest.mark.parametrize("channel", CHANNELS)
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_reports_of_several_layouts_in_one_program_arrive_in_program_order(channel, seed):
    """One jitted scan sends, at each step and by a random schedule, reports of four
    payload layouts (each its own ring), in a random order fixed at trace time: the host
    receives them in the order the program sent them, none lost."""
    rng = np.random.default_rng(seed)
    steps, layouts = 60, 4
    schedule = rng.random((steps, layouts)) < 0.5
    order = rng.permutation(layouts)  # the order of the sends in the traced step
    got: list[tuple[int, int]] = []

    def receive(i, j, *_):
        got.append((int(np.ravel(i)[0]), int(j)))

    channel_ = _channel.Channel(receive, receive, channel, slots=1024)

    def payload(i, j):
        # Layout j: a distinct tree of arrays, all carrying the step.
        extra = [(), (jnp.zeros(3, jnp.float32) + i.astype(jnp.float32),), (jnp.stack([i, i]), jnp.float32(0)),
                 (jnp.ones((2, 2), jnp.int32),)][j]  # fmt: skip
        return (i, jnp.int32(j), *extra)

    def body(carry, xs):
        i, sends = xs
        for j in order:
            jax.lax.cond(sends[j], lambda j=j: channel_.send(*payload(i, j)), lambda: None)
        return carry, None

    jax.jit(lambda s: jax.lax.scan(body, 0, (jnp.arange(steps), s))[0])(jnp.asarray(schedule))
    jax.effects_barrier()
    channel_.drain()
    lost = channel_.take_lost()
    channel_.close()
    expected = [(i, int(j)) for i in range(steps) for j in order if schedule[i, j]]
    assert lost == 0 and sorted(got) == sorted(expected)
    position = {report: k for k, report in enumerate(expected)}
    inversions = _inversions([position[report] for report in got])
    assert inversions == 0, f"{inversions} reports out of program order"
    assert got == expected


def test_a_logger_s_records_of_two_layouts_and_its_flushes_reach_the_writers_in_order():
    """Run 0 emits unvmapped, runs 1 and 2 under vmap (two layouts) in one program, and the
    host flushes all three runs after each chunk: the writers see the records in the order
    the host loop made them, across runs."""
    log: list[tuple[int, int]] = []
    metrics = jm.Metrics(logged=["x"])
    logger = jm.Logger(metrics, lambda run: [_OrderLog(log, run)], runs=3, report_channel="ring")

    def emit(state, i, when, run):
        return logger.emit(metrics.log(state, {"x": i.astype(jnp.float32)}), i, when, run=run)

    def chunk(solo, pair, first):
        def body(carry, i):
            solo, pair = carry
            solo = emit(solo, i, i == first + 2, jnp.int32(0))
            pair = jax.vmap(emit, (0, None, None, 0))(pair, i, i == first + 5, jnp.arange(1, 3))
            return (solo, pair), None

        return jax.lax.scan(body, (solo, pair), first + jnp.arange(8))[0]

    chunk = jax.jit(chunk)
    solo, pair = metrics.init(1), jax.vmap(lambda _: metrics.init(1))(jnp.arange(2))
    flushed = jax.vmap(lambda _: metrics.init(1))(jnp.arange(3))
    expected = []
    for k in range(60):
        first = 10 * k
        solo, pair = chunk(solo, pair, first)
        flushed = logger.flush(flushed, first + 9)
        expected += [(0, first + 2), (1, first + 5), (2, first + 5)]
        expected += [(0, first + 9), (1, first + 9), (2, first + 9)]
    logger.close()
    assert log == expected


def _rings(slots: int, words: int, count: int):
    """`count` rings of one channel (one device) on host memory, and its order word."""
    memories = [np.zeros(_ring.ring_words(words, slots), np.uint32) for _ in range(count)]
    order = np.zeros(_ring.ORDER_WORDS, np.uint32)
    rings = [_ring.Ring(m.ctypes.data, words, slots) for m in memories]
    return memories, rings, order


def _started(memory, ring, order, payload_word):
    """Starts a report by hand, as the writer does, and leaves its slot without its
    `tail`: its ring's counter and the channel's stamp are taken, its `head`, stamp and
    payload written. Returns a function that writes the `tail` (the report whole)."""
    seq, stamp = (int(memory[0]) + 1) % 2**32, (int(order[0]) + 1) % 2**32
    memory[0], order[0] = seq, stamp
    start = _ring.HEADER_WORDS + ((seq - 1) % ring.slots) * (ring.payload_words + 3)
    memory[start : start + 2] = (seq, stamp)
    memory[start + 2 : start + 2 + ring.payload_words] = payload_word

    def finish():
        memory[start + 2 + ring.payload_words] = seq

    return finish


def test_a_report_whose_stamp_is_taken_but_whose_slot_is_not_whole_holds_back_later_ones():
    """Ring A's report took stamp 1 and is still being written when ring B's (stamp 2)
    is whole: the merge delivers nothing until A's is whole, then both, in stamp order."""
    memories, rings, order = _rings(slots=4, words=2, count=2)
    merge = _ring.Merge(order.ctypes.data)
    finish_a = _started(memories[0], rings[0], order, 10)
    _started(memories[1], rings[1], order, 20)()
    reports, lost, _ = merge.look(rings)
    assert reports == [] and lost == 0
    finish_a()
    reports, lost, _ = merge.look(rings)
    assert [(ring, payload[0]) for ring, payload in _payloads(reports)] == [(0, 10), (1, 20)]
    assert lost == 0


def test_a_report_overwritten_before_it_was_taken_is_counted_and_stalls_nothing():
    """Ring A (one slot) gets stamps 1 and 3, ring B stamp 2: A's first report is gone
    before the reader looks. The merge counts it lost and delivers 2 then 3."""
    memories, rings, order = _rings(slots=1, words=2, count=2)
    merge = _ring.Merge(order.ctypes.data)
    _started(memories[0], rings[0], order, 10)()
    _started(memories[1], rings[1], order, 20)()
    _started(memories[0], rings[0], order, 30)()
    reports, lost, found = merge.look(rings)
    assert [(ring, payload[0]) for ring, payload in _payloads(reports)] == [(1, 20), (0, 30)]
    assert lost == 1 and found == 3


def test_the_merge_keeps_the_order_across_the_wrap_of_the_32_bit_stamps():
    """The order word wraps at 2^32 like the rings' counters: reports stamped 2^32 - 2,
    2^32 - 1, 0, 1 and 2 (over two one-slot rings; the one of stamp 1 is overwritten
    before the reader looks) come out in that order, the lost one counted."""
    memories, rings, order = _rings(slots=1, words=1, count=2)
    order[0] = 2**32 - 3  # as if that many reports had been stamped and delivered
    merge = _ring.Merge(order.ctypes.data)
    _started(memories[0], rings[0], order, 1)()
    _started(memories[1], rings[1], order, 2)()
    first = merge.look(rings)
    _started(memories[1], rings[1], order, 3)()
    _started(memories[0], rings[0], order, 4)()
    _started(memories[0], rings[0], order, 5)()
    second = merge.look(rings)
    assert order[0] == 2  # wrapped
    assert [(i, p[0]) for i, p in _payloads(first.reports)] == [(0, 1), (1, 2)]
    assert [(i, p[0]) for i, p in _payloads(second.reports)] == [(1, 3), (0, 5)]
    assert (first.lost, second.lost) == (0, 1)


def _payloads(reports):
    return [(ring, np.frombuffer(payload, np.uint32)) for ring, payload in reports]


def test_a_slow_consumer_of_two_layouts_loses_reports_counts_them_and_keeps_program_order():
    """A consumer that blocks while a program sends reports of two layouts into 2-slot
    rings: the reports taken are in program order, and taken + lost is every report sent."""
    delivered: list[tuple[int, int]] = []
    gate = threading.Event()

    def deliver(i, *rest):
        gate.wait(0.02)  # a writer that blocks
        delivered.append((int(i), len(rest)))

    channel = _channel.Channel(lambda *p: None, deliver, "ring", slots=2)

    def body(c, i):
        jax.lax.cond(sends[0](i), lambda: channel.send(i), lambda: None)
        jax.lax.cond(sends[1](i), lambda: channel.send(i, jnp.float32(1)), lambda: None)
        return c, None

    sends = (lambda i: i % 3 != 0, lambda i: i % 2 == 0)  # layout 0's, then layout 1's
    jax.jit(lambda: jax.lax.scan(body, 0, jnp.arange(60))[0])()
    jax.effects_barrier()
    channel.drain()
    lost = channel.take_lost()
    channel.close()
    sent = [(i, layout) for i in range(60) for layout in (0, 1) if sends[layout](i)]
    rest = iter(sent)
    assert all(report in rest for report in delivered), "not a subsequence of program order"
    assert lost > 0 and len(delivered) + lost == len(sent)


def test_write_history_after_a_chunk_that_emitted_comes_after_its_records():
    """A program that emits (through the ring) and keeps a report history: the history's
    records, written after the call, come after the emits the program made."""
    metrics = jm.Metrics(logged=["x"])
    memory = jm.MemoryWriter()
    logger = jm.Logger(metrics, [memory], report_channel="ring")

    def chunk(state, history, first):
        def body(carry, i):
            state, history = carry
            state = metrics.log(state, {"x": i.astype(jnp.float32)})
            state = logger.emit(state, i, i == first + 2)
            return logger.record(state, history, i, i == first + 5), None

        return jax.lax.scan(body, (state, history), first + jnp.arange(8))[0]

    chunk = jax.jit(chunk)
    state = metrics.init(1)
    for k in range(40):
        state, history = chunk(state, logger.history_init(capacity=1), 10 * k)
        logger.write_history(history)
    logger.close()
    assert [r.step for r in memory.records] == [10 * k + d for k in range(40) for d in (2, 5)]


def test_only_a_logger_that_emits_waits_for_the_device_at_a_flush(monkeypatch):
    """The wait that orders a flush after the emits before it is the emitting Logger's
    cost alone: a Logger that only flushes never waits for the device."""
    metrics = jm.Metrics(logged=["x"])
    state = metrics.log(metrics.init(1), {"x": jnp.float32(1)})
    with jm.Logger(metrics, [jm.MemoryWriter()], report_channel="ring") as logger:
        assert logger.report_channel.kind == "ring"  # the ring's self-test (it waits) is done
        waits = []
        barrier = jax.effects_barrier
        monkeypatch.setattr(jax, "effects_barrier", lambda: (waits.append(1), barrier())[1])
        for step in range(3):
            state = logger.flush(state, step)
        assert waits == []
        state = jax.jit(lambda s: logger.emit(s, 3, True))(state)
        for step in range(4, 7):
            state = logger.flush(state, step)
        assert len(waits) == 3
