"""A batch's statistics folded into the stream's per-row fields (count, moments, sum, min,
max, EMA, the windows' positions, the arrival step), elementwise: XLA runs it over the
`[R]` fields after the batch's reduction, as one kernel of its own.

Steering XLA's fusion: a field that does not depend on the batch's counts `k` (the
non-finite count, the arrival step) is written as `jnp.where(k < 0, 0, x)`. The test never
holds; it makes the field a function of `k`, so that XLA updates it in the one
multi-output kernel that updates the other per-row fields (sibling fusions must share an
operand) instead of in a kernel of its own.
"""

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from .. import _count
from .._count import Count
from .._numerics import kahan_add, log2_keep, two_sum
from ._state import INT32_MAX, StreamState


class Fields(NamedTuple):
    """The per-row fields a batch updates (`StreamState`'s), each window's `pos` and
    `filled` in `pos` and `filled`."""

    count: Count  # the field shadows tuple.count  # pyright: ignore[reportIncompatibleMethodOverride]
    nonfinite: Count
    mean: jax.Array
    m2: jax.Array
    m2_c: jax.Array
    sum: jax.Array
    sum_c: jax.Array
    min: jax.Array
    max: jax.Array
    ema: jax.Array
    ema_off: jax.Array
    ema_w: jax.Array
    ema_n: jax.Array
    steps: jax.Array
    pos: tuple[jax.Array, ...]
    filled: tuple[jax.Array, ...]

    @classmethod
    def of(cls, s: StreamState) -> "Fields":
        return cls(
            *(getattr(s, f) for f in cls._fields[:-2]),
            pos=tuple(w.pos for w in s.windows),
            filled=tuple(w.filled for w in s.windows),
        )

    def into(self, s: StreamState) -> StreamState:
        """`s` with these fields (its windows' data as they are in `s`)."""
        fields = self._asdict()
        pos, filled = fields.pop("pos"), fields.pop("filled")
        windows = tuple(w._replace(pos=p, filled=f) for w, p, f in zip(s.windows, pos, filled))
        return s._replace(**fields, windows=windows)


class Batch(NamedTuple):
    """Per row of a batch (`[R]`): its count, sum, min and max (+-inf when empty), the mean
    of its deviations from `shift` and their sum of squares around that mean, the sum of
    its `nonfinite` flags, and with an EMA its weighted sum (else None); and
    `counted_sums`, the sums of the counted rows (`[C]`)."""

    count: jax.Array  # the field shadows tuple.count  # pyright: ignore[reportIncompatibleMethodOverride]
    sum: jax.Array
    min: jax.Array
    max: jax.Array
    mean_dev: jax.Array
    m2: jax.Array
    nonfinite: jax.Array
    ema: jax.Array | None
    counted_sums: jax.Array


class Rows(NamedTuple):
    """What the update needs to know of each row: whether it has an EMA and its coefficient
    (1 where none; None: no row has one), and per window its size and whether the row is
    in it."""

    is_ema: np.ndarray | None
    coeff: np.ndarray | None
    windows: tuple[tuple[int, np.ndarray], ...]


def update(f: Fields, b: Batch, shift: jax.Array, rows: Rows, wt: jnp.dtype) -> Fields:
    """`f` with the batch's statistics `b` folded in (its counted sums aside; `shift`: what
    the batch's deviations were taken from, the period's mean where it has values; `wt`:
    the dtype of weights)."""
    dt = f.mean.dtype
    k = b.count
    kf = k.astype(wt)
    na = _count.as_float(f.count, wt)
    n = na + kf
    frac = jnp.where(n > 0, kf / jnp.maximum(n, 1), 0)
    # With values in the period, shift == mean and mean_dev (the batch's mean minus it)
    # is Chan's delta; without, the new mean is mean_dev (frac == 1) and the old mean
    # carries no weight (na == 0).
    mb = b.mean_dev
    m2, m2_c = kahan_add(f.m2, f.m2_c, b.m2 + mb * mb * (na * frac).astype(dt))
    # Every field below is a function of `k` (an empty batch leaves it as it is).
    some = k > 0
    total, total_c = kahan_add(f.sum, f.sum_c, b.sum)
    total, total_c = jnp.where(some, total, f.sum), jnp.where(some, total_c, f.sum_c)
    mean = period_mean(total, total_c, n, shift + mb * frac.astype(dt))
    vmin = jnp.where(some, jnp.minimum(f.min, b.min), f.min)
    vmax = jnp.where(some, jnp.maximum(f.max, b.max), f.max)

    ema, ema_off, ema_w, ema_n = f.ema, f.ema_off, f.ema_w, f.ema_n
    if rows.is_ema is not None:
        assert b.ema is not None  # EMA rows have their weighted sum
        ema, ema_off, ema_w = _ema_update(f, rows, k, shift, mean, b.ema)
        ema_n = ema_n + jnp.where(rows.is_ema, jnp.minimum(k, INT32_MAX - ema_n), 0)
    pos, filled = [], []
    for (size, mine), p, fill in zip(rows.windows, f.pos, f.filled):
        # Every row's `pos` and `filled`, elementwise in `k` (rows of other windows keep
        # theirs): that keeps them in the one update of the [R] fields.
        stored = jnp.minimum(k, size)
        pos.append(jnp.where(mine, (p + stored) % size, p))
        filled.append(jnp.where(mine, jnp.minimum(fill + stored, size), fill))
    return Fields(
        _count.add(f.count, k),
        # Read through `k`, like `steps` (see the module docstring).
        _count.add(f.nonfinite, jnp.where(k < 0, 0, b.nonfinite)),
        mean,
        m2,
        m2_c,
        total,
        total_c,
        vmin,
        vmax,
        ema,
        ema_off,
        ema_w,
        ema_n,
        f.steps + jnp.where(k < 0, 0, 1).astype(jnp.uint32),
        tuple(pos),
        tuple(filled),
    )


def ema_offset(
    ema_w: jax.Array, ema_off: jax.Array, shift: jax.Array
) -> tuple[jax.Array, jax.Array]:
    """Per row, from the state's `ema_w` and `ema_off` and the batch's `shift`: the offset
    the batch's EMA deviations are taken from, and whether this batch seeds the EMA (none
    seen yet)."""
    seeded = ema_w > 0
    return jnp.where(seeded, ema_off, shift), ~seeded


def _ema_update(
    f: Fields, rows: Rows, k: jax.Array, shift: jax.Array, mean: jax.Array, new: jax.Array
) -> tuple[jax.Array, jax.Array, jax.Array]:
    """New (ema, ema_off, ema_w) of every row (rows without an EMA keep theirs), from the
    batch's sum of the weighted deviations, `new`."""
    assert rows.is_ema is not None  # called for EMA rows only
    dt = f.ema.dtype
    c_all = jnp.asarray(rows.coeff, dt)
    # The deviations were taken off `base`, known before the batch. A seeding batch's
    # weights sum to 1, so its EMA moves to the offset fixed now, the period's mean as of
    # this batch, by adding `base - off`: the rounding of that first batch then decays
    # like any value, where an offset of `base` (0 for a row never seen) would stay.
    base, seeding = ema_offset(f.ema_w, f.ema_off, shift)
    seeded = ~seeding
    off = jnp.where(seeded, f.ema_off, mean)
    # (1-c)^k as `_fold.ema_weights` computes the batch's weights (`exp2` of
    # `log2_keep`; 0^0 = 1 for c = 1, as jnp.power gives): one formula for every power.
    keep = jnp.where(k == 0, 1.0, jnp.exp2(k.astype(dt) * log2_keep(c_all)))
    ema = jnp.where(seeded, keep * f.ema, 0) + new + (base - off)
    # The EMA is `off + ema` as an unevaluated sum, renormalized after every batch (`ema`
    # the rounding error of `off`): an offset fixed at seeding left the EMA of values that
    # moved far from it (a return curve that ramps) with the float32 resolution of that
    # distance, and updates below it were lost.
    off, ema = two_sum(off, ema)
    some = rows.is_ema & (k > 0)
    ema = jnp.where(some, ema, f.ema)
    ema_off = jnp.where(some, off, f.ema_off)
    ema_w = jnp.where(~seeded & some, jnp.ones_like(f.ema_w), f.ema_w)
    return ema, ema_off, ema_w


def period_mean(total: jax.Array, total_c: jax.Array, n: jax.Array, chan: jax.Array) -> jax.Array:
    """The period's mean: its compensated sum over its count, where that is finite, else
    Chan's running mean (`chan`: an empty period's 0, or a sum that overflowed).

    Chan's update `mean + delta * k / n` stops moving in float32 once `delta * k / n` is
    below the mean's ulp (one value per step at counts past ~10^5 of data near 1e4), and
    the variance then grows around the stale mean; the compensated sum holds the mean
    to a few ulp at any count, and the deviations of the next batch are taken from it."""
    dt = total.dtype
    mean = (total - total_c) / jnp.maximum(n, 1).astype(dt)
    return jnp.where((n > 0) & jnp.isfinite(mean), mean, chan)
