"""A fresh `MetricsState` of a spec, and trees shaped like it (the state's shardings)."""

from typing import Any

import jax
import jax.numpy as jnp

from . import _count, _episode, _stream
from ._metrics_state import MetricsState
from ._rows import SpecRows


def fresh(rows: SpecRows, num_envs: int, shards: int, ema_history: bool = False) -> MetricsState:
    """A zero state of `num_envs` envs in `shards` env shards; `ema_history` keeps each EMA
    row's newest values even with one shard, for a state that will be merged with other
    devices' (one per device under `pmap`), as a sharded state keeps them."""
    ep_plan = rows.ep_plan
    has_ep = ep_plan is not None
    n_counters = len(rows.stored_counters)

    def per_shard(x: jax.Array) -> jax.Array:
        return jnp.broadcast_to(x, (shards, *x.shape))

    return MetricsState(
        running=_episode.init(rows.episode_plan, num_envs) if has_ep else None,
        finished=jax.tree.map(per_shard, _stream.init(ep_plan, ema_history or shards > 1))
        if has_ep
        else None,
        shard_counts=_count.zeros((shards, _stream.counts_width(ep_plan, len(rows.shard_counters))))
        if has_ep
        else None,
        logged=_stream.init(rows.lg_plan) if rows.lg_plan else None,
        counters=_count.zeros((n_counters,)) if n_counters else None,
        spec=rows.identity,
    )


def per_field(rows: SpecRows, running: Any, per_shard: Any, replicated: Any) -> MetricsState:
    """A MetricsState-shaped tree whose leaves are `running` for the running episodes,
    `per_shard` for the finished-episode statistics and shard counts, and `replicated` for
    logged values and counters."""

    def fill(tree: Any, v: Any) -> Any:
        return jax.tree.map(lambda _: v, tree)

    shapes = jax.eval_shape(lambda: fresh(rows, 0, 2))
    return shapes._replace(
        running=fill(shapes.running, running),
        finished=fill(shapes.finished, per_shard),
        shard_counts=fill(shapes.shard_counts, per_shard),
        logged=fill(shapes.logged, replicated),
        counters=fill(shapes.counters, replicated),
    )
