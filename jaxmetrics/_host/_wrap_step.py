"""A plain step-function wrapper for raw MJX (or any JAX) loops: no Brax needed."""

from collections.abc import Callable
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp

from .._core._metrics import Metrics
from ._wrapper_reporter import Reporter


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


class WrappedStep:
    """A step function that also folds a `Metrics` spec (and reports, given a Logger):
    what `wrap_step` returns.

    Call it as `(carry, action) -> (carry, obs, reward, done)` where its carry is
    `(your_carry, metrics_state)`, or `(your_carry, metrics_state, clock)` for a
    reporting one; `init(your_carry, num_envs)` makes the first carry of either kind.
    """

    def __init__(
        self,
        step: Callable[[Any, Any], tuple[Any, Any, Any, Any]],
        metrics: Metrics,
        reporter: Reporter | None,
    ):
        self.step, self.metrics, self.reporter = step, metrics, reporter
        self._width = 2 if reporter is None else 3

    def init(self, carry: Any, num_envs: int) -> tuple[Any, ...]:
        """The first carry: `(carry, metrics.init(num_envs))`, plus the period's step
        count (int32, 0) for a reporting step. Call it where you reset your envs (inside
        your `pmap` when the envs are split over its axis)."""
        if self.reporter is None:
            return (carry, self.metrics.init(num_envs))
        return (carry, self.reporter.init(num_envs), jnp.zeros((), jnp.int32))

    def __call__(self, carry: tuple[Any, ...], action: Any) -> tuple[Any, Any, Any, Any]:
        if not isinstance(carry, tuple) or len(carry) != self._width:
            shape = (
                "pair (carry, metrics_state)"
                if self.reporter is None
                else "triple (carry, metrics_state, clock)"
            )
            raise TypeError(
                f"the wrapped step's carry must be the {shape}; start from "
                "wrapped.init(carry, num_envs)."
            )
        prev, mstate = carry[0], carry[1]
        out = self.step(prev, action)
        if not isinstance(out, tuple) or len(out) != 4:
            raise TypeError(
                "wrap_step: step(carry, action) must return the 4-tuple "
                f"(carry, obs, reward, done), got {type(out).__name__}"
                f"{f' of length {len(out)}' if isinstance(out, tuple) else ''}."
            )
        new, obs, reward, done = out
        t = Transition(prev_carry=prev, carry=new, action=action, obs=obs, reward=reward, done=done)
        mstate = self.metrics.update(mstate, t, done)
        if self.reporter is None:
            return (new, mstate), obs, reward, done
        mstate, clock = self.reporter(mstate, carry[2], jnp.shape(done)[0], 1)
        return (new, mstate, clock), obs, reward, done


def wrap_step(
    step: Callable[[Any, Any], tuple[Any, Any, Any, Any]],
    metrics: Metrics,
    logger: Any = None,
    report_every: int | None = None,
    axis_name: str | None = None,
) -> WrappedStep:
    """Wraps `step(carry, action) -> (carry, obs, reward, done)` to also fold `metrics`.

    The returned function has the same signature with `(carry, metrics_state)` as its
    carry: `((carry, metrics_state), action) -> ((carry, metrics_state), obs, reward,
    done)`. It calls `metrics.update` once per step with a `jaxmetrics.Transition` and
    the returned `done` (`[num_envs]`). Start with `wrapped.init(carry, num_envs)`, which
    is `(carry, metrics.init(num_envs))`.

    With a `logger`, the step reports by itself: its carry is `(carry, metrics_state,
    clock)` (`wrapped.init` makes it), and every `report_every` env steps it hands the
    report (at step `Counters/env_steps`) to the logger and resets the period, in-graph,
    from inside whatever jitted, scanned or vmapped loop calls it (under `vmap` over
    seeds, seed `i` goes to the logger's run `i`). Close the logger at the end.

    Args:
      step: your batched step function (e.g. `jax.vmap` of `mjx.step` plus your reward
        and done).
      metrics: the metrics spec; its terms receive a `jaxmetrics.Transition`.
      logger: a `jaxmetrics.Logger` of `metrics`, to report by itself; None: fold only.
      report_every: the period in env steps over all envs (and devices); None: every 100
        steps of the batch.
      axis_name: the `pmap`/`shard_map` axis your envs are split over, if any: the
        devices' statistics are merged at each report (not on other steps) and one
        report is written for all envs.

    Returns:
      The wrapped step function (un-jitted, pure), with `init(carry, num_envs)`.

    Examples:
      >>> import jax, jax.numpy as jnp, jaxmetrics as jm
      >>> def step(x, a):                      # 2 envs; an episode ends when x >= 2
      ...     x = x + a
      ...     return x, x, -jnp.abs(a), x >= 2.0
      >>> metrics = jm.Metrics(terms={"return": jm.Term(lambda t: t.reward, reduce="sum")})
      >>> wrapped = jm.wrap_step(step, metrics)
      >>> carry = wrapped.init(jnp.zeros(2), num_envs=2)
      >>> for a in ([1.0, 0.5], [1.0, 0.5]):
      ...     carry, obs, reward, done = jax.jit(wrapped)(carry, jnp.array(a))
      >>> metrics.to_host(metrics.compute(carry[1]))["Episode_Metrics/return"]
      -2.0

      Reporting by itself, from inside one jitted scan:

      >>> memory = jm.MemoryWriter()
      >>> with jm.Logger(metrics, [memory]) as logger:
      ...     wrapped = jm.wrap_step(step, metrics, logger=logger, report_every=4)
      ...     def run(carry):
      ...         body = lambda c, a: (wrapped(c, a)[0], None)
      ...         return jax.lax.scan(body, carry, jnp.full((4, 2), 1.0))[0]
      ...     _ = jax.jit(run)(wrapped.init(jnp.zeros(2), num_envs=2))
      >>> [(r.step, r.scalars["Episode_Metrics/return/count"]) for r in memory.records]
      [(4, 2), (8, 4)]
    """
    if not callable(step):
        raise TypeError(f"wrap_step(step=...) must be a function, got {step!r}.")
    if not isinstance(metrics, Metrics):
        raise TypeError(
            f"wrap_step(metrics=...) must be a jaxmetrics.Metrics, got {type(metrics).__name__}."
        )
    reporter = (
        None if logger is None else Reporter(metrics, logger, report_every, axis_name, "wrap_step")
    )
    return WrappedStep(step, metrics, reporter)
