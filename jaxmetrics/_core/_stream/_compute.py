"""The report statistics of a stream, per row, as `_statistics` names them."""

import operator

import jax
import jax.numpy as jnp
import numpy as np

from .. import _count, _sketch, _spec, _statistics
from .._count import Count
from ._state import (
    Ring,
    StreamPlan,
    StreamState,
    WindowGroup,
    ordered,
    take_rows,
    weight_dtype,
    window_ring,
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
    """Per row, a dict of every statistic it has; empty-period values are NaN.

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
    # Each statistic as one column over the rows that have it (`rows[j]` holds
    # `values[j]`), so that the report and its overflow count are a few vector ops
    # whatever the number of rows: per-row scalar ops were hundreds of kernels.
    columns: list[tuple[str, tuple[int, ...], jax.Array | Count]] = [
        ("mean", every, jnp.where(empty, jnp.nan, s.mean)),
        ("std", every, jnp.where(empty, jnp.nan, jnp.sqrt(var).astype(dt))),
        ("min", every, jnp.where(empty, jnp.nan, s.min)),
        ("max", every, jnp.where(empty, jnp.nan, s.max)),
        ("sum", every, s.sum - s.sum_c),
    ]
    if plan.ema_rows:
        ema = jnp.where(s.ema_w > 0, s.ema_off + s.ema, jnp.nan)
        columns.append(("ema", plan.ema_rows, take_rows(plan.ema_rows, ema)))
    for g, w in zip(plan.windows, s.windows):
        columns += _window_columns(plan, g, window_ring(g, w), take_rows(g.rows, s.steps))
    for g, h in zip(plan.hists, s.hists):
        columns.append(("histogram", g.rows, h))
    for g, c in zip(plan.sketches, s.sketches):
        levels = tuple(plan.rows[i].stats.quantiles.levels for i in g.rows)  # type: ignore[union-attr]
        for i, ls, vals in zip(g.rows, levels, _sketch.quantiles(g, c, levels, dt)):
            columns += [(_statistics.quantile(p), (i,), vals[j][None]) for j, p in enumerate(ls)]
    overflows = Count(jnp.zeros_like(s.count.lo), _overflows(plan, s, columns))
    nonfinite = _count.merge(s.nonfinite, overflows)
    out: list[dict[str, jax.Array | Count]] = [{} for _ in every]
    for i in every:
        out[i]["count"] = Count(s.count.hi[i], s.count.lo[i])
        out[i]["nonfinite"] = Count(nonfinite.hi[i], nonfinite.lo[i])
    for name, rows, values in columns:
        for j, i in enumerate(rows):
            out[i][name] = jax.tree.map(operator.itemgetter(j), values)
    return out


def _window_columns(
    plan: StreamPlan, g: WindowGroup, w: Ring, steps: jax.Array
) -> list[tuple[str, tuple[int, ...], jax.Array]]:
    """A window group's statistics as `compute`'s columns, from its ring `w` (its rows
    only) and their arrival steps `steps`."""
    dt = plan.dtype
    vals, _, valid = ordered(w, steps, dt)
    filled = w.filled
    cnt = jnp.maximum(filled, 1).astype(dt)
    wmean = jnp.sum(jnp.where(valid, vals, 0), axis=1) / cnt
    dev = jnp.where(valid, vals - wmean[:, None], 0)
    # The corrected two-pass: deviations from a rounded mean (a few hundredths off
    # for float32 values near 1e6) add its error squared to the variance; their own
    # mean is that error, which the mean gets back and the variance takes off.
    off = jnp.sum(dev, axis=1) / cnt
    wmean = wmean + off
    wstd = jnp.sqrt(jnp.maximum(jnp.sum(dev * dev, axis=1) / cnt - off * off, 0))
    wmin = jnp.min(jnp.where(valid, vals, jnp.inf), axis=1)
    wmax = jnp.max(jnp.where(valid, vals, -jnp.inf), axis=1)
    has = filled > 0
    columns = [
        ("window_mean", g.rows, jnp.where(has, wmean, jnp.nan)),
        ("window_std", g.rows, jnp.where(has, wstd, jnp.nan)),
        ("window_min", g.rows, jnp.where(has, wmin, jnp.nan)),
        ("window_max", g.rows, jnp.where(has, wmax, jnp.nan)),
        ("window_values", g.rows, jnp.where(valid, vals, jnp.nan)),
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
            columns.append((_statistics.percentile(p), rows, take_rows(at, v)))
    return columns


def _overflows(plan: StreamPlan, s: StreamState, columns) -> jax.Array:
    """`[R]` uint32: per row, its reported statistics among `columns` that overflowed the
    dtype, 0 for the rows of metrics that propagate non-finite values. A statistic the
    metric does not report (a row always has a std and a sum) is no loss."""
    r = len(plan.rows)
    has = ~_count.is_zero(s.count)
    reported = [set(_spec.reported(spec.stats)) for spec in plan.rows]
    bad = jnp.zeros((r,), jnp.uint32)
    for name, rows, values in columns:
        kind = _statistics.get(name).overflow
        if kind is None:
            continue
        flags = jnp.isinf(values) if kind == "inf" else take_rows(rows, has) & ~jnp.isfinite(values)
        flags = flags & np.array([name in reported[i] for i in rows])
        # Spread over the rows (0 where a row lacks the statistic) by a static gather.
        at = np.full(r, len(rows))
        at[list(rows)] = np.arange(len(rows))
        bad = bad + jnp.concatenate([flags, jnp.zeros((1,), bool)])[at].astype(jnp.uint32)
    counted = np.array([spec.nonfinite != "propagate" for spec in plan.rows])
    return jnp.where(counted, bad, jnp.uint32(0))
