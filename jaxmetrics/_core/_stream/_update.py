"""A batch's statistics folded into the stream's per-row fields (count, moments, sum, min,
max, EMA, the windows' positions, the arrival step), elementwise.

XLA runs it over the `[R]` fields after the batch's kernels, as one kernel of its own;
where the fused kernel folds each row in one program (`_kernel`), that program runs it on
its row's fields (`[1, 1]`) instead, and the step has one kernel fewer. Both run this
function, so both compute the same arithmetic.

Steering XLA's fusion: a field that does not depend on the batch's counts `k` (the
non-finite count, the arrival step) is written as `jnp.where(k < 0, 0, x)`. The test never
holds; it makes the field a function of `k`, so that XLA updates it in the one
multi-output kernel that updates the other per-row fields (sibling fusions must share an
operand) instead of in a kernel of its own.
"""

from collections.abc import Callable, Sequence
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax.experimental import pallas as pl

from .. import _count
from .._count import Count
from .._numerics import kahan_add, log2_keep, two_sum
from ._layout import FieldsIn, FieldsOut, Operand, Words
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
    """Per row of a batch (`[R]`; `[1, 1]` inside the fused kernel, its counted sums None
    there): its count, sum, min and max (+-inf when empty), the mean of its deviations
    from `shift` and their sum of squares around that mean, the sum of its `nonfinite`
    flags, and with an EMA its weighted sum (else None); and `counted_sums`, the sums of
    the counted rows (`[C]`)."""

    count: jax.Array  # the field shadows tuple.count  # pyright: ignore[reportIncompatibleMethodOverride]
    sum: jax.Array
    min: jax.Array
    max: jax.Array
    mean_dev: jax.Array
    m2: jax.Array
    nonfinite: jax.Array
    ema: jax.Array | None
    counted_sums: jax.Array | None


class Rows(NamedTuple):
    """What the update needs to know of each row: whether it has an EMA and its coefficient
    (1 where none; None: no row has one), and per window its size and whether the row is
    in it."""

    is_ema: np.ndarray | jax.Array | None
    coeff: np.ndarray | jax.Array | None
    windows: tuple[tuple[int, np.ndarray | jax.Array], ...]


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
    # (1-c)^k as the fused kernel weighs values (`exp2`; 0^0 = 1 for c = 1, as
    # jnp.power gives): a power is a long call on the update's path in that kernel.
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


class InKernel(NamedTuple):
    """The state's fields for the fused kernel to update each row itself (`row_updater`):
    `fields` (`[R]` each), `rows` (`Rows`, its arrays numpy), and the counted rows'
    counts (`[packs * R]`, pack p of row r at `p * R + r`)."""

    fields: Fields
    rows: Rows
    counts: Count


def kernel_operands(
    u: InKernel,
    col: Callable[[jax.Array], Operand],
    whole: Callable[[jax.Array], Operand],
    *,
    shift: Operand,
    steps: Operand,
    ema: tuple[Operand, Operand] | None,
    pos: tuple[Operand, ...],
    listed_sums: Operand | None,
) -> tuple[FieldsIn[Operand], FieldsOut[Operand]]:
    """The fields the fused kernel updates, as its inputs and outputs (`_layout`): each
    one operand in both, updated in place (an output in a buffer of its own costs a copy
    into the loop's state). `col` makes a `[R]` field's operand (a `[1, 1]` block per
    row), `whole` the counted rows' counts' (`[packs, R]`). The kernel's own inputs of
    the mean (`shift`), `steps`, the EMA's weight and offset (`ema`; None without EMA
    rows) and each window's `pos` are updated in place too; `listed_sums` (the counted
    rows' chunk sums, where the rows are read from the lists) is read only."""
    f = u.fields
    packed = _packed(u)
    count, nonfinite = Words(*map(col, f.count)), Words(*map(col, f.nonfinite))
    m2, m2_c, total, total_c, vmin, vmax = map(col, (f.m2, f.m2_c, f.sum, f.sum_c, f.min, f.max))
    value = ema_n = None
    if u.rows.is_ema is not None:
        value, ema_n = col(f.ema), col(f.ema_n)
    filled = tuple(map(col, f.filled))
    counts = Words(*map(whole, packed)) if packed else None
    ins = FieldsIn(
        count,
        nonfinite,
        m2,
        m2_c,
        total,
        total_c,
        vmin,
        vmax,
        value,
        ema_n,
        filled,
        counts,
        listed_sums,
    )
    ema_w, ema_off = ema if ema is not None else (None, None)
    outs = FieldsOut(
        count,
        nonfinite,
        shift,
        m2,
        m2_c,
        total,
        total_c,
        vmin,
        vmax,
        steps,
        value,
        ema_off,
        ema_w,
        ema_n,
        pos,
        filled,
        counts,
    )
    return ins, outs


def _packed(u: InKernel) -> list[jax.Array]:
    """The counted rows' counts as `[packs, R]` words (none without counted rows)."""
    rows = u.fields.mean.shape[0]
    packs = u.counts.lo.shape[0] // rows if rows else 0
    return [a.reshape(packs, rows) for a in u.counts] if packs else []


def from_kernel(u: InKernel, outs: FieldsOut[jax.Array]) -> tuple[Fields, Count]:
    """The fields and counted rows' counts that the kernel wrote (`kernel_operands`)."""
    f = u.fields
    o = jax.tree.map(lambda a: a.reshape(-1), outs)
    ema = (f.ema, f.ema_off, f.ema_w, f.ema_n)
    if o.ema is not None:
        assert o.ema_off is not None and o.ema_w is not None and o.ema_n is not None
        ema = (o.ema, o.ema_off, o.ema_w, o.ema_n)
    fields = Fields(
        Count(*o.count),
        Count(*o.nonfinite),
        o.mean,
        o.m2,
        o.m2_c,
        o.sum,
        o.sum_c,
        o.min,
        o.max,
        *ema,
        steps=o.steps,
        pos=o.pos,
        filled=o.filled,
    )
    return fields, u.counts if o.counts is None else Count(*o.counts)


def row_updater(
    ins: FieldsIn[Any],
    outs: FieldsOut[Any],
    shift: jax.Array,
    steps: jax.Array,
    ema: tuple[jax.Array, jax.Array, jax.Array, jax.Array] | None,
    windows: Sequence[tuple[int, jax.Array, jax.Array]],
    row: jax.Array,
) -> Callable[[Batch, Sequence[jax.Array]], None]:
    """Inside the fused kernel, by the program of row `row` (which folds the whole row):
    the row's fields read from `ins` now, so that the reads overlap the fold, and what
    then updates them (`update`) with the batch's statistics (`Batch`) and the sums of its
    counted rows (`[1, 1]` each) and writes them to `outs` (`kernel_operands`' refs:
    `[1, 1]` blocks of the row, the counts whole); `shift` and `steps` the row's mean and
    arrival step; `ema` its EMA's `(is_ema, coeff, ema_w, ema_off)` (None without EMA
    rows); `windows` per window its size, whether the row is in it and the row's `pos`."""
    count, nonfinite = (Count(*(a[...] for a in w)) for w in (ins.count, ins.nonfinite))
    m2, m2_c, total, total_c, vmin, vmax = (
        a[...] for a in (ins.m2, ins.m2_c, ins.sum, ins.sum_c, ins.min, ins.max)
    )
    # Without EMA rows `update` leaves these as they are and nothing writes them back.
    ema_fields = (shift * 0,) * 4
    rows = Rows(None, None, tuple((size, mine) for size, mine, _ in windows))
    if ema is not None:
        assert ins.ema is not None and ins.ema_n is not None  # `kernel_operands`: with EMA rows
        is_ema, coeff, ema_w, ema_off = ema
        ema_fields = (ins.ema[...], ema_off, ema_w, ins.ema_n[...])
        rows = rows._replace(is_ema=is_ema, coeff=coeff)
    f = Fields(
        count,
        nonfinite,
        shift,
        m2,
        m2_c,
        total,
        total_c,
        vmin,
        vmax,
        *ema_fields,
        steps=steps,
        pos=tuple(p for *_, p in windows),
        filled=tuple(a[...] for a in ins.filled),
    )
    words = ins.counts
    counted = [(pl.ds(p, 1), pl.ds(row, 1)) for p in range(words.hi.shape[0])] if words else []
    counts = [Count(words.hi[at], words.lo[at]) for at in counted] if words else []

    def finish(b: Batch, csums: Sequence[jax.Array]) -> None:
        new = update(f, b, shift, rows, jnp.float32)
        written = _written(new, ema is not None)
        for out, value in zip(jax.tree.leaves(outs._replace(counts=None)), written, strict=True):
            out[...] = value
        for at, count, sums in zip(counted, counts, csums):
            assert outs.counts is not None  # `counted`: there are counted rows
            outs.counts.hi[at], outs.counts.lo[at] = _count.add(
                count, jnp.where(b.count < 0, 0, sums)
            )

    return finish


def _written(f: Fields, ema: bool) -> list[jax.Array]:
    """The fields `update` changes, in `FieldsOut`'s order; the EMA's only with EMA rows
    (`ema`)."""
    out = [*f.count, *f.nonfinite, f.mean, f.m2, f.m2_c, f.sum, f.sum_c, f.min, f.max, f.steps]
    if ema:
        out += [f.ema, f.ema_off, f.ema_w, f.ema_n]
    return out + [*f.pos, *f.filled]
