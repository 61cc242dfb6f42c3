"""Report statistics over a stream of values: one row per metric, stacked.

A stream receives batches `values[R, B]` with a boolean `mask[R, B]`; within a row, the
masked-in values arrive in ascending column order (for episodes: ascending env index).
Period statistics (count/mean/std/min/max/sum/histogram/quantile sketch/nonfinite) reset
with `reset_period`; EMA and windows persist.

Each `add` is one arrival step: `steps` counts them, and every value kept in a ring
buffer (windows, EMA history) carries the step it arrived on. That stamp is what lets
`merge` interleave the streams of disjoint workers (the env shards of one sharded state,
or separate states) in arrival order: by step, then worker order, then order within the
batch, which for env shards is ascending global env index.

All rows are stacked so that one fused XLA kernel serves every metric, whatever their
number: the per-step cost grows with rows x envs elementwise, not with kernel launches.
"""

import dataclasses
import math
from collections.abc import Sequence
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from . import _count, _fused_ema, _sketch, _statistics
from ._count import Count
from ._layout import gathered
from ._numerics import kahan_add
from ._sketch import SketchGroup
from ._spec import MetricSpec


class Ring(NamedTuple):
    """Ring buffers of the newest `size` arrivals of some rows, with their arrival steps.

    The value with arrival order j (0 oldest ... size-1 newest, right-aligned) is at
    slot (pos + j) mod size, valid when j >= size - filled.

    A slot holds its value's bits and its stamp side by side (`ring_words` words of the
    stream's dtype, then the stamp), so that a step writes both in one scatter: stamps
    of their own cost a second pass over the rings (H100: 0.7 us per step).
    """

    data: jax.Array  # [rows, size, ring_words(dtype) + 1] uint32: value bits, then stamp
    pos: jax.Array  # [rows] int32, next slot to write
    filled: jax.Array  # [rows] int32 in [0, size]

    @property
    def size(self) -> int:
        return self.data.shape[-2]

    def values(self, dt) -> jax.Array:
        """`[..., rows, size]` values of dtype `dt` (the stream's)."""
        return _from_words(self.data[..., :-1], dt)

    @property
    def stamps(self) -> jax.Array:
        """`[..., rows, size]` uint32: the stream's `steps` when each value arrived."""
        return self.data[..., -1]


def ring_words(dt) -> int:
    """uint32 words that hold one value of the stream's dtype `dt` (float32 or float64)."""
    return jnp.dtype(dt).itemsize // 4


def _to_words(x: jax.Array) -> jax.Array:
    """`x[...]` (float32 or float64) as `uint32[..., ring_words(x.dtype)]`, bit for bit."""
    w = jax.lax.bitcast_convert_type(x, jnp.uint32)
    return w if x.dtype.itemsize == 8 else w[..., None]


def _from_words(w: jax.Array, dt) -> jax.Array:
    """`_to_words`' inverse."""
    return jax.lax.bitcast_convert_type(w if jnp.dtype(dt).itemsize == 8 else w[..., 0], dt)


def _packed(values: jax.Array, stamps: jax.Array) -> jax.Array:
    """`Ring.data` of `values` and their uint32 `stamps` (same shape)."""
    return jnp.concatenate([_to_words(values), stamps.astype(jnp.uint32)[..., None]], axis=-1)


class StreamState(NamedTuple):
    """Report statistics of R metrics; see the module docstring for what resets when."""

    count: Count  # [R] uint32 pair: values in this period
    mean: jax.Array  # [R] float: Welford/Chan running mean of the period
    m2: jax.Array  # [R] float: sum of squared deviations, Kahan-compensated by m2_c
    m2_c: jax.Array  # [R] float
    sum: jax.Array  # [R] float: period sum, Kahan-compensated by sum_c
    sum_c: jax.Array  # [R] float
    min: jax.Array  # [R] float, +inf when empty
    max: jax.Array  # [R] float, -inf when empty
    nonfinite: Count  # [R] uint32 pair: non-finite values left out in this period
    # EMA fields have every row (0 where a row has no EMA), so that the whole update of
    # the per-row statistics after a batch is one elementwise pass over [R] arrays.
    ema: jax.Array  # [R] float: the EMA minus `ema_off`
    ema_off: jax.Array  # [R] float: offset fixed when the EMA is seeded
    ema_w: jax.Array  # [R] float: 0 unseeded, else number of merged seeded workers
    ema_n: jax.Array  # [R] int32: values the EMA has seen (saturates at 2^31 - 1)
    ema_rings: tuple[Ring, ...]  # one per EmaGroup: the newest values, for exact merges
    # [R] uint32: arrival steps so far (wraps; only differences are used). Every row
    # advances together; kept per row so that its update is one more [R] field.
    steps: jax.Array
    # One per distinct window size; its `pos` and `filled` have every stream row (`[R]`,
    # 0 outside the group) so that they are updated with the other [R] fields.
    windows: tuple[Ring, ...]
    hists: tuple[Count, ...]  # one per distinct bin count: [R_h, bins + 2] incl. under/overflow
    # Like `hists`, int32 and zero between steps: a step's counts are scattered into it in
    # place, added to `hists` and zeroed in that same kernel (a scatter into a fresh zero
    # array costs one more kernel per step, the fill).
    hist_steps: tuple[jax.Array, ...]
    sketches: tuple[Count, ...]  # one per distinct quantile accuracy: [R_q, slots] (`_sketch`)


@dataclasses.dataclass(frozen=True)
class WindowGroup:
    size: int
    rows: tuple[int, ...]


@dataclasses.dataclass(frozen=True)
class EmaGroup:
    """EMA rows of one coefficient; `history` is how many newest values make it exact.

    A value that has `h` newer ones weighs at most `(1-c)^h` in the EMA; with
    `h = history` that is below 2^-32 (capped at `MAX_EMA_HISTORY` values), so merging
    workers by folding their newest `history` values in arrival order, on top of any
    estimate of the older EMA within the range of the values, is exact to 2^-32 of that
    range: below float32's resolution.
    """

    coeff: float
    rows: tuple[int, ...]  # indices into the stream's EMA rows (not its rows)

    @property
    def history(self) -> int:
        if self.coeff >= 1.0:
            return 1
        return min(MAX_EMA_HISTORY, math.ceil(32 * math.log(2) / -math.log1p(-self.coeff)))


MAX_EMA_HISTORY = 1 << 16


@dataclasses.dataclass(frozen=True)
class HistGroup:
    bins: int
    rows: tuple[int, ...]
    lo: tuple[float, ...]
    hi: tuple[float, ...]


@dataclasses.dataclass(frozen=True)
class StreamPlan:
    """Static layout of a stream, derived from its metric specs."""

    rows: tuple[MetricSpec, ...]
    ema_rows: tuple[int, ...]
    ema_coeffs: tuple[float, ...]
    ema_groups: tuple[EmaGroup, ...]
    windows: tuple[WindowGroup, ...]
    hists: tuple[HistGroup, ...]
    dtype: jnp.dtype
    sketches: tuple[SketchGroup, ...] = ()

    @property
    def ranked_rows(self) -> tuple[int, ...]:
        """Rows whose statistics depend on arrival order (EMA, windows)."""
        return tuple(sorted(set(self.ema_rows).union(*(g.rows for g in self.windows))))

    def stream_rows(self, g: EmaGroup) -> tuple[int, ...]:
        """The stream rows of EMA group `g` (its `rows` index the EMA rows)."""
        return tuple(self.ema_rows[j] for j in g.rows)

    def ema_by_row(self, fill: float) -> tuple[np.ndarray, np.ndarray]:
        """Per stream row: whether it has an EMA, and its coefficient (`fill` if not)."""
        coeff = dict(zip(self.ema_rows, self.ema_coeffs))
        rows = range(len(self.rows))
        return np.array([i in coeff for i in rows]), np.array([coeff.get(i, fill) for i in rows])

    @classmethod
    def build(cls, rows: Sequence[MetricSpec], dtype) -> "StreamPlan":
        rows = tuple(rows)
        ema_rows = tuple(i for i, r in enumerate(rows) if r.stats.ema is not None)
        coeffs = tuple(float(rows[i].stats.ema.coeff) for i in ema_rows)  # type: ignore[union-attr]
        ema_groups = tuple(
            EmaGroup(c, tuple(j for j, cj in enumerate(coeffs) if cj == c))
            for c in sorted(set(coeffs))
        )
        sizes = sorted({r.stats.window.size for r in rows if r.stats.window is not None})
        windows = tuple(
            WindowGroup(
                n,
                tuple(i for i, r in enumerate(rows) if r.stats.window and r.stats.window.size == n),
            )
            for n in sizes
        )
        bins = sorted({r.stats.histogram.bins for r in rows if r.stats.histogram is not None})
        hists = []
        for b in bins:
            idx = tuple(
                i
                for i, r in enumerate(rows)
                if r.stats.histogram is not None and r.stats.histogram.bins == b
            )
            hists.append(
                HistGroup(
                    b,
                    idx,
                    tuple(rows[i].stats.histogram.range[0] for i in idx),  # type: ignore[union-attr]
                    tuple(rows[i].stats.histogram.range[1] for i in idx),  # type: ignore[union-attr]
                )
            )
        accuracies = sorted({r.stats.quantiles.accuracy for r in rows if r.stats.quantiles})
        sketches = tuple(
            SketchGroup(
                a,
                tuple(
                    i
                    for i, r in enumerate(rows)
                    if r.stats.quantiles and r.stats.quantiles.accuracy == a
                ),
            )
            for a in accuracies
        )
        return cls(
            rows, ema_rows, coeffs, ema_groups, windows, tuple(hists), jnp.dtype(dtype), sketches
        )


def _ring(rows: int, size: int, dt) -> Ring:
    return Ring(
        jnp.zeros((rows, size, ring_words(dt) + 1), jnp.uint32),
        jnp.zeros((rows,), jnp.int32),
        jnp.zeros((rows,), jnp.int32),
    )


def init(plan: StreamPlan, ema_history: bool = False) -> StreamState:
    """An empty stream. `ema_history` keeps each EMA row's newest values (its group's
    `history`), which makes merging EMAs of disjoint workers exact; without it a merged
    EMA is the average of the workers' EMAs."""
    r, dt = len(plan.rows), plan.dtype
    zeros = jnp.zeros((r,), dt)
    e = r
    return StreamState(
        count=_count.zeros((r,)),
        mean=zeros,
        m2=zeros,
        m2_c=zeros,
        sum=zeros,
        sum_c=zeros,
        min=jnp.full((r,), jnp.inf, dt),
        max=jnp.full((r,), -jnp.inf, dt),
        nonfinite=_count.zeros((r,)),
        ema=jnp.zeros((e,), dt),
        ema_off=jnp.zeros((e,), dt),
        ema_w=jnp.zeros((e,), dt),
        ema_n=jnp.zeros((e,), jnp.int32),
        ema_rings=tuple(
            _ring(len(g.rows), g.history if ema_history else 0, dt) for g in plan.ema_groups
        ),
        steps=jnp.zeros((r,), jnp.uint32),
        windows=tuple(
            _ring(len(g.rows), g.size, dt)._replace(
                pos=jnp.zeros((r,), jnp.int32), filled=jnp.zeros((r,), jnp.int32)
            )
            for g in plan.windows
        ),
        hists=tuple(_count.zeros((len(g.rows), g.bins + 2)) for g in plan.hists),
        hist_steps=tuple(jnp.zeros((len(g.rows), g.bins + 2), jnp.int32) for g in plan.hists),
        sketches=tuple(_count.zeros((len(g.rows), g.slots)) for g in plan.sketches),
    )


def _weight_dtype(dt: jnp.dtype) -> jnp.dtype:
    # Counts and weights need float32's range even for a float16/bfloat16 state.
    return jnp.dtype(jnp.float64) if dt == jnp.float64 else jnp.dtype(jnp.float32)


def _take(rows: tuple[int, ...], x: jax.Array) -> jax.Array:
    if rows == tuple(range(x.shape[0])):
        return x
    # Static row slices, not a gather: keeps the env axis' sharding unambiguous.
    return jnp.stack([x[i] for i in rows])


def add(
    plan: StreamPlan,
    s: StreamState,
    values: jax.Array,
    mask: jax.Array,
    nonfinite: jax.Array | None = None,
) -> StreamState:
    """Feeds `values[R, B]` where `mask`, column order being arrival order, and counts
    `nonfinite[R, B]` (int32, per entry) into the period's non-finite counts."""
    return add_tallied(plan, s, values, mask, nonfinite, _no_tally(values), _count.zeros((0,)))[0]


def tally_width(plan: StreamPlan, tallied: int) -> int:
    """Width of the counts that `add_tallied` adds `tallied` tally rows into: padded to
    whole multiples of the stream's rows, so that (for up to R tally rows) their update
    is shaped like every other per-row field and joins that one kernel."""
    rows = len(plan.rows)
    return -(-tallied // rows) * rows if rows else 0


def add_tallied(
    plan: StreamPlan,
    s: StreamState,
    values: jax.Array,
    mask: jax.Array,
    nonfinite: jax.Array | None,
    tally: jax.Array,
    counts: Count,
    fused: bool = False,
    interpret: bool = False,
) -> tuple[StreamState, Count]:
    """`add`, and `counts` (`[tally_width(plan, C)]`) plus the sum of each row of
    `tally[C, B]` (int32), in its first C entries. The sums are taken in the batch's own
    reduction and added in the per-row fields' kernel, where separate counts would be
    two more kernels. `fused` lets a CUDA GPU fold the batch (its reduction, arrival
    ranks, EMA sum and ring writes) in one kernel of our own (`_fused_ema`, where the
    spec has an EMA or a window and the batch fits it; histograms and sketches keep
    XLA's kernels); the caller passes it only for a batch that is not split over
    devices, which that kernel cannot be. `interpret` (with `fused`) runs that kernel on
    any platform, in Pallas' interpret mode (slow: for tests)."""
    dt = plan.dtype
    width = counts.lo.shape[0]
    wt = _weight_dtype(dt)
    # Deviations from the running mean keep the moments small, so float32 stays accurate
    # for data far from zero. An empty period's mean is 0 (init, reset_period and merge
    # keep it so), so its first batch is folded as it is (Chan's pairwise update is
    # exact for constant data either way). No `count > 0` test here: with it XLA left
    # the shifted values out of the reduction's kernel (one more kernel per step).
    shift = s.mean
    if nonfinite is None:
        nonfinite = jnp.zeros(values.shape, jnp.int32)
    if plan.ema_rows or plan.windows or plan.hists or plan.sketches:
        values, mask = gathered(values), gathered(mask)
    tally = jnp.pad(tally, ((0, width - tally.shape[0]), (0, 0)))
    args = (plan, s, values, mask, nonfinite, shift, tally)
    if (plan.ema_rows or plan.windows) and fused and _fused_ema.fits(mask.shape[1], dt):
        folded = _fold_fused(*args, interpret)
    else:
        folded = _fold(*args)
    stats, ema_data, window_data, hists, hist_steps = folded
    k, bsum, bmin, bmax, mb, m2b, bad, ema_sum, tallies = stats

    kf = k.astype(wt)
    na = _count.as_float(s.count, wt)
    n = na + kf
    frac = jnp.where(n > 0, kf / jnp.maximum(n, 1), 0)
    # With values in the period, shift == s.mean and mb (the batch's mean minus it) is
    # Chan's delta; without, the new mean is mb (frac == 1) and the old mean carries no
    # weight (na == 0).
    m2, m2_c = kahan_add(s.m2, s.m2_c, m2b + mb * mb * (na * frac).astype(dt))
    # Every [R] field below is a function of `k` (an empty batch leaves it as it is),
    # which lets XLA update them all in one multi-output kernel.
    some = k > 0
    total, total_c = kahan_add(s.sum, s.sum_c, bsum)
    total, total_c = jnp.where(some, total, s.sum), jnp.where(some, total_c, s.sum_c)
    mean = _period_mean(total, total_c, n, shift + mb * frac.astype(dt))
    vmin = jnp.where(some, jnp.minimum(s.min, bmin), s.min)
    vmax = jnp.where(some, jnp.maximum(s.max, bmax), s.max)

    ema, ema_off, ema_w, ema_n = s.ema, s.ema_off, s.ema_w, s.ema_n
    ema_rings = s.ema_rings
    if plan.ema_rows:
        er = plan.ema_rows
        ek = _take(er, k)
        ema, ema_off, ema_w = _ema_update(plan, s, k, shift, mean, ema_sum)
        is_ema = plan.ema_by_row(0.0)[0]
        ema_n = ema_n + jnp.where(is_ema, jnp.minimum(k, _INT32_MAX - ema_n), 0)
        ema_rings = tuple(
            _advanced(ring._replace(data=data), _take(g.rows, ek)) if ring.size else ring
            for g, ring, data in zip(plan.ema_groups, s.ema_rings, ema_data)
        )
    windows = []
    for g, w, data in zip(plan.windows, s.windows, window_data):
        # `pos` and `filled` of every row, elementwise in `k` (rows of other groups keep
        # theirs), not the group's [R_w] ones: that keeps them in the [R] update kernel.
        mine = np.isin(np.arange(len(plan.rows)), g.rows)
        moved = _advanced(w, k)
        pos = jnp.where(mine, moved.pos, w.pos)
        filled = jnp.where(mine, moved.filled, w.filled)
        windows.append(Ring(data, pos, filled))
    sketches = tuple(
        _sketch.add(c, _sketch.slot(g, _take(g.rows, values), _take(g.rows, mask)))
        for g, c in zip(plan.sketches, s.sketches)
    )
    new = s._replace(
        count=_count.add(s.count, k),
        # `k < 0` never holds: reading `k` here lets XLA update this count in the same
        # kernel as the other [R] fields (sibling fusions must share an operand).
        nonfinite=_count.add(s.nonfinite, jnp.where(k < 0, 0, bad)),
        mean=mean,
        m2=m2,
        m2_c=m2_c,
        sum=total,
        sum_c=total_c,
        min=vmin,
        max=vmax,
        ema=ema,
        ema_off=ema_off,
        ema_w=ema_w,
        ema_n=ema_n,
        ema_rings=ema_rings,
        # Reads `k` for the same reason as `nonfinite` above.
        steps=s.steps + jnp.where(k < 0, 0, 1).astype(jnp.uint32),
        windows=tuple(windows),
        hists=hists,
        hist_steps=hist_steps,
        sketches=sketches,
    )
    # Read through `k` like `nonfinite` above, to join the same kernel.
    packs = width // len(plan.rows) if plan.rows else 0
    return new, _count.add(counts, jnp.where(jnp.tile(k, packs) < 0, 0, tallies))


def _ranked(plan: StreamPlan) -> tuple[int, ...]:
    """The rows `add` ranks by arrival. With an EMA every row is: the EMA operand is
    then an elementwise function of the batch (zero weight outside EMA rows), where a
    stack of the EMA rows and zero rows made XLA write it out (H100: 1.4 us per step)."""
    return tuple(range(len(plan.rows))) if plan.ema_rows else plan.ranked_rows


def arrivals_after(mask: jax.Array) -> tuple[jax.Array, jax.Array]:
    """Per entry of `mask[R, B]`: how many masked-in entries follow it in its row
    (`k - 1 - rank` for a masked-in entry; meaningless elsewhere); and each row's `k`.

    The mask is packed into one 32-bit word per block of 32 entries (one small
    reduction); an entry's later neighbours in its block are the popcount of the word's
    higher bits, and the later blocks' entries a reverse cumsum over the blocks. One
    cumsum over the whole row is lowered to nested reduce-windows that XLA fuses into
    one kernel recomputing the inner level per output (H100, full spec of the isolated
    bench: 6.2 us of 28 per step).
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


def _window(g: WindowGroup, w: Ring) -> Ring:
    """The ring of window group `g` with its own rows' `pos` and `filled` ([R_w])."""
    return w._replace(pos=_take(g.rows, w.pos), filled=_take(g.rows, w.filled))


def _widened(g: WindowGroup, ring: Ring, rows: int) -> Ring:
    """`_window`'s inverse: `pos` and `filled` spread to every row (0 outside `g`)."""
    at = {r: j for j, r in enumerate(g.rows)}

    def spread(x: jax.Array) -> jax.Array:
        zero = jnp.zeros_like(x[0])
        return jnp.stack([x[at[i]] if i in at else zero for i in range(rows)])

    return ring._replace(pos=spread(ring.pos), filled=spread(ring.filled))


def _batch(values, mask, nonfinite, shift, wt, ema_in, tally):
    """Per row of a batch `values[R, B]` where `mask`: the count, sum, min, max, and the
    mean and sum of squared deviations of `values - shift`; the sum of `nonfinite`; the
    sum of each row of `ema_in` (`_ema_operands`; None without EMA rows); the sum of each
    row of `tally[C, B]` (C a multiple of R, see `tally_width`).

    On accelerators one reduction gives them all: its combiner merges the moments
    pairwise (Chan's rule), so no first pass for a pivot is needed. The CPU reduces a
    row sequentially, and a sequential Welford update over 10^6 float32 values drifts;
    there the moments take two passes around the batch's mean (or `shift`). Both agree
    to float32 rounding (tests/test_core_numerics.py checks both on one input).
    """
    return jax.lax.platform_dependent(
        values,
        mask,
        nonfinite,
        shift,
        ema_in,
        tally,
        cpu=lambda v, m, nf, sh, e, t: batch_two_pass(v, m, nf, sh, wt, e, t),
        default=lambda v, m, nf, sh, e, t: batch_one_pass(v, m, nf, sh, wt, e, t),
    )


def batch_two_pass(values, mask, nonfinite, shift, wt, ema_in=None, tally=None):
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
    tallies = _no_tally(values) if tally is None else jnp.sum(tally, axis=1, dtype=jnp.int32)
    return k, bsum, bmin, bmax, mb + (pivot - shift), m2b, bad, ema_sum, tallies


def batch_one_pass(values, mask, nonfinite, shift, wt, ema_in=None, tally=None):
    """`_batch` as one variadic reduction (Chan's pairwise moments in its combiner)."""
    dt = values.dtype
    zero = jnp.zeros_like(values)
    operands = (
        mask.astype(jnp.int32),
        jnp.where(mask, values, zero),
        jnp.where(mask, values, jnp.full_like(values, jnp.inf)),
        jnp.where(mask, values, jnp.full_like(values, -jnp.inf)),
        jnp.where(mask, values - shift[:, None], zero),
        zero,
        nonfinite,
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
    tally = _no_tally(values) if tally is None else tally
    # The tally rows as summed operands shaped like the batch: their sums come out as
    # one [R] array each (several scalar outputs would need a concatenation).
    rows = values.shape[0]
    packs = tally.shape[0] // rows if rows else 0
    operands += tuple(tally[i * rows : (i + 1) * rows] for i in range(packs))
    inits += (np.int32(0),) * packs
    e = 8 if has_ema else 7

    def combine(x, y):
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
    # off the batch's mean afterwards saves ~1 us/step on an H100 but rounds Chan's
    # delta to the ulp of the mean, a variance bias of ~(ulp/sigma)^2 for data far from
    # zero (1e-4 relative at mean 1e6, std 1).
    out = jax.lax.reduce(operands, inits, combine, (1,))
    tallies = jnp.concatenate(out[e:]) if packs else jnp.zeros((0,), jnp.int32)
    return (*out[:7], out[7] if has_ema else None, tallies)


def _no_tally(values: jax.Array) -> jax.Array:
    return jnp.zeros((0, values.shape[1]), jnp.int32)


_INT32_MAX = np.int32(np.iinfo(np.int32).max)


def _ema_offset(ema_w, ema_off, shift) -> tuple[jax.Array, jax.Array]:
    """Per row, from the state's `ema_w` and `ema_off` and the batch's `shift`: the offset
    the batch's EMA deviations are taken from, and whether this batch seeds the EMA (none
    seen yet)."""
    seeded = ema_w > 0
    return jnp.where(seeded, ema_off, shift), ~seeded


def _ema_operands(plan: StreamPlan, values, mask, after, k, off, seeding):
    """The EMA's input to the batch's reduction, every row ([R, B]; zero rows where a
    row has no EMA): the deviations `x - off` weighed by their EMA weights. `after` and
    `k` are every row's arrival ranks and counts (`arrivals_after`); `off` and `seeding`
    come from `_ema_offset`."""
    # Sequential EMA over the k arrivals in closed form: the value with `after` later
    # arrivals gets weight c(1-c)^after; the old EMA gets (1-c)^k. Unseeded, the first
    # arrival (after == k - 1) seeds it and weighs (1-c)^(k-1). The EMA is kept relative
    # to an offset fixed at seeding: a float32 EMA of values far from zero otherwise
    # loses the low bits of every update and drifts.
    dt = plan.dtype
    is_ema, coeff = plan.ema_by_row(0.0)
    c = jnp.asarray(coeff, dt)[:, None]
    dev = jnp.where(mask & is_ema[:, None], values - off[:, None], 0)
    return _ema_weights(c, after, seeding[:, None], k[:, None], dt) * dev


def _ema_weights(c, after, seeding, count, dt):
    """The closed-form EMA weights of values with `after` later arrivals: c(1-c)^after,
    except the first of `count` values where `seeding`, which seeds the EMA and weighs
    (1-c)^(count-1)."""
    decay = jnp.power(1 - c, after.astype(dt))
    return jnp.where(seeding & (after == count - 1), decay, c * decay)


def _ema_update(plan: StreamPlan, s: StreamState, k, shift, mean, new):
    """New (ema, ema_off, ema_w), every row ([R]; rows without an EMA keep theirs), from
    the batch's sum of `_ema_operands`, `new`."""
    dt = plan.dtype
    is_ema, coeff = plan.ema_by_row(1.0)
    c_all = jnp.asarray(coeff, dt)
    # The deviations were taken off `base`, known before the batch. A seeding batch's
    # weights sum to 1, so its EMA moves to the offset fixed now, the period's mean as of
    # this batch, by adding `base - off`: the rounding of that first batch then decays
    # like any value, where an offset of `base` (0 for a row never seen) would stay.
    base, seeding = _ema_offset(s.ema_w, s.ema_off, shift)
    seeded = ~seeding
    off = jnp.where(seeded, s.ema_off, mean)
    keep = jnp.power(1 - c_all, k.astype(dt))
    ema = jnp.where(seeded, keep * s.ema, 0) + new + (base - off)
    some = is_ema & (k > 0)
    ema = jnp.where(some, ema, s.ema)
    ema_off = jnp.where(some, off, s.ema_off)
    ema_w = jnp.where(~seeded & some, jnp.ones_like(s.ema_w), s.ema_w)
    return ema, ema_off, ema_w


def _ring_data(w: Ring, step: jax.Array, values, mask, after, k) -> jax.Array:
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
        _packed(values, jnp.broadcast_to(step[:, None], values.shape)), mode="drop"
    )


def _advanced(w: Ring, k: jax.Array) -> Ring:
    """`w` (its data already written) with `pos` and `filled` past `k` arrivals per row."""
    stored = jnp.minimum(k, w.size)
    return w._replace(pos=(w.pos + stored) % w.size, filled=jnp.minimum(w.filled + stored, w.size))


def _fold(plan: StreamPlan, s: StreamState, values, mask, nonfinite, shift, tally):
    """The batch's statistics (`_fused_ema.Batch`), and what it adds that depends on
    arrival order, and its histograms: the data of each EMA ring and each window ring, and
    each histogram's counts with its `hist_steps`. `tally` has `tally_width` rows."""
    # One arrival rank shared by every row that needs one (EMA and window rows): how
    # many of the row's values arrive after each one (`k - 1 - rank`). It is known
    # before the batch is reduced, so the EMA's weighted sum is one more operand of the
    # batch's reduction.
    ranked = _ranked(plan)
    at = {row: i for i, row in enumerate(ranked)}
    after, k = arrivals_after(_take(ranked, mask)) if ranked else (None, None)
    ema_in = None
    if plan.ema_rows:
        off, seeding = _ema_offset(s.ema_w, s.ema_off, shift)
        ema_in = _ema_operands(plan, values, mask, after, k, off, seeding)

    def ring(w: Ring, rows: tuple[int, ...]) -> jax.Array:
        if not w.size:
            return w.data
        i = tuple(at[r] for r in rows)
        rk = _take(i, k)
        args = (_take(rows, s.steps), _take(rows, values), _take(rows, mask), _take(i, after))
        return _ring_data(w, *args, rk)

    ema_data = tuple(ring(w, plan.stream_rows(g)) for g, w in zip(plan.ema_groups, s.ema_rings))
    window_data = tuple(ring(_window(g, w), g.rows) for g, w in zip(plan.windows, s.windows))
    stats = _fused_ema.Batch(
        *_batch(values, mask, nonfinite, shift, _weight_dtype(plan.dtype), ema_in, tally)
    )
    return stats, ema_data, window_data, *_hists_add(plan, s, values, mask)


def _hists_add(plan: StreamPlan, s: StreamState, values, mask):
    """Each histogram's counts with the batch added, and its `hist_steps`."""
    return _pairs(
        _hist_add(g, h, z, _take(g.rows, values), _take(g.rows, mask), plan.dtype)
        for g, h, z in zip(plan.hists, s.hists, s.hist_steps)
    )


def _fold_fused(plan: StreamPlan, s: StreamState, values, mask, nonfinite, shift, tally, interpret):
    """`_fold` on a CUDA GPU (or where `interpret`): the batch's statistics, the EMA and
    the rings in one kernel of our own (`_fused_ema.fold`); elsewhere `_fold` itself."""
    rows = len(plan.rows)

    def where_of(members: tuple[int, ...]) -> np.ndarray:
        out = np.full(rows, -1, np.int32)
        out[list(members)] = np.arange(len(members), dtype=np.int32)
        return out

    def kernel(s, values, mask, nonfinite, shift, tally):
        rings = []
        for g, r in zip(plan.ema_groups, s.ema_rings):
            if r.size:
                own = where_of(plan.stream_rows(g))
                rings.append(_fused_ema.RingIn(r.data, r.pos, own, own))
        for g, r in zip(plan.windows, s.windows):
            mine = where_of(g.rows)  # the window's `pos` has every stream row
            pos_row = np.where(mine >= 0, np.arange(rows), -1)
            rings.append(_fused_ema.RingIn(r.data, r.pos, mine, pos_row))
        ema = None
        if plan.ema_rows:
            ema = _fused_ema.EmaIn(plan.ema_by_row(0.0)[1], s.ema_w, s.ema_off)
        stats, data = _fused_ema.fold(
            mask, values, nonfinite, shift, s.steps, tally, ema, tuple(rings), interpret
        )
        data = iter(data)
        ema_data = tuple(next(data) if r.size else r.data for r in s.ema_rings)
        return stats, ema_data, tuple(data), *_hists_add(plan, s, values, mask)

    def reference(s, values, mask, nonfinite, shift, tally):
        return _fold(plan, s, values, mask, nonfinite, shift, tally)

    args = (s, values, mask, nonfinite, shift, tally)
    if interpret:
        return kernel(*args)
    return jax.lax.platform_dependent(*args, cuda=kernel, default=reference)


def _pairs(items) -> tuple[tuple, tuple]:
    pairs = tuple(items)
    return tuple(a for a, _ in pairs), tuple(b for _, b in pairs)


def slot_counts_scatter(slot: jax.Array, into: jax.Array) -> jax.Array:
    """`into[R, nslots]` (int32) plus, per row, how many entries of `slot[R, B]` equal each
    of 0..nslots-1 (others ignored)."""
    rows = jnp.broadcast_to(jnp.arange(slot.shape[0], dtype=jnp.int32)[:, None], slot.shape)
    return into.at[rows, slot].add(1, mode="drop")


def slot_counts_compare(slot: jax.Array, into: jax.Array) -> jax.Array:
    """Same as `slot_counts_scatter`, as one compare-and-sum reduction."""
    bins = jnp.arange(into.shape[1], dtype=jnp.int32)[None, :, None]
    return into + jnp.sum(slot[:, None, :] == bins, axis=2, dtype=jnp.int32)


def _hist_add(g: HistGroup, h: Count, zero: jax.Array, values, mask, dt):
    """`h` with the batch counted in, and `zero` (`hist_steps`) as it was."""
    lo = jnp.asarray(g.lo, dt)[:, None]
    hi = jnp.asarray(g.hi, dt)[:, None]
    t = jnp.floor((values - lo) / (hi - lo) * g.bins)
    inner = jnp.clip(jnp.nan_to_num(t), 0, g.bins - 1).astype(jnp.int32) + 1
    slot = jnp.where(values < lo, 0, jnp.where(values > hi, g.bins + 1, inner))
    slot = jnp.where(mask & ~jnp.isnan(values), slot, g.bins + 2)  # matches no bin
    # A scatter-add into `zero` in place: on CPU ~3x cheaper than compare-and-count, on an
    # H100 1.0 us less per step (XLA does not fuse the compare into the reduction). TPUs
    # scatter slowly: there, compare and count.
    inc = jax.lax.platform_dependent(
        slot,
        zero,
        cpu=slot_counts_scatter,
        cuda=slot_counts_scatter,
        default=slot_counts_compare,
    )
    # `inc < 0` never holds: zeros read through `inc` join the count's kernel.
    return _count.add(h, inc), jnp.where(inc < 0, inc, 0)


def reset_period(plan: StreamPlan, s: StreamState) -> StreamState:
    """Clears the period statistics; EMA, windows and the arrival step carry on."""
    fresh = init(plan)
    return fresh._replace(
        ema=s.ema,
        ema_off=s.ema_off,
        ema_w=s.ema_w,
        ema_n=s.ema_n,
        ema_rings=s.ema_rings,
        steps=s.steps,
        windows=s.windows,
    )


_UINT32_MAX = np.uint32(np.iinfo(np.uint32).max)


def _rotated(r: Ring) -> Ring:
    """`r` rotated so that slot j holds arrival order j (oldest first, right-aligned; `pos`
    0), over any leading axes."""
    n = r.size
    if n == 0:
        return r
    j = jnp.arange(n, dtype=jnp.int32).reshape((1,) * r.pos.ndim + (n,))
    slot = (r.pos[..., None] + j) % n
    return Ring(
        jnp.take_along_axis(r.data, slot[..., None], axis=-2), jnp.zeros_like(r.pos), r.filled
    )


def _ordered(w: Ring, steps: jax.Array, dt) -> tuple[jax.Array, jax.Array, jax.Array]:
    """Ring contents right-aligned in arrival order (oldest first): values, their ages
    in arrival steps (`steps - stamp`, `steps` per ring row), and validity."""
    r = _rotated(w)
    j = jnp.arange(w.size, dtype=jnp.int32)[None, :]
    return r.values(dt), steps[:, None] - r.stamps, j >= (w.size - w.filled)[:, None]


def _union(wa: Ring, sa: jax.Array, wb: Ring, sb: jax.Array, dt):
    """Both rings' values in arrival order, oldest first: by age, then `a` before `b`
    (within a step the lower worker arrives first), invalid entries in front."""
    parts = [_ordered(wa, sa, dt), _ordered(wb, sb, dt)]
    vals, age, valid = (jnp.concatenate([p[i] for p in parts], axis=1) for i in range(3))
    key = jnp.where(valid, _UINT32_MAX - age, jnp.zeros_like(age))
    order = jnp.argsort(key, axis=1, stable=True)
    take = lambda x: jnp.take_along_axis(x, order, axis=1)  # noqa: E731
    return take(vals), take(age), take(valid)


def _newest(vals, age, valid, size: int, steps: jax.Array) -> Ring:
    """A ring holding the newest `size` of `_union`'s entries, stamped relative to `steps`
    (per ring row)."""
    keep = slice(vals.shape[1] - size, vals.shape[1])
    return Ring(
        _packed(vals[:, keep], steps[:, None] - age[:, keep]),
        jnp.zeros(vals.shape[:1], jnp.int32),
        jnp.sum(valid[:, keep], axis=1, dtype=jnp.int32),
    )


def _merge_ema(plan: StreamPlan, a: StreamState, b: StreamState):
    """EMA of both workers' values in arrival order (see `EmaGroup`), relative to `a`'s
    offset (`b`'s where `a` has no value)."""
    dt = plan.dtype
    off = jnp.where(a.ema_n == 0, b.ema_off, a.ema_off)
    wsum = a.ema_w + b.ema_w
    # Estimate of the EMA before the newest values, minus `off`; it weighs
    # (1-c)^history at most.
    rel_a = a.ema + (a.ema_off - off)
    rel_b = b.ema + (b.ema_off - off)
    tail = jnp.where(
        wsum > 0, (a.ema_w * rel_a + b.ema_w * rel_b) / jnp.maximum(wsum, 1), jnp.zeros_like(a.ema)
    )
    n = a.ema_n + jnp.minimum(b.ema_n, _INT32_MAX - a.ema_n)
    parts, rings = [], []
    # Rows merged from both workers' histories: one sequential worker again.
    sequential = jnp.zeros(a.ema.shape, jnp.bool_)
    for g, ra, rb in zip(plan.ema_groups, a.ema_rings, b.ema_rings):
        size = ra.size
        own = plan.stream_rows(g)
        rows = jnp.asarray(own, jnp.int32)
        # A side holds its history where its ring has every value it has seen, or the
        # newest `size`, and its EMA is one worker's, not an average of several. A state
        # made without history (an unsharded `init`, its rings padded to concatenate)
        # holds none: then both sides' EMAs are averaged, as for two such states.
        held = (
            (size > 0)
            & (ra.filled >= jnp.minimum(a.ema_n[rows], size))
            & (rb.filled >= jnp.minimum(b.ema_n[rows], size))
            & (a.ema_w[rows] <= 1)
            & (b.ema_w[rows] <= 1)
        )
        sa, sb = _take(own, a.steps), _take(own, b.steps)
        vals, age, valid = _union(ra, sa, rb, sb, dt)
        # Exact when the rings hold every value either worker has seen.
        exact = (a.ema_n[rows] <= size) & (b.ema_n[rows] <= size)
        total = jnp.sum(valid, axis=1, dtype=jnp.int32)
        folded = jnp.where(exact, total, jnp.minimum(total, size))[:, None]
        p = vals.shape[1] - 1 - jnp.arange(vals.shape[1], dtype=jnp.int32)[None, :]
        c = jnp.asarray(g.coeff, dt)
        w = _ema_weights(c, p, exact[:, None], folded, dt)
        dev = vals - off[rows][:, None]
        new = jnp.sum(jnp.where(valid & (p < folded), w * dev, 0), axis=1)
        keep = jnp.where(exact, 0, jnp.power(1 - c, folded[:, 0].astype(dt)) * tail[rows])
        parts.append((rows, jnp.where(held, keep + new, tail[rows])))
        sequential = sequential.at[rows].set(held)
        rings.append(_newest(vals, age, valid, size, sa))
    ema = tail
    for rows, v in parts:
        ema = ema.at[rows].set(v)
    ema = jnp.where(a.ema_n == 0, b.ema, jnp.where(b.ema_n == 0, a.ema, ema))
    wsum = jnp.where(sequential, jnp.minimum(wsum, 1), wsum)
    return ema, off, wsum, n, tuple(rings)


def _period_mean(total: jax.Array, total_c: jax.Array, n: jax.Array, chan: jax.Array) -> jax.Array:
    """The period's mean: its compensated sum over its count, where that is finite, else
    Chan's running mean (`chan`: an empty period's 0, or a sum that overflowed).

    Chan's update `mean + delta * k / n` stops moving in float32 once `delta * k / n` is
    below the mean's ulp (one value per step at counts past ~10^5 of data near 1e4), and
    the variance then grows around the stale mean; the compensated sum holds the mean
    to a few ulp at any count, and the deviations of the next batch are taken from it."""
    dt = total.dtype
    mean = (total - total_c) / jnp.maximum(n, 1).astype(dt)
    return jnp.where((n > 0) & jnp.isfinite(mean), mean, chan)


def merge(plan: StreamPlan, a: StreamState, b: StreamState) -> StreamState:
    """Combines streams of disjoint workers that ran side by side: values of `b` arrive
    after `a`'s of the same step. Period statistics are exact (Chan for mean/std);
    windows and EMA follow arrival order (see the module docstring and `EmaGroup`)."""
    dt = plan.dtype
    wt = _weight_dtype(dt)
    na, nb = _count.as_float(a.count, wt), _count.as_float(b.count, wt)
    n = na + nb
    frac = jnp.where(n > 0, nb / jnp.maximum(n, 1), 0)
    both = (na > 0) & (nb > 0)
    delta = jnp.where(both, b.mean - a.mean, 0)
    # An empty side's mean carries no weight.
    chan = jnp.where(both, a.mean + delta * frac.astype(dt), jnp.where(na > 0, a.mean, b.mean))
    m2, m2_c = kahan_add(a.m2, a.m2_c, b.m2 + delta * delta * (na * frac).astype(dt))
    m2, m2_c = kahan_add(m2, m2_c, -b.m2_c)
    total, total_c = kahan_add(a.sum, a.sum_c, b.sum)
    total, total_c = kahan_add(total, total_c, -b.sum_c)
    mean = _period_mean(total, total_c, n, chan)
    ema, ema_off, ema_w, ema_n, ema_rings = _merge_ema(plan, a, b)
    windows = tuple(
        _widened(
            g,
            _newest(
                *_union(
                    _window(g, wa),
                    _take(g.rows, a.steps),
                    _window(g, wb),
                    _take(g.rows, b.steps),
                    dt,
                ),
                g.size,
                _take(g.rows, a.steps),
            ),
            len(plan.rows),
        )
        for g, wa, wb in zip(plan.windows, a.windows, b.windows)
    )
    return StreamState(
        count=_count.merge(a.count, b.count),
        mean=mean,
        m2=m2,
        m2_c=m2_c,
        sum=total,
        sum_c=total_c,
        min=jnp.minimum(a.min, b.min),
        max=jnp.maximum(a.max, b.max),
        nonfinite=_count.merge(a.nonfinite, b.nonfinite),
        ema=ema,
        ema_off=ema_off,
        ema_w=ema_w,
        ema_n=ema_n,
        ema_rings=ema_rings,
        steps=a.steps,
        windows=windows,
        hists=tuple(_count.merge(x, y) for x, y in zip(a.hists, b.hists)),
        hist_steps=a.hist_steps,
        sketches=tuple(_count.merge(x, y) for x, y in zip(a.sketches, b.sketches)),
    )


def combine(plan: StreamPlan, shards: StreamState) -> StreamState:
    """One stream from per-shard streams stacked on a leading axis, merged in shard order.

    Shard `i` holds the `i`-th contiguous block of envs, so merging in shard order gives
    ascending global env index among values that arrive on the same step.
    """
    num = shards.steps.shape[0]
    shards = jax.tree.map(gathered, shards)  # explicit meshes: shards meet here, once
    first = jax.tree.map(lambda x: x[0], shards) if num else None
    if num == 1:
        return first
    if num == 0:
        history = any(r.size > 0 for r in shards.ema_rings)
        return init(plan, ema_history=history)
    rest = jax.tree.map(lambda x: x[1:], shards)
    return jax.lax.scan(lambda acc, sh: (merge(plan, acc, sh), None), first, rest)[0]


def pad_ema_history(s: StreamState, size: int) -> StreamState:
    """`s` with EMA rings widened to `size` (empty older slots), so it concatenates with
    a state whose rings are that wide."""

    def widen(r: Ring) -> Ring:
        extra = size - r.size
        if extra <= 0:
            return r
        # Right-aligned contents stay right-aligned once the ring is rotated to slot 0.
        r = _rotated(r)
        pad = [(0, 0)] * r.data.ndim
        pad[-2] = (extra, 0)
        return r._replace(data=jnp.pad(r.data, pad))

    return s._replace(ema_rings=tuple(widen(r) for r in s.ema_rings))


def _percentiles(sorted_vals: jax.Array, filled: jax.Array, ps: tuple[float, ...], dt):
    # numpy's "linear" method: position p/100 * (n-1) between order statistics.
    nm1 = jnp.maximum(filled - 1, 0).astype(dt)
    out = []
    for p in ps:
        pos = (p / 100.0) * nm1
        lo = jnp.floor(pos)
        i = lo.astype(jnp.int32)
        j = jnp.minimum(i + 1, jnp.maximum(filled - 1, 0))
        a = jnp.take_along_axis(sorted_vals, i[:, None], axis=1)[:, 0]
        b = jnp.take_along_axis(sorted_vals, j[:, None], axis=1)[:, 0]
        # a + (b-a)*t, written to stay exact when a == b, including infinities
        t = pos - lo
        v = jnp.where(t > 0, a + (b - a) * t, a)
        out.append(jnp.where(filled > 0, v, jnp.nan))
    return out


def compute(plan: StreamPlan, s: StreamState) -> list[dict[str, jax.Array | Count]]:
    """Per row, a dict of every statistic it has; empty-period values are NaN."""
    dt = plan.dtype
    n = _count.as_float(s.count, _weight_dtype(dt))
    empty = n == 0
    nan = jnp.full_like(s.mean, jnp.nan)
    mean = jnp.where(empty, nan, s.mean)
    var = jnp.maximum(s.m2 - s.m2_c, 0).astype(n.dtype) / jnp.maximum(n, 1)
    std = jnp.where(empty, nan, jnp.sqrt(var).astype(dt))
    out: list[dict[str, jax.Array | Count]] = [
        {
            "mean": mean[i],
            "std": std[i],
            "min": jnp.where(empty[i], jnp.nan, s.min[i]),
            "max": jnp.where(empty[i], jnp.nan, s.max[i]),
            "sum": s.sum[i] - s.sum_c[i],
            "count": Count(s.count.hi[i], s.count.lo[i]),
            "nonfinite": Count(s.nonfinite.hi[i], s.nonfinite.lo[i]),
        }
        for i in range(len(plan.rows))
    ]
    for i in plan.ema_rows:
        out[i]["ema"] = jnp.where(s.ema_w[i] > 0, s.ema_off[i] + s.ema[i], jnp.nan)
    for g, w in zip(plan.windows, s.windows):
        w = _window(g, w)
        vals, _, valid = _ordered(w, _take(g.rows, s.steps), dt)
        filled = w.filled
        cnt = jnp.maximum(filled, 1).astype(dt)
        wmean = jnp.sum(jnp.where(valid, vals, 0), axis=1) / cnt
        dev = jnp.where(valid, vals - wmean[:, None], 0)
        wstd = jnp.sqrt(jnp.sum(dev * dev, axis=1) / cnt)
        wmin = jnp.min(jnp.where(valid, vals, jnp.inf), axis=1)
        wmax = jnp.max(jnp.where(valid, vals, -jnp.inf), axis=1)
        has = filled > 0
        has_nan = jnp.any(valid & jnp.isnan(vals), axis=1)
        ps = {}
        pcts = tuple(p for r in g.rows for p in plan.rows[r].stats.window.percentiles)  # type: ignore[union-attr]
        if pcts:
            srt = jnp.sort(jnp.where(valid, vals, jnp.inf), axis=1)
            uniq = tuple(sorted(set(pcts)))
            for p, v in zip(uniq, _percentiles(srt, filled, uniq, dt)):
                ps[p] = jnp.where(has_nan, jnp.nan, v)
        for j, i in enumerate(g.rows):
            o = out[i]
            o["window_mean"] = jnp.where(has[j], wmean[j], jnp.nan)
            o["window_std"] = jnp.where(has[j], wstd[j], jnp.nan)
            o["window_min"] = jnp.where(has[j], wmin[j], jnp.nan)
            o["window_max"] = jnp.where(has[j], wmax[j], jnp.nan)
            o["window_values"] = jnp.where(valid[j], vals[j], jnp.nan)
            for p in plan.rows[i].stats.window.percentiles:  # type: ignore[union-attr]
                o[f"window_p{p:g}"] = ps[p][j]
    for g, h in zip(plan.hists, s.hists):
        for j, i in enumerate(g.rows):
            out[i]["histogram"] = Count(h.hi[j], h.lo[j])
    for g, c in zip(plan.sketches, s.sketches):
        levels = tuple(plan.rows[i].stats.quantiles.levels for i in g.rows)  # type: ignore[union-attr]
        for i, ls, vals in zip(g.rows, levels, _sketch.quantiles(g, c, levels, dt)):
            for j, p in enumerate(ls):
                out[i][_statistics.quantile(p)] = vals[j]
    return out
