"""Numerical building blocks shared by the episode accumulators and the report streams."""

import jax
import jax.numpy as jnp


def kahan_add(s: jax.Array, c: jax.Array, x: jax.Array) -> tuple[jax.Array, jax.Array]:
    """Compensated summation: returns (s', c') with s' - c' ~= (s - c) + x.

    `c` carries the low-order bits that `s` lost. Once the sum is infinite or NaN the
    compensation is cleared, so `inf` stays `inf` instead of turning into `inf - inf = NaN`.
    """
    y = x - c
    t = s + y
    comp = (t - s) - y
    return t, jnp.where(jnp.isfinite(t), comp, jnp.zeros_like(comp))


def two_sum(a: jax.Array, b: jax.Array) -> tuple[jax.Array, jax.Array]:
    """Knuth's error-free sum: `(s, e)` with `s = fl(a + b)` and `s + e == a + b` exactly."""
    s = a + b
    bb = s - a
    return s, (a - (s - bb)) + (b - bb)
