"""How the fused kernel (`_kernel`) splits a batch's rows into chunks, one program each,
and a chunk into blocks (`blocking`), and what is counted and combined for them: each
chunk's masked-in entries, by XLA before the kernel or by the program itself
(`masked_in_around`), and the chunks' partial statistics combined after it.

A row longer than `ONE_PROGRAM` entries is folded by one program per chunk of it
(`chunking`), so that the GPU's multiprocessors share the batch. With an EMA or a ring, a
chunk's program needs the row's masked-in entries before and after it, from which it knows
how many of the row's arrivals follow each of its own (its ranks, EMA weights and ring slots
are the row's): it counts them in the row's mask itself (`masked_in_around`), or one small
XLA reduction first counts each chunk's (`chunk_counts`); without either it needs no rank.
The chunks' partial statistics are combined after the kernel, in the kernel that updates the
per-row state (`combine`).
"""

import functools
from collections.abc import Callable
from typing import NamedTuple

import jax
import jax.numpy as jnp
from jax.experimental import pallas as pl

from ._selected import Selected

ONE_PROGRAM = 1024
"""Entries up to which a row is one program, and per chunk of a chunked row with ranks or of
group rows (twice that without either): a program's time is mostly latency that grows with
its entries (one of 4,096 entries 4.4 us on the H100; ten rows of 4,096 5.3 us, in forty
programs of 1,024 4.0: 0d54162)."""
PROGRAMS = 128
"""Programs up to which rows of `ONE_PROGRAM` to `LONG_ROW` entries are chunked, each chunk
counting the row's mask itself: past it more programs ran no faster than one per row (40,
64, 100 rows of 4,096: 17.4, 18.0, 22.5 us against 14.6, 17.6, 18.8; 0d54162)."""
LONG_ROW = 4096
"""Entries past which every row is chunked, at any number of rows: one program per row of
more entries leaves most of the GPU idle (XLA's kernels, which spread a row over it, were
faster: fbb3d00); group rows past it are read from the lists instead (`_reached.listed`)."""
LONG_PROGRAMS = 160
"""Programs up to which the chunks of ungrouped rows with ranks past `LONG_ROW` entries count
the row's mask themselves, not by XLA's chunk counts (1.3-1.4 us): ten rows at 8,192 envs
12.56 -> 12.13 us, at 16,384 in 160 chunks of 1,024 13.69 -> 13.41 (e5d2f9f). Past
`_reached.LONG` entries such rows are read from the lists, not chunked."""
LARGER_CHUNKS = 16384
"""Entries from which rows with ranks (and group rows) are folded in chunks of 2,048, not
1,024 (16,384 envs 13.02 -> 12.57 us; at 8,192 and 12,288 slower, 11.54 -> 12.07 and
12.13 -> 12.77: 06328a0), and rows without ranks in chunks of 4,096, not 2,048 (24,576 envs
10.22 -> 10.08 us, 65,536 15.32 -> 15.00; at 16,384 either, 9.44 / 9.41; at 8,192 2,048
faster, 8.74 against 8.97: fbf0e6c)."""
GROUPS_CHUNKED = 2048
"""Entries past which group rows are chunked at any number of rows, counted by XLA: set where
64 groups of the full spec at 4,096 envs took 42.4 us with every chunk counting its whole
row's mask, 26.4 counted by XLA (bf76232). Those batches are now read from the lists
(`_reached`); in its range since (period statistics of fewer than `_reached.ROWS` group
rows, 2,049 to 4,096 entries, more than `PROGRAMS` programs) it is not measured."""
COMBINED_BY_REDUCTIONS = 256
"""Rows from which `combine` reduces over the chunks, not elementwise in the per-row update:
with 640 rows of 16 chunks (64 groups, 16,384 envs) the elementwise fold took 9.2 us, the
two reductions 1.3 + 1.5 (94b826c, e64505b)."""


class Chunking(NamedTuple):
    """How a row is folded (`chunking`): by `n` programs of `size` entries each (one
    program: the whole row), the chunks' masked-in entries counted by each program in the
    row's mask itself (`counted_here`) or by an XLA reduction first (`chunk_counts`)."""

    size: int
    n: int
    counted_here: bool


def chunking(rows: int, batch: int, grouped: bool, *, ranked: bool) -> Chunking:
    """How each of `rows` rows of `batch` entries is folded; `grouped`: the rows include
    group rows; `ranked`: with an EMA or a ring. A row past `LONG_ROW` entries in chunks of
    `ONE_PROGRAM` entries (twice that from `LARGER_CHUNKS`) whose partial statistics `fold`
    combines, counted by XLA: one program per long row leaves most of the GPU idle, and
    smaller chunks make more programs and partial statistics than the GPU gains from.
    Ungrouped rows with ranks count them themselves where that makes at most
    `LONG_PROGRAMS` programs: the row's mask read by each of its chunks costs less than
    XLA's kernel of chunk counts there. Ungrouped rows without ranks take chunks of 2,048
    (4,096 from `LARGER_CHUNKS`): they read no chunk counts, and with fewer chunks less is
    left to combine. A shorter one past `ONE_PROGRAM` in chunks of 1,024 where that makes at
    most `PROGRAMS` programs, each counting the row's mask itself. Group rows past
    `GROUPS_CHUNKED` entries are chunked at any number of rows, counted by XLA: a chunk
    without any masked-in entry (most chunks of group rows) costs little. Else one program
    per row. The constants' docstrings give the measured rows (docs/benchmarks.md, "Why the
    fast paths")."""
    if batch > LONG_ROW:
        size = ONE_PROGRAM * (1 if ranked or grouped else 2) * (2 if batch >= LARGER_CHUNKS else 1)
        n = -(-batch // size)
        itself = ranked and not grouped and rows * n <= LONG_PROGRAMS
        return Chunking(size, n, itself)
    n = -(-batch // ONE_PROGRAM)
    if n > 1 and rows * n <= PROGRAMS:
        return Chunking(ONE_PROGRAM, n, True)
    if n > 1 and grouped and batch > GROUPS_CHUNKED:
        return Chunking(ONE_PROGRAM, n, False)
    return Chunking(batch, 1, False)


def reads_counts(rows: int, batch: int, grouped: bool, ranked: bool) -> bool:
    """Whether the kernel reads `chunk_counts` of its `rows` rows of `batch` entries: where
    they are chunked and not `counted_here`, for the ranks (`ranked`: with an EMA or a
    ring)."""
    _, n, counted_here = chunking(rows, batch, grouped, ranked=ranked)
    return n > 1 and not counted_here and ranked


def chunk_counts(batch: Selected, chunk: int) -> jax.Array:
    """Per row that `batch` selects: its masked-in entries in each chunk of `chunk`
    entries (`per_chunk`). XLA reduces the rows' masks, computing them from the source
    rows within the reduction."""
    return per_chunk(batch.dense()[1].astype(jnp.int32), chunk)


def per_chunk(marks: jax.Array, chunk: int) -> jax.Array:
    """Each row of `marks` (`[R, B]` int32) summed over each chunk of `chunk` entries
    (`[R, n]` int32, zero-padded to a power of two `n`)."""
    rows, width = marks.shape
    # The marks padded to a power of two of chunks, not the counts: XLA pads an input in
    # the reduction's kernel, an output in a kernel of its own.
    n = pl.next_power_of_2(-(-width // chunk))
    padded = jnp.pad(marks, ((0, 0), (0, n * chunk - width)))
    return jnp.sum(padded.reshape(rows, n, chunk), axis=2, dtype=jnp.int32)


def counted_input(counted: jax.Array, sources: int) -> jax.Array:
    """The counted rows (`[C, B]`) as a kernel reads them: padded to whole multiples of
    the batch's `sources` rows, so that XLA writes them in the batch's own kernel, where
    `[C, B]` is one more kernel per step."""
    more = -(-counted.shape[0] // sources) * sources - counted.shape[0]
    return jnp.pad(counted, ((0, more), (0, 0)))


def combine(floats: jax.Array, ints: jax.Array) -> tuple[jax.Array, jax.Array]:
    """A row's `floats` and `ints` from its chunks' (`[R, n, 8]`, `[R, n, I]`): sums,
    min, max, and the moments by Chan's rule for n parts. The chunks' mean deviations
    (slot 6) are taken off a pivot every chunk of the row shares (slot 7), near them:
    the sum of their squares does not cancel, and one pass takes it.

    Written as elementwise, pairwise combinations of the n chunks, not as reductions: XLA
    then computes them in the kernel that updates the per-row state, where reductions over
    the chunk axis were kernels of their own (two more per step). From
    `COMBINED_BY_REDUCTIONS` rows on as reductions: that kernel's fold over 16 chunks of
    hundreds of rows took longer than the two reductions."""
    by_reductions = floats.shape[0] >= COMBINED_BY_REDUCTIONS

    def over_chunks(
        op: Callable[[jax.Array, jax.Array], jax.Array],
        reduce: Callable[..., jax.Array],
        a: jax.Array,
    ) -> jax.Array:
        if by_reductions:
            return reduce(a, axis=1)
        # Pairwise: each thread's chain over the chunks is log2(n) ops deep, not n.
        parts = [a[:, j] for j in range(a.shape[1])]
        while len(parts) > 1:
            pairs = range(0, len(parts) - 1, 2)
            parts = [op(parts[j], parts[j + 1]) for j in pairs] + parts[len(parts) & ~1 :]
        return parts[0]

    total = functools.partial(over_chunks, jnp.add, jnp.sum)

    k = ints[..., 0].astype(jnp.float32)
    dev, pivot = floats[..., 6], floats[:, 0, 7]
    s1, s2, n = total(k * dev), total(k * dev * dev), total(k)
    mean = s1 / jnp.maximum(n, 1)
    row_floats = [
        total(floats[..., 0]),
        over_chunks(jnp.minimum, jnp.min, floats[..., 1]),
        over_chunks(jnp.maximum, jnp.max, floats[..., 2]),
        # An empty row's mean deviation is 0, as a row of one chunk gives (the pivot is
        # a value of the source row, here of no entry of the row).
        jnp.where(n > 0, pivot + mean, 0),
        total(floats[..., 4]) + jnp.maximum(s2 - s1 * mean, 0),
        total(floats[..., 5]),
    ]
    # The ints summed as one [R, I] array: stacked from [R] columns, the counted sums of
    # several packs (one row) were a concatenation that XLA wrote in a kernel of its own.
    return jnp.stack(row_floats, axis=1), total(ints)


def blocking(batch: int) -> tuple[int, int]:
    """The block (the largest power of two up to `batch`) and the number of blocks (1 or
    2) that cover a row of `batch` entries. Structural, not tuned: a Triton block's size is
    a power of two, and two overlapping blocks cover any row with no masked-off tail."""
    block = 1 << (batch.bit_length() - 1)
    return block, -(-batch // block)


def masked_in_around(
    mask_at: Callable[[int, int, jax.Array | None], jax.Array],
    batch: int,
    lo: jax.Array | int,
    hi: jax.Array,
) -> tuple[jax.Array, jax.Array]:
    """The masked-in entries of a row of `batch` entries (`Chunking.counted_here`)
    before entry `lo` and from entry `hi` on (`[1, 1]` int32 each), read in `blocking`'s
    blocks by `mask_at(start, n, fresh)` (the row's mask at `n` entries from `start`, those
    not `fresh` masked out; None: all are fresh)."""
    block, n_blocks = blocking(batch)
    earlier = later = jnp.zeros((1, 1), jnp.int32)
    for j in range(n_blocks):
        start = min(j * block, batch - block)
        at = jax.lax.broadcasted_iota(jnp.int32, (1, block), 1) + start
        m = mask_at(start, block, None if start == j * block else at >= j * block)
        m = m.astype(jnp.int32)
        earlier += jnp.sum(jnp.where(at < lo, m, 0), axis=1, keepdims=True)
        later += jnp.sum(jnp.where(at >= hi, m, 0), axis=1, keepdims=True)
    return earlier, later
