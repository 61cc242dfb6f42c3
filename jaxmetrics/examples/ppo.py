"""A jitted PPO on a Brax environment (MJX backend) or a MuJoCo Playground environment,
every metric through jaxmetrics.

The algorithm: GAE, the clipped surrogate objective, a value loss, an entropy bonus,
running observation normalization and minibatch epochs; a Gaussian policy with a
state-independent log-std whose samples are clipped to the action range [-1, 1] before
they reach the env (the log-probability is that of the unclipped sample, as in CleanRL
and PureJaxRL). Truncated episodes are handled as Brax's PPO does: the transition on
which the time limit cuts an episode carries no advantage and no value error.

One `MetricsState` holds everything: it lives in the env state (`jaxmetrics.brax.wrap`,
or `jaxmetrics.playground.wrap` for a Playground env name such as `CartpoleBalance`), the
env folds episode terms into it on every step (return, length, the env's reward
components, joint velocity, control effort), and the learner logs its values into the
same state with `Metrics.log` after each update.

In host mode the run checkpoints its whole carry with orbax-checkpoint, and a killed run
continues with `--resume`, writing exactly the records of an uninterrupted run (see
`train`).

Run `python -m jaxmetrics.examples.ppo --help`.
"""

import argparse
import dataclasses
import math
import os
import sys
import time
from collections.abc import Callable, Sequence
from typing import Any, NamedTuple

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np
import optax
from jax.sharding import AxisType, NamedSharding
from jax.sharding import PartitionSpec as P

import jaxmetrics as jm
import jaxmetrics.brax as jmb  # before Brax: imports MuJoCo without its warp lines

# isort: split
from brax import envs

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

_LOG_2PI = float(np.log(2.0 * np.pi))


@dataclasses.dataclass(frozen=True)
class PPOConfig:
    """Static configuration of a PPO run. Validated when built.

    Env steps are counted as Brax counts them: env steps x `action_repeat`.

    Attributes:
      env_name: a Brax environment name (`brax.envs.get_environment`), or a MuJoCo
        Playground one (`mujoco_playground.registry`, e.g. "CartpoleBalance"; needs the
        `playground` extra), run with MJX's JAX implementation and the env's own
        `ctrl_dt`/`sim_dt`.
      backend: the Brax physics backend (Brax envs only).
      num_envs: parallel envs per seed.
      unroll_length: env steps per env per iteration.
      total_steps: env steps to train for (rounded up to whole iterations).
      episode_length: the time limit, in env steps x `action_repeat`.
      action_repeat: physics sub-steps per env step.
      update_epochs: passes over each iteration's batch.
      num_minibatches: minibatches per pass; must divide each device's batch
        `num_envs / devices * unroll_length`.
      learning_rate: Adam's step size (annealed linearly to 0 when `anneal_lr`).
      anneal_lr: anneal the learning rate linearly to 0 over the run.
      gamma: discount.
      gae_lambda: GAE's lambda.
      clip_eps: the clipping range of the probability ratio.
      entropy_coef: weight of the entropy bonus.
      value_coef: weight of the value loss.
      max_grad_norm: global-norm gradient clipping.
      reward_scaling: rewards are multiplied by this inside the losses (not in metrics).
      hidden_sizes: hidden layers of the policy and the value networks (tanh).
      normalize_observations: running mean/std normalization of observations.
      devices: local devices to train on, data-parallel: each seed's envs are split
        evenly over them (metrics fold shard-locally), parameters are replicated, and
        each minibatch's gradient is the mean over the whole batch (XLA all-reduces it).
        Must divide `num_envs`.
    """

    env_name: str = "inverted_pendulum"
    backend: str = "mjx"
    num_envs: int = 64
    unroll_length: int = 32
    total_steps: int = 600_000
    episode_length: int = 1000
    action_repeat: int = 1
    update_epochs: int = 4
    num_minibatches: int = 4
    learning_rate: float = 1e-3
    anneal_lr: bool = True
    gamma: float = 0.99
    gae_lambda: float = 0.95
    clip_eps: float = 0.2
    entropy_coef: float = 0.0
    value_coef: float = 0.5
    max_grad_norm: float = 0.5
    reward_scaling: float = 1.0
    hidden_sizes: tuple[int, ...] = (64, 64)
    normalize_observations: bool = True
    devices: int = 1

    def __post_init__(self):
        for name in (
            "devices",
            "num_envs",
            "unroll_length",
            "total_steps",
            "episode_length",
            "action_repeat",
            "update_epochs",
            "num_minibatches",
        ):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or v < 1:
                raise ValueError(f"PPOConfig({name}=...) must be a positive int, got {v!r}.")
        if self.num_envs % self.devices:
            raise ValueError(
                f"PPOConfig: devices={self.devices} must divide num_envs={self.num_envs} "
                "(each device steps the same number of envs)."
            )
        batch = self.num_envs // self.devices * self.unroll_length
        if batch % self.num_minibatches:
            raise ValueError(
                f"PPOConfig: num_minibatches={self.num_minibatches} must divide each "
                f"device's batch num_envs / devices * unroll_length = {batch}."
            )

        def number(v: Any) -> bool:
            return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)

        for name in ("gamma", "gae_lambda"):
            v = getattr(self, name)
            if not (number(v) and 0.0 <= v <= 1.0):
                raise ValueError(f"PPOConfig({name}=...) must be in [0, 1], got {v!r}.")
        for name in ("clip_eps", "learning_rate", "max_grad_norm"):
            v = getattr(self, name)
            if not (number(v) and v > 0):
                raise ValueError(f"PPOConfig({name}=...) must be a number > 0, got {v!r}.")
        for name in ("entropy_coef", "value_coef", "reward_scaling"):
            v = getattr(self, name)
            if not (number(v) and v >= 0):
                raise ValueError(f"PPOConfig({name}=...) must be a number >= 0, got {v!r}.")
        sizes = self.hidden_sizes
        if (
            not isinstance(sizes, tuple)
            or not sizes
            or not all(isinstance(h, int) and not isinstance(h, bool) and h > 0 for h in sizes)
        ):
            raise ValueError(
                f"PPOConfig(hidden_sizes=...) must be a non-empty tuple of positive ints, "
                f"got {sizes!r}."
            )

    @property
    def steps_per_iteration(self) -> int:
        """Env steps (x `action_repeat`) collected per iteration, per seed."""
        return self.num_envs * self.unroll_length * self.action_repeat

    @property
    def num_iterations(self) -> int:
        """Iterations needed to reach `total_steps`."""
        return -(-self.total_steps // self.steps_per_iteration)

    @property
    def updates_per_iteration(self) -> int:
        """Gradient steps per iteration: epochs x minibatches."""
        return self.update_epochs * self.num_minibatches


class ObsStats(NamedTuple):
    """Running observation statistics (Welford/Chan), `[obs_size]` each."""

    count: jax.Array  # shape=(), float32: observations seen
    mean: jax.Array  # [obs_size] float32
    m2: jax.Array  # [obs_size] float32: sum of squared deviations


class TrainState(NamedTuple):
    """Everything that changes during training; the MetricsState is in `env_state.info`."""

    params: Any  # flax parameters of `ActorCritic`
    opt_state: Any  # optax state of the gradient transformation
    obs_stats: ObsStats
    env_state: Any  # the Brax `State` of all envs, with the MetricsState inside
    key: jax.Array  # PRNG key
    iteration: jax.Array  # shape=(), int32: iterations done


class _MLP(nn.Module):
    hidden: tuple[int, ...]
    out: int
    out_scale: float

    @nn.compact
    def __call__(self, x: jax.Array) -> jax.Array:
        for h in self.hidden:
            x = nn.tanh(nn.Dense(h, kernel_init=nn.initializers.orthogonal(np.sqrt(2.0)))(x))
        return nn.Dense(self.out, kernel_init=nn.initializers.orthogonal(self.out_scale))(x)


class ActorCritic(nn.Module):
    """Separate policy and value MLPs; the policy's log-std is a free parameter.

    Returns `(mean [B, A], log_std [B, A], value [B])` for observations `[B, obs_size]`.
    """

    action_size: int
    hidden: tuple[int, ...]

    @nn.compact
    def __call__(self, obs: jax.Array) -> tuple[jax.Array, jax.Array, jax.Array]:
        mean = _MLP(self.hidden, self.action_size, 0.01)(obs)
        log_std = self.param("log_std", nn.initializers.zeros, (self.action_size,), jnp.float32)
        value = _MLP(self.hidden, 1, 1.0)(obs)[:, 0]
        return mean, jnp.broadcast_to(log_std[None, :], mean.shape), value


def gaussian_log_prob(x: jax.Array, mean: jax.Array, log_std: jax.Array) -> jax.Array:
    """Log-density of a diagonal Gaussian, summed over the last axis."""
    z = (x - mean) * jnp.exp(-log_std)
    return jnp.sum(-0.5 * z * z - log_std - 0.5 * _LOG_2PI, axis=-1)


def gaussian_entropy(log_std: jax.Array) -> jax.Array:
    """Entropy of a diagonal Gaussian, summed over the last axis."""
    return jnp.sum(log_std + 0.5 * (_LOG_2PI + 1.0), axis=-1)


def init_obs_stats(obs_size: int) -> ObsStats:
    """Statistics of no observations: normalization is the identity until the first update."""
    return ObsStats(
        jnp.zeros((), jnp.float32),
        jnp.zeros((obs_size,), jnp.float32),
        jnp.zeros((obs_size,), jnp.float32),
    )


def update_obs_stats(stats: ObsStats, obs: jax.Array) -> ObsStats:
    """Folds a batch `[..., obs_size]` into the running statistics (Chan's merge)."""
    x = obs.reshape(-1, obs.shape[-1]).astype(jnp.float32)
    n = jnp.asarray(x.shape[0], jnp.float32)
    batch_mean = jnp.mean(x, axis=0)
    batch_m2 = jnp.sum(jnp.square(x - batch_mean[None, :]), axis=0)
    total = stats.count + n
    delta = batch_mean - stats.mean
    mean = stats.mean + delta * (n / total)
    m2 = stats.m2 + batch_m2 + jnp.square(delta) * (stats.count * n / total)
    return ObsStats(total, mean, m2)


def normalize_obs(stats: ObsStats, obs: jax.Array) -> jax.Array:
    """`(obs - mean) / std`, clipped to [-10, 10]; the identity before any update."""
    seen = stats.count > 0
    var = jnp.where(seen, stats.m2 / jnp.maximum(stats.count, 1.0), jnp.ones_like(stats.m2))
    mean = jnp.where(seen, stats.mean, jnp.zeros_like(stats.mean))
    return jnp.clip((obs - mean[None, :]) * jax.lax.rsqrt(var + 1e-8)[None, :], -10.0, 10.0)


def gae(
    rewards: jax.Array,
    values: jax.Array,
    last_value: jax.Array,
    termination: jax.Array,
    truncation: jax.Array,
    gamma: float,
    lam: float,
) -> tuple[jax.Array, jax.Array]:
    """Generalized advantage estimates and value targets (lambda-returns), `[T, N]` each.

    A terminated step does not bootstrap; a truncated step (time limit) is left out, as
    in Brax's `compute_gae`: its advantage is 0 and its target is its own value, because
    the env auto-resets and the next observation is the next episode's.

    Args:
      rewards: `[T, N]` (already scaled).
      values: `[T, N]` value estimates of the observations the actions were taken in.
      last_value: `[N]` value estimate of the observation after the last step.
      termination: `[T, N]` float 0/1: the episode ended by the env's own `done`.
      truncation: `[T, N]` float 0/1: the episode was cut by the time limit.
      gamma: discount.
      lam: GAE's lambda.

    Returns:
      `(advantages, targets)`.
    """
    keep = 1.0 - truncation
    next_values = jnp.concatenate([values[1:], last_value[None, :]], axis=0)
    deltas = (rewards + gamma * (1.0 - termination) * next_values - values) * keep
    carry_on = gamma * lam * (1.0 - termination) * keep

    def backward(acc, x):
        delta, c = x
        acc = delta + c * acc
        return acc, acc

    _, advantages = jax.lax.scan(
        backward, jnp.zeros_like(last_value), (deltas, carry_on), reverse=True
    )
    return advantages, advantages + values


def explained_variance(values: jax.Array, targets: jax.Array) -> jax.Array:
    """`1 - Var[targets - values] / Var[targets]` over all elements (NaN if Var is 0).

    Meaningless once the returns stop varying: on a solved `inverted_pendulum` every state
    is worth `1 / (1 - gamma)` (no termination, truncation bootstrapped), the targets'
    variance is only the value net's float32 noise (std 3e-4 on 100), and this ratio of
    two noise levels goes negative (-2 typical, down to -8) although the targets are right.
    """
    y, v = targets.reshape(-1), values.reshape(-1)
    var_y = jnp.var(y)
    return jnp.where(var_y > 0, 1.0 - jnp.var(y - v) / jnp.where(var_y > 0, var_y, 1.0), jnp.nan)


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
    terms["joint_velocity"] = jmb.norm(
        _qvel, stats=_term_stats(jm.window(100), jm.histogram(20, (0.0, 10.0)))
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
    return t.state.pipeline_state.qd if data is None else data.qvel


class PPO(NamedTuple):
    """A PPO built for one config: static parts plus un-jitted pure functions.

    Attributes:
      config: the configuration.
      env: the wrapped, batched Brax env (`jaxmetrics.brax.wrap`).
      metrics: the metrics spec (`make_metrics`).
      network: the flax module.
      init: `key -> TrainState`: fresh envs, parameters and a fresh MetricsState.
      iteration: `TrainState -> TrainState`: one rollout of `unroll_length` steps, then
        `update_epochs x num_minibatches` gradient steps; episode terms are folded during
        the rollout, learner values logged after the update. Does not reset the period.
    """

    config: PPOConfig
    env: Any
    metrics: jm.Metrics
    network: ActorCritic
    init: Callable[[jax.Array], TrainState]
    iteration: Callable[[TrainState], TrainState]


def _playground_env(name: str) -> tuple[Any, Callable[..., Any]]:
    """MuJoCo Playground's env `name` (MJX's JAX implementation: Warp's is for NVIDIA
    GPUs) and its wrap, or a ValueError naming the Brax and Playground envs there are."""
    # Brax keeps its registry in a private dict; read it only to name the choices.
    known = f"known: {sorted(getattr(envs, '_envs', {}))}"
    try:
        from mujoco_playground import registry

        import jaxmetrics.playground as jmp
    except ImportError:
        raise ValueError(
            f"unknown Brax env {name!r}; {known}. For MuJoCo Playground envs, pip install "
            "'jaxmetrics[playground]'."
        ) from None
    if name not in registry.ALL_ENVS:
        raise ValueError(
            f"unknown Brax env {name!r}, nor a MuJoCo Playground env; {known}; Playground's: "
            f"{sorted(registry.ALL_ENVS)}."
        )
    env_config = registry.get_default_config(name)
    env_config.impl = "jax"
    return registry.load(name, config=env_config), jmp.wrap


def _env_sharding(devices: int) -> NamedSharding | None:
    """The env axis split over the first `devices` local devices (None for one)."""
    if devices == 1:
        return None
    local = jax.local_devices()
    if devices > len(local):
        raise ValueError(
            f"PPOConfig(devices={devices}): only {len(local)} local device(s) "
            f"({local[0].platform}). On a CPU, XLA_FLAGS="
            f"--xla_force_host_platform_device_count={devices} makes that many."
        )
    mesh = jax.make_mesh((devices,), ("env",), axis_types=(AxisType.Auto,), devices=local[:devices])
    return NamedSharding(mesh, P("env"))


def make_ppo(config: PPOConfig = PPOConfig()) -> PPO:
    """Builds the env, the metrics spec and the pure `init`/`iteration` functions.

    Args:
      config: the configuration.

    Returns:
      A `PPO`. Nothing is compiled yet.

    Raises:
      ValueError: for an unknown env name, an env whose observation is not a flat array,
        or more `devices` than there are local devices.
    """
    if not isinstance(config, PPOConfig):
        raise TypeError(f"make_ppo(config=...) must be a PPOConfig, got {type(config).__name__}.")
    try:
        raw_env = envs.get_environment(config.env_name, backend=config.backend)
        wrap = jmb.wrap
    except KeyError:
        raw_env, wrap = _playground_env(config.env_name)
    # Brax, MJX and optax (e.g. its `decay ** count`) run under JAX's default promotion
    # whatever the user's config; this file's own code stays strict.
    with jmb.default_promotion():
        shape = jax.eval_shape(raw_env.reset, jax.random.key_data(jax.random.key(0)))
    if not isinstance(shape.obs, jax.ShapeDtypeStruct) or len(shape.obs.shape) != 1:
        raise ValueError(
            f"env {config.env_name!r} has observation {shape.obs!r}; this PPO needs a flat "
            "array observation."
        )
    obs_size, action_size = shape.obs.shape[0], raw_env.action_size
    names = sorted(shape.metrics)
    metrics = make_metrics(
        reward_components=[n for n in names if n.startswith("reward")],
        other_state_metrics=[n for n in names if not n.startswith("reward")],
        action_size=action_size,
        episode_length=config.episode_length,
    )
    env_sharding = _env_sharding(config.devices)
    env = wrap(raw_env, metrics, config.episode_length, config.action_repeat, sharding=env_sharding)
    network = ActorCritic(action_size, config.hidden_sizes)
    optimizer = optax.chain(
        optax.clip_by_global_norm(config.max_grad_norm), optax.scale_by_adam(eps=1e-5)
    )
    total_updates = config.num_iterations * config.updates_per_iteration
    c = config

    def learning_rate(update_index: jax.Array) -> jax.Array:
        if not c.anneal_lr:
            return jnp.asarray(c.learning_rate, jnp.float32)
        frac = update_index.astype(jnp.float32) / jnp.float32(total_updates)
        return jnp.float32(c.learning_rate) * (1.0 - frac)

    def init(key: jax.Array) -> TrainState:
        k_env, k_net, k_next = jax.random.split(key, 3)
        # Brax envs are written for raw uint32 keys (`rng.shape[:-1]` is the batch).
        env_state = env.reset(jax.random.key_data(jax.random.split(k_env, c.num_envs)))
        params = network.init(k_net, jnp.zeros((1, obs_size), jnp.float32))
        with jmb.default_promotion():
            opt_state = optimizer.init(params)
        return TrainState(
            params=params,
            opt_state=opt_state,
            obs_stats=init_obs_stats(obs_size),
            env_state=env_state,
            key=k_next,
            iteration=jnp.zeros((), jnp.int32),
        )

    def loss_fn(params, batch):
        mean, log_std, value = network.apply(params, batch["obs"])
        log_prob = gaussian_log_prob(batch["action"], mean, log_std)
        log_ratio = log_prob - batch["log_prob"]
        ratio = jnp.exp(log_ratio)
        adv = batch["advantage"]
        adv = (adv - jnp.mean(adv)) / (jnp.std(adv) + 1e-8)
        clipped = jnp.clip(ratio, 1.0 - c.clip_eps, 1.0 + c.clip_eps)
        policy_loss = -jnp.mean(jnp.minimum(ratio * adv, clipped * adv))
        value_loss = 0.5 * jnp.mean(jnp.square(value - batch["target"]))
        entropy = jnp.mean(gaussian_entropy(log_std))
        loss = policy_loss + c.value_coef * value_loss - c.entropy_coef * entropy
        aux = {
            "policy_loss": policy_loss,
            "value_loss": value_loss,
            "entropy": entropy,
            # Schulman's unbiased, non-negative estimator of KL(old || new).
            "approx_kl": jnp.mean((ratio - 1.0) - log_ratio),
            "clip_fraction": jnp.mean((jnp.abs(ratio - 1.0) > c.clip_eps).astype(jnp.float32)),
        }
        return loss, aux

    def iteration(ts: TrainState) -> TrainState:
        params, stats = ts.params, ts.obs_stats
        key, k_roll, k_sgd = jax.random.split(ts.key, 3)

        def env_step(env_state, k):
            obs = normalize_obs(stats, env_state.obs)
            mean, log_std, value = network.apply(params, obs)
            raw_action = mean + jnp.exp(log_std) * jax.random.normal(k, mean.shape)
            log_prob = gaussian_log_prob(raw_action, mean, log_std)
            nxt = env.step(env_state, jnp.clip(raw_action, -1.0, 1.0))
            truncation = nxt.info["truncation"]
            out = {
                "raw_obs": env_state.obs,
                "obs": obs,
                "action": raw_action,
                "log_prob": log_prob,
                "value": value,
                "reward": nxt.reward * c.reward_scaling,
                "termination": nxt.done * (1.0 - truncation),
                "truncation": truncation,
            }
            return nxt, out

        env_state, traj = jax.lax.scan(
            env_step, ts.env_state, jax.random.split(k_roll, c.unroll_length)
        )
        _, _, last_value = network.apply(params, normalize_obs(stats, env_state.obs))
        advantage, target = gae(
            traj["reward"],
            traj["value"],
            last_value,
            traj["termination"],
            traj["truncation"],
            c.gamma,
            c.gae_lambda,
        )
        batch = {
            "obs": traj["obs"],
            "action": traj["action"],
            "log_prob": traj["log_prob"],
            "advantage": advantage,
            "target": target,
        }
        # [time, env, ...] -> [devices, local batch, ...]: each device keeps its own envs'
        # transitions, shuffles them locally, and contributes an equal slice of every
        # minibatch, whose mean gradient XLA all-reduces over the devices.
        local = c.num_envs // c.devices * c.unroll_length
        batch = jax.tree.map(
            lambda x: jnp.swapaxes(x, 0, 1).reshape((c.devices, local) + x.shape[2:]), batch
        )
        if env_sharding is not None:
            batch = jax.lax.with_sharding_constraint(batch, env_sharding)
        first_update = ts.iteration * c.updates_per_iteration
        per_device = local // c.num_minibatches

        def epoch(carry, k):
            def minibatch(carry, mb):
                params, opt_state, index = carry
                (_, aux), grads = jax.value_and_grad(loss_fn, has_aux=True)(params, mb)
                lr = learning_rate(index)
                with jmb.default_promotion():
                    updates, opt_state = optimizer.update(grads, opt_state, params)
                updates = jax.tree.map(lambda u: -lr * u, updates)
                aux["grad_norm"] = optax.tree.norm(grads)
                aux["learning_rate"] = lr
                return (optax.apply_updates(params, updates), opt_state, index + 1), aux

            perm = jax.random.permutation(k, local)

            def split(x: jax.Array) -> jax.Array:
                x = x[:, perm].reshape((c.devices, c.num_minibatches, per_device) + x.shape[2:])
                x = jnp.swapaxes(x, 0, 1)
                return x.reshape((c.num_minibatches, c.devices * per_device) + x.shape[3:])

            return jax.lax.scan(minibatch, carry, jax.tree.map(split, batch))

        (params, opt_state, _), aux = jax.lax.scan(
            epoch, (params, ts.opt_state, first_update), jax.random.split(k_sgd, c.update_epochs)
        )
        aux["explained_variance"] = explained_variance(traj["value"], target)
        mstate = metrics.log(jmb.metrics_state(env_state), aux)
        mstate = metrics.increment(
            mstate, "updates", jnp.asarray(c.updates_per_iteration, jnp.int32)
        )
        env_state = jmb.replace_metrics_state(env_state, mstate)
        if c.normalize_observations:
            stats = update_obs_stats(stats, traj["raw_obs"])
        return TrainState(params, opt_state, stats, env_state, key, ts.iteration + 1)

    return PPO(config, env, metrics, network, init, iteration)


# ---------------------------------------------------------------------- running it

HEADLINE = (
    ("return", "Episode_Metrics/episode_return/window_mean"),
    ("length", "Episode_Metrics/episode_length/window_mean"),
    ("v_loss", "Train/value_loss"),
    ("kl", "Train/approx_kl"),
    ("steps/s", "Counters/env_steps/per_sec"),
)
"""What the progress bar shows: (label, tag); the return and length are over the last
100 episodes."""

MODES = ("host", "graph", "graph-history")

CHECKPOINT_EVERY = 50
"""The command line's default for `--checkpoint-every` (host mode), in iterations."""


class ProgressWriter:
    """A `jaxmetrics.Writer` that draws a progress bar per run with the headline metrics.

    One `ProgressBoard` is shared by the writers of all runs. Records arrive on the
    logger's writer thread, so the bar moves in both modes: after each host flush, and
    on each in-graph emit.
    """

    def __init__(self, board: "ProgressBoard", run: int, label: str):
        self._board, self._run, self._label = board, run, label
        self.last: dict[str, float | int] = {}

    def open(self, tags: Sequence[jm.TagInfo]) -> None:
        """Adds this run's bar."""
        self._board.add(self._run, self._label)

    def write(self, record: jm.Record) -> None:
        """Moves the bar to the record's step and shows its headline values."""
        for _, tag in HEADLINE:
            if tag in record.scalars:
                self.last[tag] = record.scalars[tag]
        shown = "  ".join(
            f"{label} {_format(self.last[tag])}" for label, tag in HEADLINE if tag in self.last
        )
        self._board.update(self._run, record.step, shown)

    def close(self) -> None:
        """Nothing to release (the board is stopped by its owner)."""


def _format(v: float | int) -> str:
    return f"{v:,.0f}" if abs(v) >= 1000 else f"{v:.3g}"


class ProgressBoard:
    """Progress bars (rich) for several runs; plain lines when rich is missing or off.

    Args:
      total: the x-axis value at the end (env steps).
      enabled: draw anything at all.
    """

    def __init__(self, total: int, enabled: bool = True):
        self._total, self._enabled = total, enabled
        self._progress: Any = None
        self._tasks: dict[int, Any] = {}
        self._last_print = 0.0
        if enabled:
            try:
                from rich.progress import (
                    BarColumn,
                    MofNCompleteColumn,
                    Progress,
                    TextColumn,
                    TimeElapsedColumn,
                )
            except ImportError:  # the `console` extra is optional: fall back to prints
                return
            self._progress = Progress(
                TextColumn("{task.description}"),
                BarColumn(),
                MofNCompleteColumn(),
                TimeElapsedColumn(),
                TextColumn("{task.fields[shown]}"),
            )
            self._progress.start()

    def add(self, run: int, label: str) -> None:
        if self._progress is not None:
            self._tasks[run] = self._progress.add_task(label, total=self._total, shown="compiling")

    def update(self, run: int, step: int, shown: str) -> None:
        if not self._enabled:
            return
        if self._progress is not None:
            self._progress.update(self._tasks[run], completed=step, shown=shown)
            return
        now = time.monotonic()
        if now - self._last_print > 2.0 or step >= self._total:
            self._last_print = now
            print(f"[run {run}] step {step:,}/{self._total:,}  {shown}", flush=True)

    def stop(self) -> None:
        if self._progress is not None:
            self._progress.stop()


class RunResult(NamedTuple):
    """What `train` returns.

    Attributes:
      state: the final `TrainState` (with a leading `[seeds]` axis for several seeds).
      run_dirs: each seed's TensorBoard run directory, in seed order.
      last: each seed's last headline values (tag -> value), in seed order.
      seconds: wall time of the whole run, compilation included.
    """

    state: TrainState
    run_dirs: tuple[str, ...]
    last: tuple[dict[str, float | int], ...]
    seconds: float


def _config_values(config: PPOConfig) -> dict[str, bool | int | float | str]:
    out: dict[str, bool | int | float | str] = {}
    for f in dataclasses.fields(config):
        v = getattr(config, f.name)
        out[f.name] = v if isinstance(v, (bool, int, float, str)) else str(v)
    return out


def _hparams(config: PPOConfig, seed: int, mode: str) -> dict[str, bool | int | float | str]:
    return {"seed": seed, "mode": mode, **_config_values(config)}


def _run_settings(config: PPOConfig, seeds: tuple[int, ...]) -> dict[str, Any]:
    """What a checkpoint records of its run, and a resume must match (JSON)."""
    return {"config": _config_values(config), "seeds": list(seeds)}


def train(
    config: PPOConfig,
    log_dir: str,
    *,
    seeds: Sequence[int] = (0,),
    mode: str = "host",
    iterations: int | None = None,
    progress: bool = True,
    jsonl: bool = False,
    checkpoint_every: int = 0,
    checkpoint_dir: str | None = None,
    resume: bool = False,
) -> RunResult:
    """Trains one PPO per seed, writing each seed's metrics to `log_dir/seed_<seed>`.

    Every iteration ends a flush period: one TensorBoard record per iteration per seed,
    at step = env steps so far (per seed). Both modes write the same tags and, for the
    same seed, the same values (up to float round-off between differently fused
    programs).

    Checkpoints (host mode): every `checkpoint_every` iterations and after the last one,
    the whole training carry of all seeds (parameters, optimizer state, observation
    statistics, env states, PRNG keys, the MetricsState as `flush` returned it, the
    iteration) goes to `checkpoint_dir/<step>` with orbax-checkpoint (the 2 newest are
    kept), once the records up to that step are written (`Logger.wait`): a checkpoint
    never exists without its records. `resume=True` restores the newest checkpoint of
    the same config and seeds and carries on: the writers drop the records a killed run
    wrote after it (`purge_step`), `Logger.resume` continues the counters' rates, and the
    run writes exactly the records an uninterrupted run writes (same values, bit for bit
    on CPU; `tests/test_ppo_resume.py` kills a run and compares).

    Args:
      config: the configuration.
      log_dir: parent directory of the run directories.
      seeds: one run per seed; several seeds are `vmap`-ed in one program.
      mode: "host": one jitted call per iteration and a `Logger.flush` between calls;
        "graph": the whole run is one jitted `lax.scan` whose reports are streamed by
        `Logger.emit`; "graph-history": the same scan keeps each iteration's report in
        an in-graph history (`Logger.record`, no host callback), written after the call
        (`Logger.write_history`).
      iterations: stop after this many iterations (default: `config.num_iterations`);
        the learning-rate schedule still spans `config.total_steps`.
      progress: show a progress bar.
      jsonl: also write each seed's records to `<run dir>/metrics.jsonl`.
      checkpoint_every: iterations between checkpoints (host mode); 0: none.
      checkpoint_dir: where checkpoints go (default: `log_dir/checkpoints`).
      resume: continue from the newest checkpoint in `checkpoint_dir` (host mode).

    Returns:
      A `RunResult`.

    Raises:
      ValueError: for an unknown mode, repeated or negative seeds, a bad `iterations` or
        `checkpoint_every`, (graph mode) a run past 2^31 env steps, whose step would
        overflow int32, or checkpoints asked for in graph mode; with `resume`, when
        there is no checkpoint or it was taken with another config or other seeds.
    """
    if mode not in MODES:
        raise ValueError(f"train(mode={mode!r}): use one of {MODES}.")
    seeds = tuple(seeds)
    if not seeds or not all(
        isinstance(s, int) and not isinstance(s, bool) and 0 <= s < 2**32 for s in seeds
    ):
        raise ValueError(
            f"train(seeds=...) must be a non-empty list of ints in [0, 2**32), got {seeds!r}."
        )
    if len(set(seeds)) != len(seeds):
        raise ValueError(f"train(seeds=...) has repeated seeds: {seeds!r}.")
    n = config.num_iterations if iterations is None else iterations
    if isinstance(n, bool) or not isinstance(n, int) or not 1 <= n <= config.num_iterations:
        raise ValueError(
            f"train(iterations={iterations!r}) must be an int in [1, {config.num_iterations}]."
        )
    if isinstance(checkpoint_every, bool) or not isinstance(checkpoint_every, int):
        raise ValueError(f"train(checkpoint_every=...) must be an int, got {checkpoint_every!r}.")
    if checkpoint_every < 0:
        raise ValueError(f"train(checkpoint_every=...) must be >= 0, got {checkpoint_every}.")
    if mode != "host" and (checkpoint_every or resume):
        raise ValueError(GRAPH_CHECKPOINTS)
    spi = config.steps_per_iteration
    if mode != "host" and n * spi >= 2**31:
        raise ValueError(
            f"train(mode={mode!r}): {n * spi:,} env steps overflow the int32 step of the "
            "in-graph emit; use mode='host' or fewer steps."
        )
    start = time.perf_counter()
    ppo = make_ppo(config)
    runs = len(seeds)
    run_dirs = tuple(os.path.join(log_dir, f"seed_{s}") for s in seeds)
    keys = jax.vmap(jax.random.key)(jnp.asarray(seeds, jnp.uint32))
    checkpoints = None
    if checkpoint_every or resume:
        checkpoints = _Checkpoints(
            checkpoint_dir or os.path.join(log_dir, "checkpoints"), _run_settings(config, seeds)
        )
    try:
        restored, done = None, 0
        if checkpoints is not None and resume:
            step = checkpoints.newest()
            restored = checkpoints.restore(step, _init_states(ppo, keys, runs))
            done = int(np.max(jax.device_get(restored.iteration)))
        # A resumed run's first record is at `(done + 1) * spi`: the writers drop what a
        # killed run wrote from there on, so that those steps are not drawn twice.
        purge = (done + 1) * spi if resume else None
        board = ProgressBoard(n * spi, enabled=progress)
        bars = [ProgressWriter(board, r, f"seed {s}") for r, s in enumerate(seeds)]

        def writers(run: int) -> list[jm.Writer]:
            tb = jm.TensorBoardWriter(
                run_dirs[run],
                hparams=_hparams(config, seeds[run], mode),
                hparam_metrics=[HEADLINE[0][1], HEADLINE[1][1]],
                purge_step=purge,
            )
            out: list[jm.Writer] = [tb, bars[run]]
            if jsonl:
                path = os.path.join(run_dirs[run], "metrics.jsonl")
                out.append(jm.JsonlWriter(path, purge_step=purge))
            return out

        try:
            summary = None
            if runs > 1:
                summary = [
                    jm.TensorBoardWriter(os.path.join(log_dir, "seeds_summary"), purge_step=purge)
                ]
            with jm.Logger(ppo.metrics, writers, runs=runs, seeds_summary=summary) as logger:
                if mode == "graph":
                    state = _train_graph(ppo, logger, keys, n)
                elif mode == "graph-history":
                    state = _train_graph_history(ppo, logger, keys, n)
                else:
                    if restored is None:
                        state = _init_states(ppo, keys, runs)
                    else:
                        state = restored
                        logger.resume(jmb.metrics_state(state.env_state), done * spi)
                    state = _train_host(ppo, logger, state, done, n, checkpoints, checkpoint_every)
        finally:
            board.stop()
    finally:
        if checkpoints is not None:
            checkpoints.close()
    return RunResult(state, run_dirs, tuple(b.last for b in bars), time.perf_counter() - start)


GRAPH_CHECKPOINTS = (
    "train(mode='graph' or 'graph-history') cannot checkpoint or resume: the whole run is "
    "one jitted scan, whose carry never reaches the host before the end. Use mode='host' "
    "(--mode host), "
    "which writes the same values and checkpoints at period ends."
)


class _Checkpoints:
    """Orbax checkpoints of the stacked `TrainState`s of all seeds, at `directory/<step>`.

    A checkpoint also holds the run's config and seeds (JSON), which a resume must match.
    Saving is asynchronous (orbax's own thread); a checkpoint appears under its step only
    once complete, so a killed run leaves the previous one to resume from.
    """

    def __init__(self, directory: str, run: dict[str, Any]):
        import orbax.checkpoint as ocp  # the `train` extra; only runs that checkpoint need it

        self._ocp = ocp
        self.directory = os.path.abspath(directory)
        self._run = run
        self._manager = ocp.CheckpointManager(
            self.directory, options=ocp.CheckpointManagerOptions(max_to_keep=2, create=True)
        )

    def save(self, step: int, state: TrainState) -> None:
        """Starts saving `state` as the checkpoint of `step` (returns before it is on disk)."""
        ocp = self._ocp
        self._manager.save(
            step,
            args=ocp.args.Composite(
                state=ocp.args.StandardSave(_without_empty(state)),
                run=ocp.args.JsonSave(self._run),
            ),
        )

    def newest(self) -> int:
        """The newest checkpoint's step, once its run's settings are checked."""
        ocp = self._ocp
        step = self._manager.latest_step()
        if step is None:
            raise ValueError(f"train(resume=True): no checkpoint in {self.directory!r}.")
        run = self._manager.restore(step, args=ocp.args.Composite(run=ocp.args.JsonRestore()))
        if run.run != self._run:
            saved, now = _flat_settings(run.run), _flat_settings(self._run)
            diff = {k: (saved.get(k), now.get(k)) for k in sorted(saved.keys() | now.keys())}
            shown = ", ".join(f"{k}: {a!r} then, {b!r} now" for k, (a, b) in diff.items() if a != b)
            raise ValueError(
                f"train(resume=True): the checkpoint {self.directory}/{step} is of a run with "
                f"other settings ({shown}). Resume with the same settings, or start a new run "
                "in another directory."
            )
        return step

    def restore(self, step: int, target: TrainState) -> TrainState:
        """The checkpoint of `step`, restored into arrays shaped and placed like `target`."""
        ocp = self._ocp
        restored = self._manager.restore(
            step,
            args=ocp.args.Composite(state=ocp.args.StandardRestore(_without_empty(target))),
        ).state
        # Zero-size leaves were not saved: they come from `target` (they hold no values).
        # Both sides are flattened with None as a leaf: the MetricsState's spec identity is
        # a None of its own, in both trees.
        leaves, treedef = jax.tree.flatten(target, is_leaf=lambda x: x is None)
        got = jax.tree.leaves(restored, is_leaf=lambda x: x is None)
        if len(got) != len(leaves):
            raise ValueError(f"the checkpoint {self.directory}/{step} does not match this run.")
        return jax.tree.unflatten(treedef, [t if g is None else g for t, g in zip(leaves, got)])

    def close(self) -> None:
        """Waits for the last save to finish."""
        self._manager.wait_until_finished()
        self._manager.close()


def _flat_settings(run: dict[str, Any]) -> dict[str, Any]:
    return {**run["config"], "seeds": run["seeds"]}


def _without_empty(state: TrainState) -> Any:
    """`state` with its zero-size arrays (MJX has some) as None: orbax refuses to save them."""
    return jax.tree.map(lambda x: None if x.size == 0 else x, state)


def _batched(fn: Callable[..., Any], runs: int) -> Callable[..., Any]:
    return jax.jit(fn if runs == 1 else jax.vmap(fn))


def _init_states(ppo: PPO, keys: jax.Array, runs: int) -> TrainState:
    """The initial state of every run, stacked on a leading axis when `runs > 1`.

    One seed at a time, not vmapped: a vmapped init batches the orthogonal initializers'
    QR factorizations, which jaxlib's CPU LAPACK kernel (0.10) splits with a blocking
    ParallelBatchMap on XLA's own thread pool; on a 2-core machine both pool threads can
    end up waiting on each other (seen as a hang in CI).
    """
    init = jax.jit(ppo.init)
    if runs == 1:
        return init(keys[0])
    return jax.tree.map(lambda *xs: jnp.stack(xs), *(init(k) for k in keys))


def _train_host(
    ppo: PPO,
    logger: jm.Logger,
    state: TrainState,
    done: int,
    n: int,
    checkpoints: _Checkpoints | None,
    every: int,
) -> TrainState:
    spi = ppo.config.steps_per_iteration
    iteration = _batched(ppo.iteration, logger.runs)
    for i in range(done, n):
        state = iteration(state)
        mstate = logger.flush(jmb.metrics_state(state.env_state), (i + 1) * spi)
        state = state._replace(env_state=jmb.replace_metrics_state(state.env_state, mstate))
        if checkpoints is not None and every and ((i + 1) % every == 0 or i + 1 == n):
            # The records up to this step are on disk before the checkpoint can exist: a
            # resume from it purges only records after it, so none can be missing.
            logger.wait()
            checkpoints.save((i + 1) * spi, state)
    return state


def _train_graph(ppo: PPO, logger: jm.Logger, keys: jax.Array, n: int) -> TrainState:
    spi = ppo.config.steps_per_iteration

    def run(state: TrainState, run_index: jax.Array) -> TrainState:
        def body(state: TrainState, _: None) -> tuple[TrainState, None]:
            state = ppo.iteration(state)
            step = state.iteration * jnp.int32(spi)
            mstate = logger.emit(
                jmb.metrics_state(state.env_state), step, jnp.bool_(True), run=run_index
            )
            return state._replace(
                env_state=jmb.replace_metrics_state(state.env_state, mstate)
            ), None

        return jax.lax.scan(body, state, None, length=n)[0]

    runs = logger.runs
    run_indices = jnp.arange(runs, dtype=jnp.int32)
    state = _init_states(ppo, keys, runs)
    args = (state, run_indices[0]) if runs == 1 else (state, run_indices)
    return jax.block_until_ready(_batched(run, runs)(*args))


def _train_graph_history(ppo: PPO, logger: jm.Logger, keys: jax.Array, n: int) -> TrainState:
    spi = ppo.config.steps_per_iteration

    def run(state: TrainState) -> tuple[TrainState, jm.History]:
        def body(carry: tuple[TrainState, jm.History], _: None) -> tuple[Any, None]:
            state, history = carry
            state = ppo.iteration(state)
            step = state.iteration * jnp.int32(spi)
            mstate, history = logger.record(
                jmb.metrics_state(state.env_state), history, step, jnp.bool_(True)
            )
            env_state = jmb.replace_metrics_state(state.env_state, mstate)
            return (state._replace(env_state=env_state), history), None

        carry = (state, logger.history_init(n))  # one record per iteration
        return jax.lax.scan(body, carry, None, length=n)[0]

    state, history = _batched(run, logger.runs)(_init_states(ppo, keys, logger.runs))
    logger.write_history(history)
    return jax.block_until_ready(state)


def _prog() -> str:
    # Run as `python -m jaxmetrics.examples.ppo`, argv[0] is this file's path; run as the
    # installed `jaxmetrics-ppo` script, it is that script.
    name = os.path.basename(sys.argv[0]) if sys.argv and sys.argv[0] else ""
    return "python -m jaxmetrics.examples.ppo" if name in ("", "ppo.py", "-c") else name


def _parser() -> argparse.ArgumentParser:
    d = PPOConfig()
    p = argparse.ArgumentParser(
        prog=_prog(),
        formatter_class=argparse.ArgumentDefaultsHelpFormatter,
        description=(
            "Train PPO on a Brax environment (MJX backend) or a MuJoCo Playground one "
            "(e.g. --env CartpoleBalance) with every metric logged "
            "through jaxmetrics to TensorBoard. The defaults train inverted_pendulum to "
            "the maximum return (1,000) in under a minute on a 2-core laptop CPU, "
            "compilation included."
        ),
    )
    p.add_argument("--env", default=d.env_name, help="Brax or MuJoCo Playground env name")
    p.add_argument("--backend", default=d.backend, help="Brax physics backend")
    p.add_argument("--num-envs", type=int, default=d.num_envs, help="envs per seed")
    p.add_argument("--steps", type=int, default=d.total_steps, help="env steps per seed")
    p.add_argument("--seeds", type=int, nargs="+", default=[0], help="one run per seed")
    p.add_argument(
        "--mode",
        choices=MODES,
        default="host",
        help="host loop, one jit streaming through emit, or one jit keeping a report history",
    )
    p.add_argument("--log-dir", default="runs/ppo/<env>-<time>", help="run dirs go here")
    p.add_argument("--episode-length", type=int, default=d.episode_length, help="time limit")
    p.add_argument("--unroll-length", type=int, default=d.unroll_length, help="steps per iteration")
    p.add_argument("--epochs", type=int, default=d.update_epochs, help="passes per batch")
    p.add_argument("--minibatches", type=int, default=d.num_minibatches, help="per pass")
    p.add_argument("--learning-rate", type=float, default=d.learning_rate, help="Adam, annealed")
    p.add_argument("--entropy-coef", type=float, default=d.entropy_coef, help="entropy bonus")
    p.add_argument(
        "--devices", type=int, default=d.devices, help="local devices, envs split over them"
    )
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.add_argument("--jsonl", action="store_true", help="also write <run dir>/metrics.jsonl")
    p.add_argument(
        "--checkpoint-every",
        type=int,
        default=argparse.SUPPRESS,  # unset: the mode's default, below
        help=f"iterations between checkpoints, 0: none (default: {CHECKPOINT_EVERY} in host "
        "mode; graph mode cannot checkpoint)",
    )
    p.add_argument("--checkpoint-dir", default="<log-dir>/checkpoints", help="where checkpoints go")
    p.add_argument(
        "--resume",
        action="store_true",
        help="continue the run in --log-dir from its newest checkpoint (host mode)",
    )
    return p


def main(argv: Sequence[str] | None = None) -> int:
    """The command line: trains, then prints where the event files and checkpoints are.

    Args:
      argv: arguments (default: `sys.argv[1:]`).

    Returns:
      The exit status.
    """
    args = _parser().parse_args(argv)
    try:
        config = PPOConfig(
            env_name=args.env,
            backend=args.backend,
            num_envs=args.num_envs,
            total_steps=args.steps,
            episode_length=args.episode_length,
            unroll_length=args.unroll_length,
            update_epochs=args.epochs,
            num_minibatches=args.minibatches,
            learning_rate=args.learning_rate,
            entropy_coef=args.entropy_coef,
            devices=args.devices,
        )
    except ValueError as e:
        _parser().error(str(e))
    if args.resume and "<time>" in args.log_dir:
        _parser().error("--resume needs the --log-dir of the run to resume.")
    every = getattr(args, "checkpoint_every", CHECKPOINT_EVERY if args.mode == "host" else 0)
    if args.mode != "host" and (args.resume or every):
        _parser().error(GRAPH_CHECKPOINTS)
    if every < 0:
        _parser().error(f"--checkpoint-every must be >= 0, got {every}.")
    log_dir = args.log_dir.replace("<env>", args.env).replace(
        "<time>", time.strftime("%Y%m%d-%H%M%S")
    )
    checkpoint_dir = args.checkpoint_dir.replace("<log-dir>", log_dir)
    result = train(
        config,
        log_dir,
        seeds=args.seeds,
        mode=args.mode,
        progress=not args.no_progress,
        jsonl=args.jsonl,
        checkpoint_every=every,
        checkpoint_dir=checkpoint_dir,
        resume=args.resume,
    )
    steps = config.num_iterations * config.steps_per_iteration
    brax_env = config.env_name in getattr(envs, "_envs", {})
    where = config.backend if brax_env else "MuJoCo Playground, MJX"
    print(
        f"\nTrained {config.env_name} ({where}) for {steps:,} env steps per seed, "
        f"{len(args.seeds)} seed(s), {args.mode} mode, in {result.seconds:.0f} s "
        "(compilation included)."
    )
    for seed, last in zip(args.seeds, result.last):
        ret = last.get(HEADLINE[0][1])
        shown = "no finished episode" if ret is None else f"{ret:.1f}"
        print(f"  seed {seed}: episode return, mean of the last 100 episodes: {shown}")
    print("TensorBoard event files:")
    for d in result.run_dirs:
        print(f"  {d}")
    if len(result.run_dirs) > 1:
        print(f"  {os.path.join(log_dir, 'seeds_summary')} (mean, IQM, 95% interval across seeds)")
    print(f"Open them with:\n  tensorboard --logdir {log_dir}")
    if every:
        print(
            f"Checkpoints: {checkpoint_dir}; a killed run continues with the same command "
            f"and --resume --log-dir {log_dir}"
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
