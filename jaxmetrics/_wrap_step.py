"""A plain step-function wrapper for raw MJX (or any JAX) loops: no Brax needed."""

from collections.abc import Callable
from typing import Any, NamedTuple

import jax

from ._metrics import Metrics


class Transition(NamedTuple):
    """What a term sees on each step of a `wrap_step` loop.

    Attributes:
      prev_carry: your carry before the step (e.g. a batched `mjx.Data`).
      carry: your carry after the step, as your `step` returned it. If your loop
        auto-resets, reset *after* the wrapped step, so that terms see the terminal
        state of each episode.
      action: the action passed in.
      obs: the observation your `step` returned.
      reward: the reward your `step` returned, `[num_envs]`.
      done: the done flags your `step` returned, `[num_envs]`: the episode ends on this
        step (it is part of that episode).
    """

    prev_carry: Any
    carry: Any
    action: Any
    obs: Any
    reward: jax.Array
    done: jax.Array


def wrap_step(
    step: Callable[[Any, Any], tuple[Any, Any, Any, Any]], metrics: Metrics
) -> Callable[[Any, Any], tuple[Any, Any, Any, Any]]:
    """Wraps `step(carry, action) -> (carry, obs, reward, done)` to also fold `metrics`.

    The returned function has the same signature with `(carry, metrics_state)` as its
    carry: `((carry, metrics_state), action) -> ((carry, metrics_state), obs, reward,
    done)`. It calls `metrics.update` once per step with a `jaxmetrics.Transition` and
    the returned `done` (`[num_envs]`). Start with `(carry, metrics.init(num_envs))`.

    Args:
      step: your batched step function (e.g. `jax.vmap` of `mjx.step` plus your reward
        and done).
      metrics: the metrics spec; its terms receive a `jaxmetrics.Transition`.

    Returns:
      The wrapped step function (un-jitted, pure).

    Examples:
      >>> import jax, jax.numpy as jnp, jaxmetrics as jm
      >>> def step(x, a):                      # 2 envs; an episode ends when x >= 2
      ...     x = x + a
      ...     return x, x, -jnp.abs(a), x >= 2.0
      >>> metrics = jm.Metrics(terms={"return": jm.Term(lambda t: t.reward, reduce="sum")})
      >>> wrapped = jax.jit(jm.wrap_step(step, metrics))
      >>> carry = (jnp.zeros(2), metrics.init(2))
      >>> for a in ([1.0, 0.5], [1.0, 0.5]):
      ...     carry, obs, reward, done = wrapped(carry, jnp.array(a))
      >>> metrics.to_host(metrics.compute(carry[1]))["Episode_Metrics/return"]
      -2.0
    """
    if not callable(step):
        raise TypeError(f"wrap_step(step=...) must be a function, got {step!r}.")
    if not isinstance(metrics, Metrics):
        raise TypeError(
            f"wrap_step(metrics=...) must be a jaxmetrics.Metrics, got {type(metrics).__name__}."
        )

    def wrapped(carry: tuple[Any, Any], action: Any) -> tuple[Any, Any, Any, Any]:
        if not isinstance(carry, tuple) or len(carry) != 2:
            raise TypeError(
                "the wrapped step's carry must be the pair (carry, metrics_state); start "
                "from (carry, metrics.init(num_envs))."
            )
        prev, mstate = carry
        out = step(prev, action)
        if not isinstance(out, tuple) or len(out) != 4:
            raise TypeError(
                "wrap_step: step(carry, action) must return the 4-tuple "
                f"(carry, obs, reward, done), got {type(out).__name__}"
                f"{f' of length {len(out)}' if isinstance(out, tuple) else ''}."
            )
        new, obs, reward, done = out
        t = Transition(prev_carry=prev, carry=new, action=action, obs=obs, reward=reward, done=done)
        return (new, metrics.update(mstate, t, done)), obs, reward, done

    return wrapped
