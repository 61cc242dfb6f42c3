"""Checkpoints of a `MetricsState`, restored into a target of the same or another number
of devices.

Orbax refuses zero-size arrays, so the statistics a spec does not keep are saved as None
and restored from a fresh state. A checkpoint also records its layout (env shards, envs):
orbax's `restore(..., strict=False)` cuts or pads every array to the target's shape, and
the shapes alone would not tell such a restore from a checkpoint of the target's layout.

A state of S env shards restores exactly into a target of T: its shards are merged in
shard order (the merge `compute` does) and that one stream becomes the target's first
shard, the others empty from its arrival step on. A merge with empty shards is the
identity, and every value that arrives later comes after all of the restored ones, so
each report equals the one the saved layout would have made.
"""

from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from . import _count, _fresh, _stream
from ._count import Count
from ._metrics_state import MetricsState
from ._rows import SpecRows


class MetricsCheckpoint(NamedTuple):
    """A `MetricsState` as saved (`Metrics.to_checkpoint`): its zero-size arrays as None,
    and the layout it was saved in.

    Attributes:
      state: the state, with None for each zero-size array.
      layout: int32 `[2]`: its env shards (1 unsharded, one per device of the env axis
        when sharded) and its envs.
    """

    state: MetricsState
    layout: jax.Array


def layout(state: MetricsState) -> tuple[int, int]:
    """`(env shards, envs)` of `state`, whose zero-size arrays may be None."""
    shards = state.shard_counts.hi if state.shard_counts is not None else None
    steps = state.running.steps if state.running is not None else None
    return (
        0 if shards is None else int(np.shape(shards)[0]),
        0 if steps is None else int(np.shape(steps)[-1]),
    )


def _without_empty(tree: Any) -> Any:
    return jax.tree.map(lambda x: None if np.size(x) == 0 else x, tree)


def _ring_widths(state: MetricsState) -> tuple[int, ...]:
    """Per EMA group, how many newest values the state keeps (None counts as 0)."""
    if state.finished is None:
        return ()
    return tuple(
        0 if r.data is None else int(np.shape(r.data)[-2]) for r in state.finished.ema_rings
    )


def to_checkpoint(state: MetricsState) -> MetricsCheckpoint:
    """`state` as saved (see `Metrics.to_checkpoint`)."""
    return MetricsCheckpoint(_without_empty(state), jnp.asarray(layout(state), jnp.int32))


def target(rows: SpecRows, num_envs: int, shards: int) -> MetricsCheckpoint:
    """The restore target of a checkpoint of `shards` env shards of `num_envs` envs, on
    the default device (see `Metrics.checkpoint_target`)."""
    return to_checkpoint(_fresh.fresh(rows, num_envs, shards))


def _described(shards: int, envs: int) -> str:
    return f"{envs} envs in {shards} env shard{'s' if shards != 1 else ''}"


def from_checkpoint(rows: SpecRows, saved: Any, target: MetricsState) -> MetricsState:
    """`saved` (`to_checkpoint`'s tree, or a whole state as flax.serialization restores
    it) laid out like `target`, or an error naming what does not match (see
    `Metrics.from_checkpoint`)."""
    recorded = None
    if isinstance(saved, MetricsCheckpoint):
        saved, recorded = saved.state, tuple(int(v) for v in np.asarray(saved.layout))
    if not isinstance(saved, MetricsState):
        raise ValueError(
            f"from_checkpoint: the saved tree ({type(saved).__name__}) is not the "
            "MetricsCheckpoint that to_checkpoint gives, nor a MetricsState. Restore the "
            "checkpoint with its target, e.g. orbax's ckpt.restore(path, "
            "metrics.to_checkpoint(metrics.init(num_envs))), or "
            "metrics.checkpoint_target(num_envs, shards) for one of another device count."
        )
    shards, envs = layout(saved)
    saved_shards, saved_envs = recorded or (shards, envs)
    t_shards, t_envs = layout(target)
    if saved_envs != t_envs or (t_shards == 0 and saved_shards != 0):
        raise ValueError(
            f"from_checkpoint: the checkpoint is of {_described(saved_shards, saved_envs)}, "
            f"but the target is of {_described(t_shards, t_envs)}. The running episodes "
            f"belong to their envs: restore into init({saved_envs}) (with any sharding of "
            f"{saved_envs} envs)."
        )
    if (saved_shards, saved_envs) != (shards, envs):
        raise ValueError(
            f"from_checkpoint: the checkpoint holds a state of "
            f"{_described(saved_shards, saved_envs)}, but its arrays came back as "
            f"{_described(shards, envs)}: it was restored against a target of another "
            "layout (orbax's restore with strict=False cuts or pads arrays to the target's "
            "shapes). Restore it against its own layout, ckpt.restore(path, "
            f"metrics.checkpoint_target({saved_envs}, shards={saved_shards})), and pass that "
            f"here: it is then laid out exactly as the target, {_described(t_shards, t_envs)}."
        )
    template = _fresh.fresh(rows, envs, shards, ema_history=any(_ring_widths(saved)))
    want = _without_empty(template)
    if jax.tree.structure(_without_empty(saved)) != jax.tree.structure(want):
        raise ValueError(
            f"from_checkpoint: the saved tree is not a state of this spec of "
            f"{_described(shards, envs)}. Restore the checkpoint with its target, e.g. "
            f"orbax's ckpt.restore(path, metrics.checkpoint_target({envs}, shards={shards}))."
        )
    for (path, x), y in zip(
        jax.tree_util.tree_leaves_with_path(_without_empty(saved)), jax.tree.leaves(want)
    ):
        if np.shape(x) != y.shape or jnp.result_type(x) != y.dtype:
            raise ValueError(
                f"from_checkpoint: {jax.tree_util.keystr(path)} is "
                f"{jnp.result_type(x)}{list(np.shape(x))}, but a state of this spec of "
                f"{_described(shards, envs)} has {y.dtype}{list(y.shape)}: restore the "
                "checkpoint of the spec it was saved with."
            )
    it = iter(jax.tree.leaves(_without_empty(saved)))
    leaves = [x if x.size == 0 else next(it) for x in jax.tree.leaves(template)]
    full = jax.tree.unflatten(jax.tree.structure(template), leaves)
    widths = _ring_widths(target)
    if (shards, _ring_widths(full)) != (t_shards, widths):
        plan = rows.ep_plan
        assert plan is not None  # env shards are kept only for a spec with episode terms
        full = jax.jit(lambda s: _relayout(plan, s, t_shards, widths))(full)
    # Host arrays (flax restores numpy) become JAX arrays, on the target's devices.
    return jax.device_put(full, jax.tree.map(lambda x: x.sharding, target))


def _relayout(
    plan: _stream.StreamPlan, state: MetricsState, shards: int, widths: tuple[int, ...]
) -> MetricsState:
    """`state` with its env shards merged into one and spread over `shards`, its EMA rings
    `widths` wide (in-graph)."""
    assert state.finished is not None and state.shard_counts is not None
    one = _stream.with_ema_history(plan, _stream.combine(plan, state.finished), widths)
    total = _count.total(state.shard_counts)
    empty = _count.zeros((shards - 1, *total.hi.shape))
    return state._replace(
        finished=_stream.spread(plan, one, shards),
        shard_counts=Count(*(jnp.concatenate([t[None], e]) for t, e in zip(total, empty))),
    )
