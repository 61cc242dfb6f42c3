"""`success_rate`: the standard success metric over finished episodes.

Isaac Lab's tasks log a `Metrics/success_rate` and its benchmark tooling stops training
on a window of it; curricula advance a level when a group's recent success passes a
threshold. Both want the same thing: the fraction of *finished* episodes that succeeded,
over the last n of them and as an EMA, per group where envs are grouped.
"""

from collections.abc import Callable, Sequence
from typing import Any

import jax
import jax.numpy as jnp

from . import _reductions
from ._spec import Groups, Stat, Term, ema, window
from ._validate import is_int


def success_rate(
    fn: Callable[..., Any],
    *,
    reduce: str = "last",
    window_size: int | None = 100,
    ema_coeff: float | None = 0.01,
    stats: Sequence[Stat] | None = None,
    groups: Groups | None = None,
) -> Term:
    """A per-episode success flag from a boolean `fn(step_input) -> [num_envs]`.

    Reduction "last" by default (success at the episode's final step); "max" is success
    at any step of the episode, "min" at every step, "mean" the fraction of its steps.
    Its report statistics are the success rate of the period (`mean`) with its episode
    count, over the newest `window_size` finished episodes (`window_mean`, with
    `window_count` for `Metrics.read`) and as an EMA: name the term "success_rate" for
    the tag Isaac Lab's tools look for (`<episode_prefix>/success_rate`; with
    `Metrics(episode_prefix="Metrics")` exactly `Metrics/success_rate`).

    Args:
      fn: the success flag of each env on each step, a bool array (e.g. a Brax
        `Transition`'s `t.state.info["success"]`, `distance < 0.05`).
      reduce: how an episode's flags make its success: "last", "max", "min" or "mean".
      window_size: episodes in the window (None: no window).
      ema_coeff: the EMA's coefficient (None: no EMA).
      stats: the report statistics instead of the above.
      groups: a `jaxmetrics.groups(...)`: the success rate is also kept per group.

    Examples:
      >>> import jax.numpy as jnp, jaxmetrics as jm
      >>> metrics = jm.Metrics(terms={"success_rate": jm.success_rate(lambda s: s > 0)})
      >>> state = metrics.init(num_envs=4)
      >>> state = metrics.update(state, jnp.array([1, 0, 2, 0]), jnp.ones(4, bool))
      >>> metrics.to_host(metrics.compute(state))["Episode_Metrics/success_rate/window_mean"]
      0.5
    """
    if not callable(fn):
        raise TypeError(f"success_rate(fn=...) must be a function of the step input, got {fn!r}.")
    if reduce not in _reductions.FLAG_REDUCTIONS:
        choices = [f"{r!r} ({says})" for r, says in _reductions.FLAG_REDUCTIONS.items()]
        raise ValueError(
            f"success_rate(reduce={reduce!r}): use {', '.join(choices[:-1])} or {choices[-1]}."
        )
    if stats is None:
        stats = ("mean", "count")
        if window_size is not None:
            if not is_int(window_size) or window_size < 1:
                raise ValueError(
                    f"success_rate(window_size={window_size!r}) must be a positive int "
                    "(episodes) or None."
                )
            stats += (window(window_size),)
        if ema_coeff is not None:
            stats += (ema(ema_coeff),)

    def flag(step_input: Any) -> jax.Array:
        v = jnp.asarray(fn(step_input))
        if v.dtype != jnp.bool_:
            raise TypeError(
                f"success_rate: fn returned {v.dtype}; return a bool array of shape "
                "[num_envs] (e.g. `distance < 0.05`)."
            )
        return v

    return Term(flag, reduce=reduce, stats=stats, groups=groups)
