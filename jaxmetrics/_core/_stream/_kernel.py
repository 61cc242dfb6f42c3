"""A batch's fold in one GPU kernel (Pallas, Triton): its statistics, arrival ranks, the
EMA's weighted sum, the ring writes and the histograms' step counts added.

`_stream.add` needs, per row of a batch `[R, B]`: the count, sum, min, max and moments of the
row's masked-in values, its non-finite flags and counted_sums summed, how many masked-in entries
arrive after each one (`after`), the EMA's weighted sum of the batch, and the newest values
written to their ring slots (windows, EMA history). XLA does that in five kernels (the
batch's reduction, the mask packed into words, the later words' counts, the weighted
deviations, the ring scatter). One Triton program per row does it all: the row is loaded
once (in one or two blocks), a cumulative sum of its mask gives the ranks, the reductions
and the weighted sum follow, and the ring slots are written in place (the rings are
aliased to the outputs; other rows never touch a row's slots). The histograms' counts of
the step, which XLA scatters, are added to their exact counts here too, where the add was
a kernel of its own; rows read from the lists (below) are counted here instead, and XLA
scatters nothing. With the full spec a step then takes 4 or 5 kernels, no more than the
hand-written floor's (docs/benchmarks.md has them and their times).

A group row (`_stream.Selected`) is read from its metric's row of the batch and the group
index, its mask built as it is loaded; the batch is not copied per group. Where `fold`
takes the rows from the lists of reached entries (`_reached`), each program reads its row
from its source row's list instead: as many entries as reach the source row on the step,
most steps one block.

A row longer than `_chunks.ONE_PROGRAM` entries is folded by one program per chunk of it
(`_chunks`: how rows are chunked, the chunks' counts that XLA takes before the kernel,
and their partial statistics combined after it). Where each row is one program (rows
`_chunks.chunking` leaves whole, rows read from the lists), that program also folds the
batch's statistics into its row's fields of the state (`_update`), in place, where XLA's
update of those `[R]` fields is one more kernel per step.

This module lays out the kernel's inputs and calls it (`fold`): it decides how the batch
is folded (`_Plan`), builds the kernel's operands by name (`_operands`: `_layout`'s
`KernelIn` and `KernelOut`, from which the flat lists and the input-output aliases of
`pl.pallas_call` follow) and reads its outputs back (`_stats`); what one program does is
`_program`'s. The kernel runs on CUDA only; elsewhere `_stream` computes the same with jnp,
and tests check that both agree (the kernel in Pallas' interpret mode).
"""

import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax.experimental import pallas as pl
from jax.experimental.pallas import triton as plt
from jax.typing import DTypeLike

from .._count import Count
from . import _reached, _update
from ._chunks import chunk_counts, chunking, combine, counted_input, reads_counts
from ._hists import HistIn, HistRows, Pairs
from ._layout import HistOf, KernelIn, KernelOut, Layout, Operand, RingOf, aliases, operands
from ._program import Static, program
from ._selected import Selected
from ._update import Batch

MIN_BATCH = 32
"""Entries from which the kernel serves a batch. Not measured: the kernel's first form
(cfcf265) served powers of two from 32 entries, a warp's lanes; smaller batches keep XLA's
kernels (the smallest batch recorded with the kernel is 256 entries, h100_scaling.json)."""
MAX_BATCH = 65536
"""Entries up to which the kernel serves a batch: the largest measured faster than XLA's
kernels (65,536 envs, simple statistics 15.69 -> 15.00 us: fbf0e6c); past it not
measured."""
WARPS = 8
"""Warps per program of rows read from the batch or from their lists in blocks of 1,024:
at 65,536 envs 4 warps took 6.68 us of our kernel against 5.82 (32f1759)."""
FEW_WARPS = 4
"""Warps per program of group rows, and of rows read from their lists in blocks of up to
512: a program of group rows mostly finds its chunk empty, and with fewer warps more such
programs run at once (64 groups, 4,096 envs, full spec 23.6 -> 21.5 us, 16,384 46.1 ->
40.6: 5040c7a); blocks of 512 fold faster with 4 (24,576 envs, our kernel 4.82 -> 4.28 us:
32f1759)."""


def fits(batch: int, dtype: DTypeLike) -> bool:
    """Whether the kernel serves a float32 batch of `batch` entries per row: any size
    from `MIN_BATCH` to `MAX_BATCH`."""
    return jnp.dtype(dtype) == jnp.float32 and MIN_BATCH <= batch <= MAX_BATCH


def one_program(rows: int, batch: int, grouped: bool, ranked: bool) -> bool:
    """Whether `fold` folds each of `rows` rows of `batch` entries in one program, when
    it reads them from the batch (`chunking`)."""
    return chunking(rows, batch, grouped, ranked=ranked).n == 1


class RingIn(NamedTuple):
    """A ring (`_stream.Ring`'s `data`, `[rows, size, 2]` uint32: value bits, stamp) and
    where each batch row goes: `row[r]` its ring row (-1: none), `pos[pos_row[r]]` the
    ring row's next slot."""

    data: jax.Array
    pos: jax.Array
    row: np.ndarray
    pos_row: np.ndarray


class EmaIn(NamedTuple):
    """Per batch row: the EMA's coefficient `coeff` (0: no EMA) and the state's `ema_w` and
    `ema_off` (float32)."""

    coeff: np.ndarray
    ema_w: jax.Array
    ema_off: jax.Array


def fold(
    batch: Selected,
    shift: jax.Array,
    steps: jax.Array,
    counted: jax.Array,
    packs: int,
    ema: EmaIn | None = None,
    rings: tuple[RingIn, ...] = (),
    interpret: bool = False,
    *,
    listed: bool,
    hists: tuple[HistIn, ...] = (),
    hist_rows: tuple[HistRows, ...] = (),
    update: _update.InKernel | None = None,
) -> tuple[Batch, tuple[jax.Array, ...], tuple[HistIn, ...], tuple[_update.Fields, Count] | None]:
    """Folds the rows `[R, B]` that `batch` selects (`Selected`; float32 values, bool
    mask, integer non-finite flags): their statistics (`Batch`; `shift[R]` float32, and the
    sums of `counted[C, B]` (integers, C up to `packs` times R) as `packs` counted rows per
    batch row, `counted` row `p * R + r` in pack p of row r: read with the batch, where a
    reduction of its own is one more kernel per step), and each ring's data with its
    rows' newest arrivals written in, stamped with the row's `steps[r]` (uint32); and
    each histogram (`HistIn`) with its step's counts added and zeroed, or, with
    `hist_rows` (one per histogram; the rows read from the lists only), with its rows'
    entries counted by the kernel, the step's counts left as they are (zero): group rows'
    by their own programs, ungrouped rows' by programs of their own after the rows', one
    per (row, histogram row) pair (`_hists.Pairs`). With
    `update` (`_update.InKernel`), where each row is one program, the kernel also
    updates the state's per-row fields and the counted rows' counts, returned as
    `(fields, counts)` (else None; `counted`'s sums are then `Batch.counted_sums`).

    The EMA's weighted sum is `sum c(1-c)^after (x - off)` over the row's masked-in
    entries, with `after` how many masked-in entries follow each one; `off` is `ema_off`
    for a seeded row (`ema_w > 0`), else `shift`, and the first arrival of an unseeded
    EMA row seeds it, weighing `(1-c)^after` instead. `interpret` runs it anywhere,
    slowly (Pallas' interpret mode). `listed`: whether the rows are read from the lists of
    reached entries (`_reached`; as `_reached.listed` says for the batch), else from the
    batch.
    """
    assert not hist_rows or (listed and len(hist_rows) == len(hists))
    plan = _Plan.of(
        batch, counted, packs, ema is not None or bool(rings), listed, hist_rows, update
    )
    ins, outs, chunk_sums = _operands(
        plan, batch, shift, steps, counted, packs, ema, rings, hists, hist_rows, update, interpret
    )
    rows = plan.rows
    static = Static(
        rows=rows,
        batch=batch.batch,
        packs=packs,
        counted=counted.shape[0] if plan.counted_here else 0,
        gather=plan.gather,
        hist_bins=tuple(h.bins for h in hist_rows),
        pairs=plan.pairs.sizes if plan.pairs else (),
        sources=not batch.grouped and batch.src == tuple(range(rows)),
    )
    warps = FEW_WARPS if batch.grouped or 0 < plan.gather <= 512 else WARPS
    programs = sum(plan.pairs.sizes) if plan.pairs else 0  # the pairs', past the rows'
    layout = Layout.of(ins, outs)
    out_ops = operands(outs)
    results = pl.pallas_call(
        functools.partial(program, layout=layout, static=static),
        out_shape=tuple(jax.ShapeDtypeStruct(o.value.shape, o.value.dtype) for o in out_ops),
        grid=(rows + programs,) if plan.n_chunks == 1 else (rows, plan.n_chunks),
        in_specs=[o.spec for o in operands(ins)],
        out_specs=tuple(o.spec for o in out_ops),
        input_output_aliases=aliases(ins, outs),
        interpret=interpret,
        compiler_params=None if interpret else plt.CompilerParams(num_warps=warps),
    )(*(o.value for o in operands(ins)))
    out: KernelOut[jax.Array] = jax.tree.unflatten(layout.outs, results)
    stats = _stats(plan, out, packs, ema is not None, chunk_sums)
    updated = None
    if update is not None and out.update is not None:
        updated = _update.from_kernel(update, out.update)
    return stats, out.rings, tuple(HistIn(h.counted, h.lo, h.hi) for h in out.hists), updated


class _Plan(NamedTuple):
    """How `fold` lays out a batch of `rows` rows: the entries a row reads from its list
    at a time (`gather`; 0: rows read from the batch), each row's `n_chunks` chunks of
    `chunk` entries, whether its rows are `ranked` (an EMA or a ring), whether the kernel
    reads the counted rows (`counted_here`), the histogram pairs counted by programs of
    their own (`pairs`), and whether each row's program updates its fields (`own`)."""

    rows: int
    gather: int
    chunk: int
    n_chunks: int
    ranked: bool
    counted_here: bool
    pairs: Pairs | None
    own: bool

    @classmethod
    def of(
        cls,
        batch: Selected,
        counted: jax.Array,
        packs: int,
        ranked: bool,
        listed: bool,
        hist_rows: tuple[HistRows, ...],
        update: _update.InKernel | None,
    ) -> "_Plan":
        rows, width = batch.rows, batch.batch
        gather = _reached.block(width) if listed else 0
        chunk, n_chunks, _ = (
            (gather, 1, False) if gather else chunking(rows, width, batch.grouped, ranked=ranked)
        )
        # The counted rows are summed over every entry, not the reached ones: read with the
        # batch, or where the rows are read from the lists, by the listing's kernel.
        counted_here = bool(packs and counted.shape[0]) and not listed
        # Ungrouped rows read from the lists have hundreds of entries a step: their
        # histograms are counted by programs of their own, one per (row, histogram row)
        # pair, beside the rows' folds, where in the rows' programs the count ran after
        # the fold (docs/benchmarks.md, "Why the fast paths"). Group rows have a few entries each.
        pairs = Pairs.of(hist_rows, batch.src) if hist_rows and not batch.grouped else None
        own = update is not None and n_chunks == 1
        return cls(rows, gather, chunk, n_chunks, ranked, counted_here, pairs, own)


def _operands(
    plan: _Plan,
    batch: Selected,
    shift: jax.Array,
    steps: jax.Array,
    counted: jax.Array,
    packs: int,
    ema: EmaIn | None,
    rings: tuple[RingIn, ...],
    hists: tuple[HistIn, ...],
    hist_rows: tuple[HistRows, ...],
    update: _update.InKernel | None,
    interpret: bool,
) -> tuple[KernelIn[Operand], KernelOut[Operand], jax.Array | None]:
    """The kernel's inputs and outputs (`fold`'s arguments, laid out as `plan` says), and
    where the rows are read from the lists, the counted rows' chunk sums (else None)."""
    rows, pairs = plan.rows, plan.pairs
    table = _table(batch, ema, rings, () if pairs else hist_rows)
    blocks = _Blocks(rows, pairs is not None)
    one = blocks.cols(1)

    def col(a: jax.Array) -> Operand:
        return Operand(a.reshape(rows, 1), one)

    ok, values, bad = (blocks.whole(a) for a in (batch.ok, batch.values, batch.bad))
    shift_in, steps_in = col(shift), col(steps.astype(jnp.uint32))
    table_in = Operand(jnp.asarray(table), blocks.cols(table.shape[1]))
    ids = blocks.whole(batch.ids) if batch.grouped else None
    lists: tuple[Operand | None, ...] = (None,) * 3
    pair_table = counts_in = chunk_sums = None
    if plan.gather:
        reached, chunk_sums = _reached.reached(batch, counted if packs else counted[:0], interpret)
        lists = tuple(None if a is None else blocks.whole(a) for a in reached)
        if pairs:
            pair_table = blocks.whole(jnp.asarray(pairs.table))
    elif reads_counts(rows, batch.batch, batch.grouped, plan.ranked):
        counts = chunk_counts(batch, plan.chunk)
        counts_in = Operand(counts, blocks.cols(pl.next_power_of_2(plan.n_chunks)))
    counted_in = None
    if plan.counted_here:
        counted_in = blocks.whole(counted_input(counted, batch.values.shape[0]))
    ema_in = None if ema is None else (col(ema.ema_w), col(ema.ema_off))
    # With `update`, each row's program reads and writes its own `pos` (windows' have
    # every row).
    ring_in = tuple(
        RingOf(blocks.whole(r.data), col(r.pos) if plan.own else blocks.whole(r.pos)) for r in rings
    )
    hist_in = tuple(HistOf(*map(blocks.whole, h)) for h in hists)
    fields_in = fields_out = None
    if update is not None and plan.own:
        assert len(rings) == len(update.rows.windows)
        sums = chunk_sums if packs and chunk_sums is not None and chunk_sums.shape[0] else None
        fields_in, fields_out = _update.kernel_operands(
            update,
            col,
            blocks.whole,
            shift=shift_in,
            steps=steps_in,
            ema=ema_in,
            pos=tuple(r.pos for r in ring_in),
            listed_sums=None if sums is None else blocks.whole(sums),
        )
    ins: KernelIn[Operand] = KernelIn(
        ok=ok,
        values=values,
        bad=bad,
        shift=shift_in,
        steps=steps_in,
        table=table_in,
        ids=ids,
        listed=lists[0],
        reached=lists[1],
        flags=lists[2],
        pairs=pair_table,
        chunk_counts=counts_in,
        counted=counted_in,
        ema_w=ema_in[0] if ema_in else None,
        ema_off=ema_in[1] if ema_in else None,
        rings=ring_in,
        hists=hist_in,
        update=fields_in,
    )
    n_int, n_chunks = pl.next_power_of_2(2 + packs), plan.n_chunks
    floats = blocks.per_program(jax.ShapeDtypeStruct((rows, 8 * n_chunks), jnp.float32), 8)
    ints = blocks.per_program(jax.ShapeDtypeStruct((rows, n_int * n_chunks), jnp.int32), n_int)
    rings_out = tuple(r.data for r in ring_in)
    return ins, KernelOut(floats, ints, rings_out, hist_in, fields_out), chunk_sums


def _stats(
    plan: _Plan, out: KernelOut[jax.Array], packs: int, ema: bool, chunk_sums: jax.Array | None
) -> Batch:
    """The rows' statistics from the programs' (`out.floats`, `out.ints`; a chunked row's
    combined, `combine`) and the counted rows' sums, from the listing's chunk sums where
    the rows were read from the lists (`chunk_sums`)."""
    rows, n_chunks = plan.rows, plan.n_chunks
    floats = out.floats.reshape(rows, n_chunks, 8)
    ints = out.ints.reshape(rows, n_chunks, -1)
    floats, ints = (floats[:, 0], ints[:, 0]) if n_chunks == 1 else combine(floats, ints)
    if plan.gather:
        assert chunk_sums is not None  # `gather`: the rows were read from the lists
        counted_sums = _reached.summed(chunk_sums)
        counted_sums = jnp.pad(counted_sums, (0, rows * packs - counted_sums.shape[0]))
    else:
        counted_sums = ints[:, 2 : 2 + packs].T.reshape(-1)
    return Batch(
        ints[:, 0],
        *(floats[:, i] for i in range(5)),
        nonfinite=ints[:, 1],
        ema=floats[:, 5] if ema else None,
        counted_sums=counted_sums,
    )


def _table(
    batch: Selected, ema: EmaIn | None, rings: tuple[RingIn, ...], hist_rows: tuple[HistRows, ...]
) -> np.ndarray:
    """The rows' static ints (`Table`): the EMA coefficient's bits, the row's selection,
    each ring's `row` and `pos_row`, each histogram's row and range where the rows'
    programs count them; padded to a power of two of columns."""
    rows = batch.rows
    coeff = np.zeros(rows, np.float32) if ema is None else np.asarray(ema.coeff, np.float32)
    table = [coeff.view(np.int32)[:, None], batch.table()]
    for r in rings:
        table += [np.stack([np.asarray(r.row, np.int32), np.asarray(r.pos_row, np.int32)], 1)]
    for h in hist_rows:
        bits = [np.asarray(a, np.float32).view(np.int32) for a in (h.lo, h.hi)]
        table += [np.stack([np.asarray(h.row, np.int32), *bits], 1)]
    out = np.concatenate(table, axis=1).astype(np.int32)
    return np.pad(out, ((0, 0), (0, pl.next_power_of_2(out.shape[1]) - out.shape[1])))


class _Blocks(NamedTuple):
    """The kernel's blocks over its `rows` rows, one a program (`pairs`: with the pairs'
    programs past the rows', which take the last row's blocks and write none)."""

    rows: int
    pairs: bool

    def whole(self, a: jax.Array) -> Operand:
        """`a` read whole by every program."""
        return Operand(a, pl.BlockSpec(a.shape, lambda *ids: (0,) * a.ndim))

    def _row_of(self, i: jax.Array) -> jax.Array:
        return jnp.minimum(i, self.rows - 1) if self.pairs else i

    def cols(self, n: int) -> pl.BlockSpec:
        """The program's row of `[R, n]`."""
        return pl.BlockSpec((1, n), lambda i, *c: (self._row_of(i), 0))

    def per_program(self, out: jax.ShapeDtypeStruct, n: int) -> Operand:
        """`out` (`[R, n * chunks]`), `n` columns a program: its row's, its chunk's."""
        return Operand(
            out, pl.BlockSpec((1, n), lambda i, *c: (i, *c) if c else (self._row_of(i), 0))
        )
