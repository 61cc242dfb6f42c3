"""A batch counted into the histograms: each value's slot, the step's counts scattered
into the state's zero array (`hist_steps`), and their add to the exact counts, by XLA
(`add`) or, on a CUDA GPU, inside the fused kernel (`HistIn`, `add_in_kernel`). Where
that kernel reads rows from the lists of reached entries, it counts them itself and XLA
scatters nothing: group rows (a few entries a row) in each row's program (`HistRows`,
`count_in_kernel`), ungrouped rows (hundreds of entries a step past 16,384 envs) in
programs of their own beside the rows' (`Pairs`, `count_pair_in_kernel`).

The step's counts are scattered in place into `hist_steps`, which the add writes back as
zeros: a scatter into a fresh zero array costs one more kernel per step, the fill.
"""

import functools
from collections.abc import Callable, Sequence
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax.experimental import pallas as pl
from jax.experimental.pallas import triton as plt
from jax.typing import DTypeLike

from .. import _count
from .._count import Count
from ._layout import HistOf
from ._selected import Selected
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


def counted_selected(g: HistGroup, zero: jax.Array, batch: Selected, dt: DTypeLike) -> jax.Array:
    """`counted` of the histogram's rows that `batch` selects (`g.rows`), on a CUDA GPU:
    with group rows, each entry of a source row scattered once per grouping into the row
    of its group (`Selected.row_of`), where the rows as arrays would be a masked copy of
    the source per group, each scattered whole. The kernel adds them to the counts
    (`HistIn`)."""
    sel = batch.take(g.rows)
    if not sel.grouped:
        return counted(g, zero, *sel.dense()[:2], dt)
    src, row = sel.row_of()
    lo, hi = (jnp.asarray((*bound, 0.0), dt)[row] for bound in (g.lo, g.hi))
    values = jnp.take(sel.values, src, axis=0)
    return zero.at[row, slot(g.bins, values, row < sel.rows, lo, hi)].add(1, mode="drop")


def add(
    g: HistGroup, h: Count, zero: jax.Array, values: jax.Array, mask: jax.Array, dt: DTypeLike
) -> tuple[Count, jax.Array]:
    """`h` with the batch counted in, and `zero` (`hist_steps`) as it was."""
    inc = counted(g, zero, values, mask, dt)
    # The zeros read through `inc` (see `_fold`'s module docstring).
    return _count.add(h, inc), jnp.where(inc < 0, inc, 0)


class HistIn(NamedTuple):
    """A histogram's counts (`HistGroup`: the low and high words, `[rows, bins + 2]`
    uint32) and the step's counts scattered into its zero array (`hist_steps`, int32), as
    the fused kernel takes them."""

    counted: jax.Array
    lo: jax.Array
    hi: jax.Array


def add_in_kernel(row: jax.Array, ins: Sequence[HistOf[Any]], outs: Sequence[HistOf[Any]]) -> None:
    """Inside the fused kernel: row `row` of each histogram (where it has one), its step
    counts added to its words with the carry (`_count.add`), and zeroed (`HistIn`; `ins`
    and `outs` the histograms' refs, `_layout.HistOf`). A histogram's rows are some of the
    batch's, so the batch's programs cover them, each a row."""
    for (step, lo, hi), (out_step, out_lo, out_hi) in zip(ins, outs):
        rows, slots = step.shape
        c = jax.lax.broadcasted_iota(jnp.int32, (1, pl.next_power_of_2(slots)), 1)
        there = (c < slots) & (row < rows)
        # Entries left out are pointed past the row (Pallas' interpret mode writes them
        # back).
        at = (jnp.broadcast_to(jnp.minimum(row, rows - 1), c.shape), jnp.where(there, c, slots))
        inc = plt.load(step.at[at], mask=there, other=0).astype(jnp.uint32)
        _add_with_carry(inc, at, there, lo, hi, out_lo, out_hi)
        plt.store(out_step.at[at], jnp.zeros_like(inc, step.dtype), mask=there)


def _add_with_carry(
    inc: jax.Array,
    at: tuple[jax.Array, jax.Array],
    there: jax.Array,
    lo: Any,
    hi: Any,
    lo_out: Any,
    hi_out: Any,
) -> None:
    """Inside the fused kernel: `inc` (uint32) added to a histogram's low words at `at`
    (where `there`) with the carry into its high words (`_count.add`), read from `lo`,
    `hi` and written to `lo_out`, `hi_out`."""
    low = plt.load(lo.at[at], mask=there, other=0)
    high = plt.load(hi.at[at], mask=there, other=0)
    plt.store(lo_out.at[at], low + inc, mask=there)
    plt.store(hi_out.at[at], high + (inc > ~low).astype(jnp.uint32), mask=there)


class HistRows(NamedTuple):
    """A histogram that the fused kernel counts itself: its bins, and per batch row its
    row of the histogram (-1: none) and that row's range (float32, 0 where none)."""

    bins: int
    row: np.ndarray
    lo: np.ndarray
    hi: np.ndarray

    @classmethod
    def of(cls, g: HistGroup, row: np.ndarray) -> "HistRows":
        """`g` with `row`, its row of each batch row (`g.rows` are batch rows)."""
        lo, hi = np.zeros(row.shape, np.float32), np.zeros(row.shape, np.float32)
        lo[list(g.rows)], hi[list(g.rows)] = g.lo, g.hi
        return cls(g.bins, row, lo, hi)


def count_in_kernel(
    bins: int,
    spec: tuple[jax.Array, ...],
    blocks: Callable[..., Any],
    values_of: Callable[[], Any],
    total: jax.Array,
    words: tuple[Any, Any, Any, Any],
) -> None:
    """Inside the fused kernel, reading a row from its list: the row's entries counted into
    its row of a histogram of `bins` bins, if it has one. `spec` is the row's table columns
    as three `[1, 1]` slices (Triton's arrays are powers of two): its histogram row (-1:
    none) and the float32 bits of `lo` and `hi`. `blocks` and `values_of` read the row
    (`_program`'s `_fold_blocks`), `total` is its masked-in entries, `words` the histogram's
    low and high words in, then out."""
    row = jnp.sum(spec[0])
    lo, hi = (jax.lax.bitcast_convert_type(c, jnp.float32) for c in spec[1:])

    def count() -> None:
        def body(m: jax.Array, bad: jax.Array, *rest: Any) -> jax.Array:
            *_, x, acc = rest
            return acc + counted_in_kernel(bins, x, m, lo, hi)

        zero = jnp.zeros((pl.next_power_of_2(bins + 2), 1), jnp.int32)
        add_counted_in_kernel(row, blocks(body, zero, values_of()), *words)

    jax.lax.cond((row >= 0) & (jnp.sum(total) > 0), count, lambda: None)


class Pairs(NamedTuple):
    """The (batch row, histogram row) pairs that programs of their own count (`of`), as the
    fused kernel takes them: `table` (`[P, 4]` int32, P a power of two: the batch row's
    source row, its histogram row, the float32 bits of the row's `lo` and `hi`) and each
    histogram's number of pairs (`sizes`), the pairs in histogram order."""

    table: np.ndarray
    sizes: tuple[int, ...]

    @classmethod
    def of(cls, hist_rows: tuple[HistRows, ...], src: tuple[int, ...]) -> "Pairs":
        """The pairs of `hist_rows` (one per histogram), each histogram's in batch row
        order; `src`: each batch row's source row (`Selected`), whose list it reads."""
        table, sizes = [], []
        for h in hist_rows:
            mine = np.flatnonzero(h.row >= 0)
            bits = [np.asarray(a, np.float32)[mine].view(np.int32) for a in (h.lo, h.hi)]
            table += list(zip(np.asarray(src)[mine], h.row[mine], *bits))
            sizes.append(len(mine))
        out = np.zeros((pl.next_power_of_2(max(len(table), 1)), 4), np.int32)
        out[: len(table)] = np.array(table, np.int32).reshape(-1, 4)
        return cls(out, tuple(sizes))


def count_pair_in_kernel(
    j: jax.Array,
    sizes: tuple[int, ...],
    bins: tuple[int, ...],
    table_ref: Any,
    entries_of: Callable[[jax.Array], tuple[jax.Array, Callable[[Any], Any], int]],
    ins: Sequence[HistOf[Any]],
    outs: Sequence[HistOf[Any]],
) -> None:
    """Inside the fused kernel, the program of pair `j` (`Pairs`: `table_ref` its table,
    `sizes` its pairs per histogram; `bins` each histogram's): the entries of the pair's
    batch row, read from its list, counted into its row of the histogram.
    `entries_of(src)` gives the length of source row `src`'s list, what reads a block of
    it at an entry (`[1, n]` mask and values, in entry order) and the block's `n`;
    `ins` and `outs` are the histograms' refs (`_layout.HistOf`). Apart from the rows'
    programs, the count runs beside their folds, where in a row's program it would run
    after it."""
    src, row, lo, hi = (table_ref[pl.ds(j, 1), pl.ds(c, 1)] for c in range(4))
    src, row = jnp.sum(src), jnp.sum(row)
    lo, hi = (jax.lax.bitcast_convert_type(c, jnp.float32) for c in (lo, hi))
    length, block, n = entries_of(src)

    def count(i: int, nbins: int) -> None:
        def step(k: jax.Array, acc: jax.Array) -> jax.Array:
            mask, values = block(k * n)
            return acc + counted_in_kernel(nbins, values, mask, lo, hi)

        zero = jnp.zeros((pl.next_power_of_2(nbins + 2), 1), jnp.int32)
        inc = jax.lax.fori_loop(0, (length + n - 1) // n, step, zero)
        add_counted_in_kernel(row, inc, ins[i].lo, ins[i].hi, outs[i].lo, outs[i].hi)

    start = 0
    for i, (size, nbins) in enumerate(zip(sizes, bins)):
        if size:
            mine = (j >= start) & (j < start + size) & (length > 0)
            jax.lax.cond(mine, functools.partial(count, i, nbins), lambda: None)
        start += size


def counted_in_kernel(
    bins: int, values: jax.Array, mask: jax.Array, lo: jax.Array, hi: jax.Array
) -> jax.Array:
    """Inside the fused kernel: a block's counts per slot of `values` where `mask` (`[1, n]`;
    `lo`, `hi`: `[1, 1]`), `[P, 1]` int32 with P a power of two past the `bins + 2` slots,
    each entry's slot compared with every slot."""
    s = slot(bins, values, mask, lo, hi)
    c = jax.lax.broadcasted_iota(jnp.int32, (pl.next_power_of_2(bins + 2), 1), 0)
    return jnp.sum((s == c).astype(jnp.int32), axis=1, keepdims=True)


def add_counted_in_kernel(
    row: jax.Array, inc: jax.Array, lo: Any, hi: Any, lo_out: Any, hi_out: Any
) -> None:
    """Inside the fused kernel: `inc` (`counted_in_kernel`) added to row `row` (a scalar) of
    a histogram's words with the carry (`_count.add`), read from `lo`, `hi` and written to
    `lo_out`, `hi_out`."""
    slots = lo.shape[1]
    c = jax.lax.broadcasted_iota(jnp.int32, inc.shape, 0)
    there = c < slots
    # Entries left out are pointed past the row (Pallas' interpret mode writes them back).
    at = (jnp.broadcast_to(row, c.shape), jnp.where(there, c, slots))
    _add_with_carry(inc.astype(jnp.uint32), at, there, lo, hi, lo_out, hi_out)
