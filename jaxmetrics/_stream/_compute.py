"""The report statistics of a stream, per row, as `_statistics` names them."""

import jax
import jax.numpy as jnp

from .. import _count, _sketch, _statistics
from .._count import Count
from ._state import StreamPlan, StreamState, ordered, take_rows, weight_dtype, window_ring


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
    n = _count.as_float(s.count, weight_dtype(dt))
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
        w = window_ring(g, w)
        vals, _, valid = ordered(w, take_rows(g.rows, s.steps), dt)
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


def count_overflow(row: dict[str, jax.Array | Count]) -> dict[str, jax.Array | Count]:
    """`row` (one row of `compute`) with the statistics that overflowed the dtype added to
    its `nonfinite` count (which statistics can, and how, is the registry's `overflow`).
    Such a statistic is not written, so the count is what makes the loss visible (warned
    about or raised at flush)."""
    has = ~_count.is_zero(row["count"])
    bad = []
    for name, v in row.items():
        kind = _statistics.get(name).overflow
        if kind == "period":
            bad.append(has & ~jnp.isfinite(v))
        elif kind == "inf":
            bad.append(jnp.isinf(v))
    n = jnp.sum(jnp.stack(bad), dtype=jnp.uint32)
    return {**row, "nonfinite": _count.merge(row["nonfinite"], Count(jnp.uint32(0), n))}
