"""Checkpoints of a `MetricsState`: orbax refuses zero-size arrays, so the statistics a
spec does not keep are saved as None and restored from a fresh state."""

import jax
import jax.numpy as jnp

from ._metrics_state import MetricsState


def to_checkpoint(state: MetricsState) -> MetricsState:
    """`state` with its zero-size arrays set to None (see `Metrics.to_checkpoint`)."""
    return jax.tree.map(lambda x: None if x.size == 0 else x, state)


def from_checkpoint(saved: MetricsState, target: MetricsState) -> MetricsState:
    """`saved` (from `to_checkpoint`) with its None leaves back as `target`'s zero-size
    arrays, or an error naming what does not match (see `Metrics.from_checkpoint`)."""
    want = to_checkpoint(target)
    if not isinstance(saved, MetricsState) or (
        jax.tree.structure(saved) != jax.tree.structure(want)
    ):
        raise ValueError(
            f"from_checkpoint: the saved tree ({type(saved).__name__}) is not the "
            "MetricsState that to_checkpoint(target) gives. Restore the checkpoint with "
            "its target, e.g. orbax's ckpt.restore(path, metrics.to_checkpoint("
            "metrics.init(num_envs))), with the spec, num_envs and sharding it was "
            "saved with."
        )
    for (path, x), y in zip(jax.tree_util.tree_leaves_with_path(saved), jax.tree.leaves(want)):
        if jnp.shape(x) != y.shape or jnp.result_type(x) != y.dtype:
            where = jax.tree_util.keystr(path)
            raise ValueError(
                f"from_checkpoint: {where} is {jnp.result_type(x)}{list(jnp.shape(x))}, "
                f"but the target has {y.dtype}{list(y.shape)}: pass init() of the spec, "
                "num_envs and sharding the checkpoint was made with."
            )
    it = iter(jax.tree.leaves(saved))
    leaves = [x if x.size == 0 else next(it) for x in jax.tree.leaves(target)]
    return jax.tree.unflatten(jax.tree.structure(target), leaves)
