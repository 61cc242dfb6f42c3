"""Running observation statistics, and the normalization the policy sees through them."""

from typing import NamedTuple

import jax
import jax.numpy as jnp


class ObsStats(NamedTuple):
    """Running observation statistics (Welford/Chan), `[obs_size]` each."""

    count: jax.Array  # shape=(), float32: observations seen (shadows tuple.count)  # pyright: ignore[reportIncompatibleMethodOverride]
    mean: jax.Array  # [obs_size] float32
    m2: jax.Array  # [obs_size] float32: sum of squared deviations


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
