"""The Brax `MetricsWrapper`: Brax's `EpisodeWrapper` plus metrics folded on every sub-step.

Where the MetricsState lives, and why the wrapper sits where it does:

- The MetricsState is one batched object for all envs of a batched env (its per-env
  accumulators already have an env axis, and its report streams have none). So it is
  stored once, in `State.info[STATE_KEY]`, by a wrapper that sits *above* the
  `VmapWrapper` (Brax's per-env `info` leaves are vmapped; this one must not be).
- It replaces `EpisodeWrapper` rather than wrapping it: with `action_repeat > 1` only the
  loop over sub-steps sees every sub-step (google/brax#610), and the time limit must be
  known to end an episode on the right step.
- It sits *below* `AutoResetWrapper`, which swaps `obs` and `pipeline_state` for the reset
  ones on done steps: terms must see the terminal state, not the next episode's first.

Hence the order `AutoResetWrapper(MetricsWrapper(VmapWrapper(env)))`, built by `wrap`.
"""

import sys
from collections.abc import Callable
from typing import Any, NamedTuple, cast

import jax
import jax.numpy as jnp
from brax.envs.base import Env, State, Wrapper
from brax.envs.wrappers import training as brax_training

from .._core._metrics import Metrics
from .._core._metrics_state import MetricsState
from .._core._sharding import placed
from .._core._validate import is_int
from .._host._wrapper_reporter import Reporter, mergeable_init
from . import _on_reset
from ._upstream import default_promotion

STATE_KEY = "jaxmetrics"
"""The `State.info` key under which the MetricsState of the whole batch is kept."""

CLOCK_KEY = "jaxmetrics_clock"
"""The `State.info` key of a reporting wrapper's step count into the current period."""

BRAX_AXIS = "i"
"""The axis Brax's trainers (`ppo.train`, `sac.train`) `pmap` their env batch over."""


class Transition(NamedTuple):
    """What a term sees on each (sub-)step of a `MetricsWrapper` env.

    Every array has the env axis first (`[num_envs, ...]`). With `action_repeat > 1`
    terms are evaluated once per physics sub-step (each call of the inner env's `step`),
    and every sub-step is a step of the episode: a "mean" term is the mean over all
    sub-steps (equal to averaging each env step's sub-step mean), a "sum" term sums every
    sub-step (as Brax sums rewards), "max"/"min" run over all sub-steps, "last" is the
    last sub-step's value, `jaxmetrics.discounted(gamma)` discounts per sub-step (`t` =
    env step x `action_repeat` + sub-step). The episode ends on the last sub-step of the
    env step where `done` is set.

    Attributes:
      prev_state: the inner (batched) env's `State` before this sub-step; on the first
        step of an episode, the reset state.
      state: the inner env's `State` after this sub-step, before any auto-reset: on the
        terminal step it is the terminal state. `state.reward` and `state.metrics` are
        this sub-step's; `state.info` holds the episode keys of the previous env step
        (use the fields below for this step's flags).
      action: the action `[num_envs, action_size]`, the same on every sub-step.
      done: bool `[num_envs]`, the episode ends on this sub-step (termination or
        truncation); only ever set on the last sub-step of an env step.
      truncation: bool `[num_envs]`, the episode ends here because the time limit
        (`episode_length`) was reached and the env did not terminate (Brax's
        `info['truncation']`).
      termination: bool `[num_envs]`, the episode ends here because the env set `done`
        (`done & ~truncation`).
      dt: seconds per sub-step (the inner env's `dt`), or None if the env has none.
      episode_length: the time limit in sub-steps (Brax's units, as `info['steps']`).
    """

    prev_state: State
    state: State
    action: jax.Array
    done: jax.Array
    truncation: jax.Array
    termination: jax.Array
    dt: float | None
    episode_length: int


def _strong_types(tree: Any) -> Any:
    # Inner envs often build flags with Python scalars (`jnp.where(c, 1.0, 0.0)`), which
    # are weakly typed in `step` but not in `reset`: a jitted host loop would compile
    # twice. Every leaf leaves this wrapper with the strong type reset gives it.
    def strong(x: Any) -> Any:
        return x.astype(x.dtype) if getattr(jax.typeof(x), "weak_type", False) else x

    return jax.tree.map(strong, tree)


def _positive_int(value: Any, name: str) -> int:
    if not is_int(value) or value < 1:
        raise ValueError(f"MetricsWrapper({name}=...) must be a positive int, got {value!r}.")
    return value


def _in_brax_evaluator() -> bool:
    """Whether the env is being stepped (traced) by Brax's `Evaluator`.

    Brax's trainers build the evaluation env with the same `wrap_env_fn` as the training
    env, and step it through `brax.envs.wrappers.training.EvalWrapper`, which sits above
    this wrapper; nothing in the state it passes down tells the two apart, so this looks
    for an `EvalWrapper` among the callers. Trace time only: the compiled step holds
    nothing of it.
    """
    frame = sys._getframe(1)
    while frame is not None:
        if isinstance(frame.f_locals.get("self"), brax_training.EvalWrapper):
            return True
        frame = frame.f_back
    return False


def _ppo_env_steps(plan: dict[str, Any]) -> int:
    """`brax.training.agents.ppo.train`'s env steps to its end: epochs of
    `num_training_steps_per_epoch` training steps, `max(num_resets_per_eval, 1)` per eval."""
    return (
        int(plan["num_evals_after_init"])
        * max(int(plan["num_resets_per_eval"]), 1)
        * int(plan["num_training_steps_per_epoch"])
        * int(plan["env_step_per_training_step"])
    )


def _sac_env_steps(plan: dict[str, Any]) -> int:
    """`brax.training.agents.sac.train`'s env steps to its end: the replay prefill, then
    one actor step per training step of each epoch."""
    return int(plan["num_prefill_env_steps"]) + int(plan["num_evals_after_init"]) * int(
        plan["num_training_steps_per_epoch"]
    ) * int(plan["env_steps_per_actor_step"])


_BRAX_TRAINERS = {
    "brax.training.agents.ppo.train": _ppo_env_steps,
    "brax.training.agents.sac.train": _sac_env_steps,
}


def _brax_training_env_steps() -> int | None:
    """The env steps Brax's `ppo.train` or `sac.train` runs to its end (Brax's final
    step), when it is tracing this env's step, else None.

    Read from the trainer's own frame (its plan of epochs, computed before training), as
    `_in_brax_evaluator` reads the stack: trace time only, and None for a Brax whose
    trainer keeps its plan under other names. `Logger.close` compares it with the last
    record's step, to say how many env steps after that record were not reported.
    """
    frame = sys._getframe(1)
    while frame is not None:
        env_steps = _BRAX_TRAINERS.get(str(frame.f_globals.get("__name__")))
        if env_steps is not None and frame.f_code.co_name == "train":
            try:
                return env_steps(frame.f_locals)
            except (KeyError, TypeError, ValueError):
                return None
        frame = frame.f_back
    return None


def _wraps(env: Any, wrapper: "MetricsWrapper") -> bool:
    """Whether `wrapper` is `env` or one of the envs it wraps, down the stack.

    Follows each wrapper's `env` attribute rather than Brax's `Wrapper` class: every
    wrapper library keeps the env it wraps there, and the stacks Brax's trainers are given
    mix libraries (Playground's `BraxAutoResetWrapper` is a `mujoco_playground` `Wrapper`,
    not a Brax one, and sits above this wrapper in `jaxmetrics.playground.wrap`'s stack).
    The ids seen stop the walk on an `env` that leads back into the stack.
    """
    seen: set[int] = set()
    while env is not None and id(env) not in seen:
        if env is wrapper:
            return True
        seen.add(id(env))
        env = getattr(env, "env", None)
    return False


def _brax_reset_from(wrapper: "MetricsWrapper") -> dict[str, Any] | None:
    """The `info` of the env state Brax's PPO resets `wrapper`'s env from, when it resets
    the envs between epochs (`num_resets_per_eval > 0`), else None.

    Brax resets them through `reset_fn_donated_env_state(env_state_donated, key_envs)`,
    which is handed the last state and drops it (it calls `env.reset(key_envs)`); this
    reads it from that frame, so that the wrapper's statistics survive the reset. Trace
    time only, as `_in_brax_evaluator`; the frame's `env` must be a stack holding this
    wrapper, so a state of another env is never taken. The state is Brax's `State` or
    Playground's (another class with the same `info`): what is read is that `info` holds
    a MetricsState.
    """
    frame = sys._getframe(1)
    while frame is not None:
        if frame.f_code.co_name == "reset_fn_donated_env_state" and str(
            frame.f_globals.get("__name__")
        ).startswith("brax."):
            env, state = frame.f_locals.get("env"), frame.f_locals.get("env_state_donated")
            info = getattr(state, "info", None)
            if _wraps(env, wrapper) and isinstance(info, dict) and STATE_KEY in info:
                return info
            return None
        frame = frame.f_back
    return None


def _check_inner(env: Env) -> None:
    e = env
    while isinstance(e, Wrapper):
        if isinstance(e, MetricsWrapper):
            raise ValueError("MetricsWrapper is already in this env stack; wrap an env only once.")
        if isinstance(e, (brax_training.EpisodeWrapper, brax_training.AutoResetWrapper)):
            raise ValueError(
                f"MetricsWrapper must wrap the batched env directly, but found "
                f"{type(e).__name__} below it. MetricsWrapper replaces EpisodeWrapper and "
                "must sit below AutoResetWrapper: AutoResetWrapper(MetricsWrapper("
                "VmapWrapper(env), metrics, episode_length)), which "
                "jaxmetrics.brax.wrap(env, metrics, episode_length) builds."
            )
        e = e.env


class MetricsWrapper(Wrapper):
    """Brax's `EpisodeWrapper` that also folds a `Metrics` spec on every physics sub-step.

    A drop-in replacement for `brax.envs.wrappers.training.EpisodeWrapper`: it steps the
    inner env `action_repeat` times per env step, ends episodes at `episode_length`
    (counted in sub-steps, as Brax does), and writes Brax's keys `info['steps']`,
    `info['truncation']`, `info['episode_done']` and `info['episode_metrics']` with
    Brax's exact semantics, so code reading them keeps working. In addition it keeps the
    MetricsState of the whole batch in `info[STATE_KEY]` and calls `metrics.update` on
    every sub-step with a `Transition`.

    Required order (what `wrap` builds)::

        AutoResetWrapper(MetricsWrapper(VmapWrapper(env), metrics, episode_length))

    It must wrap the batched env directly (no `EpisodeWrapper` below it: it is one) and
    sit below `AutoResetWrapper`, so that terms see the terminal state of each episode.
    The MetricsState is not per env: code that maps over every `info` leaf assuming a
    leading env axis must leave `info[STATE_KEY]` alone. `reset` starts a fresh
    MetricsState, except for a wrapper that reports or has `on_reset` when Brax's PPO
    resets it between epochs (`num_resets_per_eval`): its statistics, counters and period
    go on, and only the running episodes end. `Counters/env_steps` counts sub-steps (env
    steps x `action_repeat`, Brax's `num_timesteps` convention). As with Brax's
    `EpisodeWrapper`, without an `AutoResetWrapper` above it envs keep stepping past
    `done`, and every further step with `done` set counts as an episode.

    Args:
      env: a batched Brax env (`VmapWrapper` or `DomainRandomizationVmapWrapper`, or any
        env whose `done` has shape `[num_envs]`).
      metrics: the metrics spec; its terms receive a `Transition`.
      episode_length: the time limit, in sub-steps.
      action_repeat: inner env steps per env step; terms are evaluated on each.
      sharding: the env batch's sharding when envs are split over devices (e.g.
        `NamedSharding(mesh, P("env"))`); `reset` lays the MetricsState out to match
        (`Metrics.init(num_envs, sharding=...)`) and constrains the reset keys to it, so
        every step folds metrics shard-locally.
      logger: a `jaxmetrics.Logger` of the same spec: the wrapper then reports by itself,
        from inside whatever jitted, scanned, vmapped or pmapped code steps it. At the
        end of each period it hands the report (its step: `Counters/env_steps` over all
        envs) to the logger and resets the period, in-graph; the trainer never has to
        hand the env state back. Under Brax's `pmap` the devices' statistics are merged
        at the report (no communication on other steps) and one report is written for
        all envs. Under `vmap` over seeds, seed `i` reports to the logger's run `i`.
        Envs stepped by Brax's evaluator (its `EvalWrapper`) fold but never report: the
        training statistics hold training episodes only. A logger takes the reports of
        one wrapper (one training): another one's step is refused at trace time. None:
        fold only.
      report_every: the period in env steps over all envs and devices (sub-steps, like
        Brax's `num_timesteps`); a report is made at the first env step that reaches it.
        None: every 100 env steps of the batch (`100 * num_envs * action_repeat`).
      axis_name: the `pmap` axis a trainer splits the envs over, where it is bound (Brax's
        trainers use "i"); elsewhere the batch is the whole run.
      on_reset: `on_reset(read, state) -> state`, for curricula and adaptive settings
        driven by live statistics: called in-graph on every step with the batched env
        state as it leaves the wrapper (the terminal state of the envs whose episode
        ends, `state.done` set), and at `reset` with the fresh state; its result is
        kept for the envs that begin a new episode (the done ones; every env at
        `reset`), the other envs keep theirs. `read(metric, statistic="mean",
        by_group=False)` is `Metrics.read` of the live statistics, this step's finished
        episodes included: of the whole run under a trainer's `pmap` over `axis_name`
        (every device reads the same global value; the devices' statistics are gathered
        for it on every step), and across Brax's resets between epochs. Put what the
        episodes depend on in `state.info` (e.g. `info["level"]`), where the env's
        `step` reads it: the auto-reset above this wrapper replaces `obs` and
        `pipeline_state` by the first ones. See docs/curriculum.md.

    Raises:
      ValueError: for a non-positive length/repeat/period, an env that already contains
        an `EpisodeWrapper`, `AutoResetWrapper` or `MetricsWrapper`, a logger of another
        spec, or (at `reset`) an unbatched env.
    """

    def __init__(
        self,
        env: Env,
        metrics: Metrics,
        episode_length: int,
        action_repeat: int = 1,
        sharding: jax.sharding.Sharding | None = None,
        logger: Any = None,
        report_every: int | None = None,
        axis_name: str | None = BRAX_AXIS,
        on_reset: _on_reset.OnReset | None = None,
    ):
        super().__init__(env)
        if not isinstance(metrics, Metrics):
            raise TypeError(
                f"MetricsWrapper(metrics=...) must be a jaxmetrics.Metrics, got "
                f"{type(metrics).__name__}."
            )
        _check_inner(env)
        self.metrics = metrics
        self.episode_length = _positive_int(episode_length, "episode_length")
        self.action_repeat = _positive_int(action_repeat, "action_repeat")
        dt = getattr(env, "dt", None)
        self.sub_dt = None if dt is None else float(dt)
        self.sharding = sharding
        # Under Auto mesh axes XLA chooses the layout of a jit's outputs; pinning the
        # MetricsState after each step keeps it split like the envs across jit calls.
        # `state_sharding` refuses a sharding other than a NamedSharding (TypeError).
        self._state_sharding = (
            None
            if sharding is None
            else metrics.state_sharding(cast(jax.sharding.NamedSharding, sharding))
        )
        self.reporter = (
            None
            if logger is None
            else Reporter(metrics, logger, report_every, axis_name, "MetricsWrapper")
        )
        self.on_reset = _on_reset.check(on_reset)
        self.axis_name = axis_name

    def reset(self, rng: jax.Array) -> State:
        if self.sharding is not None:
            # The whole env batch follows its keys' layout from here on.
            rng = placed(rng, self.sharding)
        with default_promotion():
            state = self.env.reset(rng)
        done = jnp.asarray(state.done)
        if done.ndim != 1:
            raise ValueError(
                f"MetricsWrapper needs a batched env (done of shape [num_envs]), got done of "
                f"shape {done.shape}. Wrap the env in brax.envs.training.VmapWrapper first "
                "(jaxmetrics.brax.wrap does) and reset it with one key per env."
            )
        if STATE_KEY in state.info:
            raise ValueError(f"the inner env already uses info[{STATE_KEY!r}].")
        zeros = jnp.zeros(done.shape, jnp.float32)
        episode_metrics = {"sum_reward": zeros, "length": zeros}
        episode_metrics.update({k: zeros for k in state.metrics})
        info = dict(state.info)
        info.update(
            steps=zeros,
            truncation=zeros,
            episode_done=zeros,
            episode_metrics=episode_metrics,
        )
        # Statistics used inside the trainer (reported, or read live) are merged over
        # the device axis and go on through Brax's resets; otherwise Brax's reset starts
        # afresh, as Brax's own does.
        used = self.reporter is not None or self.on_reset is not None
        if self.sharding is not None:
            mstate = self.metrics.init(done.shape[0], sharding=self.sharding)
        elif used:
            mstate = mergeable_init(self.metrics, done.shape[0], self.axis_name)
        else:
            mstate = self.metrics.init(done.shape[0])
        clock = jnp.zeros((), jnp.int32)
        previous = _brax_reset_from(self) if used else None
        if previous is not None:
            # Brax resets the envs, not the training: statistics, windows, EMAs,
            # counters and the period go on, so records keep Brax's step, none is lost
            # and a curriculum keeps its levels; only the running episodes end,
            # unfinished, with their envs.
            mstate = previous[STATE_KEY]._replace(running=mstate.running)
            clock = previous.get(CLOCK_KEY, clock)
        # flax.struct adds `replace` to Brax's State at run time.
        state = state.replace(info=info)  # pyright: ignore[reportAttributeAccessIssue]
        if self.on_reset is not None:
            begins = jnp.ones(done.shape, bool)
            state = _on_reset.begin(
                self.on_reset, self.metrics, self.axis_name, mstate, state, begins
            )
        info = dict(state.info)
        if self.reporter is not None:
            info[CLOCK_KEY] = clock
        info[STATE_KEY] = mstate
        return _strong_types(state.replace(info=info))  # pyright: ignore[reportAttributeAccessIssue]

    def step(self, state: State, action: jax.Array) -> State:
        info = dict(state.info)
        if STATE_KEY not in info:
            raise ValueError(
                f"this State has no info[{STATE_KEY!r}]: reset it with this wrapper's reset "
                "(or replace_metrics_state) before stepping."
            )
        mstate = info.pop(STATE_KEY)
        clock = info.pop(CLOCK_KEY, None)
        if self.reporter is not None and clock is None:
            raise ValueError(
                f"this State has no info[{CLOCK_KEY!r}]: reset it with this wrapper's reset "
                "before stepping."
            )
        inner = state.replace(info=info)  # flax.struct's  # pyright: ignore[reportAttributeAccessIssue]
        steps = info["steps"] + self.action_repeat
        time_up = steps >= self.episode_length
        last_index = self.action_repeat - 1

        def sub_step(carry, k):
            prev, ms = carry
            # Envs mutate the dicts of the state they are given (Brax's ant updates
            # `state.metrics` in place): give them copies so `prev` stays the pre-step state.
            with default_promotion():
                nxt = self.env.step(
                    prev.replace(metrics=dict(prev.metrics), info=dict(prev.info)), action
                )
            last = k == last_index
            terminated = last & (jnp.asarray(nxt.done) != 0)
            truncated = last & time_up & ~terminated
            done = terminated | truncated
            t = Transition(
                prev_state=prev,
                state=nxt,
                action=action,
                done=done,
                truncation=truncated,
                termination=terminated,
                dt=self.sub_dt,
                episode_length=self.episode_length,
            )
            return (nxt, self.metrics.update(ms, t, done)), nxt.reward

        (nstate, mstate), rewards = jax.lax.scan(
            sub_step, (inner, mstate), jnp.arange(self.action_repeat, dtype=jnp.int32)
        )
        # Brax's EpisodeWrapper bookkeeping, same operations in the same order.
        reward = jnp.sum(rewards, axis=0)
        one = jnp.ones_like(nstate.done)
        zero = jnp.zeros_like(nstate.done)
        done = jnp.where(time_up, one, nstate.done)
        keep = 1 - info["episode_done"]
        old = info["episode_metrics"]
        episode_metrics = dict(old)
        episode_metrics["sum_reward"] = old["sum_reward"] * keep + reward
        episode_metrics["length"] = old["length"] * keep + self.action_repeat
        for name, value in nstate.metrics.items():
            if name != "reward":
                episode_metrics[name] = old[name] * keep + value
        new_info = dict(nstate.info)
        new_info.update(
            steps=steps,
            truncation=jnp.where(time_up, 1 - nstate.done, zero),
            episode_done=done,
            episode_metrics=episode_metrics,
        )
        # flax.struct adds `replace` to Brax's State at run time.
        nstate = nstate.replace(reward=reward, done=done, info=new_info)  # pyright: ignore[reportAttributeAccessIssue]
        if self.on_reset is not None:
            # Before the report resets the period: the read includes this step's episodes.
            nstate = _on_reset.begin(
                self.on_reset, self.metrics, self.axis_name, mstate, nstate, done != 0
            )
            new_info = dict(nstate.info)
        if self.reporter is not None:
            if not _in_brax_evaluator():
                mstate, clock = self.reporter(
                    mstate,
                    clock,
                    nstate.done.shape[0],
                    self.action_repeat,
                    planned=_brax_training_env_steps(),
                )
            new_info[CLOCK_KEY] = clock
        if self._state_sharding is not None:
            mstate = placed(mstate, self._state_sharding)
        new_info[STATE_KEY] = mstate
        # flax.struct adds `replace` to Brax's State at run time.
        return _strong_types(nstate.replace(info=new_info))  # pyright: ignore[reportAttributeAccessIssue]


def wrap(
    env: Env,
    metrics: Metrics,
    episode_length: int = 1000,
    action_repeat: int = 1,
    randomization_fn: Callable[..., Any] | None = None,
    sharding: jax.sharding.Sharding | None = None,
    logger: Any = None,
    report_every: int | None = None,
    axis_name: str | None = BRAX_AXIS,
    on_reset: _on_reset.OnReset | None = None,
) -> Wrapper:
    """`brax.envs.training.wrap` with `MetricsWrapper` in place of `EpisodeWrapper`.

    Builds `AutoResetWrapper(MetricsWrapper(VmapWrapper(env), metrics, episode_length,
    action_repeat))` (`DomainRandomizationVmapWrapper` when `randomization_fn` is given),
    the same stack and info keys as Brax's, with the same signature plus `metrics`.

    Args:
      env: an unbatched Brax env, e.g. `brax.envs.get_environment("ant", backend="mjx")`.
      metrics: the metrics spec; its terms receive a `jaxmetrics.brax.Transition`.
      episode_length: the time limit, in sub-steps (env steps x `action_repeat`).
      action_repeat: inner env steps per env step; terms are evaluated on each.
      randomization_fn: as in Brax: makes a vectorized system and its vmap in_axes.
      sharding: the env batch's sharding when envs are split over devices, e.g.
        `NamedSharding(mesh, P("env"))`: the reset keys, hence the env batch, and the
        MetricsState are laid out by it, and metrics fold shard-locally.
      logger: a `jaxmetrics.Logger` of `metrics`: the env then reports by itself every
        `report_every` env steps (see `MetricsWrapper`), e.g. inside Brax's own trainer:
        `ppo.train(..., wrap_env_fn=functools.partial(jmb.wrap, metrics=metrics,
        logger=logger))`. Close the logger after training to write what is pending.
      report_every: the period in env steps over all envs and devices; None: every 100
        env steps of the batch.
      axis_name: the `pmap` axis of the trainer's devices (Brax's: "i").
      on_reset: `on_reset(read, state) -> state`: sets up the envs that begin an
        episode from live statistics (a curriculum; see `MetricsWrapper`).

    Returns:
      The wrapped env; `reset` takes one key per env (`[num_envs, 2]`).

    Examples:
      A rollout (not run here: compiling MJX takes a while)::

          import jax, jax.numpy as jnp, jaxmetrics as jm, jaxmetrics.brax as jmb
          from brax import envs

          metrics = jm.Metrics(terms={
              "return": jmb.episode_return(),
              "length": jmb.episode_length(),
              "truncated": jmb.truncation_rate(),
              "joint_vel": jmb.joint_velocity(),
          })
          env = jmb.wrap(envs.get_environment("inverted_pendulum", backend="mjx"),
                         metrics, episode_length=100)
          state = env.reset(jax.random.split(jax.random.PRNGKey(0), 8))
          state, _ = jax.lax.scan(
              lambda s, a: (env.step(s, a), None), state, jnp.zeros((200, 8, 1)))
          report = metrics.to_host(metrics.compute(jmb.metrics_state(state)))
    """
    if randomization_fn is None:
        batched = brax_training.VmapWrapper(env)
    else:
        batched = brax_training.DomainRandomizationVmapWrapper(env, randomization_fn)
    return brax_training.AutoResetWrapper(
        MetricsWrapper(
            batched,
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


def metrics_state(env_state: State) -> MetricsState:
    """The MetricsState of the whole batch, kept in `env_state.info`.

    Raises:
      ValueError: if the env was not wrapped by `MetricsWrapper`.
    """
    info = getattr(env_state, "info", None)
    if not isinstance(info, dict) or STATE_KEY not in info:
        raise ValueError(
            f"this env state has no info[{STATE_KEY!r}]: build the env with "
            "jaxmetrics.brax.wrap(env, metrics, ...) (or MetricsWrapper) and reset it."
        )
    return info[STATE_KEY]


def replace_metrics_state(env_state: State, state: MetricsState) -> State:
    """`env_state` with its MetricsState replaced (after `reset_period`, `log`, ...).

    Examples:
      After a flush, start a new period without leaving the graph::

          ms = jmb.metrics_state(env_state)
          report = metrics.compute(ms)
          env_state = jmb.replace_metrics_state(env_state, metrics.reset_period(ms))
    """
    metrics_state(env_state)
    if not isinstance(state, MetricsState):
        raise TypeError(f"expected a MetricsState, got {type(state).__name__}.")
    # flax.struct adds `replace` to Brax's State at run time.
    return env_state.replace(info={**env_state.info, STATE_KEY: state})  # pyright: ignore[reportAttributeAccessIssue]
