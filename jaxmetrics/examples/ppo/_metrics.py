"""The run's metrics spec: the env's episode terms and the learner's logged values."""

from collections.abc import Sequence
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

import jaxmetrics as jm
import jaxmetrics.brax as jmb

LEARNER_METRICS = (
    "policy_loss",
    "value_loss",
    "entropy",
    "approx_kl",
    "clip_fraction",
    "explained_variance",
    "grad_norm",
    "learning_rate",
)
"""The learner's logged values (tags `Train/<name>`), one value per minibatch update
(`explained_variance`: one per iteration, over the whole batch; it turns negative once the
task is solved, see `explained_variance`)."""


def _term_stats(*extra: Any) -> tuple[Any, ...]:
    return ("mean", "std", "min", "max", "count", *extra)


def make_metrics(
    reward_components: Sequence[str] = (),
    other_state_metrics: Sequence[str] = (),
    action_size: int = 1,
    episode_length: int = 1000,
) -> jm.Metrics:
    """The PPO's metrics spec: episode, physical and learner metrics in one `Metrics`.

    Args:
      reward_components: Brax `State.metrics` names summed over each episode.
      other_state_metrics: Brax `State.metrics` names averaged over each episode.
      action_size: the env's action size (the control-effort histogram spans
        `[0, sqrt(action_size)]`, the range of the norm of an action in [-1, 1]).
      episode_length: the time limit (the episode-length histogram spans `[0, it]`).

    Returns:
      The spec. Episode terms: `episode_return`, `episode_length` (mean/std/min/max/count,
      a 100-episode window with p10/p50/p90), the given `State.metrics` entries,
      `joint_velocity` and `control_effort` (per-episode mean of the L2 norm of
      `qvel` / of the action; window and histogram). Logged: `LEARNER_METRICS`.

    Examples:
      >>> m = make_metrics(action_size=1)
      >>> "Episode_Metrics/control_effort/histogram" in {t.tag for t in m.tags}
      True
    """
    window = jm.window(100, percentiles=(10, 50, 90))
    terms: dict[str, Any] = {
        "episode_return": jmb.episode_return(stats=_term_stats(window)),
        "episode_length": jmb.episode_length(
            stats=_term_stats(window, jm.histogram(20, (0.0, float(episode_length))))
        ),
    }
    if reward_components:
        terms.update(jmb.state_metrics(list(reward_components), reduce="sum"))
    if other_state_metrics:
        terms.update(jmb.state_metrics(list(other_state_metrics), reduce="mean"))
    terms["joint_velocity"] = jm.Term(
        lambda t: jnp.linalg.norm(_qvel(t), axis=-1),
        stats=_term_stats(jm.window(100), jm.histogram(20, (0.0, 10.0))),
    )
    terms["control_effort"] = jmb.control_effort(
        stats=_term_stats(jm.window(100), jm.histogram(20, (0.0, float(np.sqrt(action_size)))))
    )
    per_update = jm.Logged(stats=("mean", "std", "min", "max"))
    logged = {name: per_update for name in LEARNER_METRICS}
    logged["explained_variance"] = jm.Logged(stats=("mean",))  # one value per iteration
    return jm.Metrics(terms=terms, logged=logged, counters=("updates",))


def _qvel(t: jmb.Transition) -> jax.Array:
    """The generalized velocity: Playground's `State.data.qvel`, Brax's `pipeline_state.qd`."""
    data = getattr(t.state, "data", None)
    if data is not None:
        return data.qvel
    assert t.state.pipeline_state is not None  # every Brax backend's env has one
    return t.state.pipeline_state.qd
