"""The policy and value networks, and the diagonal Gaussian the policy samples from."""

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np

_LOG_2PI = float(np.log(2.0 * np.pi))


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
