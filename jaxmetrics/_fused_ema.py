"""A batch's arrival-ordered statistics in one GPU kernel (Pallas, Triton): arrival
ranks, the EMA's weighted sum and the ring inserts.

`_stream.add` needs, per row of a batch `[R, B]`, how many masked-in entries arrive after
each one (`after`), then the EMA's weighted sum of the batch and the newest values written
to their ring slots (windows, EMA history). XLA does that in four kernels (the mask packed
into words, the later words' counts, the weighted deviations, the ring scatter). One Triton
program per row does it all: a cumulative sum of the row's mask gives the ranks, the
weighted sum follows, and the ring slots are written in place (the rings are aliased to
the outputs; other rows never touch a row's slots).

The kernel runs on CUDA only; elsewhere `_stream` computes the same with jnp, and tests
check that both agree (the kernel in Pallas' interpret mode).
"""

import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax.experimental import pallas as pl
from jax.experimental.pallas import triton as plt

MIN_BATCH = 32
MAX_BATCH = 4096


def fits(batch: int, dtype) -> bool:
    """Whether the kernel serves a float32 batch of `batch` entries per row (a power of
    two, one Triton block)."""
    pow2 = batch & (batch - 1) == 0
    return jnp.dtype(dtype) == jnp.float32 and pow2 and MIN_BATCH <= batch <= MAX_BATCH


class RingIn(NamedTuple):
    """A ring (`_stream.Ring`'s `data`, `[rows, size, 2]` uint32: value bits, stamp) and
    where each batch row goes: `row[r]` its ring row (-1: none), `pos[pos_row[r]]` the
    ring row's next slot."""

    data: jax.Array
    pos: jax.Array
    row: np.ndarray
    pos_row: np.ndarray


class EmaIn(NamedTuple):
    """Per batch row: the EMA's coefficient `coeff` (0: no EMA) and the state's `ema_w`,
    `ema_off` and the batch's `shift` (float32)."""

    coeff: np.ndarray
    ema_w: jax.Array
    ema_off: jax.Array
    shift: jax.Array


def _kernel(*refs, ema: bool, rings: tuple[int, ...]):
    """One batch row; `rings` are the ring sizes. `table` holds the row's static ints:
    the EMA coefficient's bits, then each ring's `row` and `pos_row`."""
    m_ref, x_ref, step_ref, table, *refs = refs
    if ema:
        w_ref, eoff_ref, shift_ref, *refs = refs
    ring_in, refs = refs[: 2 * len(rings)], refs[2 * len(rings) :]
    if ema:
        ema_ref, *refs = refs

    m = m_ref[...].astype(jnp.int32)  # [1, B]
    on = m != 0
    x = x_ref[...]
    total = jnp.sum(m, axis=1, keepdims=True)
    after = total - jnp.cumsum(m, axis=1)
    if ema:
        c = jax.lax.bitcast_convert_type(table[:, 0:1], jnp.float32)  # [1, 1]
        # (1-c)^after; 0^0 = 1 for c = 1, as jnp.power gives.
        decay = jnp.where(after == 0, 1.0, jnp.exp2(after.astype(jnp.float32) * jnp.log2(1 - c)))
        # The offset and seeding are worked out here from the state's own fields:
        # computed outside, XLA put them in the per-row update's kernel, which then had
        # to run before this one and copied seven fields to keep their old values (H100:
        # +6.5 us per step).
        seeded = w_ref[...] > 0
        off = jnp.where(seeded, eoff_ref[...], shift_ref[...])
        first = ~seeded & (c > 0) & (after == total - 1)
        weight = jnp.where(first, decay, c * decay)
        dev = jnp.where(on, x - off, 0.0)
        ema_ref[...] = jnp.sum(weight * dev, axis=1, keepdims=True)

    # Only the last `size` arrivals go in, to consecutive slots in arrival order. The
    # rings are aliased to their outputs: what this row does not write stays. Entries
    # left out are also pointed past the ring (Pallas' interpret mode writes them back).
    bits = jax.lax.bitcast_convert_type(x, jnp.uint32)
    stamp = jnp.broadcast_to(step_ref[...], x.shape)
    for i, (size, out) in enumerate(zip(rings, refs)):
        row = table[:, 1 + 2 * i : 2 + 2 * i]  # [1, 1]
        pos_row = jnp.maximum(table[:, 2 + 2 * i : 3 + 2 * i], 0)
        pos = plt.load(ring_in[2 * i + 1].at[pos_row[:, 0]])[:, None]
        stored = jnp.minimum(total, size)
        keep = on & (after < size) & (row >= 0)
        slot = jnp.where(keep, jax.lax.rem(pos + stored - 1 - after, size), size)
        rows = jnp.broadcast_to(jnp.maximum(row, 0), x.shape)
        plt.store(out.at[rows, slot, jnp.zeros_like(slot)], bits, mask=keep)
        plt.store(out.at[rows, slot, jnp.ones_like(slot)], stamp, mask=keep)


def fold(
    mask: jax.Array,
    values: jax.Array,
    steps: jax.Array,
    ema: EmaIn | None = None,
    rings: tuple[RingIn, ...] = (),
    interpret: bool = False,
) -> tuple[jax.Array | None, tuple[jax.Array, ...]]:
    """Folds a batch `values[R, B]` (float32) where `mask` (bool) into the EMA and the
    rings. Returns: per row, `sum c(1-c)^after (x - off)` over its masked-in entries
    (`[R]`; None without `ema`), with `after` how many masked-in entries follow each
    one; and each ring's data with its rows' newest arrivals written in, stamped with
    the row's `steps[r]` (uint32).

    With `ema`: `off` is `ema_off` for a seeded row (`ema_w > 0`), else `shift`, and the
    first arrival of an unseeded EMA row seeds it, weighing `(1-c)^after` instead.
    `interpret` runs it anywhere, slowly (Pallas' interpret mode).
    """
    rows, batch = mask.shape
    coeff = np.zeros(rows, np.float32) if ema is None else np.asarray(ema.coeff, np.float32)
    table = [coeff.view(np.int32)]
    for r in rings:
        table += [np.asarray(r.row, np.int32), np.asarray(r.pos_row, np.int32)]
    table = np.stack(table, axis=1)
    table = np.pad(table, ((0, 0), (0, pl.next_power_of_2(table.shape[1]) - table.shape[1])))

    def whole(a):
        return pl.BlockSpec(a.shape, lambda i: (0,) * a.ndim)

    def col(a):
        return a.reshape(rows, 1)

    line = pl.BlockSpec((1, batch), lambda i: (i, 0))
    one = pl.BlockSpec((1, 1), lambda i: (i, 0))
    args = [
        (mask, line),
        (values, line),
        (col(steps.astype(jnp.uint32)), one),
        (jnp.asarray(table), pl.BlockSpec((1, table.shape[1]), lambda i: (i, 0))),
    ]
    if ema is not None:
        args += [(col(a), one) for a in (ema.ema_w, ema.ema_off, ema.shift)]
    first_ring = len(args)
    for r in rings:
        args += [(r.data, whole(r.data)), (r.pos, whole(r.pos))]
    outs = [(jax.ShapeDtypeStruct((rows, 1), jnp.float32), one)] if ema is not None else []
    outs += [(jax.ShapeDtypeStruct(r.data.shape, r.data.dtype), whole(r.data)) for r in rings]
    out = pl.pallas_call(
        functools.partial(
            _kernel, ema=ema is not None, rings=tuple(r.data.shape[1] for r in rings)
        ),
        out_shape=tuple(s for s, _ in outs),
        grid=(rows,),
        in_specs=[s for _, s in args],
        out_specs=tuple(s for _, s in outs),
        input_output_aliases={
            first_ring + 2 * i: len(outs) - len(rings) + i for i in range(len(rings))
        },
        interpret=interpret,
        compiler_params=None if interpret else plt.CompilerParams(num_warps=8),
    )(*(a for a, _ in args))
    ema_sum = out[0][:, 0] if ema is not None else None
    return ema_sum, tuple(out[len(out) - len(rings) :])
