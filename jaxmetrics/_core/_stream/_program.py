"""One program of the fused kernel (`_kernel.fold`): one chunk of a row of a batch, folded.

A program reads its refs by name (`_layout.KernelIn`, `KernelOut`) and its row's static
ints from the table (`_layout.Table`); `Static` holds what else `fold` fixes. `program`
sets up the row (`_row`) and the update of its fields (`_row_update`), folds the chunk
(`_fold_chunk`) or, past the rows' programs, counts a histogram pair (`_count_pair`), and
adds the step's histogram counts (`_add_step_counts`).

Reading. The row is read from its source row of the batch (`Selected`), its mask built as
it is read: the source's mask and, for a group row, its group index equal to the row's
group; its non-finite flags count in the same group (`_reader`, `_read`). Triton's blocks
are powers of two: a row (or chunk) that is not one is loaded as two blocks (`blocking`),
the last ending at the row's end with the entries already covered masked out, so that no
load reaches past the row (Pallas' interpret mode cannot) (`_load_block`, `_load_chunk`).
With `Static.gather` (one program per row) the row is read at the entries of its source
row's list (`_reached`) instead, in blocks of `gather` entries, in entry order, so that
ranks, EMA weights and ring slots come out as from the batch (`_fold_listed`).

Folding (`_fold_blocks`). The mask, flags and counted rows are read first and counted; a
chunk with masked-in entries then reads its values and makes two passes over them
(`_passes`): the first (`_first`) sums what needs no arrival rank, the second (`_second`)
takes the ranks, the moments around the first pass's mean, the EMA's weighted sum
(`_ema_weighted`) and the ring writes (`_write_rings`). A chunk without any (at most steps,
most chunks of group rows) skips both. A chunk's ranks add the row's masked-in entries in
later chunks (`_around`: counted in the row's mask by `_chunks.masked_in_around`, or read
from `KernelIn.chunk_counts`), and its EMA weights and ring slots (`_ring_slots`) follow
from those global ranks and the row's count. Its mean deviation is also written off a pivot
that every chunk of the row shares (the row's first value), so that the chunks' means
combine without the rounding of means far from zero (`_write`).

Histograms. The first chunk of row i adds the step's counts of row i of each histogram
to its words, with the carry, and zeroes them (`_add_step_counts`): XLA's scatter counts
them, and their add would be a kernel of its own. With `Static.hist_bins` (rows read from
the lists) the program counts its own row's entries into its row of each histogram
instead (`_count_hists`), a few entries a step where XLA's scatter reads every entry of the
batch; with `Static.pairs` as well (ungrouped rows), the programs past the rows' count
them, a (row, histogram row) pair each, beside the rows' folds (`_count_pair`).

With `KernelIn.update` (one program per row) the program also folds the batch's statistics
into its row's fields of the state (`_row_update`, `_update.row_updater`), where XLA's
update of the `[R]` fields is a kernel of its own.
"""

import functools
from collections.abc import Callable, Sequence
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
from jax.experimental import pallas as pl
from jax.experimental.pallas import triton as plt

from .._numerics import log2_keep
from . import _reached, _update
from ._chunks import blocking, chunking, masked_in_around
from ._hists import add_in_kernel, count_in_kernel, count_pair_in_kernel
from ._layout import KernelIn, KernelOut, Layout, Table
from ._update import Batch

Read = tuple[list[jax.Array], Callable[[], jax.Array]]
"""A block as read: its mask, non-finite flags and counted rows (`[1, n]` each), and what
reads its values."""
Blocks = Callable[..., Any]
"""`blocks(body, init, xs=None, *extra)`: `body(*a block's mask, flags, counted...,
[its values of xs,] *extra, carry)` folded over a chunk's blocks."""
Finish = Callable[[Batch, Sequence[jax.Array]], None]
"""What writes a row's updated fields, from its batch statistics and counted sums."""
Stats = tuple[jax.Array, ...]
"""A chunk's sum, min, max, mean deviation `p`, deviations from `p` summed and squared,
and EMA weighted sum (`[1, 1]` each)."""

_row_sum = functools.partial(jnp.sum, axis=1, keepdims=True)


class Static(NamedTuple):
    """A program's static arguments besides its refs' layout: the batch's `rows` and its
    entries per row (`batch`); `packs` counted rows per batch row, of the first `counted`
    rows of `KernelIn.counted` (row `p * rows + r` in pack p of row r; 0: none read
    there); `gather`, the block a row reads from its list at a time (0: rows read from the
    batch); `hist_bins`, each histogram's bins where the kernel counts the rows' entries
    (`_hists.HistRows`); `pairs`, each histogram's pairs where programs of their own
    count them (`_hists.Pairs`); `sources`: row r is source row r, ungrouped."""

    rows: int
    batch: int
    packs: int
    counted: int
    gather: int
    hist_bins: tuple[int, ...]
    pairs: tuple[int, ...]
    sources: bool


class _Row(NamedTuple):
    """What the parts of a program share: its refs and `Static`; its chunk (`chunk`
    entries, one of `n_chunks`, `chunk_id`) of row `r`, that row's source row, grouping
    and group (`Selected`), its counted rows (-1: none), its masked-in entries before and
    after the chunk (None: it is the whole row, or has no ranks), its `shift` and EMA
    coefficient (None: no EMA); and the `[1, 1]` zeros the folds start from."""

    ins: KernelIn[Any]
    outs: KernelOut[Any]
    static: Static
    chunk: int
    n_chunks: int
    chunk_id: jax.Array | int
    r: jax.Array
    src: jax.Array
    kind: jax.Array
    group: jax.Array
    counted_rows: list[jax.Array]
    izero: jax.Array
    fzero: jax.Array
    earlier: jax.Array | None = None
    later: jax.Array | None = None
    shift: Any = None
    coeff: jax.Array | None = None

    @property
    def rings(self) -> tuple[int, ...]:
        """The rings' sizes."""
        return tuple(r.data.shape[1] for r in self.ins.rings)

    @property
    def ranked(self) -> bool:
        """Whether the row's arrivals are ranked: with an EMA or a ring."""
        return self.ins.ema_w is not None or bool(self.ins.rings)


class _Ranks(NamedTuple):
    """A chunk's masked-in entries (`total`), the row's after the chunk (`ahead`) and in
    all (`row_total`), and `total` as a float32 divisor (`k`, at least 1)."""

    total: jax.Array
    ahead: jax.Array
    row_total: jax.Array
    k: jax.Array


class _Ema(NamedTuple):
    """What weighs a row's arrivals in its EMA: `log2(1 - c)` (`log_keep`), the offset the
    deviations are taken from, and whether this batch seeds the EMA."""

    log_keep: jax.Array
    off: jax.Array
    seeding: jax.Array


def program(*refs: Any, layout: Layout, static: Static) -> None:
    """One program of the fused kernel: `refs` are its inputs and outputs (`layout`)."""
    ins, outs = layout.refs(refs)
    row = _row(ins, outs, static)
    finish = _row_update(row)
    # A chunk with no entry (most group rows of a step, and every row of a step where no
    # episode ends) reads no value: its sums are zero, its min and max +-inf, and it
    # writes no ring slot.
    empty = (row.fzero, row.fzero + jnp.inf, row.fzero - jnp.inf) + (row.fzero,) * 4
    fold = functools.partial(_fold_chunk, row, finish, empty)
    if static.pairs:
        j = pl.program_id(0) - static.rows
        jax.lax.cond(j < 0, fold, functools.partial(_count_pair, row, j))
    else:
        fold()
    if ins.hists and not static.hist_bins:
        _add_step_counts(row)


def _row(ins: KernelIn[Any], outs: KernelOut[Any], static: Static) -> _Row:
    """The program's row and chunk, and what it reads of them before the fold."""
    grouped, ema = ins.ids is not None, ins.ema_w is not None
    ranked = ema or bool(ins.rings)
    chunk, n_chunks, _ = (
        (static.gather, 1, False)
        if static.gather
        else chunking(static.rows, static.batch, grouped, ranked=ranked)
    )
    r = pl.program_id(0)
    if static.pairs:
        # The pairs' programs come after the rows' and read the last row's blocks
        # (`fold`): what they read of it here goes unused.
        r = jnp.minimum(r, static.rows - 1)
    # Where each row is its own source row (`sources`), the row's reads take its source
    # from the program's id, not from the table in memory, which they would wait for.
    table = ins.table
    src = r if static.sources else table[0, Table.SRC]
    kind, group = table[0, Table.KIND], table[0, Table.GROUP]
    counted_rows = _packed_rows(static, r, static.counted)
    chunk_id = pl.program_id(1) if n_chunks > 1 else 0
    izero = jnp.zeros((1, 1), jnp.int32)
    fzero = jnp.zeros((1, 1), jnp.float32)
    row = _Row(
        ins, outs, static, chunk, n_chunks, chunk_id, r, src, kind, group, counted_rows,
        izero, fzero,
    )  # fmt: skip
    earlier, later = _around(row)
    shift = ins.shift[...]
    coeff = None
    if ema:
        coeff = jax.lax.bitcast_convert_type(table[:, Table.COEFF : Table.COEFF + 1], jnp.float32)
    return row._replace(earlier=earlier, later=later, shift=shift, coeff=coeff)


def _packed_rows(static: Static, r: jax.Array, n: int) -> list[jax.Array]:
    """Per pack p, row `r`'s counted row `p * rows + r` of `n` (-1: past them)."""
    rows = static.rows
    return [jnp.where(r + rows * p < n, r + rows * p, -1) for p in range(static.packs)]


def _around(row: _Row) -> tuple[jax.Array | None, jax.Array | None]:
    """The row's masked-in entries before and after the chunk (`[1, 1]` each), which its
    arrival ranks add: from the chunks' counts where the kernel reads them, else counted
    in the row's mask where the row is chunked and ranked (None: neither)."""
    counts = row.ins.chunk_counts
    if counts is not None:
        marks = counts[...]
        at = jax.lax.broadcasted_iota(jnp.int32, marks.shape, 1)
        earlier = _row_sum(jnp.where(at < row.chunk_id, marks, 0))
        return earlier, _row_sum(jnp.where(at > row.chunk_id, marks, 0))
    if row.n_chunks > 1 and row.ranked:
        lo = row.chunk_id * row.chunk
        hi = jnp.minimum(lo + row.chunk, row.static.batch)
        return masked_in_around(functools.partial(_mask_at, row), row.static.batch, lo, hi)
    return None, None


def _reader(
    row: _Row, start: Any, n: int, fresh: jax.Array | None, cols: jax.Array | None = None
) -> tuple[Callable[..., jax.Array], jax.Array | None]:
    """What reads a row of an input at `n` entries from `start` (or at the entries `cols`,
    `[1, n]`), those not `fresh` (None: all are) masked out, and where the group index
    there is the row's group (None: not a group row)."""
    full = jnp.ones((1, n), jnp.bool_) if fresh is None else fresh

    def at(ref: Any, src: Any, where: jax.Array = full) -> jax.Array:
        other = jnp.zeros((), ref.dtype)
        if cols is not None:
            rows = jnp.broadcast_to(src, (1, n))
            return plt.load(ref.at[rows, cols], mask=where, other=other)
        if fresh is None and where is full:
            return ref[pl.ds(src, 1), pl.ds(start, n)]
        return plt.load(ref.at[pl.ds(src, 1), pl.ds(start, n)], mask=where, other=other)

    ids = row.ins.ids
    if ids is None:
        return at, None
    match = (row.kind < 0) | (at(ids, jnp.maximum(row.kind, 0)) == row.group)
    if cols is None:
        return at, match

    def at_group(ref: Any, src: Any, where: jax.Array = full) -> jax.Array:
        # A list holds every group's entries: another group's are not loaded at all
        # (the row's program would read each one its source row's groups times).
        return at(ref, src, where & match)

    return at_group, match


def _mask_at(row: _Row, start: Any, n: int, fresh: jax.Array | None) -> jax.Array:
    """The row's mask at `n` entries from `start` (`_reader`)."""
    at, match = _reader(row, start, n, fresh)
    m = at(row.ins.ok, row.src)
    return m if match is None else m & match


def _read(
    row: _Row, start: Any, n: int, fresh: jax.Array | None, cols: jax.Array | None = None
) -> Read:
    """The row's mask, non-finite flags and counted rows at `n` entries from `start` or
    at `cols` (`_reader`), and what reads its values there."""
    ins = row.ins
    at, match = _reader(row, start, n, fresh, cols)
    # The flags and counted rows come narrower than the int32 they are summed in.
    m, bad = at(ins.ok, row.src), at(ins.bad, row.src).astype(jnp.int32)
    values = functools.partial(at, ins.values, row.src)
    if match is not None:
        m = m & match
        bad = bad * match.astype(jnp.int32)
    if ins.counted is None:
        return [m, bad, *(jnp.zeros((1, n), jnp.int32) for _ in row.counted_rows)], values
    full = jnp.ones((1, n), jnp.bool_) if fresh is None else fresh
    sums = [
        at(ins.counted, jnp.maximum(c, 0), full & (c >= 0)).astype(jnp.int32)
        for c in row.counted_rows
    ]
    return [m, bad, *sums], values


def _load_block(row: _Row, block: int, j: int) -> Read:
    """Block `j` of the chunk (`blocking`): the last one ends at the chunk's end, its
    entries of the block before masked out."""
    start = min(j * block, row.chunk - block)
    if start == j * block:
        return _read(row, start, block, None)
    fresh = jax.lax.broadcasted_iota(jnp.int32, (1, block), 1) >= j * block - start
    return _read(row, start, block, fresh)


def _load_chunk(row: _Row) -> Read:
    """The program's chunk of its row, in one block: the last chunk of a row that chunks
    do not divide ends at the row's end, its entries of the chunk before masked out."""
    chunk, batch = row.chunk, row.static.batch
    lo = row.chunk_id * chunk
    if batch % chunk == 0:
        return _read(row, lo, chunk, None)
    start = jnp.minimum(lo, batch - chunk)
    return _read(
        row, start, chunk, jax.lax.broadcasted_iota(jnp.int32, (1, chunk), 1) + start >= lo
    )


def _fold_chunk(row: _Row, finish: Finish | None, empty: Stats) -> None:
    """The program's chunk folded, read from the batch: in one or two blocks, loaded
    once for every pass; or from its source row's list (`_fold_listed`)."""
    if row.static.gather:
        _fold_listed(row, finish, empty)
        return
    block, n_blocks = blocking(row.chunk)
    if row.n_chunks == 1:
        loaded = [_load_block(row, block, j) for j in range(n_blocks)]
    else:
        loaded = [_load_chunk(row)]

    def blocks(body: Callable[..., Any], init: Any, xs: Any = None, *extra: Any) -> Any:
        for j, (marks, _) in enumerate(loaded):
            init = body(*marks, *([] if xs is None else [xs[j]]), *extra, init)
        return init

    _fold_blocks(row, finish, empty, blocks, lambda: [values() for _, values in loaded])


def _fold_listed(row: _Row, finish: Finish | None, empty: Stats) -> None:
    """The row read from its source row's list of reached entries (`_reached`): in one
    block of `gather` entries at most steps, loaded once for every pass; else in blocks
    of that size, loaded by each pass."""
    ins, chunk = row.ins, row.chunk
    length, entries = _reached.list_reader(ins.listed, ins.reached, row.src, row.static.batch)
    flags = None if ins.flags is None else _reached.summed_in_kernel(ins.flags, row.src)

    def block(start: Any, n: int) -> Read:
        if ins.flags is None:
            return _read(row, None, n, *entries(start, n))
        # Every entry of the list is masked in; the flags are summed per chunk (`flags`).
        there, x = entries(start, n)
        zeros = [jnp.zeros(there.shape, jnp.int32) for _ in range(1 + row.static.packs)]
        return [there, *zeros], lambda: x

    def one_block() -> None:
        marks, values = block(0, chunk)
        x = values()

        def blocks(body: Callable[..., Any], init: Any, xs: Any = None, *extra: Any) -> Any:
            return body(*marks, *([] if xs is None else [x]), *extra, init)

        _fold_blocks(row, finish, empty, blocks, lambda: True, flags)

    def blocks_of(size: int) -> None:
        def blocks(body: Callable[..., Any], init: Any, xs: Any = None, *extra: Any) -> Any:
            def step(j: jax.Array, carry: Any) -> Any:
                marks, values = block(j * size, size)
                return body(*marks, *([] if xs is None else [values()]), *extra, carry)

            return jax.lax.fori_loop(0, (length + size - 1) // size, step, init)

        _fold_blocks(row, finish, empty, blocks, lambda: True, flags)

    jax.lax.cond(length <= chunk, one_block, lambda: blocks_of(chunk))


def _fold_blocks(
    row: _Row,
    finish: Finish | None,
    empty: Stats,
    blocks: Blocks,
    values_of: Callable[[], Any],
    flags: jax.Array | None = None,
) -> None:
    """The chunk's statistics folded over its blocks and written (`_write`), with its
    ring writes and histogram counts: `blocks` folds a body over them, with each block's
    values from `values_of()`; `flags`: the row's non-finite flags, where its blocks have
    none."""
    izero = row.izero
    init = (izero, izero if flags is None else flags, (izero,) * row.static.packs)
    total, nbad, csums = blocks(_counts, init)
    ahead = izero if row.later is None else row.later
    row_total = (
        total if row.earlier is None or row.later is None else row.earlier + total + row.later
    )
    ranks = _Ranks(total, ahead, row_total, jnp.maximum(total, 1).astype(jnp.float32))
    ema = _ema_weights(row) if row.coeff is not None else None
    slots = _ring_slots(row, row_total)

    def passes() -> Stats:
        return _passes(row, blocks, values_of, ranks, ema, slots)

    stats = jax.lax.cond(jnp.sum(total) > 0, passes, lambda: empty)
    _write(row, finish, *stats, total=total, nbad=nbad, csums=csums)
    _count_hists(row, blocks, values_of, total)


def _counts(m: jax.Array, bad: jax.Array, *rest: Any) -> Any:
    """A block's masked-in entries, flags and counted rows added to the carry (`rest[-1]`),
    in one reduction."""
    *counted, acc = rest
    total, nbad, csums = acc
    n, b, *sums = _stacked(jnp.sum, 0, m.astype(jnp.int32), bad, *counted)
    return total + n, nbad + b, tuple(s + t for s, t in zip(csums, sums))


def _first(shift: jax.Array, m: jax.Array, bad: jax.Array, *rest: Any) -> Any:
    """The first pass over a block (its values `rest[-2]`): what needs no arrival rank,
    the sum, min, max and the deviations from `shift` summed."""
    *_, x, acc = rest
    xsum, xmin, xmax, dsum = acc
    zero = jnp.zeros_like(x)
    s, d = _stacked(jnp.sum, 0, jnp.where(m, x, zero), jnp.where(m, x - shift, zero))
    # The min as the max of the negated values, in the max's reduction.
    low, high = _stacked(jnp.max, -jnp.inf, jnp.where(m, -x, -jnp.inf), jnp.where(m, x, -jnp.inf))
    return xsum + s, jnp.minimum(xmin, -low), jnp.maximum(xmax, high), dsum + d


def _passes(
    row: _Row,
    blocks: Blocks,
    values_of: Callable[[], Any],
    ranks: _Ranks,
    ema: _Ema | None,
    slots: list[tuple[jax.Array, jax.Array]],
) -> Stats:
    """The chunk's two passes over its values. The moments take two: deviations from
    `shift`, then from their rounded mean `p`, corrected by the mean of the second
    deviations (exact for any `p`; accurate for one near the mean, as a float32 sum of
    values far from zero gives)."""
    xs = values_of()
    fzero = row.fzero
    init = (fzero, fzero + jnp.inf, fzero - jnp.inf, fzero)
    xsum, xmin, xmax, dsum = blocks(functools.partial(_first, row.shift), init, xs)
    p = dsum / ranks.k
    second = functools.partial(_second, row, ranks, ema, slots)
    _, s1, s2, wsum = blocks(second, (row.izero, fzero, fzero, fzero), xs, p)
    return xsum, xmin, xmax, p, s1, s2, wsum


def _second(
    row: _Row,
    ranks: _Ranks,
    ema: _Ema | None,
    slots: list[tuple[jax.Array, jax.Array]],
    on: jax.Array,
    bad: jax.Array,
    *rest: Any,
) -> tuple[jax.Array, jax.Array, jax.Array, jax.Array]:
    """The second pass over a block (its values and `p`, then the carry, in `rest`): each
    masked-in entry's arrivals after it (`after`, from the entries before the block and
    in it), the deviations from `p` summed and squared, the EMA's weighted sum, and the
    ring writes."""
    *_, x, p, acc = rest
    before, s1, s2, wsum = acc
    m = on.astype(jnp.int32)
    zero = jnp.zeros_like(x)
    after = ranks.ahead + ranks.total - before - jnp.cumsum(m, axis=1)
    e = jnp.where(on, x - row.shift - p, zero)
    weighted = None if ema is None else _ema_weighted(row, ema, ranks, x, on, after, zero)
    _write_rings(row, slots, x, on, after)
    de, sq, *w = _stacked(jnp.sum, 0, e, e * e, *([] if weighted is None else [weighted]))
    return before + _row_sum(m), s1 + de, s2 + sq, (wsum + w[0]) if w else wsum


def _ema_weights(row: _Row) -> _Ema:
    """The row's EMA weights' parts. The offset and seeding are worked out here from the
    state's own fields: computed outside, XLA put them in the per-row update's kernel,
    which then had to run before this one and copied seven fields to keep their old
    values."""
    ins, coeff = row.ins, row.coeff
    assert coeff is not None and ins.ema_w is not None and ins.ema_off is not None
    log_keep = log2_keep(coeff)
    off, seeding = _update.ema_offset(ins.ema_w[...], ins.ema_off[...], row.shift)
    return _Ema(log_keep, off, seeding & (coeff > 0))


def _ema_weighted(
    row: _Row,
    ema: _Ema,
    ranks: _Ranks,
    x: jax.Array,
    on: jax.Array,
    after: jax.Array,
    zero: jax.Array,
) -> jax.Array:
    """Each masked-in entry's deviation from the EMA's offset (`zero` where not `on`),
    weighed `c(1-c)^after`, or `(1-c)^after` for the first arrival of a seeding row."""
    assert row.coeff is not None
    # (1-c)^after; 0^0 = 1 for c = 1, as jnp.power gives.
    decay = jnp.where(after == 0, 1.0, jnp.exp2(after.astype(jnp.float32) * ema.log_keep))
    first = ema.seeding & (after == ranks.row_total - 1)
    weight = jnp.where(first, decay, row.coeff * decay)
    return weight * jnp.where(on, x - ema.off, zero)


def _ring_slots(row: _Row, row_total: jax.Array) -> list[tuple[jax.Array, jax.Array]]:
    """Per ring, the row's ring row (`[1, 1]`, -1: none) and the slot of its newest
    arrival: its `pos` (the row's own where the kernel updates the fields, else read at
    the table's `pos_row`) plus its arrivals, at most the ring's size, less one."""
    ins, table = row.ins, row.ins.table
    out = []
    for i, (size, ring) in enumerate(zip(row.rings, ins.rings)):
        at = Table.ring(i)
        ring_row = table[:, at : at + 1]
        pos_row = jnp.maximum(table[:, at + 1 : at + 2], 0)
        if ins.update is not None:
            pos = ring.pos[...]  # the row's own (`_update.row_updater`)
        else:
            pos = plt.load(ring.pos.at[pos_row[:, 0]])[:, None]
        out.append((ring_row, pos + jnp.minimum(row_total, size) - 1))
    return out


def _write_rings(
    row: _Row,
    slots: list[tuple[jax.Array, jax.Array]],
    x: jax.Array,
    on: jax.Array,
    after: jax.Array,
) -> None:
    """A block's arrivals written to each ring (value bits and stamp). Only the last
    `size` arrivals go in, to consecutive slots in arrival order. The rings are aliased
    to their outputs: what this program does not write stays. Entries left out are also
    pointed past the ring (Pallas' interpret mode writes them back)."""
    bits = jax.lax.bitcast_convert_type(x, jnp.uint32)
    stamp = jnp.broadcast_to(row.ins.steps[...], x.shape)
    for size, out, (ring_row, newest) in zip(row.rings, row.outs.rings, slots):
        keep = on & (after < size) & (ring_row >= 0)
        slot = jnp.where(keep, jax.lax.rem(newest - after, size), size)
        rows = jnp.broadcast_to(jnp.maximum(ring_row, 0), x.shape)
        plt.store(out.at[rows, slot, jnp.zeros_like(slot)], bits, mask=keep)
        plt.store(out.at[rows, slot, jnp.ones_like(slot)], stamp, mask=keep)


def _write(
    row: _Row,
    finish: Finish | None,
    xsum: jax.Array,
    xmin: jax.Array,
    xmax: jax.Array,
    p: jax.Array,
    s1: jax.Array,
    s2: jax.Array,
    wsum: jax.Array,
    total: jax.Array,
    nbad: jax.Array,
    csums: Sequence[jax.Array],
) -> None:
    """The chunk's statistics written to its slots of `floats` and `ints`, and where the
    program updates the row's fields, those (`finish`)."""
    floats, ints = row.outs.floats, row.outs.ints
    ema = row.coeff is not None
    k = jnp.maximum(total, 1).astype(jnp.float32)
    mean_dev, m2 = p + s1 / k, jnp.maximum(s2 - s1 * s1 / k, 0)
    floats[:, 0:1] = xsum
    floats[:, 1:2] = xmin
    floats[:, 2:3] = xmax
    floats[:, 3:4] = mean_dev
    floats[:, 4:5] = m2
    if finish is not None:
        finish(
            Batch(total, xsum, xmin, xmax, mean_dev, m2, nbad, wsum if ema else None, None), csums
        )
    if ema:
        floats[:, 5:6] = wsum
    if row.n_chunks > 1:
        # Every chunk, empty or not, writes the pivot: `combine` takes chunk 0's.
        lead = row.ins.values[pl.ds(row.src, 1), pl.ds(0, 1)] - row.shift
        pivot = jnp.where(jnp.isfinite(lead), lead, 0)
        floats[:, 6:7] = (p - pivot) + s1 / k
        floats[:, 7:8] = pivot
    ints[:, 0:1] = total
    ints[:, 1:2] = nbad
    for j, s in enumerate(csums):
        ints[:, 2 + j : 3 + j] = s


def _row_update(row: _Row) -> Finish | None:
    """Where the program updates its row's fields (`KernelIn.update`): the fields read
    now, before the fold, whose loads their reads then overlap, and what writes them once
    the row is folded (`_update.row_updater`); with the listing's chunk sums of the
    counted rows, it sums its counted rows' from them."""
    ins, coeff = row.ins, row.coeff
    u, outs = ins.update, row.outs.update
    if u is None or outs is None:
        return None
    listed_sums = None
    if u.listed_sums is not None:
        at = _packed_rows(row.static, row.r, u.listed_sums.shape[0])
        listed_sums = [_reached.summed_in_kernel(u.listed_sums, c) for c in at]
    emas = None
    if coeff is not None:
        assert ins.ema_w is not None and ins.ema_off is not None
        emas = (coeff > 0, jnp.where(coeff > 0, coeff, 1.0), ins.ema_w[...], ins.ema_off[...])
    windows = [
        (size, ins.table[:, Table.ring(i) : Table.ring(i) + 1] >= 0, ring.pos[...])
        for i, (size, ring) in enumerate(zip(row.rings, ins.rings))
    ]
    finish = _update.row_updater(u, outs, row.shift, ins.steps[...], emas, windows, row.r)

    def finish_row(b: Batch, csums: Sequence[jax.Array]) -> None:
        finish(b, csums if listed_sums is None else listed_sums)

    return finish_row


def _count_hists(row: _Row, blocks: Blocks, values_of: Callable[[], Any], total: jax.Array) -> None:
    """The row's entries counted into its row of each histogram, where the program counts
    them (`Static.hist_bins`, without `pairs`)."""
    ins, outs = row.ins, row.outs
    for i, bins in enumerate(() if row.static.pairs else row.static.hist_bins):
        at = Table.hist(len(row.rings), i)
        words = (ins.hists[i].lo, ins.hists[i].hi, outs.hists[i].lo, outs.hists[i].hi)
        spec = tuple(ins.table[:, j : j + 1] for j in range(at, at + 3))
        count_in_kernel(bins, spec, blocks, values_of, total, words)


def _count_pair(row: _Row, j: jax.Array) -> None:
    """The program of pair `j` past the rows' (`_hists.Pairs`): its row's entries, read
    from its source row's list, counted into its histogram row. Pairs are ungrouped
    rows: their lists hold masked-in entries' values only, so an entry the list has is
    masked in."""
    ins, chunk = row.ins, row.chunk

    def entries_of(src: jax.Array) -> tuple[jax.Array, Callable[[Any], Any], int]:
        length, entries = _reached.list_reader(ins.listed, ins.reached, src, row.static.batch)
        return length, functools.partial(entries, n=chunk), chunk

    static = row.static
    count_pair_in_kernel(
        j, static.pairs, static.hist_bins, ins.pairs, entries_of, ins.hists, row.outs.hists
    )


def _add_step_counts(row: _Row) -> None:
    """The step's histogram counts of row `r` added to the histograms, by the row's first
    chunk (`add_in_kernel`)."""
    add = functools.partial(add_in_kernel, row.r, row.ins.hists, row.outs.hists)
    if row.n_chunks == 1:
        add()
    else:
        jax.lax.cond(row.chunk_id == 0, add, lambda: None)


def _stacked(reduce: Callable[..., jax.Array], fill: Any, *xs: jax.Array) -> list[jax.Array]:
    """`reduce` of each of `xs` (`[1, n]`, one dtype) over its row (`[1, 1]` each), as one
    reduction of their stack: Triton synchronizes a program's warps once per reduction,
    however many rows it has."""
    k, n = pl.next_power_of_2(len(xs)), xs[0].shape[1]
    row = jax.lax.broadcasted_iota(jnp.int32, (k, n), 0)
    stack = jnp.full((k, n), fill, xs[0].dtype)
    for i, x in enumerate(xs):
        stack = jnp.where(row == i, x, stack)
    out = reduce(stack, axis=1, keepdims=True)
    row = jax.lax.broadcasted_iota(jnp.int32, (k, 1), 0)
    return [reduce(jnp.where(row == i, out, fill), axis=0, keepdims=True) for i in range(len(xs))]
