"""Folding a batch into the stream: the period statistics, the EMA, the rings and the
histograms, in jnp on every backend.

The batch's statistics go into the per-row fields by `_update`, after the batch's
reduction.

Steering XLA's fusion: a per-row field that does not depend on the batch's counts `k`
(the counted sums, the zeroed histogram step counts; `_update`'s own fields likewise) is
written as `jnp.where(k < 0, 0, x)` (or through another operand that never satisfies its
test). The test never holds; it makes the field a function of `k`, so that XLA updates it
in the one multi-output kernel that updates the other per-row fields (sibling fusions
must share an operand) instead of in a kernel of its own.
"""

from collections.abc import Iterable
from typing import TypeVar

import jax
import jax.numpy as jnp
import numpy as np
from jax.typing import ArrayLike, DTypeLike

from .. import _count, _sketch
from .._count import Count
from .._numerics import log2_keep
from .._sharding import gathered
from . import _hists, _segments, _update
from ._segments import SegmentPlan
from ._selected import Selected
from ._state import Ring, StreamPlan, StreamState, packed, take_rows, weight_dtype, window_ring

A = TypeVar("A")
B = TypeVar("B")
BatchStats = tuple[
    jax.Array, jax.Array, jax.Array, jax.Array, jax.Array, jax.Array, jax.Array,
    jax.Array | None, jax.Array,
]  # fmt: skip
"""A batch's statistics in `_update.Batch`'s order (its EMA sum None where there is
none)."""
Folded = tuple[
    _update.Batch,
    tuple[jax.Array, ...],
    tuple[jax.Array, ...],
    tuple[Count, ...],
    tuple[jax.Array, ...],
]
"""What a fold gives (`_fold`): the batch's statistics, each EMA ring's and each window
ring's data, each histogram's counts and `hist_steps`."""


def add(
    plan: StreamPlan,
    s: StreamState,
    values: jax.Array,
    mask: jax.Array,
    nonfinite: jax.Array | None = None,
) -> StreamState:
    """Feeds `values[R, B]` where `mask`, column order being arrival order, and counts
    `nonfinite[R, B]` (an integer per entry) into the period's non-finite counts."""
    if nonfinite is None:
        nonfinite = jnp.zeros(values.shape, jnp.uint8)
    batch = Selected.every(values, mask, nonfinite)
    return add_with_counts(plan, s, batch, _nothing_counted(values), _count.zeros((0,)))[0]


def counts_width(plan: StreamPlan, n: int) -> int:
    """Width of the counts that `add_with_counts` adds `n` counted rows into: padded to
    whole multiples of the stream's rows, so that (for up to R counted rows) their update
    is shaped like every other per-row field and joins that one kernel."""
    rows = len(plan.rows)
    return -(-n // rows) * rows if rows else 0


def add_with_counts(
    plan: StreamPlan,
    s: StreamState,
    batch: Selected,
    counted: jax.Array,
    counts: Count,
    segments: tuple[SegmentPlan, tuple[jax.Array, ...]] | None = None,
) -> tuple[StreamState, Count]:
    """`add` of the rows that `batch` selects (`Selected`), and `counts`
    (`[counts_width(plan, C)]`) plus the sum of each row of `counted[C, B]` (integers), in
    its first C entries. The sums are taken in the batch's own reduction and added in
    the update of the per-row fields (`_update`), where separate counts would be two more
    kernels.

    `segments`, for a stream with segment rows (`_segments`): its `SegmentPlan` and the
    segment sources' batch (values, ok, non-finite counts, group index, `[sources, B]`);
    `batch` then selects the other rows (the plan's `dense` rows). Both halves' batch
    statistics are put in row order before the one update of the per-row fields."""
    width = counts.lo.shape[0]
    # Deviations from the running mean keep the moments small, so float32 stays accurate
    # for data far from zero. An empty period's mean is 0 (init, reset_period and merge
    # keep it so), so its first batch is folded as it is (Chan's pairwise update is
    # exact for constant data either way). No `count > 0` test here: with it XLA left
    # the shifted values out of the reduction's kernel (one more kernel per step).
    shift = s.mean
    if plan.ema_rows or plan.windows or plan.hists or plan.sketches:
        batch = batch.arrays(gathered)
    folds = plan
    if segments is None:
        folded = _fold_dense(plan, s, batch, shift, counted)
    else:
        sp, sources = segments
        folds = sp.dense_plan
        part = _segments.dense_state(sp, s)
        folded = _fold_dense(folds, part, batch, part.mean, counted)
        grouped = _segments.segment_batch(
            *(gathered(a) for a in sources),
            groups=sp.groups,
            shift=_segments.segment_rows(sp, shift),
        )
        joined = _segments.joined(sp, folded[0], grouped, counted.shape[0], width)
        folded = (joined, *folded[1:])
    stats, ema_data, window_data, hists, hist_steps = folded
    k = stats[0]
    fields, counts = _updated(plan, s, stats, shift, counts)
    ema_rings = s.ema_rings
    if plan.ema_rows:
        ek = take_rows(plan.ema_rows, k)
        ema_rings = tuple(
            _advanced(ring._replace(data=data), take_rows(g.rows, ek)) if ring.size else ring
            for g, ring, data in zip(plan.ema_groups, s.ema_rings, ema_data)
        )
    sketches = tuple(
        _sketch.add(c, _sketch.slot(g, *batch.take(g.rows).dense()[:2]))
        for g, c in zip(folds.sketches, s.sketches)
    )
    new = fields.into(s)
    new = new._replace(
        ema_rings=ema_rings,
        windows=tuple(w._replace(data=d) for w, d in zip(new.windows, window_data)),
        hists=hists,
        hist_steps=hist_steps,
        sketches=sketches,
    )
    return new, counts


def _updated(
    plan: StreamPlan, s: StreamState, stats: _update.Batch, shift: jax.Array, counts: Count
) -> tuple[_update.Fields, Count]:
    """The state's per-row fields with the batch's statistics (`_update.Batch`) folded in
    (`_update.update`), and the counted rows' `counts` plus the batch's counted sums."""
    wt = weight_dtype(plan.dtype)
    fields = _update.update(_update.Fields.of(s), stats, shift, _update_rows(plan), wt)
    packs = counts.lo.shape[0] // len(plan.rows) if plan.rows else 0
    k = jnp.tile(stats.count, packs)
    return fields, _count.add(counts, jnp.where(k < 0, 0, stats.counted_sums))


def _update_rows(plan: StreamPlan) -> _update.Rows:
    """What `_update.update` needs to know of the plan's rows."""
    is_ema, coeff = plan.ema_by_row(1.0) if plan.ema_rows else (None, None)
    rows = np.arange(len(plan.rows))
    return _update.Rows(is_ema, coeff, tuple((g.size, np.isin(rows, g.rows)) for g in plan.windows))


def _fold_dense(
    plan: StreamPlan, s: StreamState, batch: Selected, shift: jax.Array, counted: jax.Array
) -> Folded:
    """`_fold` of the rows `batch` selects, as arrays, with `counted` (`[C, B]`) padded to
    `counts_width` rows."""
    width = counts_width(plan, counted.shape[0])
    counted = jnp.pad(counted, ((0, width - counted.shape[0]), (0, 0)))
    return _fold(plan, s, *batch.dense(), shift, counted)


def _ranked(plan: StreamPlan) -> tuple[int, ...]:
    """The rows `add` ranks by arrival. With an EMA every row is: the EMA operand is
    then an elementwise function of the batch (zero weight outside EMA rows), where a
    stack of the EMA rows and zero rows made XLA write it out to memory."""
    return tuple(range(len(plan.rows))) if plan.ema_rows else plan.ranked_rows


def arrivals_after(mask: jax.Array) -> tuple[jax.Array, jax.Array]:
    """Per entry of `mask[R, B]`: how many masked-in entries follow it in its row
    (`k - 1 - rank` for a masked-in entry; meaningless elsewhere); and each row's `k`.

    The mask is packed into one 32-bit word per block of 32 entries (one small
    reduction); an entry's later neighbours in its block are the popcount of the word's
    higher bits, and the later blocks' entries a reverse cumsum over the blocks. One
    cumsum over the whole row is lowered to nested reduce-windows that XLA fuses into
    one kernel recomputing the inner level per output, the slowest kernel of the step.
    """
    rows, n = mask.shape
    if n == 0:
        return jnp.zeros((rows, 0), jnp.int32), jnp.zeros((rows,), jnp.int32)
    blocks = -(-n // 32)
    x = jnp.pad(mask.astype(jnp.uint32), ((0, 0), (0, blocks * 32 - n)))
    j = jnp.arange(32, dtype=jnp.uint32)[None, None, :]
    words = jnp.sum(x.reshape(rows, blocks, 32) << j, axis=2, dtype=jnp.uint32)
    totals = jax.lax.population_count(words).astype(jnp.int32)
    later = jax.lax.cumsum(totals, axis=1, reverse=True) - totals
    # Bits above j: shifted by j, then by 1 (a shift by 32 is not defined for uint32).
    within = jax.lax.population_count((words[..., None] >> j) >> 1).astype(jnp.int32)
    after = (within + later[..., None]).reshape(rows, blocks * 32)[:, :n]
    return after, later[:, 0] + totals[:, 0]


def _batch(
    values: jax.Array,
    mask: jax.Array,
    nonfinite: jax.Array,
    shift: jax.Array,
    wt: jnp.dtype,
    ema_in: jax.Array | None,
    counted: jax.Array,
) -> BatchStats:
    """Per row of a batch `values[R, B]` where `mask`: the count, sum, min, max, and the
    mean and sum of squared deviations of `values - shift`; the sum of `nonfinite`; the
    sum of each row of `ema_in` (`_ema_operands`; None without EMA rows); the sum of each
    row of `counted[C, B]` (C a multiple of R, see `counts_width`).

    On accelerators one reduction gives them all: its combiner merges the moments
    pairwise (Chan's rule), so no first pass for a pivot is needed. The CPU reduces a
    row sequentially, and a sequential Welford update over 10^6 float32 values drifts;
    there the moments take two passes around the batch's mean (or `shift`). Both agree
    to float32 rounding (tests/core/test_core_numerics.py checks both on one input).
    """
    return jax.lax.platform_dependent(
        values,
        mask,
        nonfinite,
        shift,
        ema_in,
        counted,
        cpu=lambda v, m, nf, sh, e, t: batch_two_pass(v, m, nf, sh, wt, e, t),
        default=lambda v, m, nf, sh, e, t: batch_one_pass(v, m, nf, sh, wt, e, t),
    )


def batch_two_pass(
    values: jax.Array,
    mask: jax.Array,
    nonfinite: jax.Array,
    shift: jax.Array,
    wt: DTypeLike,
    ema_in: jax.Array | None = None,
    counted: jax.Array | None = None,
) -> BatchStats:
    """`_batch` in two passes: count, sum, min, max, then moments around a pivot (`shift`
    where it is non-zero, else the batch's mean)."""
    dt = values.dtype
    k = jnp.sum(mask, axis=1, dtype=jnp.int32)
    bsum = jnp.sum(jnp.where(mask, values, 0), axis=1)
    bmin = jnp.min(jnp.where(mask, values, jnp.inf), axis=1)
    bmax = jnp.max(jnp.where(mask, values, -jnp.inf), axis=1)
    kd = jnp.maximum(k, 1).astype(dt)
    pivot = jnp.where(shift != 0, shift, bsum / kd)
    d = jnp.where(mask, values - pivot[:, None], jnp.zeros_like(values))
    s1 = jnp.sum(d, axis=1)
    s2 = jnp.sum(d * d, axis=1)
    mb = s1 / kd
    m2b = jnp.maximum(s2 - s1 * mb, 0)
    bad = jnp.sum(nonfinite, axis=1, dtype=jnp.int32)
    ema_sum = None if ema_in is None else jnp.sum(ema_in, axis=1)
    counted_sums = (
        _nothing_counted(values) if counted is None else jnp.sum(counted, axis=1, dtype=jnp.int32)
    )
    return k, bsum, bmin, bmax, mb + (pivot - shift), m2b, bad, ema_sum, counted_sums


ONE_STAGE = 4096
"""Entries up to which `batch_one_pass` reduces a row in one stage: XLA reduced a row of
16,384 in one program, 6.4 us of a 14.0 us step; in two stages 2.4 + 1.5, the step 9.7, and
8,192 10.1 -> 8.9 (a0e5b9d). At 4,096 and below one stage, not measured against two."""
PART = 256
"""Entries per part of a longer row (`batch_one_pass`). Not measured against other sizes:
any size works; chosen so that a part's partial statistics are a small fraction of the
row's reads."""


def batch_one_pass(
    values: jax.Array,
    mask: jax.Array,
    nonfinite: jax.Array,
    shift: jax.Array,
    wt: DTypeLike,
    ema_in: jax.Array | None = None,
    counted: jax.Array | None = None,
) -> BatchStats:
    """`_batch` as one variadic reduction (Chan's pairwise moments in its combiner). A row
    past `ONE_STAGE` entries is reduced in two: its parts of `PART` entries, then their
    partial statistics. XLA reduces a row of 16,384 entries in one program, which leaves
    most of the GPU idle with ten rows (docs/benchmarks.md, "Why the fast paths"); it splits rows of
    24,576 and more itself, in parts of about the same size."""
    dt = values.dtype
    zero = jnp.zeros_like(values)
    operands = (
        mask.astype(jnp.int32),
        jnp.where(mask, values, zero),
        jnp.where(mask, values, jnp.full_like(values, jnp.inf)),
        jnp.where(mask, values, jnp.full_like(values, -jnp.inf)),
        jnp.where(mask, values - shift[:, None], zero),
        zero,
        # Summed as int32; the flags and counted rows come narrower (`Metrics.update`).
        nonfinite.astype(jnp.int32),
    )
    inits = (
        np.int32(0),
        np.array(0, dt),
        np.array(np.inf, dt),
        np.array(-np.inf, dt),
        np.array(0, dt),
        np.array(0, dt),
        np.int32(0),
    )

    has_ema = ema_in is not None
    if has_ema:
        operands += (ema_in,)
        inits += (np.array(0, dt),)
    counted = _nothing_counted(values) if counted is None else counted
    # The counted rows as summed operands shaped like the batch: their sums come out as
    # one [R] array each (several scalar outputs would need a concatenation).
    rows = values.shape[0]
    packs = counted.shape[0] // rows if rows else 0
    operands += tuple(counted[i * rows : (i + 1) * rows].astype(jnp.int32) for i in range(packs))
    inits += (np.int32(0),) * packs
    e = 8 if has_ema else 7

    def combine(x: tuple[jax.Array, ...], y: tuple[jax.Array, ...]) -> tuple[jax.Array, ...]:
        ka, sa, lo_a, hi_a, ma, qa, na = x[:7]
        kb, sb, lo_b, hi_b, mb, qb, nb = y[:7]
        fa, fb = ka.astype(wt), kb.astype(wt)
        frac = (fb / jnp.maximum(fa + fb, 1)).astype(dt)
        delta = mb - ma
        both = (ka > 0) & (kb > 0)
        # An empty side carries no weight (and no inf - inf from a non-finite mean).
        m = jnp.where(both, ma + delta * frac, jnp.where(ka > 0, ma, mb))
        q = jnp.where(both, qa + qb + delta * delta * (fa.astype(dt) * frac), qa + qb)
        lo, hi = jnp.minimum(lo_a, lo_b), jnp.maximum(hi_a, hi_b)
        out = (ka + kb, sa + sb, lo, hi, m, q, na + nb)
        if has_ema:
            out += (x[7] + y[7],)
        return (*out, *(ta + tb for ta, tb in zip(x[e:], y[e:])))

    # Deviations from `shift` (the running mean) go in, not the values: taking the shift
    # off the batch's mean afterwards saves one operand's pass but rounds Chan's
    # delta to the ulp of the mean, a variance bias of ~(ulp/sigma)^2 for data far from
    # zero (1e-4 relative at mean 1e6, std 1).
    width = values.shape[1]
    if width > ONE_STAGE:
        # Each row in parts of `PART` entries, then the parts: the padding is each
        # operand's identity (an empty part).
        n = -(-width // PART)
        operands = tuple(
            jnp.pad(o, ((0, 0), (0, n * PART - width)), constant_values=i).reshape(rows, n, PART)
            for o, i in zip(operands, inits)
        )
        operands = jax.lax.reduce(operands, inits, combine, (2,))
    out = jax.lax.reduce(operands, inits, combine, (1,))
    counted_sums = jnp.concatenate(out[e:]) if packs else jnp.zeros((0,), jnp.int32)
    return (*out[:7], out[7] if has_ema else None, counted_sums)


def _nothing_counted(values: jax.Array) -> jax.Array:
    return jnp.zeros((0, values.shape[1]), jnp.int32)


def _ema_operands(
    plan: StreamPlan,
    values: jax.Array,
    mask: jax.Array,
    after: jax.Array,
    k: jax.Array,
    off: jax.Array,
    seeding: jax.Array,
) -> jax.Array:
    """The EMA's input to the batch's reduction, every row ([R, B]; zero rows where a
    row has no EMA): the deviations `x - off` weighed by their EMA weights. `after` and
    `k` are every row's arrival ranks and counts (`arrivals_after`); `off` and `seeding`
    come from `_update.ema_offset`."""
    # Sequential EMA over the k arrivals in closed form: the value with `after` later
    # arrivals gets weight c(1-c)^after; the old EMA gets (1-c)^k. Unseeded, the first
    # arrival (after == k - 1) seeds it and weighs (1-c)^(k-1). The EMA is kept relative
    # to an offset fixed at seeding: a float32 EMA of values far from zero otherwise
    # loses the low bits of every update and drifts.
    dt = plan.dtype
    is_ema, coeff = plan.ema_by_row(0.0)
    c = jnp.asarray(coeff, dt)[:, None]
    dev = jnp.where(mask & is_ema[:, None], values - off[:, None], 0)
    return ema_weights(c, after, seeding[:, None], k[:, None], dt) * dev


def ema_weights(
    c: jax.Array, after: jax.Array, seeding: ArrayLike, count: ArrayLike, dt: DTypeLike
) -> jax.Array:
    """The closed-form EMA weights of values with `after` later arrivals: c(1-c)^after,
    except the first of `count` values where `seeding`, which seeds the EMA and weighs
    (1-c)^(count-1)."""
    decay = jnp.where(after == 0, 1.0, jnp.exp2(after.astype(dt) * log2_keep(c)))
    return jnp.where(seeding & (after == count - 1), decay, c * decay)


def _ring_data(
    w: Ring, step: jax.Array, values: jax.Array, mask: jax.Array, after: jax.Array, k: jax.Array
) -> jax.Array:
    """`w.data` with the batch's arrivals added; `step` is each ring row's arrival step."""
    # Only the last `size` arrivals survive (those with fewer than `size` after them);
    # they go to consecutive ring slots in order: one scatter writes each value with
    # its stamp.
    n = w.size
    stored = jnp.minimum(k, n)
    keep = mask & (after < n)
    last = (w.pos + stored - 1)[:, None]
    slot = jnp.where(keep, (last - after) % n, n)  # n = out of bounds: dropped
    rows = jnp.broadcast_to(jnp.arange(values.shape[0], dtype=jnp.int32)[:, None], slot.shape)
    return w.data.at[rows, slot].set(
        packed(values, jnp.broadcast_to(step[:, None], values.shape)), mode="drop"
    )


def _advanced(w: Ring, k: jax.Array) -> Ring:
    """`w` (its data already written) with `pos` and `filled` past `k` arrivals per row."""
    stored = jnp.minimum(k, w.size)
    return w._replace(pos=(w.pos + stored) % w.size, filled=jnp.minimum(w.filled + stored, w.size))


def _fold(
    plan: StreamPlan,
    s: StreamState,
    values: jax.Array,
    mask: jax.Array,
    nonfinite: jax.Array,
    shift: jax.Array,
    counted: jax.Array,
) -> Folded:
    """The batch's statistics (`_update.Batch`), and what it adds that depends on
    arrival order, and its histograms: the data of each EMA ring and each window ring, and
    each histogram's counts with its `hist_steps`. `counted` has `counts_width` rows."""
    # One arrival rank shared by every row that needs one (EMA and window rows): how
    # many of the row's values arrive after each one (`k - 1 - rank`). It is known
    # before the batch is reduced, so the EMA's weighted sum is one more operand of the
    # batch's reduction.
    ranked = _ranked(plan)
    at = {row: i for i, row in enumerate(ranked)}
    after, k = arrivals_after(take_rows(ranked, mask)) if ranked else (None, None)
    ema_in = None
    if plan.ema_rows:
        off, seeding = _update.ema_offset(s.ema_w, s.ema_off, shift)
        assert after is not None and k is not None  # every row is ranked (`_ranked`)
        ema_in = _ema_operands(plan, values, mask, after, k, off, seeding)

    def ring(w: Ring, rows: tuple[int, ...]) -> jax.Array:
        if not w.size:
            return w.data
        # A ring's rows are ranked rows (`_ranked`): `after` and `k` are set.
        assert after is not None and k is not None
        i = tuple(at[r] for r in rows)
        rk = take_rows(i, k)
        args = (
            take_rows(rows, s.steps),
            take_rows(rows, values),
            take_rows(rows, mask),
            take_rows(i, after),
        )
        return _ring_data(w, *args, rk)

    ema_data = tuple(ring(w, plan.stream_rows(g)) for g, w in zip(plan.ema_groups, s.ema_rings))
    window_data = tuple(ring(window_ring(g, w), g.rows) for g, w in zip(plan.windows, s.windows))
    stats = _update.Batch(
        *_batch(values, mask, nonfinite, shift, weight_dtype(plan.dtype), ema_in, counted)
    )
    return stats, ema_data, window_data, *_hists_add(plan, s, values, mask)


def _hists_add(
    plan: StreamPlan, s: StreamState, values: jax.Array, mask: jax.Array
) -> tuple[tuple[Count, ...], tuple[jax.Array, ...]]:
    """Each histogram's counts with the batch added, and its `hist_steps`."""
    return _pairs(
        _hists.add(g, h, z, take_rows(g.rows, values), take_rows(g.rows, mask), plan.dtype)
        for g, h, z in zip(plan.hists, s.hists, s.hist_steps)
    )


def _pairs(items: Iterable[tuple[A, B]]) -> tuple[tuple[A, ...], tuple[B, ...]]:
    pairs = tuple(items)
    return tuple(a for a, _ in pairs), tuple(b for _, b in pairs)
