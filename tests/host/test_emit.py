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


# A line `w0 + w1 * x` fitted to a batch per step by SGD inside one jitted scan, whose loss
# function logs its loss and emits (the report is a side effect of the forward pass).
FIT_STEPS, FIT_PERIOD, FIT_LR, FIT_BATCH = 8, 4, 0.05, 5


def _fit_data(seed):
    """Per step, a batch of inputs and targets (float32)."""
    rng = np.random.default_rng(seed)
    x = rng.uniform(-2.0, 2.0, (FIT_STEPS, FIT_BATCH)).astype(np.float32)
    y = (0.5 + 1.5 * x + rng.normal(0.0, 0.1, x.shape)).astype(np.float32)
    return x, y


def _fit_reference(x, y):
    """Hand-unrolled float64 SGD: each step's loss and gradient."""
    w = np.zeros(2)
    losses, grads = [], []
    for xi, yi in zip(x.astype(np.float64), y.astype(np.float64)):
        r = w[0] + w[1] * xi - yi
        losses.append(np.mean(r**2))
        grads.append(np.array([np.mean(2 * r), np.mean(2 * r * xi)]))
        w = w - FIT_LR * grads[-1]
    return np.array(losses), np.array(grads)


def _fit(loss_fn, value_and_grad, init):
    """SGD over `loss_fn(w, carry, x, y, i, *args) -> (loss, carry)` as a function of the
    data (and `args`: the run), which returns each step's gradient."""

    def fit(x, y, *args):
        def body(carry, inputs):
            w, aux = carry
            x_i, y_i, i = inputs
            if value_and_grad:
                (_, aux), g = jax.value_and_grad(loss_fn, has_aux=True)(w, aux, x_i, y_i, i, *args)
            else:
                g, aux = jax.grad(loss_fn, has_aux=True)(w, aux, x_i, y_i, i, *args)
            return (w - FIT_LR * g, aux), g

        steps = jnp.arange(FIT_STEPS)
        return jax.lax.scan(body, (jnp.zeros(2, jnp.float32), init), (x, y, steps))[1]

    return fit


def _mse(w, x, y):
    return jnp.mean((w[0] + w[1] * x - y) ** 2)


@pytest.mark.parametrize("channel", ["io_callback", "ring"])
@pytest.mark.parametrize("how", ["grad", "value_and_grad", "vmap"])
def test_emit_inside_grad_reports_the_primal_loss_and_leaves_the_gradient_unchanged(channel, how):
    # The loss function logged its (differentiated) loss and emitted: under jit the log
    # failed with "TypeError ... ad_util.Zero", eagerly the emit with "IO callbacks do not
    # support JVP".
    metrics = jm.Metrics(logged=["loss"])
    runs = 2 if how == "vmap" else 1
    memories = [jm.MemoryWriter() for _ in range(runs)]
    logger = jm.Logger(metrics, lambda run: [memories[run]], runs=runs, report_channel=channel)

    def logged_loss(w, state, x, y, i, run=None):
        loss = _mse(w, x, y)
        state = metrics.log(state, {"loss": loss})
        return loss, logger.emit(state, i, i % FIT_PERIOD == FIT_PERIOD - 1, run=run)

    def plain_loss(w, carry, x, y, i, run=None):
        return _mse(w, x, y), carry

    data = [_fit_data(seed) for seed in range(runs)]
    vg = how != "grad"
    fit = _fit(logged_loss, vg, metrics.init(1))
    plain = _fit(plain_loss, vg, jnp.zeros((), jnp.float32))
    if how == "vmap":
        x, y = (jnp.stack([d[k] for d in data]) for k in (0, 1))
        grads = jax.jit(jax.vmap(fit))(x, y, jnp.arange(runs))
        want_grads = jax.jit(jax.vmap(plain))(x, y, jnp.arange(runs))
    else:
        grads = jax.jit(fit)(*data[0])[None]
        want_grads = jax.jit(plain)(*data[0])[None]
    logger.close()

    # The gradient is the one of the same loss without the logging, to the bit.
    np.testing.assert_array_equal(grads, want_grads)
    ends = list(range(FIT_PERIOD - 1, FIT_STEPS, FIT_PERIOD))
    for run, memory in enumerate(memories):
        losses, ref_grads = _fit_reference(*data[run])
        np.testing.assert_allclose(grads[run], ref_grads, rtol=1e-5, atol=1e-6)
        # Each record holds the mean of the primal losses of its period.
        want = [losses[e - FIT_PERIOD + 1 : e + 1].mean() for e in ends]
        got = [
            (r.step, r.scalars["Train/loss"], r.scalars["Train/loss/count"]) for r in memory.records
        ]
        assert [(s, c) for s, _, c in got] == [(e, FIT_PERIOD) for e in ends]
        np.testing.assert_allclose([v for _, v, _ in got], want, rtol=1e-5)


@pytest.mark.parametrize("channel", ["io_callback", "ring"])
def test_grad_through_a_scan_that_updates_logs_and_emits_reports_the_primal_values(channel):
    # A differentiable rollout (Brax's APG differentiates through its env steps): each
    # step's rewards go into an episode term and their mean into a logged value, inside
    # the scan that jax.value_and_grad differentiates.
    metrics = jm.Metrics(
        terms={"reward": jm.Term(lambda r: r, reduce="sum", stats=("mean", "count"))},
        logged=["step_reward"],
    )
    memory = jm.MemoryWriter()
    logger = jm.Logger(metrics, [memory], report_channel=channel)
    rng = np.random.default_rng(7)
    a, b = rng.uniform(-1.0, 1.0, (2, STEPS, NUM_ENVS)).astype(np.float32)

    def rollout(theta, metrics_on):
        def body(carry, inputs):
            total, state = carry
            a_i, b_i, i = inputs
            reward = -((theta * a_i - b_i) ** 2)
            if metrics_on:
                state = metrics.update(state, reward, jnp.ones(NUM_ENVS, jnp.bool_))
                state = metrics.log(state, {"step_reward": jnp.mean(reward)})
                state = logger.emit(state, i, i % PERIOD == PERIOD - 1)
            return (total + jnp.mean(reward), state), None

        init = (jnp.zeros((), jnp.float32), metrics.init(NUM_ENVS))
        return jax.lax.scan(body, init, (a, b, jnp.arange(STEPS)))[0][0]

    theta = jnp.float32(0.7)
    value, grad = jax.jit(jax.value_and_grad(lambda t: rollout(t, True)))(theta)
    want_value, want_grad = jax.jit(jax.value_and_grad(lambda t: rollout(t, False)))(theta)
    logger.close()
    np.testing.assert_array_equal([value, grad], [want_value, want_grad])

    # Reference: float64, the derivative by hand.
    a64, b64, t64 = a.astype(np.float64), b.astype(np.float64), np.float64(np.float32(0.7))
    rewards = -((t64 * a64 - b64) ** 2)
    np.testing.assert_allclose(
        grad, np.sum(np.mean(-2 * a64 * (t64 * a64 - b64), axis=1)), rtol=1e-5
    )
    ends = list(range(PERIOD - 1, STEPS, PERIOD))
    assert [r.step for r in memory.records] == ends
    for record, e in zip(memory.records, ends):
        period = rewards[e - PERIOD + 1 : e + 1]
        assert record.scalars["Episode_Metrics/reward/count"] == PERIOD * NUM_ENVS
        np.testing.assert_allclose(
            record.scalars["Episode_Metrics/reward"], period.mean(), rtol=1e-5
        )
        np.testing.assert_allclose(record.scalars["Train/step_reward"], period.mean(), rtol=1e-5)


@pytest.mark.parametrize("channel", ["io_callback", "ring"])
def test_emit_of_a_state_that_carries_a_tangent_reports_its_primal_values(channel):
    # A training carry differentiated as a whole (jax.jvp over it) hands emit a state whose
    # float arrays carry tangents: the io_callback refused it ("IO callbacks do not
    # support JVP").
    metrics = jm.Metrics(logged=["x"])
    memory = jm.MemoryWriter()
    logger = jm.Logger(metrics, [memory], report_channel=channel)
    values = np.array([1.5, -2.0, 4.25], np.float32)
    state = jax.jit(lambda: metrics.log(metrics.init(1), {"x": jnp.asarray(values)}))()

    def tangent(a):
        if jnp.issubdtype(a.dtype, jnp.floating):
            return jnp.ones_like(a)
        return np.zeros(a.shape, jax.dtypes.float0)

    def step(s, t):
        return jax.jvp(lambda s: logger.emit(s, 3, jnp.bool_(True)), (s,), (t,))[0]

    out = jax.jit(step)(state, jax.tree.map(tangent, state))
    logger.close()
    (record,) = memory.records
    assert record.step == 3 and record.scalars["Train/x/count"] == 3
    np.testing.assert_allclose(
        record.scalars["Train/x"], np.mean(values, dtype=np.float64), rtol=1e-6
    )
    assert record.scalars["Train/x/max"] == 4.25
    # The period was reset, as an emit outside jvp resets it.
    reset = metrics.reset_period(state)
    jax.tree.map(np.testing.assert_array_equal, out, reset)
