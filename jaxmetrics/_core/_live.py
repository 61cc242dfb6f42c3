"""`Metrics.read`: one live statistic of a state, in-graph, as `compute` reports it.

A curriculum or an adaptive setting reads a statistic every step (a group's windowed
success rate, an EMA of returns) to decide what the next episodes look like. `read` takes
the value from `compute`'s own column, so it is by construction the number the report
writes at that step. It costs what that one statistic costs, not a whole report: under
`jit` XLA drops the columns nothing uses (the state of one shard is read where it lies;
a state of several shards is merged first, as `compute` merges it).
"""

from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np

from . import _count, _stream
from ._count import Count
from ._metrics_state import MetricsState
from ._report import Report
from ._rows import SpecRows

WINDOW_COUNT = "window_count"
"""A statistic `read` has beyond `compute`'s: the number of values in a metric's window
(`window(n)` holds the newest n; fewer until n have arrived)."""


def _stat_tag(rows: SpecRows, metric: str, statistic: str, asked: str | None = None) -> str:
    """The report tag of `metric`'s `statistic`, or an error naming what exists (and the
    statistic `asked` for, where it is read from another)."""
    infos = [i for i in rows.tags if i.metric == metric]
    if not infos:
        names = sorted({i.metric for i in rows.tags if i.group != "counter"})
        counters = [i.metric for i in rows.tags if i.group == "counter"]
        raise ValueError(
            f"Metrics.read: no metric {metric!r} in this spec; its metrics are {names} "
            f"(a group's own row is '<metric>/<group>') and its counters {counters}."
        )
    for i in infos:
        if i.stat == statistic:
            return i.tag
    have = [i.stat for i in infos]
    if infos[0].group != "counter" and any(s.startswith("window_") for s in have):
        have.append(WINDOW_COUNT)
    raise ValueError(
        f"Metrics.read: metric {metric!r} has no statistic {asked or statistic!r}; it has {have}. "
        "Ask for it in the term's stats=(...) (e.g. jm.window(100) for window_mean, "
        "jm.ema(0.01) for ema)."
    )


def _group_metrics(rows: SpecRows, metric: str) -> tuple[str, ...]:
    """The per-group rows of `metric` (`<metric>/<group>`), in the group order."""
    names = tuple(
        s.name for s in rows.ep_defined if s.group is not None and s.name == f"{metric}/{s.group}"
    )
    if not names:
        raise ValueError(
            f"Metrics.read(..., by_group=True): metric {metric!r} has no groups; give its "
            "term groups=jm.groups(fn, names) (or the spec Metrics(groups=...)), or read "
            "it with by_group=False."
        )
    return names


def _as_float(values: jax.Array | Count, dtype: jnp.dtype) -> jax.Array:
    return _count.as_float(values, dtype) if isinstance(values, Count) else values


def read(
    rows: SpecRows,
    compute: Callable[[MetricsState], Report],
    state: MetricsState,
    metric: str,
    statistic: str,
    by_group: bool,
) -> jax.Array:
    """`Metrics.read` of the spec `rows`, whose `compute` is given."""
    names = _group_metrics(rows, metric) if by_group else (metric,)
    if statistic == WINDOW_COUNT:
        out = _window_counts(rows, state, names)
        return out if by_group else out[0]
    tags = [_stat_tag(rows, m, statistic) for m in names]
    report = compute(state)
    at = [report.layout.at[t] for t in tags]
    (column,) = {c for c, _ in at}  # one statistic: one column for every row
    values = _as_float(report.columns[column], rows.dtype)
    axis = values.ndim - 1 - report.layout.trailing[column]
    out = jnp.take(values, np.asarray([j for _, j in at], np.int32), axis=axis)
    return out if by_group else jnp.squeeze(out, axis)


def _window_counts(rows: SpecRows, state: MetricsState, names: tuple[str, ...]) -> jax.Array:
    """`[len(names)]`: the values in each metric's window."""
    for m in names:  # a window is asked for by its statistics: window_mean has one
        _stat_tag(rows, m, "window_mean", asked=WINDOW_COUNT)
    info = next(i for i in rows.tags if i.metric == names[0])
    if info.group == "episode":
        plan = rows.ep_plan
        assert plan is not None and state.finished is not None  # an episode metric's
        stream = _stream.combine(plan, state.finished)
    else:
        plan = rows.lg_plan
        assert plan is not None and state.logged is not None  # a logged value's
        stream = state.logged
    index = [next(i for i, s in enumerate(plan.rows) if s.name == m) for m in names]
    filled = []
    for i in index:
        k = next(k for k, g in enumerate(plan.windows) if i in g.rows)
        filled.append(stream.windows[k].filled[i])
    return jnp.stack(filled).astype(rows.dtype)
