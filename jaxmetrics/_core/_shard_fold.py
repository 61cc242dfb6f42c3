"""A step's finished episodes folded shard by shard: the batch `[M, E]` split into the
state's env shards (`[S, M, E/S]`, shard s the s-th block of envs) and each shard folded by
`_stream.add_with_counts` into its own accumulators and counters, with no collective.

Where the trace knows the devices' axes of the shards (`_sharding.shard_axes`), each device
folds its shard on its own inside `jax.shard_map`: the program says that a step moves
nothing between devices, where a batch of shards (`vmap`) leaves the partitioning to XLA.
Where the trace cannot tell the axes, the shards are folded as that batch."""

from collections.abc import Sequence
from typing import Any

import jax
import jax.numpy as jnp

from . import _stream
from ._inputs import Segments
from ._spec import Groups


def shard_counters(done: jax.Array, group_ids: Sequence[jax.Array], groupings: Sequence[Groups]):
    """Per env, what each shard counts (`_rows.SHARD_COUNTERS`): the step, an ended episode
    and, with groupings, how many of its group indices are out of range; `[C, E]`, uint8
    where that holds the count (an int32 `[C, E]` array costs bandwidth at many envs)."""
    counts = [jnp.ones_like(done), done]
    if group_ids:
        out_of_range = [
            done & ((i < 0) | (i >= len(g.names))) for g, i in zip(groupings, group_ids)
        ]
        counts.append(jnp.sum(jnp.stack(out_of_range), axis=0, dtype=jnp.int32))
    narrow = jnp.uint8 if len(groupings) < 256 else jnp.int32
    return jnp.stack([c.astype(narrow) for c in counts])


def fold_shards(
    plan: _stream.StreamPlan,
    segments_plan: _stream.SegmentPlan | None,
    finished: Any,
    shard_counts: Any,
    rows: _stream.Selected,
    counted: jax.Array,
    segments: Segments | None,
    axes: tuple[str, ...] | None,
) -> tuple[Any, Any]:
    """`(finished, shard_counts)` with this step's rows `[M, E]` (and segment sources, and
    per-env counts `[C, E]`) folded into each of the state's shards: `finished` and
    `shard_counts` carry a leading shard axis. `axes`: the mesh axes the shards lie on
    (`_sharding.shard_axes`), or None where the trace does not know them."""
    shards = jax.tree.leaves(shard_counts)[0].shape[0]
    num_envs = counted.shape[-1]

    def by_shard(a: jax.Array) -> jax.Array:
        # [M, E] -> [S, M, E/S]: with the env axis split over devices in S blocks this is
        # a local view, and everything below reduces within a shard only.
        return jnp.moveaxis(a.reshape(a.shape[0], shards, num_envs // shards), 1, 0)

    def fold(st, b, t, e, g):
        with_segments = None
        if g is not None:
            assert segments_plan is not None  # `g`: the segment sources' batch
            with_segments = (segments_plan, g)
        return _stream.add_with_counts(plan, st, b, t, e, segments=with_segments)

    def one_shard(*args):
        # A vmap of size 1 would still batch the fold's scatters: the shard is folded as
        # it is.
        first = jax.tree.map(lambda a: a[0], args)
        return jax.tree.map(lambda a: a[None], fold(*first))

    args = (
        finished,
        rows.arrays(by_shard),
        by_shard(counted),
        shard_counts,
        None if segments is None else tuple(by_shard(a) for a in segments),
    )
    if shards == 1:
        return one_shard(*args)
    if axes is not None:
        # No collective: every input and output is split over `axes` on its shard axis.
        spec = jax.sharding.PartitionSpec(axes)
        return jax.shard_map(one_shard, in_specs=spec, out_specs=spec)(*args)
    return jax.vmap(fold)(*args)
