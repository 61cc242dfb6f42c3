"""In-graph emit: an ordered io_callback under lax.cond that fires at period ends only,
under vmap over seeds each seed to its own run directory (read back from TensorBoard)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from tensorboard.backend.event_processing import event_accumulator as ea

import jaxmetrics as jm

SEEDS, STEPS, PERIOD, NUM_ENVS = 3, 12, 4, 2


def _values(seed, i):
    """What seed `seed` logs at step `i` (distinct per seed and step), as float32."""
    return np.float32(100.0 * seed + i * i / 8.0)


def _make():
    return jm.Metrics(
        terms={"speed": jm.Term(lambda x: x, reduce="max", stats=("mean", "count"))},
        logged={"loss": jm.Logged(stats=("mean", "max", "count"))},
    )


def _train(metrics, logger, seed, run, when_fn):
    def body(state, i):
        v = seed * 100.0 + i.astype(jnp.float32) ** 2 / 8.0
        state = metrics.log(state, {"loss": v})
        # Every env ends an episode on each step; speed = v + env index.
        speed = v + jnp.arange(NUM_ENVS, dtype=jnp.float32)
        state = metrics.update(state, speed, jnp.ones(NUM_ENVS, jnp.bool_))
        return logger.emit(state, i, when_fn(i, run), run=run), None

    return jax.lax.scan(body, metrics.init(NUM_ENVS), jnp.arange(STEPS))[0]


def _read(logdir, tag):
    acc = ea.EventAccumulator(str(logdir), size_guidance={ea.SCALARS: 0})
    acc.Reload()
    return [(e.step, e.value) for e in acc.Scalars(tag)]


def test_emit_under_vmap_writes_each_seed_to_its_own_run_at_period_ends(tmp_path):
    metrics = _make()
    logger = jm.Logger(
        metrics, lambda run: [jm.TensorBoardWriter(tmp_path / f"seed_{run}")], runs=SEEDS
    )
    train = jax.jit(
        jax.vmap(lambda s, r: _train(metrics, logger, s, r, lambda i, _: i % PERIOD == PERIOD - 1))
    )
    train(jnp.arange(SEEDS, dtype=jnp.float32), jnp.arange(SEEDS))
    logger.close()
    assert logger.emit_calls == STEPS // PERIOD  # one callback per period end, all seeds in it

    ends = list(range(PERIOD - 1, STEPS, PERIOD))
    for seed in range(SEEDS):
        loss = _read(tmp_path / f"seed_{seed}", "Train/loss")
        assert [s for s, _ in loss] == ends  # this seed's records, in step order
        # Reference: a hand-unrolled loop over this seed's steps, float64 means per period.
        want = [
            np.mean([_values(seed, i) for i in range(e - PERIOD + 1, e + 1)], dtype=np.float64)
            for e in ends
        ]
        np.testing.assert_allclose([v for _, v in loss], want, rtol=1e-6)
        loss_max = _read(tmp_path / f"seed_{seed}", "Train/loss/max")
        np.testing.assert_array_equal([v for _, v in loss_max], [_values(seed, e) for e in ends])
        speed = _read(tmp_path / f"seed_{seed}", "Episode_Metrics/speed")
        np.testing.assert_allclose([v for _, v in speed], np.array(want) + 0.5, rtol=1e-6)
        count = _read(tmp_path / f"seed_{seed}", "Episode_Metrics/speed/count")
        assert [v for _, v in count] == [PERIOD * NUM_ENVS] * len(ends)


def test_emit_with_per_seed_period_ends_resets_only_the_seeds_that_emitted():
    metrics = _make()
    memories = [jm.MemoryWriter() for _ in range(SEEDS)]
    logger = jm.Logger(metrics, lambda run: [memories[run]], runs=SEEDS)
    period = lambda run: run + 2  # noqa: E731 (seed r ends a period every r + 2 steps)
    train = jax.jit(
        jax.vmap(
            lambda s, r: _train(metrics, logger, s, r, lambda i, r: i % period(r) == period(r) - 1)
        )
    )
    train(jnp.arange(SEEDS, dtype=jnp.float32), jnp.arange(SEEDS))
    logger.close()
    all_ends = set()
    for seed, memory in enumerate(memories):
        p = seed + 2
        ends = list(range(p - 1, STEPS, p))
        all_ends |= set(ends)
        got = [(r.step, r.scalars["Train/loss"]) for r in memory.records]
        want = [np.mean([_values(seed, i) for i in range(e - p + 1, e + 1)]) for e in ends]
        assert [s for s, _ in got] == ends
        np.testing.assert_allclose([v for _, v in got], want, rtol=1e-6)
    assert logger.emit_calls == len(all_ends)


def test_emit_without_vmap_and_under_nested_vmap():
    metrics = _make()
    single = jm.MemoryWriter()
    logger = jm.Logger(metrics, [single])
    jax.jit(lambda s: _train(metrics, logger, s, None, lambda i, _: i == STEPS - 1))(jnp.float32(1))
    logger.close()
    assert [r.step for r in single.records] == [STEPS - 1] and logger.emit_calls == 1
    want = np.mean([_values(1, i) for i in range(STEPS)])
    assert single.records[0].scalars["Train/loss"] == pytest.approx(want, rel=1e-6)

    memories = [jm.MemoryWriter() for _ in range(4)]
    logger = jm.Logger(metrics, lambda run: [memories[run]], runs=4)
    inner = jax.vmap(lambda s, r: _train(metrics, logger, s, r, lambda i, _: i == STEPS - 1))
    seeds = jnp.arange(4, dtype=jnp.float32).reshape(2, 2)
    jax.jit(jax.vmap(inner))(seeds, jnp.arange(4).reshape(2, 2))
    logger.close()
    assert logger.emit_calls == 1
    for run, memory in enumerate(memories):
        want = np.mean([_values(run, i) for i in range(STEPS)])
        assert memory.records[0].scalars["Train/loss"] == pytest.approx(want, rel=1e-6)


def test_emit_misuse_is_rejected_at_trace_time_with_the_fix():
    metrics = jm.Metrics(logged=["x"])
    one = jm.Logger(metrics, [jm.MemoryWriter()])
    three = jm.Logger(metrics, lambda run: [jm.MemoryWriter()], runs=3)
    state = metrics.init(1)
    batched = jax.vmap(lambda _: metrics.init(1))(jnp.arange(3))
    with pytest.raises(ValueError, match="run=seed_index"):
        jax.vmap(lambda s: one.emit(s, 0, True))(batched)
    with pytest.raises(ValueError, match="run=seed_index"):
        jax.vmap(lambda s: three.emit(s, 0, True, run=0))(batched)
    with pytest.raises(TypeError, match="needs run="):
        three.emit(state, 0, True)
    with pytest.raises(TypeError, match="when must be a bool scalar"):
        one.emit(state, 0, 1)
    with pytest.raises(TypeError, match="step must be an int scalar"):
        one.emit(state, 0.5, True)
    one.close()
    three.close()


def test_emit_nonfinite_raise_surfaces_at_close_after_writing():
    metrics = jm.Metrics(logged={"x": jm.Logged(nonfinite="raise")})
    memory = jm.MemoryWriter()
    logger = jm.Logger(metrics, [memory])

    def train(state):
        state = logger.emit(metrics.log(state, {"x": 1.0}), 0, True)
        return logger.emit(metrics.log(state, {"x": jnp.nan}), 1, True)

    jax.jit(train)(metrics.init(1))
    with pytest.raises(jm.NonFiniteError, match="step 1, run 0: .*'x'"):
        logger.close()
    assert [r.step for r in memory.records] == [0, 1]


def test_emit_of_a_state_sharded_over_devices(env_sharded):
    metrics = _make()
    memory = jm.MemoryWriter()
    logger = jm.Logger(metrics, [memory])

    def step(state, x):
        state = metrics.update(state, x, jnp.ones(8, jnp.bool_))
        return logger.emit(state, 5, True)

    x = jax.device_put(jnp.arange(8.0, dtype=jnp.float32), env_sharded)
    with jax.default_device(jax.devices("cpu")[0]):  # also where the default is one GPU
        jax.jit(step)(metrics.init(8), x)
    logger.close()
    (record,) = memory.records
    assert (record.step, record.scalars["Episode_Metrics/speed"]) == (5, 3.5)
    assert logger.emit_calls == 1
