"""Merging the streams of disjoint workers (env shards, separate states) in arrival order."""

import jax
import jax.numpy as jnp
from jax.typing import DTypeLike

from .. import _count
from .._numerics import kahan_add, log2_keep
from .._sharding import gathered
from ._fold import ema_weights
from ._state import (
    INT32_MAX,
    MAX_EMA_HISTORY,
    MIN_MERGED_EMA,
    UINT32_MAX,
    Ring,
    StreamPlan,
    StreamState,
    init,
    ordered,
    packed,
    ring_words,
    rotated,
    take_rows,
    weight_dtype,
    widened_ring,
    window_ring,
)
from ._update import period_mean


def _union(
    wa: Ring, sa: jax.Array, wb: Ring, sb: jax.Array, dt: DTypeLike
) -> tuple[jax.Array, jax.Array, jax.Array]:
    """Both rings' values in arrival order, oldest first: by age, then `a` before `b`
    (within a step the lower worker arrives first), invalid entries in front."""
    parts = [ordered(wa, sa, dt), ordered(wb, sb, dt)]
    vals, age, valid = (jnp.concatenate([p[i] for p in parts], axis=1) for i in range(3))
    key = jnp.where(valid, UINT32_MAX - age, jnp.zeros_like(age))
    order = jnp.argsort(key, axis=1, stable=True)
    take = lambda x: jnp.take_along_axis(x, order, axis=1)  # noqa: E731
    return take(vals), take(age), take(valid)


def _newest(vals: jax.Array, age: jax.Array, valid: jax.Array, size: int, steps: jax.Array) -> Ring:
    """A ring holding the newest `size` of `_union`'s entries, stamped relative to `steps`
    (per ring row)."""
    keep = slice(vals.shape[1] - size, vals.shape[1])
    return Ring(
        packed(vals[:, keep], steps[:, None] - age[:, keep]),
        jnp.zeros(vals.shape[:1], jnp.int32),
        jnp.sum(valid[:, keep], axis=1, dtype=jnp.int32),
    )


def check_mergeable(plan: StreamPlan) -> None:
    """Refuses, when a merge is traced, the EMA coefficients it cannot merge exactly (below
    `MIN_MERGED_EMA`): the part older than the kept history would be an estimate weighing
    up to (1-c)^65536 (52% for c = 1e-5)."""
    small = [
        (plan.rows[plan.ema_rows[j]].name, g.coeff)
        for g in plan.ema_groups
        if g.coeff < MIN_MERGED_EMA
        for j in g.rows
    ]
    if small:
        name, c = small[0]
        raise ValueError(
            f"metric {name!r}: ema({c:g}) cannot be merged across devices or workers (a "
            "sharded state, Brax's pmap over several devices, Metrics.merge): each keeps its "
            f"newest {MAX_EMA_HISTORY} values, and below a coefficient of "
            f"{MIN_MERGED_EMA:.4g} the older EMA they leave out weighs more than 2^-32 "
            f"((1-c)^{MAX_EMA_HISTORY} = {(1 - c) ** MAX_EMA_HISTORY:.3g}). Use an EMA "
            f"coefficient of at least {MIN_MERGED_EMA:.4g}, or keep this EMA on one device."
        )


def _merge_ema(
    plan: StreamPlan, a: StreamState, b: StreamState
) -> tuple[jax.Array, jax.Array, jax.Array, jax.Array, tuple[Ring, ...]]:
    """EMA of both workers' values in arrival order (see `EmaGroup`), relative to `a`'s
    offset (`b`'s where `a` has no value)."""
    check_mergeable(plan)
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
    n = a.ema_n + jnp.minimum(b.ema_n, INT32_MAX - a.ema_n)
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
        sa, sb = take_rows(own, a.steps), take_rows(own, b.steps)
        vals, age, valid = _union(ra, sa, rb, sb, dt)
        # Exact when the rings hold every value either worker has seen.
        exact = (a.ema_n[rows] <= size) & (b.ema_n[rows] <= size)
        total = jnp.sum(valid, axis=1, dtype=jnp.int32)
        folded = jnp.where(exact, total, jnp.minimum(total, size))[:, None]
        p = vals.shape[1] - 1 - jnp.arange(vals.shape[1], dtype=jnp.int32)[None, :]
        c = jnp.asarray(g.coeff, dt)
        w = ema_weights(c, p, exact[:, None], folded, dt)
        dev = vals - off[rows][:, None]
        new = jnp.sum(jnp.where(valid & (p < folded), w * dev, 0), axis=1)
        decay = jnp.where(folded == 0, 1.0, jnp.exp2(folded.astype(dt) * log2_keep(c)))[:, 0]
        keep = jnp.where(exact, 0, decay * tail[rows])
        parts.append((rows, jnp.where(held, keep + new, tail[rows])))
        sequential = sequential.at[rows].set(held)
        rings.append(_newest(vals, age, valid, size, sa))
    ema = tail
    for rows, v in parts:
        ema = ema.at[rows].set(v)
    ema = jnp.where(a.ema_n == 0, b.ema, jnp.where(b.ema_n == 0, a.ema, ema))
    wsum = jnp.where(sequential, jnp.minimum(wsum, 1), wsum)
    return ema, off, wsum, n, tuple(rings)


def merge(plan: StreamPlan, a: StreamState, b: StreamState) -> StreamState:
    """Combines streams of disjoint workers that ran side by side: values of `b` arrive
    after `a`'s of the same step. Period statistics are exact (Chan for mean/std);
    windows and EMA follow arrival order (see the module docstring and `EmaGroup`)."""
    dt = plan.dtype
    wt = weight_dtype(dt)
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
    mean = period_mean(total, total_c, n, chan)
    ema, ema_off, ema_w, ema_n, ema_rings = _merge_ema(plan, a, b)
    windows = tuple(
        widened_ring(
            g,
            _newest(
                *_union(
                    window_ring(g, wa),
                    take_rows(g.rows, a.steps),
                    window_ring(g, wb),
                    take_rows(g.rows, b.steps),
                    dt,
                ),
                g.size,
                take_rows(g.rows, a.steps),
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
    if num == 0:
        history = any(r.size > 0 for r in shards.ema_rings)
        return init(plan, ema_history=history)
    first = jax.tree.map(lambda x: x[0], shards)
    if num == 1:
        return first
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
        r = rotated(r)
        pad = [(0, 0)] * r.data.ndim
        pad[-2] = (extra, 0)
        return r._replace(data=jnp.pad(r.data, pad))

    return s._replace(ema_rings=tuple(widen(r) for r in s.ema_rings))


def with_ema_history(plan: StreamPlan, s: StreamState, widths: tuple[int, ...]) -> StreamState:
    """One worker's stream `s` with its EMA rings `widths` wide (per EMA group: 0, or the
    group's `history`), as a state of another layout keeps them.

    A ring is dropped where the layout keeps none: the EMA itself is whole without it.
    Where `s` keeps none (an unsharded state) and the layout does, the EMA so far becomes
    the ring's one value, stamped on the last arrival step, and the row counts one value
    seen: merged with other workers, the later values then fold onto it in arrival order
    (an EMA is seeded by its first value), as exactly as for a state made with history.
    """
    rings, ema_n = list(s.ema_rings), s.ema_n
    for i, (g, r, width) in enumerate(zip(plan.ema_groups, s.ema_rings, widths)):
        if r.size == width:
            continue
        own = plan.stream_rows(g)
        zeros = jnp.zeros((len(own),), jnp.int32)
        if width == 0:
            rings[i] = Ring(r.data[:, :0], zeros, zeros)
            continue
        assert r.size == 0, "a ring is empty or as wide as its group's history"
        rows = jnp.asarray(own, jnp.int32)
        seen = s.ema_n[rows] > 0
        stamp = take_rows(own, s.steps) - jnp.uint32(1)
        data = jnp.zeros((len(own), width, ring_words(plan.dtype) + 1), jnp.uint32)
        data = data.at[:, width - 1].set(packed((s.ema_off + s.ema)[rows], stamp))
        rings[i] = Ring(data, zeros, seen.astype(jnp.int32))
        ema_n = ema_n.at[rows].set(seen.astype(jnp.int32))
    return s._replace(ema_rings=tuple(rings), ema_n=ema_n)


def spread(plan: StreamPlan, s: StreamState, shards: int) -> StreamState:
    """`s` as the first of `shards` per-shard streams (stacked on a leading axis), the
    others empty at its arrival step: `combine` gives `s` back (a merge with an empty
    stream is the identity), and values that arrive later, on any shard, come after all
    of `s`'s."""
    history = any(r.size > 0 for r in s.ema_rings)
    empty = init(plan, ema_history=history)._replace(steps=s.steps)
    return jax.tree.map(
        lambda a, b: jnp.concatenate([a[None], jnp.broadcast_to(b, (shards - 1, *b.shape))]),
        s,
        empty,
    )
