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

This module lays out the kernel's inputs and calls it (`fold`); what one program does is
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

from . import _reached, _update
from ._chunks import chunk_counts, chunking, combine, counted_input, reads_counts
from ._hists import HistIn, HistRows, Pairs
from ._program import program
from ._selected import Selected
from ._update import Batch

MIN_BATCH = 32
MAX_BATCH = 65536


def fits(batch: int, dtype) -> bool:
    """Whether the kernel serves a float32 batch of `batch` entries per row: any size
    from `MIN_BATCH` to `MAX_BATCH`, the largest measured faster than XLA's kernels
    (docs/benchmarks.md)."""
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
) -> tuple[Batch, tuple[jax.Array, ...], tuple[HistIn, ...], tuple | None]:
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
    rows, width = batch.rows, batch.batch
    gather = _reached.block(width) if listed else 0
    assert not hist_rows or (gather and len(hist_rows) == len(hists))
    ranked = ema is not None or bool(rings)
    chunk, n_chunks, _ = (
        (gather, 1, False) if gather else chunking(rows, width, batch.grouped, ranked=ranked)
    )
    # The counted rows are summed over every entry, not the reached ones: read with the
    # batch, or where the rows are read from the lists, by the listing's kernel.
    counted_here = bool(packs and counted.shape[0]) and not listed
    coeff = np.zeros(rows, np.float32) if ema is None else np.asarray(ema.coeff, np.float32)
    table = [coeff.view(np.int32)[:, None], batch.table()]
    for r in rings:
        table += [np.stack([np.asarray(r.row, np.int32), np.asarray(r.pos_row, np.int32)], 1)]
    # Ungrouped rows read from the lists have hundreds of entries a step: their histograms
    # are counted by programs of their own, one per (row, histogram row) pair, beside the
    # rows' folds, where in the rows' programs the count ran after the fold
    # (docs/benchmarks.md, "Scaling"). Group rows have a few entries each.
    pairs = Pairs.of(hist_rows, batch.src) if hist_rows and not batch.grouped else None
    programs = sum(pairs.sizes) if pairs else 0  # the pairs'
    for h in () if pairs else hist_rows:
        bits = [np.asarray(a, np.float32).view(np.int32) for a in (h.lo, h.hi)]
        table += [np.stack([np.asarray(h.row, np.int32), *bits], 1)]
    table = np.concatenate(table, axis=1).astype(np.int32)
    table = np.pad(table, ((0, 0), (0, pl.next_power_of_2(table.shape[1]) - table.shape[1])))

    def whole(a):
        return pl.BlockSpec(a.shape, lambda *ids: (0,) * a.ndim)

    def col(a):
        return a.reshape(rows, 1)

    def row_of(i):
        # The pairs' programs, past the rows', take the last row's blocks and write none.
        return jnp.minimum(i, rows - 1) if pairs else i

    def cols(n):
        return pl.BlockSpec((1, n), lambda i, *c: (row_of(i), 0))

    def per_program(n):
        return pl.BlockSpec((1, n), lambda i, *c: (i, *c) if c else (row_of(i), 0))

    one = cols(1)
    args = [(a, whole(a)) for a in (batch.ok, batch.values, batch.bad)]
    args += [
        (col(shift), one),
        (col(steps.astype(jnp.uint32)), one),
        (jnp.asarray(table), cols(table.shape[1])),
    ]
    if batch.grouped:
        args.append((batch.ids, whole(batch.ids)))
    chunk_sums = None  # the counted rows' chunk sums, where `gather`
    if gather:
        lists, chunk_sums = _reached.reached(batch, counted if packs else counted[:0], interpret)
        args += [(a, whole(a)) for a in lists if a is not None]
        if pairs:
            args.append((jnp.asarray(pairs.table), whole(pairs.table)))
    elif reads_counts(rows, width, batch.grouped, ranked):
        args.append((chunk_counts(batch, chunk), cols(pl.next_power_of_2(n_chunks))))
    if counted_here:
        padded = counted_input(counted, batch.values.shape[0])
        args.append((padded, whole(padded)))
    if ema is not None:
        args += [(col(a), one) for a in (ema.ema_w, ema.ema_off)]
    own = update is not None and n_chunks == 1
    first_ring = len(args)
    for r in rings:
        # With `update`, each row's program reads and writes its own `pos` (windows'
        # have every row).
        args += [(r.data, whole(r.data)), (col(r.pos), one) if own else (r.pos, whole(r.pos))]
    first_hist = len(args)
    words = [a for h in hists for a in h]
    args += [(a, whole(a)) for a in words]
    listed_sums = chunk_sums.shape[0] if own and packs and chunk_sums is not None else 0
    first_update = len(args)
    if own:
        assert update is not None  # `own` needs it
        assert len(rings) == len(update.rows.windows)
        ins = _update.kernel_inputs(update)
        args += [(col(a), one) if a.ndim == 1 else (a, whole(a)) for a in ins]
        if listed_sums:
            assert chunk_sums is not None
            args.append((chunk_sums, whole(chunk_sums)))
    n_int = pl.next_power_of_2(2 + packs)
    outs = [
        (jax.ShapeDtypeStruct((rows, 8 * n_chunks), jnp.float32), per_program(8)),
        (jax.ShapeDtypeStruct((rows, n_int * n_chunks), jnp.int32), per_program(n_int)),
    ]
    outs += [(jax.ShapeDtypeStruct(r.data.shape, r.data.dtype), whole(r.data)) for r in rings]
    outs += [(jax.ShapeDtypeStruct(a.shape, a.dtype), whole(a)) for a in words]
    if own:
        assert update is not None
        outs += [
            (jax.ShapeDtypeStruct((rows, 1), o.dtype), one) if len(o.shape) == 1 else (o, whole(o))
            for o in _update.kernel_outputs(update)
        ]
    kernel = functools.partial(
        program,
        ema=ema is not None,
        rings=tuple(r.data.shape[1] for r in rings),
        packs=packs,
        counted=counted.shape[0] if counted_here else 0,
        rows=rows,
        batch=width,
        grouped=batch.grouped,
        gather=gather,
        hists=len(hists),
        hist_bins=tuple(h.bins for h in hist_rows),
        pairs=pairs.sizes if pairs else (),
        sources=not batch.grouped and batch.src == tuple(range(rows)),
        updates=(ema is not None, listed_sums) if own else None,
    )
    # A program of group rows mostly finds its chunk empty or nearly so: with fewer warps
    # more such programs run at once (docs/benchmarks.md, "Per-group statistics"). A row
    # read from its list in blocks of up to 512 entries folds them faster with 4 warps
    # too; in blocks of 1,024, with 8 (docs/benchmarks.md, "Scaling").
    warps = 4 if batch.grouped or 0 < gather <= 512 else 8
    floats, ints, *data = pl.pallas_call(
        kernel,
        out_shape=tuple(s for s, _ in outs),
        grid=(rows + programs,) if n_chunks == 1 else (rows, n_chunks),
        in_specs=[s for _, s in args],
        out_specs=tuple(s for _, s in outs),
        input_output_aliases={
            **{first_ring + 2 * i: 2 + i for i in range(len(rings))},
            **{first_hist + i: 2 + len(rings) + i for i in range(len(words))},
            **(
                _update.aliases(
                    update,
                    first_update,
                    2 + len(rings) + len(words),
                    shift=3,
                    steps=4,
                    ema=first_ring - 2 if ema is not None else None,
                    pos=[first_ring + 2 * i + 1 for i in range(len(rings))],
                )
                if own and update is not None
                else {}
            ),
        },
        interpret=interpret,
        compiler_params=None if interpret else plt.CompilerParams(num_warps=warps),
    )(*(a for a, _ in args))
    floats = floats.reshape(rows, n_chunks, 8)
    ints = ints.reshape(rows, n_chunks, n_int)
    floats, ints = (floats[:, 0], ints[:, 0]) if n_chunks == 1 else combine(floats, ints)
    if listed:
        assert chunk_sums is not None  # `listed`: the rows were read from the lists
        counted_sums = _reached.summed(chunk_sums)
        counted_sums = jnp.pad(counted_sums, (0, rows * packs - counted_sums.shape[0]))
    else:
        counted_sums = ints[:, 2 : 2 + packs].T.reshape(-1)
    stats = Batch(
        ints[:, 0],
        *(floats[:, i] for i in range(5)),
        nonfinite=ints[:, 1],
        ema=floats[:, 5] if ema is not None else None,
        counted_sums=counted_sums,
    )
    data, words = data[: len(rings)], data[len(rings) :]
    words, updated = words[: 3 * len(hists)], words[3 * len(hists) :]
    hists = tuple(HistIn(*words[i : i + 3]) for i in range(0, len(words), 3))
    return (
        stats,
        tuple(data),
        hists,
        _update.from_kernel(update, updated) if own and update is not None else None,
    )
