"""The entries of a batch's source rows that its rows can reach, listed in order.

A group row is its source row masked to one group: of the batch's entries it is reached
only by those that are masked in or carry a non-finite flag, a few per step where
episodes end (1% of them at an episode of 100 steps). Folded from the batch, each of
`groups x sources` rows reads every entry to find its few: work in rows x entries, where
the entries that reach any are sources x arrivals. Listed first, per source row, in
entry order (each chunk of the row lists its reached entries in its own segment of the
list and counts them), every row of the batch, group rows and overall rows alike, is
then read from its source row's list (`_program`, `gather`): the chunks' counts place each
of the list's first entries in its segment, as many as the list has, in the order of
the batch, so that ranks, EMA weights and ring slots come out as from the batch itself.
The chunks need no count of the entries before them: the listing is one kernel. A step
where every entry arrives lists them all, and the rows then read the whole batch. A
batch with an EMA or a ring past `LONG` entries is read from the lists with or without
group rows: its rows then need no chunks, no chunk counts and no combination of the
chunks' statistics. Without group rows a list holds its masked-in entries' values, the
flags summed beside it, and with them its reached entries' indices (`Reached`).
"""

import functools
from collections.abc import Callable
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
from jax.experimental import pallas as pl
from jax.experimental.pallas import triton as plt

from ._chunks import LONG_ROW, counted_input
from ._selected import Selected

CHUNK = 1024
"""Entries per program of the listing, up to `SEGMENTS` chunks a row. Structural, not tuned
(any power of two works; chosen as `_chunks.ONE_PROGRAM`, a program's entries there)."""
SEGMENTS = 16
"""Chunks of a row past which the listing's chunks grow (`chunk`): a row's reader places
its list's entries among that many segments, `[SEGMENTS, block]` in its registers.
Structural, not tuned (any power of two works; chosen to keep that compare small)."""
LONG = 16384
"""Entries past which a batch without group rows but with ranks is read from the lists
(`listed`): from 24,576 entries its chunks' counts and combination cost more than the
listing (24,576 envs 13.57 us against 14.22 chunked); at 16,384 its chunks, counting the
row's mask themselves, cost less (13.11-13.26 against 13.52: bb95847, recorded in
a5a3332)."""
ROWS = 64
"""Group rows without ranks from which a batch of up to `_chunks.LONG_ROW` entries reads
them from the lists (`listed`): period statistics at 4,096 envs, lists against the batch,
1 group 13.5 / 12.2 us, 8 groups 13.5 / 13.1, 64 groups 13.3 / 16.5-17.0 (2b38303)."""
LIST_WARPS = 4
"""Warps per program of the listing (`reached`). Not measured: any number works; chosen as
the fused kernel's for group rows, whose programs likewise find few entries each."""


class Reached(NamedTuple):
    """Per source row of a batch (`[S, W]`, W the batch rounded up to whole chunks): its
    listed entries, chunk c's in order from entry `c * chunk` on, then entries of no
    meaning (`listed`); and its listed entries per chunk (`counts`, `[S, n]` int32), whose
    sum is the list's length.

    With group rows (`Selected.grouped`) the entries are the reached ones and `listed`
    holds their indices (int32): a row reads their mask, flags and group index at them.
    Without, the entries are the masked-in ones and `listed` holds their values (`by_value`),
    and `flags` (`[S, n]` int32) each chunk's non-finite flags summed: a row, every entry
    its own, reads its values from its list, where at the listed indices it would wait for
    the list and then gather them (docs/benchmarks.md, "Why the fast paths")."""

    listed: jax.Array
    counts: jax.Array
    flags: jax.Array | None


def by_value(batch: Selected) -> bool:
    """Whether `batch`'s lists hold values, not indices (`Reached`): where it has no group
    rows."""
    return not batch.grouped


def listed(rows: int, batch: int, ranked: bool) -> bool:
    """Whether a batch of `batch` entries with `rows` group rows is read from the lists
    (every row of it); `ranked`: with an EMA or a ring. Group rows with ranks always are
    (from the batch, every chunk of a row counts the row's arrivals around it), and so
    are group rows past `_chunks.LONG_ROW` entries (from the batch, their chunks are
    counted by XLA first) and ranked batches past `LONG` entries. The period statistics of
    fewer than `ROWS` group rows over a smaller batch fold their chunks from the batch
    at less than the listing's two kernels cost, and ungrouped ones at any size, their
    chunks needing no counts (docs/benchmarks.md, "Why the fast paths")."""
    if rows == 0:
        return ranked and batch > LONG
    return ranked or batch > LONG_ROW or rows >= ROWS


def block(batch: int) -> int:
    """The entries a row reads from its list at a time: about one in 64 of the
    batch's, so that a step's arrivals (an episode's last step, at 1 in 100 or fewer of
    them) take one block; at most a chunk, at least 32. Structural, not tuned (any power of
    two works; more blocks when more arrive): the 1/64 is chosen from episode lengths, not
    from a measured row."""
    return min(chunk(batch), max(32, pl.next_power_of_2(-(-batch // 64))))


def chunk(batch: int) -> int:
    """Entries per program of the listing: `CHUNK`, or more where that makes more than
    `SEGMENTS` chunks of a row; at most the batch (a power of two)."""
    size = max(CHUNK, pl.next_power_of_2(-(-batch // SEGMENTS)))
    return min(size, 1 << (batch.bit_length() - 1))


def _list_kernel(
    ok_ref: Any, bad_ref: Any, *refs: Any, batch: int, chunk: int, counted: int, values: bool
) -> None:
    """One chunk of a source row: each listed entry stored at its rank in the chunk, in
    the chunk's segment of the row's list, and the chunk's listed entries counted: with
    `values`, its masked-in entries' values, its flags summed; else its reached entries'
    indices (`Reached`). Programs past the source rows sum a chunk of a counted row
    instead. The last chunk of a row that chunks do not divide ends at the row's end, its
    entries of the chunk before masked out."""
    x_ref = counted_ref = None
    rest = list(refs)
    if values:
        x_ref, *rest = rest
    if counted:
        counted_ref, *rest = rest
    listed_ref, counts_ref, *rest = rest
    flags_ref = rest.pop(0) if values else None
    sums_ref = rest[0] if counted else None
    row, c = pl.program_id(0), pl.program_id(1)
    sources = ok_ref.shape[0]
    lo = c * chunk
    start = lo if batch % chunk == 0 else jnp.minimum(lo, batch - chunk)
    at = jax.lax.broadcasted_iota(jnp.int32, (1, chunk), 1) + start

    def listing() -> None:
        cols = (pl.ds(row, 1), pl.ds(start, chunk))
        here = at >= lo
        bad = jnp.where(here, bad_ref[cols].astype(jnp.int32), 0)
        kept = ok_ref[cols] & here if values else (ok_ref[cols] | (bad != 0)) & here
        rank = jnp.cumsum(kept.astype(jnp.int32), axis=1) - 1
        # Entries left out are pointed past the list (Pallas' interpret mode writes them
        # back).
        slot = jnp.where(kept, lo + rank, listed_ref.shape[1])
        if values:
            assert x_ref is not None and flags_ref is not None
            # Only the listed entries' values are loaded: the whole chunk's cost the listing
            # twice as much (docs/benchmarks.md, "Why the fast paths").
            entry = plt.load(x_ref.at[cols], mask=kept, other=0.0)
            flags_ref[pl.ds(row, 1), pl.ds(c, 1)] = jnp.sum(bad, axis=1, keepdims=True)
        else:
            entry = at
        plt.store(listed_ref.at[jnp.broadcast_to(row, at.shape), slot], entry, mask=kept)
        counts_ref[pl.ds(row, 1), pl.ds(c, 1)] = jnp.sum(
            kept.astype(jnp.int32), axis=1, keepdims=True
        )

    def summing() -> None:
        assert counted_ref is not None and sums_ref is not None  # run only with `counted`
        r = pl.ds(row - sources, 1)
        part = jnp.where(at >= lo, counted_ref[r, pl.ds(start, chunk)].astype(jnp.int32), 0)
        sums_ref[r, pl.ds(c, 1)] = jnp.sum(part, axis=1, keepdims=True)

    if counted:
        jax.lax.cond(row < sources, listing, summing)
    else:
        listing()


def list_reader(
    listed_ref: Any, counts_ref: Any, src: jax.Array, batch: int
) -> tuple[jax.Array, Callable[..., tuple[jax.Array, jax.Array]]]:
    """Inside the fused kernel: the length of source row `src`'s list (`Reached`, its
    `listed` and `counts` as `listed_ref` and `counts_ref`, of a batch of `batch` entries),
    and `entries(start, n)`: which of the list's entries `start` to `start + n - 1` it has
    (`[1, n]` bool) and what the list holds of them (`[1, n]`: their indices in the batch
    or their values, 0 where it has none), in entry order. The list's k-th entry lies in
    the segment of the first chunk whose counts up to it pass k, at k less the entries of
    the chunks before: `[chunks, n]` compares (at most `SEGMENTS` chunks)."""
    chunks = counts_ref.shape[1]
    c = jax.lax.broadcasted_iota(jnp.int32, (pl.next_power_of_2(chunks), 1), 0)
    counts = plt.load(counts_ref.at[jnp.broadcast_to(src, c.shape), c], mask=c < chunks, other=0)
    ends = jnp.cumsum(counts, axis=0)
    length = jnp.sum(counts)
    size = chunk(batch)
    zero = jnp.zeros((), listed_ref.dtype)

    def entries(start: Any, n: int) -> tuple[jax.Array, jax.Array]:
        k = jax.lax.broadcasted_iota(jnp.int32, (1, n), 1) + start
        there = k < length
        before = ends <= k  # [chunks, n]: the chunks wholly before entry k
        seg = jnp.sum(before.astype(jnp.int32), axis=0, keepdims=True)
        rank = k - jnp.sum(jnp.where(before, counts, 0), axis=0, keepdims=True)
        at = jnp.where(there, seg * size + rank, 0)
        rows = jnp.broadcast_to(src, k.shape)
        return there, plt.load(listed_ref.at[rows, at], mask=there, other=zero)

    return length, entries


def reached(
    batch: Selected, counted: jax.Array, interpret: bool = False
) -> tuple[Reached, jax.Array]:
    """The lists of `batch`'s source rows (`Reached`), and the sums of `counted`'s rows
    (`[C, B]` integers: a counted row sums every entry, reached or not) per chunk (`[C,
    n]`, added up by `summed`). One program per chunk lists and counts a chunk's entries,
    or sums a counted row's."""
    sources, width = batch.ok.shape
    size = chunk(width)
    n = -(-width // size)
    values = by_value(batch)

    def whole(a: jax.Array | jax.ShapeDtypeStruct) -> pl.BlockSpec:
        return pl.BlockSpec(a.shape, lambda *ids: (0,) * a.ndim)

    ins = [batch.ok, batch.bad, *([batch.values] if values else [])]
    rows = counted.shape[0]
    if rows:
        ins.append(counted_input(counted, sources))
    per_chunk = jax.ShapeDtypeStruct((sources, n), jnp.int32)
    outs = [
        jax.ShapeDtypeStruct((sources, n * size), batch.values.dtype if values else jnp.int32),
        per_chunk,
        *([per_chunk] if values else []),
    ]
    outs += [jax.ShapeDtypeStruct((rows, n), jnp.int32)] if rows else []
    listed, counts, *rest = pl.pallas_call(
        functools.partial(_list_kernel, batch=width, chunk=size, counted=rows, values=values),
        out_shape=tuple(outs),
        grid=(sources + rows, n),
        in_specs=[whole(a) for a in ins],
        out_specs=tuple(whole(o) for o in outs),
        interpret=interpret,
        compiler_params=None if interpret else plt.CompilerParams(num_warps=LIST_WARPS),
    )(*ins)
    flags = rest.pop(0) if values else None
    return Reached(listed, counts, flags), rest[0] if rows else counts[:0]


def summed_in_kernel(sums_ref: Any, row: jax.Array) -> jax.Array:
    """Inside a kernel: counted row `row`'s sum (`[1, 1]`; 0 for `row` -1) from its chunks'
    (`sums_ref`, `[C, n]`, `reached`'s), as `summed` adds them outside; or so a source
    row's flags (`Reached.flags`)."""
    n = sums_ref.shape[1]
    j = jax.lax.broadcasted_iota(jnp.int32, (1, pl.next_power_of_2(n)), 1)
    at = sums_ref.at[jnp.broadcast_to(jnp.maximum(row, 0), j.shape), j]
    return jnp.sum(plt.load(at, mask=(j < n) & (row >= 0), other=0), axis=1, keepdims=True)


def summed(sums: jax.Array) -> jax.Array:
    """The counted rows' sums (`[C]`) from their chunks' (`[C, n]`, `reached`'s), added
    elementwise: XLA computes them in the kernel that updates the per-row state, where a
    reduction would be a kernel of its own."""
    return functools.reduce(jnp.add, [sums[:, j] for j in range(sums.shape[1])])
