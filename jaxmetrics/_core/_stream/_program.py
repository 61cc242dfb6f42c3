"""One program of the fused kernel (`_kernel.fold`): one chunk of a row of a batch, folded.

Its inputs are `fold`'s, in its order; `Table` is the layout of the row's static ints that
`fold` builds and the program reads.
"""

import functools
from collections.abc import Callable, Sequence
from typing import Any

import jax
import jax.numpy as jnp
from jax.experimental import pallas as pl
from jax.experimental.pallas import triton as plt

from .._numerics import log2_keep
from . import _reached, _update
from ._chunks import blocking, chunking, masked_in_around, reads_counts
from ._hists import add_in_kernel, count_in_kernel, count_pair_in_kernel
from ._update import Batch


class Table:
    """The columns of a batch row's static ints (`fold`'s `table`, `[R, n]` int32): the
    EMA coefficient's float32 bits, the row's source row, grouping (-1: none) and group
    (`Selected`), then each ring's `row` and `pos_row` (`RingIn`), then each
    histogram's row and the float32 bits of its range where the kernel counts them
    (`HistRows`)."""

    COEFF, SRC, KIND, GROUP = range(4)

    @staticmethod
    def ring(i: int) -> int:
        """The column of ring `i`'s `row` (its `pos_row` follows)."""
        return Table.GROUP + 1 + 2 * i

    @staticmethod
    def hist(rings: int, i: int) -> int:
        """The column of histogram `i`'s row (its `lo` and `hi` bits follow)."""
        return Table.ring(rings) + 3 * i


def _stacked(reduce, fill, *xs) -> list[jax.Array]:
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


def program(
    *refs,
    ema: bool,
    rings: tuple[int, ...],
    packs: int,
    counted: int,
    rows: int,
    batch: int,
    grouped: bool,
    gather: int = 0,
    hists: int = 0,
    hist_bins: tuple[int, ...] = (),
    pairs: tuple[int, ...] = (),
    sources: bool = False,
    updates: tuple[bool, int] | None = None,
) -> None:
    """One chunk of a row of a batch `[rows, batch]` (`chunking`); `rings` are the ring
    sizes, `packs` the counted rows per batch row (of the first `counted` rows of a
    counted input, row `p * rows + r` in pack p of row r; 0: none has any). `table` holds
    the row's static ints (`Table`); `counts` (`reads_counts`) the row's masked-in entries
    per chunk; `sources`: row r is source row r, ungrouped.

    The row is read from its source row of the batch (`Selected`), with its mask built
    as it is read: the source's mask and, for a group row (`grouped`), its group index
    equal to the row's group; its non-finite flags count in the same group. With
    `gather` (one program per row, no counted row), at the entries of its source row's
    list (`_reached.Reached`: `listed`, `[S, W]`, and `reached`, its chunks' counts, and
    without group rows `flags`: `_reached.list_reader`) in blocks of `gather` entries, in
    entry order: ranks, EMA weights and ring slots come out as from the batch.

    Triton's blocks are powers of two: a row (or chunk) that is not one is loaded as two
    blocks (`blocking`), the last ending at the row's end with the entries already covered
    masked out, so that no load reaches past the row (Pallas' interpret mode cannot). The
    mask, flags and counted rows are read first and counted; a chunk with masked-in entries
    then reads its values and makes two passes over them: the first sums what needs no
    arrival rank, the second takes the ranks, the moments around the first pass's mean, the
    EMA's weighted sum and the ring writes. A chunk without any (at most steps, most chunks
    of group rows) skips both. A chunk's ranks add the row's masked-in entries in later
    chunks (counted in the row's mask by `_chunks.masked_in_around`, or from `counts`), and
    its EMA weights and ring slots follow from those global ranks and the row's count. Its
    mean deviation is also written off a pivot that every chunk of the row shares (the row's
    first value), so that the chunks' means combine without the rounding of means far from
    zero.

    The first chunk of row i also adds the step's counts of row i of each of `hists`
    histograms (as it has rows) to its words, with the carry, and zeroes them (`HistIn`):
    XLA's scatter counts them, and their add would be a kernel of its own. With
    `hist_bins` (only with `gather`) the program counts its own row's entries into its
    row of each histogram instead (`HistRows`), a few entries a step where XLA's scatter
    reads every entry of the batch. With `pairs` as well (each histogram's number of
    `_hists.Pairs`; ungrouped rows only), the programs past the rows' count them instead,
    a (row, histogram row) pair each, beside the rows' folds (`count_pair_in_kernel`).

    With `updates` (one program per row; `(ema, listed sums)`) the program also folds the
    batch's statistics into its row's fields of the state (`_update.row_updater`), where
    XLA's update of the `[R]` fields is a kernel of its own; with listed sums (`[C, n]`,
    the listing's chunks') it sums its counted rows' from them."""
    m_ref, x_ref, bad_ref, shift_ref, step_ref, table, *refs = refs
    # The optional inputs, each set where its input is passed.
    ids_ref = listed_ref = reached_ref = flags_ref = pairs_ref = counted_ref = None
    w_ref = eoff_ref = update_in = None
    if grouped:
        ids_ref, *refs = refs
    if gather:
        listed_ref, reached_ref, *refs = refs
        # Without group rows the lists hold the masked-in entries' values
        # (`_reached.by_value`), and each chunk's flags summed.
        flags_ref = None if grouped else refs.pop(0)
    if pairs:
        pairs_ref, *refs = refs
    ranked = ema or bool(rings)
    chunk, n_chunks, _ = (
        (gather, 1, False) if gather else chunking(rows, batch, grouped, ranked=ranked)
    )
    counts_ref = None
    if not gather and reads_counts(rows, batch, grouped, ranked):
        counts_ref, *refs = refs
    if counted:
        counted_ref, *refs = refs
    if ema:
        w_ref, eoff_ref, *refs = refs
    ring_in, refs = refs[: 2 * len(rings)], refs[2 * len(rings) :]
    hist_in, refs = refs[: 3 * hists], refs[3 * hists :]
    if updates:
        n_in = 10 + 2 * ema + len(rings) + 2 * (packs > 0) + (updates[1] > 0)
        update_in, refs = refs[:n_in], refs[n_in:]
    floats, ints, *refs = refs
    refs, hist_out = refs[: len(rings)], refs[len(rings) :]
    hist_out, update_out = hist_out[: 3 * hists], hist_out[3 * hists :]
    block, n_blocks = blocking(chunk)

    def entry(col: int) -> jax.Array:
        return table[0, col]

    # Where each row is its own source row (`sources`), the row's reads take its source
    # from the program's id, not from the table in memory, which they would wait for.
    r = pl.program_id(0)
    if pairs:
        # The pairs' programs come after the rows' and read the last row's blocks
        # (`fold`): what they read of it here goes unused.
        r = jnp.minimum(r, rows - 1)
    src = r if sources else entry(Table.SRC)
    kind, group = entry(Table.KIND), entry(Table.GROUP)

    def packed_rows(n: int) -> list[jax.Array]:
        """Per pack p, this row's counted row `p * rows + r` of `n` (-1: past them)."""
        return [jnp.where(r + rows * p < n, r + rows * p, -1) for p in range(packs)]

    counted_rows = packed_rows(counted)

    def reader(
        start, n: int, fresh, cols=None
    ) -> tuple[Callable[..., jax.Array], jax.Array | None]:
        """What reads a row of an input at `n` entries from `start` (or at the entries
        `cols`, `[1, n]`), those not `fresh` (None: all are) masked out, and where the
        group index there is the row's group (None: not a group row)."""
        full = jnp.ones((1, n), jnp.bool_) if fresh is None else fresh

        def at(ref, row, where=full):
            other = jnp.zeros((), ref.dtype)
            if cols is not None:
                rows = jnp.broadcast_to(row, (1, n))
                return plt.load(ref.at[rows, cols], mask=where, other=other)
            if fresh is None and where is full:
                return ref[pl.ds(row, 1), pl.ds(start, n)]
            return plt.load(ref.at[pl.ds(row, 1), pl.ds(start, n)], mask=where, other=other)

        if not grouped:
            return at, None
        match = (kind < 0) | (at(ids_ref, jnp.maximum(kind, 0)) == group)
        if cols is None:
            return at, match

        def at_group(ref, row, where=full):
            # A list holds every group's entries: another group's are not loaded at all
            # (the row's program would read each one its source row's groups times).
            return at(ref, row, where & match)

        return at_group, match

    def mask_at(start, n: int, fresh) -> jax.Array:
        """The row's mask at `n` entries from `start` (`reader`)."""
        at, match = reader(start, n, fresh)
        m = at(m_ref, src)
        return m if match is None else m & match

    def read(start, n: int, fresh, cols=None) -> tuple[list[jax.Array], Callable[[], jax.Array]]:
        """The row's mask, non-finite flags and counted rows at `n` entries from `start`
        or at `cols` (`reader`), and what reads its values there."""
        at, match = reader(start, n, fresh, cols)
        # The flags and counted rows come narrower than the int32 they are summed in.
        m, bad = at(m_ref, src), at(bad_ref, src).astype(jnp.int32)
        values = functools.partial(at, x_ref, src)
        if match is not None:
            m = m & match
            bad = bad * match.astype(jnp.int32)
        if not counted:
            return [m, bad, *(jnp.zeros((1, n), jnp.int32) for _ in counted_rows)], values
        full = jnp.ones((1, n), jnp.bool_) if fresh is None else fresh
        sums = [
            at(counted_ref, jnp.maximum(c, 0), full & (c >= 0)).astype(jnp.int32)
            for c in counted_rows
        ]
        return [m, bad, *sums], values

    def load(j):
        start = min(j * block, chunk - block)
        if start == j * block:
            return read(start, block, None)
        return read(
            start, block, jax.lax.broadcasted_iota(jnp.int32, (1, block), 1) >= j * block - start
        )

    def load_chunk(c):
        # The last chunk of a row that chunks do not divide ends at the row's end; its
        # entries of the chunk before are masked out.
        lo = c * chunk
        if batch % chunk == 0:
            return [read(lo, chunk, None)]
        start = jnp.minimum(lo, batch - chunk)
        return [
            read(start, chunk, jax.lax.broadcasted_iota(jnp.int32, (1, chunk), 1) + start >= lo)
        ]

    row_sum = functools.partial(jnp.sum, axis=1, keepdims=True)
    chunk_id = pl.program_id(1) if n_chunks > 1 else 0
    izero = jnp.zeros((1, 1), jnp.int32)
    fzero = jnp.zeros((1, 1), jnp.float32)
    earlier = later = None
    if counts_ref is not None:
        marks = counts_ref[...]
        at = jax.lax.broadcasted_iota(jnp.int32, marks.shape, 1)
        earlier = row_sum(jnp.where(at < chunk_id, marks, 0))
        later = row_sum(jnp.where(at > chunk_id, marks, 0))
    elif n_chunks > 1 and ranked:
        lo = chunk_id * chunk
        earlier, later = masked_in_around(mask_at, batch, lo, jnp.minimum(lo + chunk, batch))
    shift = shift_ref[...]
    coeff = None
    if ema:
        coeff = jax.lax.bitcast_convert_type(table[:, Table.COEFF : Table.COEFF + 1], jnp.float32)

    finish = listed_sums = None
    if updates:
        # The row's fields of the state are read here, before the fold, whose loads
        # their reads then overlap; they are written once the row is folded.
        assert update_in is not None
        ins = list(update_in)
        if updates[1]:
            sums_ref = ins.pop()
            listed_sums = [_reached.summed_in_kernel(sums_ref, c) for c in packed_rows(updates[1])]
        emas = None
        if ema:
            assert coeff is not None and w_ref is not None and eoff_ref is not None
            emas = (coeff > 0, jnp.where(coeff > 0, coeff, 1.0), w_ref[...], eoff_ref[...])
        windows = [
            (size, table[:, Table.ring(i) : Table.ring(i) + 1] >= 0, ring_in[2 * i + 1][...])
            for i, size in enumerate(rings)
        ]
        finish = _update.row_updater(ins, update_out, shift, step_ref[...], emas, windows, r)

    def write(
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
        k = jnp.maximum(total, 1).astype(jnp.float32)
        mean_dev, m2 = p + s1 / k, jnp.maximum(s2 - s1 * s1 / k, 0)
        floats[:, 0:1] = xsum
        floats[:, 1:2] = xmin
        floats[:, 2:3] = xmax
        floats[:, 3:4] = mean_dev
        floats[:, 4:5] = m2
        if updates:
            assert finish is not None
            stats = Batch(total, xsum, xmin, xmax, mean_dev, m2, nbad, wsum if ema else None, None)
            finish(stats, csums if listed_sums is None else listed_sums)
        if ema:
            floats[:, 5:6] = wsum
        if n_chunks > 1:
            # Every chunk, empty or not, writes the pivot: `combine` takes chunk 0's.
            lead = x_ref[pl.ds(src, 1), pl.ds(0, 1)] - shift
            pivot = jnp.where(jnp.isfinite(lead), lead, 0)
            floats[:, 6:7] = (p - pivot) + s1 / k
            floats[:, 7:8] = pivot
        ints[:, 0:1] = total
        ints[:, 1:2] = nbad
        for j, s in enumerate(csums):
            ints[:, 2 + j : 3 + j] = s

    # A chunk with no entry (most group rows of a step, and every row of a step where no
    # episode ends) reads no value: its sums are zero, its min and max +-inf, and it
    # writes no ring slot.
    empty = (fzero, fzero + jnp.inf, fzero - jnp.inf) + (fzero,) * 4

    def fold_chunk():
        if gather:
            return fold_listed()
        loaded = [load(j) for j in range(n_blocks)] if n_chunks == 1 else load_chunk(chunk_id)

        def blocks(body, init, xs=None, *extra):
            """`body(*a block's mask, flags, counted..., [its values of xs,] *extra, carry)`
            folded over the chunk's blocks."""
            for j, (marks, _) in enumerate(loaded):
                init = body(*marks, *([] if xs is None else [xs[j]]), *extra, init)
            return init

        fold_blocks(blocks, lambda: [values() for _, values in loaded])

    def fold_listed():
        # The row read from its source row's list of reached entries (`_reached`): in one
        # block of `gather` entries at most steps, loaded once for every pass; else in
        # blocks of that size, loaded by each pass.
        length, entries = _reached.list_reader(listed_ref, reached_ref, src, batch)
        flags = None if flags_ref is None else _reached.summed_in_kernel(flags_ref, src)

        def block(start, n: int):
            if flags_ref is None:
                return read(None, n, *entries(start, n))
            # Every entry of the list is masked in; the flags are summed per chunk (`flags`).
            there, x = entries(start, n)
            zeros = [jnp.zeros(there.shape, jnp.int32) for _ in range(1 + packs)]
            return [there, *zeros], lambda: x

        def one_block():
            marks, values = block(0, chunk)
            x = values()

            def blocks(body, init, xs=None, *extra):
                return body(*marks, *([] if xs is None else [x]), *extra, init)

            fold_blocks(blocks, lambda: True, flags)

        def blocks_of(size: int):
            def blocks(body, init, xs=None, *extra):
                def step(j, carry):
                    marks, values = block(j * size, size)
                    return body(*marks, *([] if xs is None else [values()]), *extra, carry)

                return jax.lax.fori_loop(0, (length + size - 1) // size, step, init)

            fold_blocks(blocks, lambda: True, flags)

        jax.lax.cond(length <= chunk, one_block, lambda: blocks_of(chunk))

    def fold_blocks(
        blocks: Callable[..., Any], values_of: Callable[[], Any], flags: jax.Array | None = None
    ) -> None:
        """The row's statistics folded over its blocks: `blocks(body, init, xs, *extra)`
        folds `body` over them, with each block's values from `xs` (`values_of()`);
        `flags`: the row's non-finite flags, where its blocks have none."""

        def counts(m, bad, *rest):
            *counted, acc = rest
            total, nbad, csums = acc
            n, b, *sums = _stacked(jnp.sum, 0, m.astype(jnp.int32), bad, *counted)
            return total + n, nbad + b, tuple(s + t for s, t in zip(csums, sums))

        def first(m, bad, *rest):
            *_, x, acc = rest
            xsum, xmin, xmax, dsum = acc
            zero = jnp.zeros_like(x)
            s, d = _stacked(jnp.sum, 0, jnp.where(m, x, zero), jnp.where(m, x - shift, zero))
            # The min as the max of the negated values, in the max's reduction.
            low, high = _stacked(
                jnp.max, -jnp.inf, jnp.where(m, -x, -jnp.inf), jnp.where(m, x, -jnp.inf)
            )
            return xsum + s, jnp.minimum(xmin, -low), jnp.maximum(xmax, high), dsum + d

        total, nbad, csums = blocks(
            counts, (izero, izero if flags is None else flags, (izero,) * packs)
        )
        ahead = izero if later is None else later
        row_total = total if earlier is None or later is None else earlier + total + later
        k = jnp.maximum(total, 1).astype(jnp.float32)
        log_keep = off = seeding = None
        if ema:
            assert coeff is not None and w_ref is not None and eoff_ref is not None
            log_keep = log2_keep(coeff)
            # The offset and seeding are worked out here from the state's own fields:
            # computed outside, XLA put them in the per-row update's kernel, which then
            # had to run before this one and copied seven fields to keep their old values.
            off, seeding = _update.ema_offset(w_ref[...], eoff_ref[...], shift)
            seeding = seeding & (coeff > 0)
        ring_at = []
        for i, size in enumerate(rings):
            at = Table.ring(i)
            row = table[:, at : at + 1]  # [1, 1]
            pos_row = jnp.maximum(table[:, at + 1 : at + 2], 0)
            if updates:
                pos = ring_in[2 * i + 1][...]  # the row's own (`_update.row_updater`)
            else:
                pos = plt.load(ring_in[2 * i + 1].at[pos_row[:, 0]])[:, None]
            ring_at.append((row, pos + jnp.minimum(row_total, size) - 1))

        def second(
            on: jax.Array, bad: jax.Array, *rest: Any
        ) -> tuple[jax.Array, jax.Array, jax.Array, jax.Array]:
            *_, x, p, acc = rest
            before, s1, s2, wsum = acc
            m = on.astype(jnp.int32)
            zero = jnp.zeros_like(x)
            after = ahead + total - before - jnp.cumsum(m, axis=1)
            e = jnp.where(on, x - shift - p, zero)
            weighted = None
            if ema:
                assert coeff is not None and log_keep is not None
                assert off is not None and seeding is not None
                # (1-c)^after; 0^0 = 1 for c = 1, as jnp.power gives.
                decay = jnp.where(after == 0, 1.0, jnp.exp2(after.astype(jnp.float32) * log_keep))
                weight = jnp.where(seeding & (after == row_total - 1), decay, coeff * decay)
                weighted = weight * jnp.where(on, x - off, zero)
            # Only the last `size` arrivals go in, to consecutive slots in arrival order.
            # The rings are aliased to their outputs: what this program does not write
            # stays. Entries left out are also pointed past the ring (Pallas' interpret
            # mode writes them back).
            bits = jax.lax.bitcast_convert_type(x, jnp.uint32)
            stamp = jnp.broadcast_to(step_ref[...], x.shape)
            for size, out, (row, newest) in zip(rings, refs, ring_at):
                keep = on & (after < size) & (row >= 0)
                slot = jnp.where(keep, jax.lax.rem(newest - after, size), size)
                rows = jnp.broadcast_to(jnp.maximum(row, 0), x.shape)
                plt.store(out.at[rows, slot, jnp.zeros_like(slot)], bits, mask=keep)
                plt.store(out.at[rows, slot, jnp.ones_like(slot)], stamp, mask=keep)
            de, sq, *w = _stacked(jnp.sum, 0, e, e * e, *([weighted] if ema else []))
            return before + row_sum(m), s1 + de, s2 + sq, (wsum + w[0]) if ema else wsum

        def passes():
            # The moments take two passes: deviations from `shift`, then from their
            # rounded mean `p`, corrected by the mean of the second deviations (exact for
            # any `p`; accurate for one near the mean, as a float32 sum of values far from
            # zero gives).
            xs = values_of()
            init = (fzero, fzero + jnp.inf, fzero - jnp.inf, fzero)
            xsum, xmin, xmax, dsum = blocks(first, init, xs)
            p = dsum / k
            _, s1, s2, wsum = blocks(second, (izero, fzero, fzero, fzero), xs, p)
            return xsum, xmin, xmax, p, s1, s2, wsum

        write(
            *jax.lax.cond(jnp.sum(total) > 0, passes, lambda: empty),
            total=total,
            nbad=nbad,
            csums=csums,
        )
        for i, bins in enumerate(() if pairs else hist_bins):
            at = Table.hist(len(rings), i)
            words = (*hist_in[3 * i + 1 : 3 * i + 3], *hist_out[3 * i + 1 : 3 * i + 3])
            spec = tuple(table[:, j : j + 1] for j in range(at, at + 3))
            count_in_kernel(bins, spec, blocks, values_of, total, words)

    def entries_of(src):
        # A pair's source row read from its list (`count_pair_in_kernel`).
        # Pairs are ungrouped rows: their lists hold masked-in entries' values only, so an
        # entry the list has is masked in.
        length, entries = _reached.list_reader(listed_ref, reached_ref, src, batch)
        return length, functools.partial(entries, n=chunk), chunk

    if pairs:
        j = pl.program_id(0) - rows
        count = functools.partial(
            count_pair_in_kernel, j, pairs, hist_bins, pairs_ref, entries_of, hist_in, hist_out
        )
        jax.lax.cond(j < 0, fold_chunk, count)
    else:
        fold_chunk()
    if hists and not hist_bins:
        add = functools.partial(add_in_kernel, r, hist_in, hist_out)
        if n_chunks == 1:
            add()
        else:
            jax.lax.cond(chunk_id == 0, add, lambda: None)
