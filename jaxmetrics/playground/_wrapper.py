"""MuJoCo Playground envs in Playground's own training stack, with `MetricsWrapper`
in place of Brax's `EpisodeWrapper`.

Playground's `wrapper.wrap_for_brax_training` builds
`BraxAutoResetWrapper(EpisodeWrapper(VmapWrapper(env)))` from Brax's `EpisodeWrapper`
and `VmapWrapper` and its own auto-reset; `wrap` builds the same stack around
`jaxmetrics.brax.MetricsWrapper`, which is Brax's `EpisodeWrapper` plus the fold
(its bookkeeping works on Playground's `State` as on Brax's: both are dataclasses with
`obs`, `reward`, `done`, `metrics` and `info`).
"""

from collections.abc import Callable
from typing import Any

import jax
from brax.envs.wrappers import training as brax_training
from mujoco_playground import MjxEnv
from mujoco_playground import wrapper as playground_wrapper

from .._core._metrics import Metrics
from ..brax._on_reset import OnReset
from ..brax._wrapper import BRAX_AXIS, MetricsWrapper


def _check_env(env: Any) -> None:
    if not isinstance(env, MjxEnv):
        raise TypeError(
            f"jaxmetrics.playground.wrap: env must be a MuJoCo Playground MjxEnv (e.g. "
            f"mujoco_playground.registry.load('CartpoleBalance')), got {type(env).__name__}; "
            "for a Brax env use jaxmetrics.brax.wrap."
        )
    e = env
    while isinstance(e, (playground_wrapper.Wrapper, brax_training.Wrapper)):
        if isinstance(
            e,
            (
                MetricsWrapper,
                brax_training.EpisodeWrapper,
                brax_training.VmapWrapper,
                playground_wrapper.BraxAutoResetWrapper,
                playground_wrapper.BraxDomainRandomizationVmapWrapper,
            ),
        ):
            raise ValueError(
                f"jaxmetrics.playground.wrap: env is already wrapped for training "
                f"({type(e).__name__} inside); pass the unwrapped env "
                "(mujoco_playground.registry.load(name)): wrap builds the whole stack, as "
                "wrapper.wrap_for_brax_training does."
            )
        e = e.env


def wrap(
    env: MjxEnv,
    metrics: Metrics,
    episode_length: int = 1000,
    action_repeat: int = 1,
    randomization_fn: Callable[..., Any] | None = None,
    full_reset: bool = False,
    sharding: jax.sharding.Sharding | None = None,
    logger: Any = None,
    report_every: int | None = None,
    axis_name: str | None = BRAX_AXIS,
    on_reset: OnReset | None = None,
) -> playground_wrapper.Wrapper:
    """`mujoco_playground.wrapper.wrap_for_brax_training` with metrics.

    Builds `BraxAutoResetWrapper(MetricsWrapper(VmapWrapper(env), metrics,
    episode_length, action_repeat))` (`BraxDomainRandomizationVmapWrapper` when
    `randomization_fn` is given): Playground's stack, info keys and auto-reset (to the
    cached first state), with the same signature plus `metrics`. Terms receive a
    `jaxmetrics.playground.Transition` on every sub-step (each of the `action_repeat`
    inner steps of an env step); its `state` is Playground's `State`, whose `data` is the
    `mjx.Data` (`t.state.data.qvel`) and whose `metrics` hold the reward components.
    On the terminal step terms see the terminal state, before the auto-reset.

    For Brax's PPO (what Playground's `learning/train_jax_ppo.py` runs):
    `ppo.train(..., wrap_env_fn=functools.partial(jaxmetrics.playground.wrap,
    metrics=metrics, logger=logger))` reports every period while training runs.

    Args:
      env: an unwrapped Playground env, e.g. `registry.load("CartpoleBalance")`.
      metrics: the metrics spec.
      episode_length: the time limit, in sub-steps (env steps x `action_repeat`).
      action_repeat: inner env steps per env step; terms are evaluated on each.
      randomization_fn: as in Playground: makes a vectorized model and its in_axes.
      full_reset: must be False (Playground's default). Playground's full reset maps
        `where(done, reset, current)` over every `State.info` leaf as if it had an env
        axis; the MetricsState kept there has none.
      sharding: the env batch's sharding when envs are split over devices (see
        `jaxmetrics.brax.wrap`).
      logger: a `jaxmetrics.Logger` of `metrics`: the env reports by itself every
        `report_every` env steps, also inside Brax's trainer (see
        `jaxmetrics.brax.MetricsWrapper`). None: fold only.
      report_every: the period in env steps over all envs and devices; None: every 100
        env steps of the batch.
      axis_name: the `pmap` axis of the trainer's devices (Brax's: "i").
      on_reset: `on_reset(read, state) -> state`: sets up the envs that begin an
        episode from live statistics, e.g. a curriculum level in `state.info` (see
        `jaxmetrics.brax.MetricsWrapper` and docs/curriculum.md).

    Returns:
      The wrapped env; `reset` takes one key per env (`[num_envs, 2]`).

    Raises:
      TypeError: `env` is not a Playground `MjxEnv`.
      ValueError: `env` is already wrapped for training, or `full_reset=True`.
    """
    _check_env(env)
    if full_reset is not False:
        raise ValueError(
            "jaxmetrics.playground.wrap(full_reset=True) is not supported: Playground's full "
            "reset overwrites every State.info leaf of the envs that are done, which would "
            "corrupt the MetricsState kept in State.info. Use full_reset=False (the default: "
            "envs reset to their cached first state)."
        )
    # Playground's envs go through Brax's wrappers by duck typing (as in Playground's own
    # wrap_for_brax_training).
    if randomization_fn is None:
        batched = brax_training.VmapWrapper(env)  # pyright: ignore[reportArgumentType]
    else:
        batched = playground_wrapper.BraxDomainRandomizationVmapWrapper(env, randomization_fn)
    return playground_wrapper.BraxAutoResetWrapper(
        MetricsWrapper(
            batched,  # pyright: ignore[reportArgumentType]
            metrics,
            episode_length,
            action_repeat,
            sharding,
            logger=logger,
            report_every=report_every,
            axis_name=axis_name,
            on_reset=on_reset,
        )
    )
