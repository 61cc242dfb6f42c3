"""A batch counted into the histograms (`add`): each value's slot, the step's counts
scattered into the state's zero array (`hist_steps`), and their add to the exact counts.

The step's counts are scattered in place into `hist_steps`, which the add writes back as
zeros: a scatter into a fresh zero array costs one more kernel per step, the fill.
"""

import jax
import jax.numpy as jnp
from jax.typing import DTypeLike

from .. import _count
from .._count import Count
from ._state import HistGroup


def slot_counts_scatter(slot: jax.Array, into: jax.Array) -> jax.Array:
    """`into[R, nslots]` (int32) plus, per row, how many entries of `slot[R, B]` equal each
    of 0..nslots-1 (others ignored)."""
    rows = jnp.broadcast_to(jnp.arange(slot.shape[0], dtype=jnp.int32)[:, None], slot.shape)
    return into.at[rows, slot].add(1, mode="drop")


def slot_counts_compare(slot: jax.Array, into: jax.Array) -> jax.Array:
    """Same as `slot_counts_scatter`, as one compare-and-sum reduction."""
    bins = jnp.arange(into.shape[1], dtype=jnp.int32)[None, :, None]
    return into + jnp.sum(slot[:, None, :] == bins, axis=2, dtype=jnp.int32)


def slot(bins: int, values: jax.Array, mask: jax.Array, lo: jax.Array, hi: jax.Array) -> jax.Array:
    """Each value's histogram slot (0: under `lo`, `bins + 1`: over `hi`), or `bins + 2`
    (no slot) where not `mask` or NaN."""
    t = jnp.floor((values - lo) / (hi - lo) * bins)
    inner = jnp.clip(jnp.nan_to_num(t), 0, bins - 1).astype(jnp.int32) + 1
    slots = jnp.where(values < lo, 0, jnp.where(values > hi, bins + 1, inner))
    return jnp.where(mask & ~jnp.isnan(values), slots, bins + 2)


def counted(
    g: HistGroup, zero: jax.Array, values: jax.Array, mask: jax.Array, dt: DTypeLike
) -> jax.Array:
    """The step's counts of histogram `g`'s rows (`values`, `mask`: `[R_h, B]`) scattered
    into `zero` (`hist_steps`)."""
    lo = jnp.asarray(g.lo, dt)[:, None]
    hi = jnp.asarray(g.hi, dt)[:, None]
    # A scatter-add into `zero` in place: cheaper than compare-and-count on CPU and CUDA
    # (XLA does not fuse the compare into the reduction). TPUs scatter slowly: there,
    # compare and count.
    return jax.lax.platform_dependent(
        slot(g.bins, values, mask, lo, hi),
        zero,
        cpu=slot_counts_scatter,
        cuda=slot_counts_scatter,
        default=slot_counts_compare,
    )


def add(
    g: HistGroup, h: Count, zero: jax.Array, values: jax.Array, mask: jax.Array, dt: DTypeLike
) -> tuple[Count, jax.Array]:
    """`h` with the batch counted in, and `zero` (`hist_steps`) as it was."""
    inc = counted(g, zero, values, mask, dt)
    # The zeros read through `inc` (see `_fold`'s module docstring).
    return _count.add(h, inc), jnp.where(inc < 0, inc, 0)
