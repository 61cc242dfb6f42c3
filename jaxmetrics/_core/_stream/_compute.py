"""The report statistics of a stream, as columns over its rows, as `_statistics` names them."""

import jax
import jax.numpy as jnp
import numpy as np
from jax.typing import DTypeLike

from .. import _count, _sketch, _spec, _statistics
from .._count import Count
from ._state import (
    Ring,
    StreamPlan,
    StreamState,
    WindowGroup,
    ordered,
    weight_dtype,
)


def _percentiles(
    sorted_vals: jax.Array, filled: jax.Array, ps: tuple[float, ...], dt: DTypeLike
) -> list[jax.Array]:
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


Column = tuple[str, tuple[int, ...], jax.Array | Count]
"""A statistic over the rows that have it: `(name, rows, values)`, `values[j]` (its first
axis) being row `rows[j]`'s."""


def compute(plan: StreamPlan, s: StreamState) -> list[Column]:
    """Every statistic of every row, as columns (a row's statistics are those of the
    columns that list it); empty-period values are NaN.

    A row whose metric leaves non-finite values out (any policy but "propagate") also
    counts in its `nonfinite` the reported statistics that overflowed the dtype (which
    statistics can overflow, and how, the registry's `overflow` says). Such a statistic is
    not written, so the count is what makes the loss visible (warned about or raised at
    flush).
    """
    dt = plan.dtype
    every = tuple(range(len(plan.rows)))
    n = _count.as_float(s.count, weight_dtype(dt))
    empty = n == 0
    var = jnp.maximum(s.m2 - s.m2_c, 0).astype(n.dtype) / jnp.maximum(n, 1)
    # Each statistic is one column over the rows that have it, whatever their number:
    # per-row scalar ops were hundreds of kernels, and per-row outputs (a grouped metric
    # has a row per group) made compile time grow faster than the rows.
    columns: list[Column] = [
        ("mean", every, jnp.where(empty, jnp.nan, s.mean)),
        ("std", every, jnp.where(empty, jnp.nan, jnp.sqrt(var).astype(dt))),
        ("min", every, jnp.where(empty, jnp.nan, s.min)),
        ("max", every, jnp.where(empty, jnp.nan, s.max)),
        ("sum", every, s.sum - s.sum_c),
    ]
    if plan.ema_rows:
        ema = jnp.where(s.ema_w > 0, s.ema_off + s.ema, jnp.nan)
        columns.append(("ema", plan.ema_rows, _gathered(plan.ema_rows, ema)))
    for g, w in zip(plan.windows, s.windows):
        ring = w._replace(pos=_gathered(g.rows, w.pos), filled=_gathered(g.rows, w.filled))
        columns += _window_columns(plan, g, ring, _gathered(g.rows, s.steps))
    for g, h in zip(plan.hists, s.hists):
        columns.append(("histogram", g.rows, h))
    for g, c in zip(plan.sketches, s.sketches):
        levels = tuple(plan.rows[i].stats.quantiles.levels for i in g.rows)  # type: ignore[union-attr]
        values = _sketch.quantiles(g, c, levels, dt)
        for p in sorted({p for ls in levels for p in ls}):
            at = [(j, ls.index(p)) for j, ls in enumerate(levels) if p in ls]
            rows = tuple(g.rows[j] for j, _ in at)
            column = values[np.array([j for j, _ in at]), np.array([k for _, k in at])]
            columns.append((_statistics.quantile(p), rows, column))
    overflows = Count(jnp.zeros_like(s.count.lo), _overflows(plan, s, columns))
    nonfinite = _count.merge(s.nonfinite, overflows)
    return [("count", every, s.count), ("nonfinite", every, nonfinite), *columns]


def _gathered(rows: tuple[int, ...], x: jax.Array) -> jax.Array:
    """Rows `rows` of `x` by one gather of static indices. (`take_rows` slices each row,
    which keeps an env axis' sharding unambiguous in a step; a report's arrays have no
    env axis, and a slice per row is an op per row.)"""
    if rows == tuple(range(x.shape[0])):
        return x
    return x[np.asarray(rows, np.int32)]


def _window_columns(plan: StreamPlan, g: WindowGroup, w: Ring, steps: jax.Array) -> list[Column]:
    """A window group's statistics as `compute`'s columns, from its ring `w` (its rows
    only) and their arrival steps `steps`.

    Only `window_values` needs the arrival order; the other statistics are taken over the
    slots as they lie, so that a program that reads a window's mean every step
    (`Metrics.read`, a curriculum) has no rotation of the ring to pay for, and the mean
    is one reduction (`_compensated_sum`), not a mean and a correction of it after.
    """
    dt = plan.dtype
    n = w.size
    filled = w.filled
    slot = jnp.arange(n, dtype=jnp.int32)[None, :]
    # Slot s holds arrival order (s - pos) mod n (`Ring`), valid in the newest `filled`.
    valid = (slot - w.pos[:, None]) % n >= (n - filled)[:, None]
    vals = w.values(dt)
    cnt = jnp.maximum(filled, 1).astype(dt)
    wmean = _compensated_sum(jnp.where(valid, vals, 0)) / cnt
    dev = jnp.where(valid, vals - wmean[:, None], 0)
    # The corrected two-pass: the deviations' own mean is the mean's rounding error,
    # whose square the variance takes off.
    off = jnp.sum(dev, axis=1) / cnt
    wstd = jnp.sqrt(jnp.maximum(jnp.sum(dev * dev, axis=1) / cnt - off * off, 0))
    wmin = jnp.min(jnp.where(valid, vals, jnp.inf), axis=1)
    wmax = jnp.max(jnp.where(valid, vals, -jnp.inf), axis=1)
    has = filled > 0
    in_order, _, in_order_valid = ordered(w, steps, dt)
    columns: list[Column] = [
        ("window_mean", g.rows, jnp.where(has, wmean, jnp.nan)),
        ("window_std", g.rows, jnp.where(has, wstd, jnp.nan)),
        ("window_min", g.rows, jnp.where(has, wmin, jnp.nan)),
        ("window_max", g.rows, jnp.where(has, wmax, jnp.nan)),
        ("window_values", g.rows, jnp.where(in_order_valid, in_order, jnp.nan)),
    ]
    wanted = [plan.rows[i].stats.window.percentiles for i in g.rows]  # type: ignore[union-attr]
    uniq = tuple(sorted({p for ps in wanted for p in ps}))
    if uniq:
        has_nan = jnp.any(valid & jnp.isnan(vals), axis=1)
        srt = jnp.sort(jnp.where(valid, vals, jnp.inf), axis=1)
        for p, v in zip(uniq, _percentiles(srt, filled, uniq, dt)):
            at = tuple(j for j, ps in enumerate(wanted) if p in ps)
            v = jnp.where(has_nan, jnp.nan, v)
            rows = tuple(g.rows[j] for j in at)
            columns.append((_statistics.percentile(p), rows, _gathered(at, v)))
    return columns


def _compensated_sum(x: jax.Array) -> jax.Array:
    """The sums of `x[R, n]`'s rows, close to the exact sums rounded once (unless they
    overflow): one reduction carrying each partial sum's rounding error beside it (Knuth's
    TwoSum). Near 1e6 a float32 plain sum of a window of 100 put its mean up to 0.18 off,
    this up to 0.07 (300 random windows); 1e30 + 1 - 1e30 sums to 1. A non-finite sum is
    the plain sum's (an inf among finite values stays inf; its error terms, inf - inf,
    are NaN)."""

    def add(a: tuple[jax.Array, jax.Array], b: tuple[jax.Array, jax.Array]):
        s = a[0] + b[0]
        bb = s - a[0]
        return s, a[1] + b[1] + ((a[0] - (s - bb)) + (b[0] - bb))

    zero = jnp.zeros((), x.dtype)
    s, err = jax.lax.reduce((x, jnp.zeros_like(x)), (zero, zero), add, (1,))
    return jnp.where(jnp.isfinite(s), s + err, s)


def _overflows(plan: StreamPlan, s: StreamState, columns: list[Column]) -> jax.Array:
    """`[R]` uint32: per row, its reported statistics among `columns` that overflowed the
    dtype, 0 for the rows of metrics that propagate non-finite values. A statistic the
    metric does not report (a row always has a std and a sum) is no loss."""
    r = len(plan.rows)
    every = tuple(range(r))
    has = ~_count.is_zero(s.count)
    reported = [set(_spec.reported(spec.stats)) for spec in plan.rows]
    bad = jnp.zeros((r,), jnp.uint32)
    for name, rows, values in columns:
        kind = _statistics.get(name).overflow
        if kind is None:
            continue
        assert not isinstance(values, Count)  # statistics that overflow are floats
        flags = jnp.isinf(values) if kind == "inf" else _gathered(rows, has) & ~jnp.isfinite(values)
        flags = flags & np.array([name in reported[i] for i in rows])
        if rows != every:
            # Spread over the rows (0 where a row lacks the statistic) by a static gather;
            # a column of every row is spread already.
            at = np.full(r, len(rows))
            at[list(rows)] = np.arange(len(rows))
            flags = jnp.concatenate([flags, jnp.zeros((1,), bool)])[at]
        bad = bad + flags.astype(jnp.uint32)
    counted = np.array([spec.nonfinite != "propagate" for spec in plan.rows])
    return jnp.where(counted, bad, jnp.uint32(0))
