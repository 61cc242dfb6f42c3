"""Ready-made terms over a `jaxmetrics.brax.Transition`, each a `jaxmetrics.Term`.

Every helper states its default episode reduction; all take `stats` (report statistics,
default `jaxmetrics.Term`'s) and `nonfinite` as `Term` does.
"""

from collections.abc import Callable, Mapping, Sequence
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from .._core import _reductions
from .._core._spec import DEFAULT_STATS, Stat, Term
from .._core._validate import is_int
from ._wrapper import Transition


def episode_return(*, stats: Sequence[Stat] = DEFAULT_STATS, nonfinite: str | None = None) -> Term:
    """The undiscounted return: `state.reward` summed over every sub-step of the episode.

    Reduction "sum". Equals Brax's `info['episode_metrics']['sum_reward']` at episode end.

    Examples:
      >>> import jaxmetrics.brax as jmb
      >>> jmb.episode_return().reduce
      'sum'
    """
    return Term(lambda t: t.state.reward, reduce="sum", stats=stats, nonfinite=nonfinite)


def episode_length(*, stats: Sequence[Stat] = DEFAULT_STATS) -> Term:
    """The episode length in sub-steps (env steps x `action_repeat`, Brax's units).

    Reduction "sum" of 1 per sub-step. Equals Brax's `info['episode_metrics']['length']`
    (and `info['steps']`) at episode end.

    Examples:
      >>> import jaxmetrics.brax as jmb
      >>> jmb.episode_length().reduce
      'sum'
    """
    return Term(lambda t: jnp.ones(t.done.shape, jnp.int32), reduce="sum", stats=stats)


def termination_rate(*, stats: Sequence[Stat] = DEFAULT_STATS) -> Term:
    """1 for an episode that ended because the env set `done`, else 0.

    Reduction "last": its report mean is the fraction of episodes that terminated (fell,
    failed, or succeeded, whatever `done` means for the env) rather than timed out.

    Examples:
      >>> import jaxmetrics.brax as jmb
      >>> jmb.termination_rate().reduce
      'last'
    """
    return Term(lambda t: t.termination, reduce="last", stats=stats)


def truncation_rate(*, stats: Sequence[Stat] = DEFAULT_STATS) -> Term:
    """1 for an episode cut by the time limit (`episode_length`) without terminating.

    Reduction "last": its report mean is the fraction of episodes that timed out.
    `termination_rate + truncation_rate` is 1 for every episode.

    Examples:
      >>> import jaxmetrics.brax as jmb
      >>> jmb.truncation_rate().reduce
      'last'
    """
    return Term(lambda t: t.truncation, reduce="last", stats=stats)


def state_metrics(
    names: Sequence[str] | Mapping[str, str],
    *,
    reduce: str = "sum",
    per_second: bool = False,
    stats: Sequence[Stat] = DEFAULT_STATS,
    nonfinite: str | None = None,
) -> dict[str, Term]:
    """Brax's own `State.metrics` entries as terms, one per name, to splat into `terms`.

    Each entry is read from `transition.state.metrics[name]` on every sub-step.

    - Reward components (the default, "sum"): the episode sum, consistent with
      `episode_return` (every sub-step counted, unlike Brax's `EpisodeWrapper`, which
      adds only the last sub-step's metrics when `action_repeat > 1`).
    - `per_second=True` (Isaac Lab / mjlab's reward logging): the episode sum divided by
      the maximum episode length in seconds, `episode_length * dt`, so episodes that end
      early weigh less. Needs every reduction to be "sum".
    - Anything else (positions, velocities): pass a dict `{name: reduction}`, e.g.
      `{"x_position": "last", "x_velocity": "mean"}`; names in a dict override `reduce`.

    Args:
      names: metric names, or name -> episode reduction.
      reduce: the reduction of names given without one. Default "sum".
      per_second: divide the episode sum by the max episode length in seconds.
      stats: report statistics of each.
      nonfinite: NaN/inf policy of each (None: the `Metrics` default).

    Returns:
      name -> `Term`, e.g. `terms={"return": episode_return(), **state_metrics([...])}`
      reports `Episode_Metrics/<name>`.

    Examples:
      >>> import jaxmetrics.brax as jmb
      >>> terms = jmb.state_metrics({"reward_forward": "sum", "x_position": "last"})
      >>> {k: t.reduce for k, t in terms.items()}
      {'reward_forward': 'sum', 'x_position': 'last'}
    """
    if isinstance(names, str):
        raise TypeError(f"state_metrics: names must be a list or dict, got the string {names!r}.")
    _reductions.check(reduce, "state_metrics")
    table = dict(names) if isinstance(names, Mapping) else {n: reduce for n in names}
    if not table:
        raise ValueError("state_metrics: give at least one State.metrics name.")
    for name, r in table.items():
        if not isinstance(name, str) or not name:
            raise ValueError(f"state_metrics: names must be non-empty strings, got {name!r}.")
        _reductions.check(r, f"state_metrics[{name!r}]")
        if per_second and r != "sum":
            raise ValueError(
                f"state_metrics(per_second=True) divides episode sums by the max episode "
                f"length in seconds; {name!r} has reduction {r!r}. Use 'sum', or list it in a "
                "separate state_metrics call without per_second."
            )

    def read(t: Transition, name: str) -> jax.Array:
        if name not in t.state.metrics:
            raise ValueError(
                f"state_metrics: {name!r} is not in State.metrics; this env has "
                f"{sorted(t.state.metrics)}."
            )
        v = t.state.metrics[name]
        if not per_second:
            return v
        if t.dt is None:
            raise ValueError(
                f"state_metrics({name!r}, per_second=True): the env has no `dt`; "
                "divide by your episode duration in a Term of your own."
            )
        return v / jnp.asarray(t.episode_length * t.dt, jnp.result_type(v))

    return {
        name: Term(read, reduce=r, stats=stats, params={"name": name}, nonfinite=nonfinite)
        for name, r in table.items()
    }


def _index(indices: Any, where: str) -> Any:
    if indices is None or isinstance(indices, slice):
        return indices
    if is_int(indices):
        return np.array([int(indices)])
    idx = np.asarray(indices)
    if idx.ndim != 1 or not np.issubdtype(idx.dtype, np.integer):
        raise ValueError(
            f"{where}: indices must be None, a slice, an int or a list of ints, got {indices!r}."
        )
    return idx


def norm(
    get: Callable[[Transition], Any],
    indices: Any = None,
    *,
    ord: float = 2,  # noqa: A002
    reduce: str = "mean",
    stats: Sequence[Stat] = DEFAULT_STATS,
) -> Term:
    """The norm of a slice of a per-env vector, e.g. some joints' velocities.

    Reduction "mean" (per-episode mean over sub-steps) by default.

    Args:
      get: transition -> `[num_envs, D]` array.
      indices: which of the D entries: None (all), a slice, an int or a list of ints.
      ord: 1, 2 or `inf` (max absolute value).
      reduce: episode reduction.
      stats: report statistics.

    The builder behind `joint_velocity` and `control_effort`; a term of your own is a
    `jm.Term` of `jnp.linalg.norm(...)`.
    """
    if not callable(get):
        raise TypeError(f"norm(get=...) must be a function of the Transition, got {get!r}.")
    if ord not in (1, 2, np.inf):
        raise ValueError(f"norm(ord={ord!r}): use 1, 2 or numpy.inf.")
    _reductions.check(reduce, "norm")
    idx = _index(indices, "norm")

    def fn(t: Transition) -> jax.Array:
        x = jnp.asarray(get(t))
        if x.ndim != 2:
            raise ValueError(f"norm: get(transition) must be [num_envs, D], got shape {x.shape}.")
        if idx is not None:
            x = x[:, idx]
        return jnp.linalg.norm(x, ord=ord, axis=-1)

    return Term(fn, reduce=reduce, stats=stats)


def joint_velocity(
    indices: Any = None,
    *,
    ord: float = 2,  # noqa: A002
    reduce: str = "mean",
    stats: Sequence[Stat] = DEFAULT_STATS,
) -> Term:
    """The norm of the generalized velocity `pipeline_state.qd` (qvel on MJX) or a slice.

    Reduction "mean" by default; `qd` exists on every Brax backend. For a free-floating
    base the first 6 entries are the base's: `joint_velocity(slice(6, None))` for the
    joints only.

    Examples:
      >>> import jaxmetrics.brax as jmb
      >>> jmb.joint_velocity(slice(6, None)).reduce
      'mean'
    """

    def qd(t: Transition) -> jax.Array:
        assert t.state.pipeline_state is not None  # every Brax backend's env has one
        return t.state.pipeline_state.qd

    return norm(qd, indices, ord=ord, reduce=reduce, stats=stats)


def control_effort(
    indices: Any = None,
    *,
    ord: float = 2,  # noqa: A002
    reduce: str = "mean",
    stats: Sequence[Stat] = DEFAULT_STATS,
) -> Term:
    """The norm of the action (or a slice of it), the control effort on every backend.

    Reduction "mean" by default.

    Examples:
      >>> import jaxmetrics.brax as jmb
      >>> jmb.control_effort(ord=1, reduce="sum").reduce
      'sum'
    """
    return norm(lambda t: t.action, indices, ord=ord, reduce=reduce, stats=stats)
