"""The loops of `train`'s three modes (see its `mode`): each iteration ends a flush
period, and several seeds are `vmap`-ed in one program."""

from collections.abc import Callable
from typing import Any

import jax
import jax.numpy as jnp

import jaxmetrics as jm

from ._algorithm import PPO, TrainState
from ._checkpoints import Checkpoints

MODES = ("host", "graph", "graph-history")


def _batched(fn: Callable[..., Any], runs: int) -> Callable[..., Any]:
    return jax.jit(fn if runs == 1 else jax.vmap(fn))


def init_states(ppo: PPO, keys: jax.Array, runs: int) -> TrainState:
    """The initial state of every run, stacked on a leading axis when `runs > 1`.

    One seed at a time, not vmapped: a vmapped init batches the orthogonal initializers'
    QR factorizations, which jaxlib's CPU LAPACK kernel (0.10) splits with a blocking
    ParallelBatchMap on XLA's own thread pool; on a 2-core machine both pool threads can
    end up waiting on each other, and the init hangs.
    """
    init = jax.jit(ppo.init)
    if runs == 1:
        return init(keys[0])
    return jax.tree.map(lambda *xs: jnp.stack(xs), *(init(k) for k in keys))


def train_host(
    ppo: PPO,
    logger: jm.Logger,
    state: TrainState,
    done: int,
    n: int,
    checkpoints: Checkpoints | None,
    every: int,
) -> TrainState:
    """Iterations `done` to `n` from `state`, a checkpoint every `every` and after the last."""
    spi = ppo.config.steps_per_iteration
    iteration = _batched(ppo.iteration, logger.runs)
    for i in range(done, n):
        state = iteration(state)
        state = state.with_metrics_state(logger.flush(state.metrics_state(), (i + 1) * spi))
        if checkpoints is not None and every and ((i + 1) % every == 0 or i + 1 == n):
            # The records up to this step are on disk before the checkpoint can exist: a
            # resume from it purges only records after it, so none can be missing.
            logger.wait()
            checkpoints.save((i + 1) * spi, state)
    return state


def train_graph(ppo: PPO, logger: jm.Logger, keys: jax.Array, n: int) -> TrainState:
    """`n` iterations in one jitted scan, each one's report streamed by `Logger.emit`."""
    spi = ppo.config.steps_per_iteration

    def run(state: TrainState, run_index: jax.Array) -> TrainState:
        def body(state: TrainState, _: None) -> tuple[TrainState, None]:
            state = ppo.iteration(state)
            step = state.iteration * jnp.int32(spi)
            mstate = logger.emit(state.metrics_state(), step, jnp.bool_(True), run=run_index)
            return state.with_metrics_state(mstate), None

        return jax.lax.scan(body, state, None, length=n)[0]

    runs = logger.runs
    run_indices = jnp.arange(runs, dtype=jnp.int32)
    state = init_states(ppo, keys, runs)
    args = (state, run_indices[0]) if runs == 1 else (state, run_indices)
    return jax.block_until_ready(_batched(run, runs)(*args))


def train_graph_history(ppo: PPO, logger: jm.Logger, keys: jax.Array, n: int) -> TrainState:
    """`n` iterations in one jitted scan that keeps their reports, written after it."""
    spi = ppo.config.steps_per_iteration

    def run(state: TrainState) -> tuple[TrainState, jm.History]:
        def body(carry: tuple[TrainState, jm.History], _: None) -> tuple[Any, None]:
            state, history = carry
            state = ppo.iteration(state)
            step = state.iteration * jnp.int32(spi)
            mstate, history = logger.record(state.metrics_state(), history, step, jnp.bool_(True))
            return (state.with_metrics_state(mstate), history), None

        carry = (state, logger.history_init(n))  # one record per iteration
        return jax.lax.scan(body, carry, None, length=n)[0]

    state, history = _batched(run, logger.runs)(init_states(ppo, keys, logger.runs))
    logger.write_history(history)
    return jax.block_until_ready(state)
