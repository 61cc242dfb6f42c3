"""Report history without callbacks: `Logger.record` keeps packed reports in an in-graph
buffer, `Logger.write_history` writes them after the jitted call. The same records as
`emit` (per seed under vmap, per-seed period ends), sharded states, the persistent
compilation cache, overflow, misuse, and writer errors while writing a history."""

import json
import os
import subprocess
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxmetrics as jm

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
SEEDS, STEPS, NUM_ENVS = 3, 12, 2


def _make():
    return jm.Metrics(
        terms={
            "speed": jm.Term(
                lambda x: x,
                reduce="max",
                stats=("mean", "count", jm.window(4, (50,)), jm.histogram(4, (0.0, 400.0))),
            )
        },
        logged={"loss": jm.Logged(stats=("mean", "max", "count", jm.ema(0.5)))},
        counters=["updates"],
    )


def _value(seed, i):
    """What seed `seed` logs at step `i`, in float64 (it is exact in float32)."""
    return 100.0 * seed + i * i / 8.0


def _period(run):
    return run + 2  # seed r ends a period every r + 2 steps


def _train(metrics, period_end, seed, run, carry):
    """STEPS steps of one seed; `period_end(state, carry, step, when)` ends periods."""

    def body(c, i):
        state, extra = c
        v = seed * 100.0 + i.astype(jnp.float32) ** 2 / 8.0
        state = metrics.log(state, {"loss": v})
        state = metrics.increment(state, "updates")
        speed = v + jnp.arange(NUM_ENVS, dtype=jnp.float32)
        state = metrics.update(state, speed, jnp.ones(NUM_ENVS, jnp.bool_))
        when = i % _period(run) == _period(run) - 1
        return period_end(state, extra, i, when, run), None

    return jax.lax.scan(body, (metrics.init(NUM_ENVS), carry), jnp.arange(STEPS))[0]


def _emit_run(metrics, memories, summary):
    logger = jm.Logger(metrics, lambda r: [memories[r]], runs=SEEDS, seeds_summary=[summary])

    def end(state, extra, i, when, run):
        return logger.emit(state, i, when, run=run), extra

    seeds = jnp.arange(SEEDS, dtype=jnp.float32)
    jax.jit(jax.vmap(lambda s, r: _train(metrics, end, s, r, jnp.int32(0))))(
        seeds, jnp.arange(SEEDS)
    )
    logger.close()


def _history_run(metrics, memories, summary, capacity=6):
    logger = jm.Logger(metrics, lambda r: [memories[r]], runs=SEEDS, seeds_summary=[summary])

    def end(state, history, i, when, run):
        return logger.record(state, history, i, when)

    def train(seed, run):
        return _train(metrics, end, seed, run, logger.history_init(capacity))

    _, history = jax.jit(jax.vmap(train))(jnp.arange(SEEDS, dtype=jnp.float32), jnp.arange(SEEDS))
    logger.write_history(history)
    logger.close()
    return history


def _comparable(record):
    """A record without what depends on the host clock (rates, wall time)."""
    scalars = {t: v for t, v in record.scalars.items() if "/per_sec" not in t}
    hists = {t: (h.counts.tolist(), h.underflow, h.overflow) for t, h in record.histograms.items()}
    windows = {t: w.tolist() for t, w in record.windows.items()}
    return record.step, scalars, hists, windows


def test_history_writes_the_records_emit_writes_per_seed_under_vmap():
    metrics = _make()
    by_emit = [jm.MemoryWriter() for _ in range(SEEDS)]
    by_history = [jm.MemoryWriter() for _ in range(SEEDS)]
    summary_emit, summary_history = jm.MemoryWriter(), jm.MemoryWriter()
    _emit_run(metrics, by_emit, summary_emit)
    _history_run(metrics, by_history, summary_history)
    for seed in range(SEEDS):
        got = [_comparable(r) for r in by_history[seed].records]
        assert got == [_comparable(r) for r in by_emit[seed].records]
        # Reference: this seed's periods unrolled by hand, float64.
        p = _period(seed)
        ends = list(range(p - 1, STEPS, p))
        assert [r.step for r in by_history[seed].records] == ends
        want = [np.mean([_value(seed, i) for i in range(e - p + 1, e + 1)]) for e in ends]
        loss = [r.scalars["Train/loss"] for r in by_history[seed].records]
        np.testing.assert_allclose(loss, want, rtol=1e-6)
        assert [r.scalars["Counters/updates"] for r in by_history[seed].records] == [
            e + 1 for e in ends
        ]
        # No host clock ran between the records of a history: no rates.
        assert not [t for r in by_history[seed].records for t in r.scalars if "per_sec" in t]
    # The summary joins the seeds by step whatever their period ends.
    assert [_comparable(r) for r in summary_history.records] == [
        _comparable(r) for r in summary_emit.records
    ]
    ends = sorted({e for r in range(SEEDS) for e in range(_period(r) - 1, STEPS, _period(r))})
    assert [r.step for r in summary_history.records] == ends


def test_history_of_a_state_sharded_over_devices(env_sharded):
    metrics = _make()
    memory = jm.MemoryWriter()
    logger = jm.Logger(metrics, [memory])

    def step(state, history, x):
        state = metrics.update(state, x, jnp.ones(8, jnp.bool_))
        return logger.record(state, history, jnp.int32(5), jnp.bool_(True))

    x = jax.device_put(jnp.arange(8.0, dtype=jnp.float32), env_sharded)
    state = metrics.init(8, sharding=env_sharded)
    with jax.default_device(jax.devices("cpu")[0]):
        state, history = jax.jit(step)(state, logger.history_init(1), x)
    logger.write_history(history)
    logger.close()
    (record,) = memory.records
    assert (record.step, record.scalars["Episode_Metrics/speed"]) == (5, 3.5)
    assert record.scalars["Episode_Metrics/speed/count"] == 8
    assert len(state.finished.count.hi) == 2  # still one set of statistics per shard


CACHE_SCRIPT = """
import os, sys
import jax, jax.numpy as jnp
cache = sys.argv[1]
jax.config.update("jax_compilation_cache_dir", cache)
jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)
import jaxmetrics as jm

events = []
jax.monitoring.register_event_listener(lambda name, **kw: events.append(name))
metrics = jm.Metrics(logged=["x"])
memory = jm.MemoryWriter()
logger = jm.Logger(metrics, [memory])

def body(state, i):
    return metrics.log(state, {"x": i.astype(jnp.float32)})

def with_history(state, history):
    def step(c, i):
        return logger.record(body(c[0], i), c[1], i, i % 2 == 1), None
    return jax.lax.scan(step, (state, history), jnp.arange(4))[0]

def with_emit(state):
    def step(s, i):
        return logger.emit(body(s, i), i, i % 2 == 1), None
    return jax.lax.scan(step, state, jnp.arange(4))[0]

args = {"history": (metrics.init(1), logger.history_init(2)), "emit": (metrics.init(1),)}
for name, fn in (("history", with_history), ("emit", with_emit)):
    before = len(os.listdir(cache))
    jax.jit(fn).lower(*args[name]).compile()
    written = len(os.listdir(cache)) - before
    jax.clear_caches()
    events.clear()
    compiled = jax.jit(fn).lower(*args[name]).compile()
    print(name, written, events.count("/jax/compilation_cache/cache_hits"))
    if name == "history":
        logger.write_history(compiled(*args[name])[1])
    else:
        compiled(*args[name])  # a program served from the cache still reports
        jax.effects_barrier()
logger.close()
print("records", [(r.step, r.scalars["Train/x"]) for r in memory.records])
"""


def test_history_program_is_served_by_the_persistent_compilation_cache(tmp_path):
    # A fresh process with a fresh cache directory: compile, clear JAX's in-memory
    # caches, compile again and count the persistent cache's hits for that compile.
    env = dict(os.environ, PYTHONPATH=ROOT, JAX_PLATFORMS="cpu")
    out = subprocess.run(
        [sys.executable, "-c", CACHE_SCRIPT, str(tmp_path)],
        capture_output=True,
        text=True,
        env=env,
        timeout=300,
    )
    assert out.returncode == 0, out.stderr
    lines = out.stdout.split("\n")
    name, written, hits = lines[0].split()
    assert (name, hits) == ("history", "1") and int(written) > 0  # stored, then served
    # The io_callback's program: JAX 0.10 and 0.11 neither store nor serve it, 0.12 does
    # both; either way a stored program is served, and it reports what it should.
    name, written, hits = lines[1].split()
    assert name == "emit" and written == hits and written in ("0", "1")
    assert lines[2] == "records [(1, 0.5), (3, 2.5), (1, 0.5), (3, 2.5)]"


def test_an_overflowing_history_writes_what_it_holds_and_raises_with_the_capacity_needed():
    metrics = jm.Metrics(logged=["x"])
    memory = jm.MemoryWriter()
    logger = jm.Logger(metrics, [memory])

    def train(state, history):
        def step(c, i):
            state = metrics.log(c[0], {"x": i.astype(jnp.float32)})
            return logger.record(state, c[1], i, jnp.bool_(True)), None

        return jax.lax.scan(step, (state, history), jnp.arange(5))[0]

    state, history = jax.jit(train)(metrics.init(1), logger.history_init(2))
    assert int(history.ends) == 5
    with pytest.raises(ValueError, match=r"overflowed \(run 0: 5 period ends; capacity 2\).*"):
        logger.write_history(history)
    logger.wait()
    assert [(r.step, r.scalars["Train/x"]) for r in memory.records] == [(0, 0.0), (1, 1.0)]
    # The periods past the capacity were not reset: the returned state still holds them.
    logger.flush(state, 4)
    logger.close()
    last = memory.records[-1]
    assert (last.step, last.scalars["Train/x/count"]) == (4, 3)
    assert last.scalars["Train/x"] == pytest.approx(np.mean([2.0, 3.0, 4.0]))


def test_history_misuse_is_rejected_with_the_fix():
    metrics = jm.Metrics(logged=["x"])
    other = jm.Metrics(logged=["y"])
    logger = jm.Logger(metrics, [jm.MemoryWriter()])
    three = jm.Logger(metrics, lambda r: [jm.MemoryWriter()], runs=3)
    foreign = jm.Logger(other, [jm.MemoryWriter()])
    for bad in (0, -1, 2.5, True, None):
        with pytest.raises(ValueError, match="capacity must be an int >= 1"):
            logger.history_init(bad)
    state, history = metrics.init(1), logger.history_init(2)
    with pytest.raises(ValueError, match="made by history_init of a Logger of another Metrics"):
        jax.jit(lambda s, h: logger.record(s, h, 0, True))(state, foreign.history_init(2))
    with pytest.raises(ValueError, match="made by history_init of a Logger of another Metrics"):
        logger.write_history(foreign.history_init(2))
    with pytest.raises(ValueError, match=r"expected \(3, 'capacity', 4\)"):
        three.write_history(history)
    with pytest.raises(TypeError, match="expected the History of logger.history_init"):
        logger.write_history((history.floats,))
    with pytest.raises(TypeError, match="when must be a bool scalar"):
        logger.record(state, history, 0, 1)
    with pytest.raises(TypeError, match="step must be an int scalar"):
        logger.record(state, history, 0.5, True)
    with pytest.raises(TypeError, match="write_history is a host call"):
        jax.jit(lambda h: logger.write_history(h))(history)
    for lg in (three, foreign):
        lg.close()
    logger.close()
    for call in (
        lambda: logger.history_init(2),
        lambda: logger.record(state, history, 0, True),
        lambda: logger.write_history(history),
    ):
        with pytest.raises(RuntimeError, match="the logger is closed; create a new Logger"):
            call()


class FailingAt:
    """A writer that fails on the record of one step (a full disk, a lost connection)."""

    def __init__(self, step):
        self.step, self.steps = step, []

    def open(self, tags):
        pass

    def write(self, record):
        if record.step == self.step:
            raise OSError("disk full")
        self.steps.append(record.step)

    def close(self):
        pass


def test_writer_errors_while_writing_a_history_lose_nothing_else(tmp_path):
    metrics = jm.Metrics(logged=["x"])
    failing = FailingAt(2**32 - 6)
    path = tmp_path / "metrics.jsonl"
    logger = jm.Logger(metrics, [failing, jm.JsonlWriter(path)])

    def train(state, history):
        def step(c, i):
            state = metrics.log(c[0], {"x": i.astype(jnp.float32)})
            # Steps as uint32 reach the writers exactly past 2^31.
            s = jnp.uint32(2**32 - 8) + i.astype(jnp.uint32)
            return logger.record(state, c[1], s, jnp.bool_(True)), None

        return jax.lax.scan(step, (state, history), jnp.arange(4))[0]

    _, history = jax.jit(train)(metrics.init(1), logger.history_init(4))
    logger.write_history(history)
    with pytest.raises(jm.WriterError, match=r"FailingAt.* of run 0 failed at step 4294967290"):
        logger.close()
    # The failing writer lost only the record it failed on; the other has every one.
    steps = [2**32 - 8 + i for i in range(4)]
    assert failing.steps == [s for s in steps if s != 2**32 - 6]
    with open(path) as f:
        lines = [json.loads(line) for line in f]
    assert [line["step"] for line in lines] == steps
    assert [line["scalars"]["Train/x"] for line in lines] == [0.0, 1.0, 2.0, 3.0]


def test_nonfinite_values_in_a_history_raise_after_every_record_is_written():
    metrics = jm.Metrics(logged={"x": jm.Logged(nonfinite="raise")})
    memory = jm.MemoryWriter()
    logger = jm.Logger(metrics, [memory])

    def train(state, history):
        state, history = logger.record(metrics.log(state, {"x": 1.0}), history, 0, True)
        return logger.record(metrics.log(state, {"x": jnp.nan}), history, 1, True)

    _, history = jax.jit(train)(metrics.init(1), logger.history_init(2))
    logger.write_history(history)
    with pytest.raises(jm.NonFiniteError, match="step 1, run 0: .*'x'"):
        logger.close()
    assert [r.step for r in memory.records] == [0, 1]
