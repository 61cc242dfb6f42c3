"""Report statistics over a stream of values: one row per metric, stacked.

A stream receives batches `values[R, B]` with a boolean `mask[R, B]`; within a row, the
masked-in values arrive in ascending column order (for episodes: ascending env index).
Period statistics (count/mean/std/min/max/sum/histogram/nonfinite) reset with
`reset_period`; EMA and windows persist.

All rows are stacked so that one fused XLA kernel serves every metric, whatever their
number: the per-step cost grows with rows x envs elementwise, not with kernel launches.
"""

import dataclasses
from collections.abc import Sequence
from typing import NamedTuple

import jax
import jax.numpy as jnp

from . import _count
from ._count import Count
from ._numerics import kahan_add
from ._spec import MetricSpec


class WindowState(NamedTuple):
    """Ring buffers of one window size, for the rows that have such a window.

    The value with arrival order j (0 oldest ... size-1 newest, right-aligned) is at
    slot (pos + j) mod size, valid when j >= size - filled.
    """

    buf: jax.Array  # [rows, size] float
    pos: jax.Array  # [rows] int32, next slot to write
    filled: jax.Array  # [rows] int32 in [0, size]


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
    ema: jax.Array  # [R_ema] float
    ema_w: jax.Array  # [R_ema] float: 0 unseeded, else number of merged seeded workers
    windows: tuple[WindowState, ...]  # one per distinct window size
    hists: tuple[Count, ...]  # one per distinct bin count: [R_h, bins + 2] incl. under/overflow


@dataclasses.dataclass(frozen=True)
class WindowGroup:
    size: int
    rows: tuple[int, ...]


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
    windows: tuple[WindowGroup, ...]
    hists: tuple[HistGroup, ...]
    dtype: jnp.dtype

    @property
    def ranked_rows(self) -> tuple[int, ...]:
        """Rows whose statistics depend on arrival order (EMA, windows)."""
        return tuple(sorted(set(self.ema_rows).union(*(g.rows for g in self.windows))))

    @classmethod
    def build(cls, rows: Sequence[MetricSpec], dtype) -> "StreamPlan":
        rows = tuple(rows)
        ema_rows = tuple(i for i, r in enumerate(rows) if r.stats.ema is not None)
        coeffs = tuple(float(rows[i].stats.ema.coeff) for i in ema_rows)  # type: ignore[union-attr]
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
        return cls(rows, ema_rows, coeffs, windows, tuple(hists), jnp.dtype(dtype))


def init(plan: StreamPlan) -> StreamState:
    r, dt = len(plan.rows), plan.dtype
    zeros = jnp.zeros((r,), dt)
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
        ema=jnp.zeros((len(plan.ema_rows),), dt),
        ema_w=jnp.zeros((len(plan.ema_rows),), dt),
        windows=tuple(
            WindowState(
                jnp.zeros((len(g.rows), g.size), dt),
                jnp.zeros((len(g.rows),), jnp.int32),
                jnp.zeros((len(g.rows),), jnp.int32),
            )
            for g in plan.windows
        ),
        hists=tuple(_count.zeros((len(g.rows), g.bins + 2)) for g in plan.hists),
    )


def _weight_dtype(dt: jnp.dtype) -> jnp.dtype:
    # Counts and weights need float32's range even for a float16/bfloat16 state.
    return jnp.dtype(jnp.float64) if dt == jnp.float64 else jnp.dtype(jnp.float32)


def _gathered(x: jax.Array) -> jax.Array:
    """`x` unsharded, where it is sharded over explicit mesh axes (a no-op otherwise).

    Order-dependent statistics (EMA, windows, histograms) scan the env axis in order;
    under explicit sharding JAX asks for that axis to be whole first.
    """
    spec = getattr(jax.typeof(x).sharding, "spec", None)
    if spec is None or all(p is None for p in spec):
        return x
    return jax.sharding.reshard(x, jax.sharding.PartitionSpec())


def _take(rows: tuple[int, ...], x: jax.Array) -> jax.Array:
    if rows == tuple(range(x.shape[0])):
        return x
    # Static row slices, not a gather: keeps the env axis' sharding unambiguous.
    return jnp.stack([x[i] for i in rows])


def add(plan: StreamPlan, s: StreamState, values: jax.Array, mask: jax.Array) -> StreamState:
    """Feeds `values[R, B]` where `mask[R, B]`, column order being arrival order."""
    dt = plan.dtype
    wt = _weight_dtype(dt)
    has = ~_count.is_zero(s.count)
    k = jnp.sum(mask, axis=1, dtype=jnp.int32)
    bsum = jnp.sum(jnp.where(mask, values, 0), axis=1)
    bmin = jnp.min(jnp.where(mask, values, jnp.inf), axis=1)
    bmax = jnp.max(jnp.where(mask, values, -jnp.inf), axis=1)
    # Shifted moments: deviations from the running mean (or, for the first batch, the
    # batch's plain mean) keep sums of squares small, so float32 stays accurate for data
    # far from zero (a second pass over the batch, but exact for constant data).
    shift = jnp.where(has, s.mean, bsum / jnp.maximum(k, 1).astype(dt))
    d = jnp.where(mask, values - shift[:, None], jnp.zeros_like(values))
    s1 = jnp.sum(d, axis=1)
    s2 = jnp.sum(d * d, axis=1)

    kf = k.astype(wt)
    na = _count.as_float(s.count, wt)
    mb = s1 / jnp.maximum(kf, 1).astype(dt)
    m2b = jnp.maximum(s2 - s1 * mb, 0)
    n = na + kf
    frac = jnp.where(n > 0, kf / jnp.maximum(n, 1), 0)
    # With history, shift == s.mean and mb is the Chan delta; without, the new mean is
    # shift + mb (frac == 1) and the old mean carries no weight (na == 0).
    mean = shift + mb * frac.astype(dt)
    m2, m2_c = kahan_add(s.m2, s.m2_c, m2b + mb * mb * (na * frac).astype(dt))
    total, total_c = kahan_add(s.sum, s.sum_c, bsum)
    vmin = jnp.minimum(s.min, bmin)
    vmax = jnp.maximum(s.max, bmax)

    if plan.ema_rows or plan.windows or plan.hists:
        values, mask = _gathered(values), _gathered(mask)
    # One arrival rank (a cumsum over envs, the costliest op here) shared by every row
    # that needs one: EMA and window rows.
    ranked = plan.ranked_rows
    rank = jnp.cumsum(_take(ranked, mask), axis=1, dtype=jnp.int32) - 1 if ranked else None
    at = {row: i for i, row in enumerate(ranked)}
    ema, ema_w = s.ema, s.ema_w
    if plan.ema_rows:
        sub = tuple(at[r] for r in plan.ema_rows)
        ema, ema_w = _ema_add(plan, s, values, mask, _take(sub, rank), _take(plan.ema_rows, k))
    windows = tuple(
        _window_add(
            g,
            w,
            _take(g.rows, values),
            _take(g.rows, mask),
            _take(tuple(at[r] for r in g.rows), rank),
            _take(g.rows, k),
        )
        for g, w in zip(plan.windows, s.windows)
    )
    hists = tuple(
        _hist_add(g, h, _take(g.rows, values), _take(g.rows, mask), dt)
        for g, h in zip(plan.hists, s.hists)
    )
    return s._replace(
        count=_count.add(s.count, k),
        mean=mean,
        m2=m2,
        m2_c=m2_c,
        sum=total,
        sum_c=total_c,
        min=vmin,
        max=vmax,
        ema=ema,
        ema_w=ema_w,
        windows=windows,
        hists=hists,
    )


def _ema_add(plan: StreamPlan, s: StreamState, values, mask, r, k):
    # Sequential EMA over the k arrivals in closed form: value with rank r gets weight
    # c(1-c)^(k-1-r); the old EMA gets (1-c)^k. Unseeded, the first arrival seeds it
    # (weight (1-c)^(k-1)) and the old EMA gets none.
    v = _take(plan.ema_rows, values)
    m = _take(plan.ema_rows, mask)
    dt = plan.dtype
    c = jnp.asarray(plan.ema_coeffs, dt)[:, None]
    decay = jnp.power(1 - c, (k[:, None] - 1 - r).astype(dt))
    seeded = (s.ema_w > 0)[:, None]
    w = jnp.where(seeded | (r > 0), c * decay, decay)
    new = jnp.sum(jnp.where(m, w * v, 0), axis=1)
    keep = jnp.power(1 - c[:, 0], k.astype(dt))
    ema = jnp.where(seeded[:, 0], keep * s.ema, 0) + new
    ema = jnp.where(k > 0, ema, s.ema)
    ema_w = jnp.where((s.ema_w == 0) & (k > 0), jnp.ones_like(s.ema_w), s.ema_w)
    return ema, ema_w


def _window_add(g: WindowGroup, w: WindowState, values, mask, r, k) -> WindowState:
    # Only the last `size` arrivals survive; they go to consecutive ring slots in order.
    n = g.size
    skip = jnp.maximum(k - n, 0)[:, None]
    keep = mask & (r >= skip)
    slot = jnp.where(keep, (w.pos[:, None] + r - skip) % n, n)  # n = out of bounds: dropped
    rows = jnp.broadcast_to(jnp.arange(values.shape[0], dtype=jnp.int32)[:, None], slot.shape)
    buf = w.buf.at[rows, slot].set(values, mode="drop")
    stored = jnp.minimum(k, n)
    return WindowState(buf, (w.pos + stored) % n, jnp.minimum(w.filled + stored, n))


def slot_counts_scatter(slot: jax.Array, nslots: int) -> jax.Array:
    """Per row, how many entries of `slot[R, B]` equal each of 0..nslots-1 (others ignored)."""
    rows = jnp.broadcast_to(jnp.arange(slot.shape[0], dtype=jnp.int32)[:, None], slot.shape)
    zeros = jnp.zeros((slot.shape[0], nslots), jnp.int32)
    return zeros.at[rows, slot].add(1, mode="drop")


def slot_counts_compare(slot: jax.Array, nslots: int) -> jax.Array:
    """Same as `slot_counts_scatter`, as one compare-and-sum reduction."""
    bins = jnp.arange(nslots, dtype=jnp.int32)[None, :, None]
    return jnp.sum(slot[:, None, :] == bins, axis=2, dtype=jnp.int32)


def _hist_add(g: HistGroup, h: Count, values, mask, dt) -> Count:
    lo = jnp.asarray(g.lo, dt)[:, None]
    hi = jnp.asarray(g.hi, dt)[:, None]
    t = jnp.floor((values - lo) / (hi - lo) * g.bins)
    inner = jnp.clip(jnp.nan_to_num(t), 0, g.bins - 1).astype(jnp.int32) + 1
    slot = jnp.where(values < lo, 0, jnp.where(values > hi, g.bins + 1, inner))
    slot = jnp.where(mask & ~jnp.isnan(values), slot, g.bins + 2)  # matches no bin
    # On accelerators, compare-and-count is one fused reduction where a scatter-add is a
    # zero fill plus an atomic scatter kernel; on CPU the scatter is ~3x cheaper.
    inc = jax.lax.platform_dependent(
        slot,
        cpu=lambda x: slot_counts_scatter(x, g.bins + 2),
        default=lambda x: slot_counts_compare(x, g.bins + 2),
    )
    return _count.add(h, inc)


def add_nonfinite(s: StreamState, n: jax.Array) -> StreamState:
    return s._replace(nonfinite=_count.add(s.nonfinite, n))


def reset_period(plan: StreamPlan, s: StreamState) -> StreamState:
    """Clears the period statistics; EMA and windows carry on."""
    fresh = init(plan)
    return fresh._replace(ema=s.ema, ema_w=s.ema_w, windows=s.windows)


def _ordered(g: WindowGroup, w: WindowState) -> tuple[jax.Array, jax.Array]:
    """Window contents right-aligned in arrival order (oldest first) and their validity."""
    j = jnp.arange(g.size, dtype=jnp.int32)[None, :]
    slot = (w.pos[:, None] + j) % g.size
    vals = jnp.take_along_axis(w.buf, slot, axis=1)
    return vals, j >= (g.size - w.filled)[:, None]


def merge(plan: StreamPlan, a: StreamState, b: StreamState) -> StreamState:
    """Combines streams of disjoint workers; `b`'s values count as the newer ones."""
    dt = plan.dtype
    wt = _weight_dtype(dt)
    na, nb = _count.as_float(a.count, wt), _count.as_float(b.count, wt)
    n = na + nb
    frac = jnp.where(n > 0, nb / jnp.maximum(n, 1), 0)
    both = (na > 0) & (nb > 0)
    delta = jnp.where(both, b.mean - a.mean, 0)
    # An empty side's mean carries no weight.
    mean = jnp.where(both, a.mean + delta * frac.astype(dt), jnp.where(na > 0, a.mean, b.mean))
    m2, m2_c = kahan_add(a.m2, a.m2_c, b.m2 + delta * delta * (na * frac).astype(dt))
    m2, m2_c = kahan_add(m2, m2_c, -b.m2_c)
    total, total_c = kahan_add(a.sum, a.sum_c, b.sum)
    total, total_c = kahan_add(total, total_c, -b.sum_c)
    wsum = a.ema_w + b.ema_w
    ema = jnp.where(
        wsum > 0, (a.ema_w * a.ema + b.ema_w * b.ema) / jnp.maximum(wsum, 1), jnp.zeros_like(a.ema)
    )
    windows = []
    for g, wa, wb in zip(plan.windows, a.windows, b.windows):
        va, _ = _ordered(g, wa)
        vb, _ = _ordered(g, wb)
        # Newest `size` of (a's values, then b's): b right-aligned, a's newest just before.
        both = jnp.concatenate([va, vb], axis=1)
        j = jnp.arange(g.size, dtype=jnp.int32)[None, :]
        src = jnp.where(j >= g.size - wb.filled[:, None], g.size + j, j + wb.filled[:, None])
        buf = jnp.take_along_axis(both, src, axis=1)
        filled = jnp.minimum(wa.filled + wb.filled, g.size)
        windows.append(WindowState(buf, jnp.zeros_like(wa.pos), filled))
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
        ema_w=wsum,
        windows=tuple(windows),
        hists=tuple(_count.merge(x, y) for x, y in zip(a.hists, b.hists)),
    )


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
    for j, i in enumerate(plan.ema_rows):
        out[i]["ema"] = jnp.where(s.ema_w[j] > 0, s.ema[j], jnp.nan)
    for g, w in zip(plan.windows, s.windows):
        vals, valid = _ordered(g, w)
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
    return out
