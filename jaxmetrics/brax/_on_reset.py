"""`on_reset`: the envs that begin an episode set up from live statistics (curricula).

A wrapper's `on_reset(read, state) -> state` is written for the whole batch; what it
returns is kept for the envs that begin an episode only, so a rule needs no `where` of
its own. `read` is `Metrics.read` of the live statistics: under a trainer's device axis
those of every device, gathered on each step (what the statistics read merge from).
"""

import functools
from collections.abc import Callable
from typing import Any

import jax
import jax.numpy as jnp

from .._core._metrics import Metrics
from .._core._metrics_state import MetricsState
from .._host._wrapper_reporter import axis_size, gathered

OnReset = Callable[[Callable[..., jax.Array], Any], Any]
"""`on_reset(read, state) -> state`."""


def check(on_reset: Any) -> OnReset | None:
    """`on_reset` as a wrapper takes it (None: none), or a TypeError naming the fix."""
    if on_reset is not None and not callable(on_reset):
        raise TypeError(
            f"MetricsWrapper(on_reset=...) must be a function (read, state) -> state, got "
            f"{on_reset!r}."
        )
    return on_reset


def begin(
    on_reset: OnReset,
    metrics: Metrics,
    axis_name: str | None,
    mstate: MetricsState,
    state: Any,
    begins: jax.Array,
) -> Any:
    """`state` with `on_reset`'s result for the envs that `begins` (bool `[num_envs]`),
    reading `mstate` (merged over `axis_name` where that axis has several devices)."""
    live = mstate
    if (axis_size(axis_name) or 1) > 1:
        assert axis_name is not None  # an axis of more than one device
        live = gathered(mstate, axis_name)
    new = on_reset(functools.partial(metrics.read, live), state)
    return _kept_where(begins, new, state)


def _kept_where(begins: jax.Array, new: Any, old: Any) -> Any:
    """`new` for the envs that `begins`, `old` for the others, leaf by leaf; a leaf that
    `on_reset` returned unchanged costs nothing."""
    new_leaves, new_def = jax.tree.flatten_with_path(new)
    old_leaves, old_def = jax.tree.flatten_with_path(old)
    if new_def != old_def:
        raise ValueError(
            "MetricsWrapper(on_reset=...) must return the env state it was given with the "
            "same structure (change values, e.g. state.replace(info={**state.info, "
            "'level': level})); it returned another structure: "
            f"{new_def} instead of {old_def}."
        )
    n = begins.shape[0]
    out = []
    for (path, x), (_, y) in zip(new_leaves, old_leaves):
        if x is y:
            out.append(y)
            continue
        x, y = jnp.asarray(x), jnp.asarray(y)
        if x.shape != y.shape or x.shape[:1] != (n,):
            raise ValueError(
                f"MetricsWrapper(on_reset=...) returned state{jax.tree_util.keystr(path)} of "
                f"shape {x.shape} where the env state has {y.shape}; on_reset works on the "
                f"batched state: every leaf keeps its shape, with the {n} envs first."
            )
        keep = begins.reshape((n,) + (1,) * (y.ndim - 1))
        out.append(jnp.where(keep, x.astype(y.dtype), y))
    return jax.tree.unflatten(old_def, out)
