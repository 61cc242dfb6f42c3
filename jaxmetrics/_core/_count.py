"""Exact counters that do not overflow at 2^31, without `jax_enable_x64`.

A count is two uint32 words (`hi`, `lo`): value = hi * 2^32 + lo, exact up to 2^64 - 1.
Brax and MuJoCo Playground keep step counters in int32 and wrap after 2^31 env steps
(about 9 minutes of 4096 envs at 1000 steps/s); this is the fix.
"""

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from ._sharding import gathered

_TWO_32 = 4294967296.0


class Count(NamedTuple):
    """An exact count, elementwise over any shape (counts are non-negative; a counter may
    be decremented, see `add_at`).

    Attributes:
      hi: high 32 bits, dtype uint32.
      lo: low 32 bits, dtype uint32.
    """

    hi: jax.Array
    lo: jax.Array


def zeros(shape: tuple[int, ...] = ()) -> Count:
    """A zero count of the given shape."""
    return Count(jnp.zeros(shape, jnp.uint32), jnp.zeros(shape, jnp.uint32))


def add(count: Count, inc: jax.Array) -> Count:
    """Adds a non-negative integer increment (< 2^32) with carry into the high word."""
    inc = jnp.asarray(inc).astype(jnp.uint32)
    # The carry from the old low word, not the new one: both words are then functions
    # of (lo, inc), which XLA computes in one kernel without keeping a copy of `lo`.
    carry = (inc > ~count.lo).astype(jnp.uint32)
    return Count(count.hi + carry, count.lo + inc)


def add_at(count: Count, index: int, inc: jax.Array) -> Count:
    """Adds a scalar integer `inc` to element `index` of a `[n]` count, exactly modulo
    2^64: a signed `inc` is sign-extended, so a negative one subtracts (and `to_int`
    reads a count that went below zero as negative)."""
    inc = jnp.asarray(inc)
    neg = (inc < 0) if jnp.issubdtype(inc.dtype, jnp.signedinteger) else jnp.bool_(False)
    word = jnp.zeros(count.lo.shape, jnp.uint32).at[index].set(inc.astype(jnp.uint32))
    high = (
        jnp.zeros(count.hi.shape, jnp.uint32)
        .at[index]
        .set(jnp.where(neg, jnp.uint32(0xFFFFFFFF), jnp.uint32(0)))
    )
    return merge(count, Count(high, word))


def merge(a: Count, b: Count) -> Count:
    """Exact sum of two counts."""
    carry = (b.lo > ~a.lo).astype(jnp.uint32)
    return Count(a.hi + b.hi + carry, a.lo + b.lo)


def as_float(count: Count, dtype: jnp.dtype) -> jax.Array:
    """The count as a float (rounded where it exceeds the float's mantissa), for weights."""
    return count.hi.astype(dtype) * _TWO_32 + count.lo.astype(dtype)


def is_zero(count: Count) -> jax.Array:
    return (count.hi == 0) & (count.lo == 0)


def to_int(count: Count) -> int | np.ndarray:
    """Host side: the exact count as a Python int (scalar) or an int64 numpy array; the
    64 bits are read as a signed integer (a counter decremented below zero is negative)."""
    hi = np.asarray(count.hi).astype(np.uint64)
    lo = np.asarray(count.lo).astype(np.uint64)
    exact = ((hi << np.uint64(32)) | lo).astype(np.int64)
    if exact.ndim == 0:
        return int(exact)
    return exact


def total(count: Count) -> Count:
    """Exact sum of a count along its leading axis (a scalar count for a `[n]` one)."""
    count = Count(gathered(count.hi), gathered(count.lo))
    zero = zeros(count.hi.shape[1:])
    if count.hi.shape[0] == 0:
        return zero
    return jax.lax.scan(lambda acc, c: (merge(acc, Count(*c)), None), zero, tuple(count))[0]
