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


def update(f: Fields, b: Batch, shift, rows: Rows, wt) -> Fields:
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


def ema_offset(ema_w, ema_off, shift) -> tuple[jax.Array, jax.Array]:
    """Per row, from the state's `ema_w` and `ema_off` and the batch's `shift`: the offset
    the batch's EMA deviations are taken from, and whether this batch seeds the EMA (none
    seen yet)."""
    seeded = ema_w > 0
    return jnp.where(seeded, ema_off, shift), ~seeded


def _ema_update(f: Fields, rows: Rows, k, shift, mean, new):
    """New (ema, ema_off, ema_w) of every row (rows without an EMA keep theirs), from the
    batch's sum of the weighted deviations, `new`."""
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


def kernel_inputs(u: InKernel) -> list[jax.Array]:
    """The fields the kernel reads besides its own inputs (the mean, the step, the EMA's
    offset and weight, the windows' `pos`), in `row_updater`'s order: count, non-finite
    count, m2, sum, min, max, with an EMA the EMA and its count, each window's `filled`,
    each `[R]`; then the counted rows' counts as `[packs, R]`."""
    f = u.fields
    ins = [*f.count, *f.nonfinite, f.m2, f.m2_c, f.sum, f.sum_c, f.min, f.max]
    if u.rows.is_ema is not None:
        ins += [f.ema, f.ema_n]
    return ins + list(f.filled) + _packed(u)


def kernel_outputs(u: InKernel) -> list[jax.ShapeDtypeStruct]:
    """What the kernel writes: every field `update` changes, and the counted rows' counts
    (`[packs, R]`); `Out` names their positions."""
    outs = _written(u.fields, u.rows.is_ema is not None) + _packed(u)
    return [jax.ShapeDtypeStruct(a.shape, a.dtype) for a in outs]


def _written(f: Fields, ema: bool) -> list[jax.Array]:
    """The fields `update` changes, in the kernel's output order (`Out`); the EMA's only
    with EMA rows (`ema`)."""
    out = [*f.count, *f.nonfinite, f.mean, f.m2, f.m2_c, f.sum, f.sum_c, f.min, f.max, f.steps]
    if ema:
        out += [f.ema, f.ema_off, f.ema_w, f.ema_n]
    return out + [*f.pos, *f.filled]


class Out:
    """Positions in `kernel_outputs`."""

    MEAN, STEPS = 4, 11
    EMA, EMA_OFF, EMA_W, EMA_N = 12, 13, 14, 15

    @staticmethod
    def pos(u: InKernel, i: int) -> int:
        return Out.EMA + 4 * (u.rows.is_ema is not None) + i

    @staticmethod
    def of_inputs(u: InKernel) -> list[int]:
        """Per `kernel_inputs` entry, its output: each field is updated in place."""
        ema = u.rows.is_ema is not None
        windows = len(u.fields.pos)
        out = [0, 1, 2, 3, 5, 6, 7, 8, 9, 10] + ([Out.EMA, Out.EMA_N] if ema else [])
        first = Out.pos(u, windows)
        out += list(range(first, first + windows))
        return out + [first + windows + i for i in range(len(_packed(u)))]


def aliases(u: InKernel, first_in: int, first_out: int, *, shift, steps, ema, pos) -> dict:
    """The fused kernel's input-output aliases of the fields it updates, each in place (an
    output in a buffer of its own costs a copy into the loop's state): `kernel_inputs`
    from input `first_in` on, to `kernel_outputs` from output `first_out` on; and the
    kernel's own inputs of the fields, at `shift` (the mean), `steps`, `ema` (the EMA's
    weight, then its offset; None without EMA rows) and `pos` (each window's)."""
    out = {first_in + i: first_out + o for i, o in enumerate(Out.of_inputs(u))}
    out[shift] = first_out + Out.MEAN
    out[steps] = first_out + Out.STEPS
    if ema is not None:
        out[ema], out[ema + 1] = first_out + Out.EMA_W, first_out + Out.EMA_OFF
    for i, at in enumerate(pos):
        out[at] = first_out + Out.pos(u, i)
    return out


def _packed(u: InKernel) -> list[jax.Array]:
    """The counted rows' counts as `[packs, R]` words (none without counted rows)."""
    rows = u.fields.mean.shape[0]
    packs = u.counts.lo.shape[0] // rows if rows else 0
    return [a.reshape(packs, rows) for a in u.counts] if packs else []


def from_kernel(u: InKernel, outs: list[jax.Array]) -> tuple[Fields, Count]:
    """The fields and counted rows' counts that the kernel wrote (`kernel_outputs`)."""
    f = u.fields
    outs = [a.reshape(-1) for a in outs]
    count, nonfinite = Count(*outs[0:2]), Count(*outs[2:4])
    mean, m2, m2_c, total, total_c, vmin, vmax, steps = outs[4:12]
    rest = outs[12:]
    ema = (f.ema, f.ema_off, f.ema_w, f.ema_n)
    if u.rows.is_ema is not None:
        ema, rest = tuple(rest[:4]), rest[4:]
    w = len(f.pos)
    pos, filled, rest = tuple(rest[:w]), tuple(rest[w : 2 * w]), rest[2 * w :]
    counts = Count(*rest) if rest else u.counts
    fields = Fields(
        count,
        nonfinite,
        mean,
        m2,
        m2_c,
        total,
        total_c,
        vmin,
        vmax,
        *ema,
        steps=steps,
        pos=pos,
        filled=filled,
    )
    return fields, counts


def row_updater(
    ins: Sequence[Any],
    outs: Sequence[Any],
    shift: jax.Array,
    steps: jax.Array,
    ema: tuple[jax.Array, jax.Array, jax.Array, jax.Array] | None,
    windows: Sequence[tuple[int, jax.Array, jax.Array]],
    row: jax.Array,
) -> Callable[[Batch, Sequence[jax.Array]], None]:
    """Inside the fused kernel, by the program of row `row` (which folds the whole row):
    the row's fields read from `ins` now, so that the reads overlap the fold, and what
    then updates them (`update`) with the batch's statistics (`Batch`) and the sums of its
    counted rows (`[1, 1]` each) and writes them to `outs`. `ins` and `outs` are
    `kernel_inputs` and `kernel_outputs` (`[1, 1]` blocks of the row, the counts whole);
    `shift` and `steps` the row's mean and arrival step; `ema` its EMA's `(is_ema, coeff,
    ema_w, ema_off)` (None without EMA rows); `windows` per window its size, whether the
    row is in it and the row's `pos`."""
    ins = list(ins)

    def take(n):
        return [ins.pop(0)[...] for _ in range(n)]

    count_hi, count_lo, nf_hi, nf_lo, m2, m2_c, total, total_c, vmin, vmax = take(10)
    # Without EMA rows `update` leaves these as they are and nothing writes them back.
    ema_fields = (shift * 0,) * 4
    rows = Rows(None, None, tuple((size, mine) for size, mine, _ in windows))
    if ema is not None:
        is_ema, coeff, ema_w, ema_off = ema
        value, ema_n = take(2)
        ema_fields = (value, ema_off, ema_w, ema_n)
        rows = rows._replace(is_ema=is_ema, coeff=coeff)
    pos, filled = [p for *_, p in windows], take(len(windows))
    f = Fields(
        Count(count_hi, count_lo),
        Count(nf_hi, nf_lo),
        shift,
        m2,
        m2_c,
        total,
        total_c,
        vmin,
        vmax,
        *ema_fields,
        steps=steps,
        pos=tuple(pos),
        filled=tuple(filled),
    )
    counted = [(pl.ds(p, 1), pl.ds(row, 1)) for p in range(ins[0].shape[0])] if ins else []
    counts = [Count(ins[0][at], ins[1][at]) for at in counted]

    def finish(b: Batch, csums: Sequence[jax.Array]) -> None:
        written = _written(update(f, b, shift, rows, jnp.float32), ema is not None)
        for out, value in zip(outs, written):
            out[...] = value
        words = outs[len(written) :]
        for at, count, sums in zip(counted, counts, csums):
            words[0][at], words[1][at] = _count.add(count, jnp.where(b.count < 0, 0, sums))

    return finish
