"""Arrival ranks and the EMA's batch sum in one GPU kernel (Pallas, Triton).

`_stream.add` needs, per row of a batch `[R, B]`, how many masked-in entries arrive after
each one (`after`, for the window slots and the EMA weights) and the EMA's weighted sum of
the batch. XLA computes them in three kernels: the mask packed into words, the later words'
counts, and the weighted deviations, which it will not fuse into the batch's reduction. One
Triton program per row does all of it: a cumulative sum of the row's mask, and the weighted
sum. On an H100 that is one kernel where XLA had three (isolated full spec, 4096 envs: 10 ->
8 ops, about 0.7 us less per step; with 64 groups 66 -> 45 us), for batches up to
`MAX_BATCH` entries: a row is one block, and from 8192 entries on XLA's two-level rank is
faster.

The kernel runs on CUDA only; elsewhere `_stream` computes the same with jnp, and a test
checks that both agree (the kernel in Pallas' interpret mode).
"""

import jax
import jax.numpy as jnp
from jax.experimental import pallas as pl
from jax.experimental.pallas import triton as plt

MIN_BATCH = 32
MAX_BATCH = 4096


def fits(batch: int, dtype) -> bool:
    """Whether the kernel serves a float32 batch of `batch` entries per row (a power of
    two, one Triton block)."""
    pow2 = batch & (batch - 1) == 0
    return jnp.dtype(dtype) == jnp.float32 and pow2 and MIN_BATCH <= batch <= MAX_BATCH


def _kernel(m_ref, x_ref, c_ref, w_ref, eoff_ref, shift_ref, after_ref, k_ref, ema_ref):
    m = m_ref[...].astype(jnp.int32)  # [1, B]
    total = jnp.sum(m, axis=1, keepdims=True)
    after = total - jnp.cumsum(m, axis=1)
    after_ref[...] = after
    k_ref[...] = total
    c = c_ref[...]  # [1, 1]
    # (1-c)^after; 0^0 = 1 for c = 1, as jnp.power gives.
    decay = jnp.where(after == 0, 1.0, jnp.exp2(after.astype(jnp.float32) * jnp.log2(1 - c)))
    # The offset and seeding are worked out here from the state's own fields: computed
    # outside, XLA put them in the per-row update's kernel, which then had to run before
    # this one and copied seven fields to keep their old values (H100: +6.5 us per step).
    seeded = w_ref[...] > 0
    off = jnp.where(seeded, eoff_ref[...], shift_ref[...])
    first = ~seeded & (c > 0) & (after == total - 1)
    weight = jnp.where(first, decay, c * decay)
    dev = jnp.where(m != 0, x_ref[...] - off, 0.0)
    ema_ref[...] = jnp.sum(weight * dev, axis=1, keepdims=True)


def ranks_and_ema(
    mask: jax.Array,
    values: jax.Array,
    coeff: jax.Array,
    ema_w: jax.Array,
    ema_off: jax.Array,
    shift: jax.Array,
    interpret: bool = False,
) -> tuple[jax.Array, jax.Array, jax.Array]:
    """Per row of `mask[R, B]` (bool) and `values[R, B]` (float32): `after` (`[R, B]`
    int32, how many masked-in entries follow each one), the row's count `k` (`[R]`), and
    `sum c(1-c)^after (x - off)` over its masked-in entries (`[R]`). Per row (float32):
    `coeff` (0 for a row without an EMA), and the state's `ema_w`, `ema_off` and `shift`;
    `off` is `ema_off` for a seeded row (`ema_w > 0`), else `shift`, and the first arrival
    of an unseeded EMA row seeds it, weighing `(1-c)^after` instead."""
    rows, batch = mask.shape
    row = pl.BlockSpec((1, batch), lambda i: (i, 0))
    one = pl.BlockSpec((1, 1), lambda i: (i, 0))
    after, k, ema = pl.pallas_call(
        _kernel,
        out_shape=(
            jax.ShapeDtypeStruct((rows, batch), jnp.int32),
            jax.ShapeDtypeStruct((rows, 1), jnp.int32),
            jax.ShapeDtypeStruct((rows, 1), jnp.float32),
        ),
        grid=(rows,),
        in_specs=[row, row, one, one, one, one],
        out_specs=(row, one, one),
        interpret=interpret,
        compiler_params=None if interpret else plt.CompilerParams(num_warps=8),
    )(
        mask,
        values,
        *(a.reshape(rows, 1) for a in (coeff, ema_w, ema_off, shift)),
    )
    return after, k[:, 0], ema[:, 0]
