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


_LOG2_E = 1.4426950408889634


def log2_keep(c: jax.Array) -> jax.Array:
    """`log2(1 - c)`, the EMA's per-value decay in the exponent of `exp2`. Through `log1p`:
    `1 - c` rounded to float32 moves a coefficient of 1e-6 by up to 5%, `log1p(-c)` keeps
    it to float32's relative precision. `-inf` for `c = 1` (callers take 0^0 as 1)."""
    return jnp.log1p(-c) * jnp.asarray(_LOG2_E, c.dtype)


def two_sum(a: jax.Array, b: jax.Array) -> tuple[jax.Array, jax.Array]:
    """Knuth's error-free sum: `(s, e)` with `s = fl(a + b)` and `s + e == a + b` exactly."""
    s = a + b
    bb = s - a
    return s, (a - (s - bb)) + (b - bb)
