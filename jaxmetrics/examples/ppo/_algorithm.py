"""PPO itself: the pure `init` and `iteration` functions of a run, and the estimates they
are made of.

GAE, the clipped surrogate objective, a value loss, an entropy bonus, running observation
normalization and minibatch epochs; a Gaussian policy with a state-independent log-std whose
samples are clipped to the action range [-1, 1] before they reach the env (the
log-probability is that of the unclipped sample, as in CleanRL and PureJaxRL). Truncated
episodes are handled as Brax's PPO does: the transition on which the time limit cuts an
episode carries no advantage and no value error.
"""

from collections.abc import Callable
from typing import Any, NamedTuple, cast

import jax
import jax.numpy as jnp
import optax

import jaxmetrics as jm
import jaxmetrics.brax as jmb

from ._config import PPOConfig
from ._envs import make_env
from ._networks import ActorCritic, gaussian_entropy, gaussian_log_prob
from ._obs_stats import ObsStats, init_obs_stats, normalize_obs, update_obs_stats

# `ActorCritic`'s outputs (mean, log_std, value): what `network.apply` returns without
# mutable collections (flax annotates it for both).
_Outputs = tuple[jax.Array, jax.Array, jax.Array]


class TrainState(NamedTuple):
    """Everything that changes during training; the MetricsState is in `env_state.info`."""

    params: Any  # flax parameters of `ActorCritic`
    opt_state: Any  # optax state of the gradient transformation
    obs_stats: ObsStats
    env_state: Any  # the Brax `State` of all envs, with the MetricsState inside
    key: jax.Array  # PRNG key
    iteration: jax.Array  # shape=(), int32: iterations done

    def metrics_state(self) -> jm.MetricsState:
        """The MetricsState of all envs, which the env state carries."""
        return jmb.metrics_state(self.env_state)

    def with_metrics_state(self, mstate: jm.MetricsState) -> "TrainState":
        """This state with `mstate` (as `Logger.flush` or `emit` returned it) in its env state."""
        return self._replace(env_state=jmb.replace_metrics_state(self.env_state, mstate))


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
    variance is only the value net's float32 noise, and this ratio of two noise levels
    goes negative although the targets are right.
    """
    y, v = targets.reshape(-1), values.reshape(-1)
    var_y = jnp.var(y)
    return jnp.where(var_y > 0, 1.0 - jnp.var(y - v) / jnp.where(var_y > 0, var_y, 1.0), jnp.nan)


class PPO(NamedTuple):
    """A PPO built for one config: static parts plus un-jitted pure functions.

    Attributes:
      config: the configuration.
      env: the wrapped, batched env (`make_env`).
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


_DEFAULT_CONFIG = PPOConfig()


def make_ppo(config: PPOConfig = _DEFAULT_CONFIG) -> PPO:
    """Builds the env and its metrics spec (`make_env`), and the pure `init`/`iteration`
    functions.

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
    env, metrics, obs_size, action_size, env_sharding = make_env(config)
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
        # optax (e.g. its `decay ** count`) runs under JAX's default promotion whatever the
        # user's config, as Brax does in `make_env`.
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
        mean, log_std, value = cast(_Outputs, network.apply(params, batch["obs"]))
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
            mean, log_std, value = cast(_Outputs, network.apply(params, obs))
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
        _, _, last_value = cast(
            _Outputs, network.apply(params, normalize_obs(stats, env_state.obs))
        )
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
