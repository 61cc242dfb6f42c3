"""Static configuration: terms, logged values, report statistics. Validated when built.

Nothing here is traced: these objects live in the builder's closure, never in the state.
"""

import dataclasses
import math
from collections.abc import Callable, Mapping, Sequence
from typing import Any

from . import _statistics
from ._reductions import Discounted
from ._statistics import SIMPLE_STATS
from ._validate import is_int, is_number

NONFINITE_POLICIES = ("skip", "propagate", "raise")
DEFAULT_STATS = ("mean", "std", "min", "max", "count")


@dataclasses.dataclass(frozen=True)
class Ema:
    """Exponential moving average `ema = c*x + (1-c)*ema`, seeded by the first value.

    Carried across periods; no bias correction (RLlib's semantics).
    """

    coeff: float = 0.01

    def __post_init__(self):
        c = self.coeff
        if not is_number(c) or not (0.0 < c <= 1.0):
            raise ValueError(
                f"ema coefficient must be a number in (0, 1], got {c!r}. "
                "Use e.g. jaxmetrics.ema(0.01): 0.01 weighs the newest value 1%."
            )


MAX_WINDOW = 2**20
"""The largest `window` size: 8 MiB of state per float32 metric."""


@dataclasses.dataclass(frozen=True)
class Window:
    """Statistics of the last `size` values (mean/std/min/max and exact percentiles).

    Persists across periods. Percentiles use linear interpolation (numpy's default).
    """

    size: int
    percentiles: tuple[float, ...] = ()

    def __post_init__(self):
        n = self.size
        if not is_int(n) or n <= 0:
            raise ValueError(
                f"window size must be a positive int, got {n!r}. Use e.g. jaxmetrics.window(100)."
            )
        if n > MAX_WINDOW:
            raise ValueError(
                f"window size {n} is over {MAX_WINDOW} (2^20): a window keeps its values and "
                "their arrival steps in the state, in every metric and group that has it "
                f"(window({n}) needs {8 * n / 2**20:,.1f} MiB per metric in float32), and each "
                "report sorts them. For statistics over more values use the period "
                "statistics or jaxmetrics.quantiles(...)."
            )
        ps = tuple(self.percentiles)
        for p in ps:
            if not is_number(p) or not _statistics.is_level(p):
                raise ValueError(
                    f"window percentiles must be numbers in [0, 100] with at most "
                    f"{_statistics.LEVEL_DECIMALS} decimals, got {p!r} in {ps!r}."
                )
        ps = tuple(float(p) + 0.0 for p in ps)  # -0.0 is 0.0
        if len(set(ps)) != len(ps):
            raise ValueError(f"window percentiles must be distinct, got {ps!r}.")
        object.__setattr__(self, "size", int(n))
        object.__setattr__(self, "percentiles", ps)


@dataclasses.dataclass(frozen=True)
class Histogram:
    """Counts of values in `bins` equal-width bins over `range` (numpy's edges), per period.

    Values below or above the range are counted as underflow/overflow; the right edge
    belongs to the last bin, as in `numpy.histogram`.
    """

    bins: int
    range: tuple[float, float]

    def __post_init__(self):
        b = self.bins
        if not is_int(b) or b <= 0:
            raise ValueError(f"histogram bins must be a positive int, got {b!r}.")
        r = tuple(self.range)
        if len(r) != 2 or not all(is_number(v) and math.isfinite(v) for v in r):
            raise ValueError(
                f"histogram range must be two finite numbers (lo, hi), got {self.range!r}."
            )
        if not r[0] < r[1]:
            raise ValueError(f"histogram range needs lo < hi, got {r!r}.")
        object.__setattr__(self, "bins", int(b))
        object.__setattr__(self, "range", (float(r[0]), float(r[1])))


@dataclasses.dataclass(frozen=True)
class Quantiles:
    """Quantiles of every value of a period, each within relative `accuracy` of the exact
    one, from a fixed-size mergeable sketch (see `quantiles`)."""

    levels: tuple[float, ...] = (50.0, 90.0, 99.0)
    accuracy: float = 0.01


QUANTILE_MAGNITUDES = (1e-9, 1e9)
"""The magnitudes a quantile sketch represents; values outside (but non-zero) are counted
as under/overflow, and a quantile that falls on them is NaN and counted in `/nonfinite`."""
MIN_ACCURACY = 1e-3
"""The finest quantile accuracy (about 41,500 buckets, 332 KB per metric)."""


def check_quantiles(q: Quantiles, where: str) -> Quantiles:
    """`q` with its levels as floats, or an error naming `where` and the fix."""
    a = q.accuracy
    if not is_number(a) or not (MIN_ACCURACY <= a < 1.0):
        raise ValueError(
            f"{where}: quantiles(accuracy=...) must be a number in [{MIN_ACCURACY:g}, 1), "
            f"got {a!r}. Use e.g. jaxmetrics.quantiles((50, 90, 99), accuracy=0.01): "
            "each quantile within 1% of the exact one."
        )
    try:
        levels = () if isinstance(q.levels, str) else tuple(q.levels)
    except TypeError:
        levels = ()
    if not levels:
        raise ValueError(
            f"{where}: quantiles(levels=...) must be a non-empty sequence of percentiles "
            f"in [0, 100], got {q.levels!r}. Use e.g. jaxmetrics.quantiles((50, 90, 99))."
        )
    for p in levels:
        if not is_number(p) or not _statistics.is_level(p):
            raise ValueError(
                f"{where}: quantile levels must be percentiles in [0, 100] with at most "
                f"{_statistics.LEVEL_DECIMALS} decimals, got {p!r} in {levels!r}."
            )
    floats = tuple(float(p) + 0.0 for p in levels)  # -0.0 is 0.0
    if len(set(floats)) != len(floats):
        raise ValueError(
            f"{where}: quantile levels must be distinct, got {levels!r}; list each once."
        )
    return Quantiles(floats, float(a))


def ema(coeff: float = 0.01) -> Ema:
    """Report statistic: exponential moving average with coefficient `coeff` in (0, 1].

    Examples:
      >>> import jaxmetrics as jm
      >>> jm.ema(0.1)
      Ema(coeff=0.1)
    """
    return Ema(coeff)


def window(size: int, percentiles: Sequence[float] = ()) -> Window:
    """Report statistic: mean/std/min/max (and percentiles) of the last `size` values.

    Examples:
      >>> import jaxmetrics as jm
      >>> jm.window(100, percentiles=(50, 90))
      Window(size=100, percentiles=(50.0, 90.0))
    """
    return Window(size, tuple(percentiles))


def histogram(bins: int, range: tuple[float, float]) -> Histogram:  # noqa: A002
    """Report statistic: a per-period histogram with `bins` bins over `range`.

    Examples:
      >>> import jaxmetrics as jm
      >>> jm.histogram(10, (0.0, 1.0))
      Histogram(bins=10, range=(0.0, 1.0))
    """
    return Histogram(bins, range)


def quantiles(levels: Sequence[float] = (50, 90, 99), accuracy: float = 0.01) -> Quantiles:
    """Report statistic: quantiles of every value of the period (not just a window), each
    within relative `accuracy` of the exact one.

    The period's values are counted in a DDSketch-style sketch of logarithmic buckets
    (fixed size, exact integer counts, merged exactly across shards, hosts and seeds,
    O(1) per value); it resets with the period. `<metric>/q<p>` is the value of rank
    `floor(p/100 * (n-1))` among the period's `n` values (numpy's "lower" method), within
    `accuracy` of it in relative terms, for values of magnitude in (1e-9, 1e9] and 0.
    Levels are percentiles in [0, 100] with at most 4 decimals; `accuracy` is in
    [0.001, 1). Both are checked, naming the metric, when the `Metrics` spec is built.

    Examples:
      >>> import jaxmetrics as jm
      >>> m = jm.Metrics(logged={"loss": jm.Logged(stats=(jm.quantiles((50, 90)),))})
      >>> s = m.log(m.init(0), {"loss": [1.0, 2.0, 3.0, 4.0, 100.0]})
      >>> r = m.to_host(m.compute(s))
      >>> round(r["Train/loss/q50"], 3), round(r["Train/loss/q90"], 3)  # exact: 3 and 4
      (3.022, 3.998)
    """
    return Quantiles(levels, accuracy)  # type: ignore[arg-type]


@dataclasses.dataclass(frozen=True)
class Groups:
    """A grouping of envs: every statistic of a grouped metric is also kept per group.

    `fn(step_input, **params)` returns each env's group index (`[num_envs]`, int or
    bool): 0 for `names[0]`, 1 for `names[1]`, ... An episode belongs to the group its
    env is in on the step the episode ends. An index outside `[0, len(names))` puts the
    episode in the metric's overall statistics only; such episodes are counted in the
    `ungrouped` counter.

    Args:
      fn: the group function, evaluated on every `update`.
      names: the group names, in index order; each becomes a tag component
        (`Episode_Metrics/<metric>/<name>[/<stat>]`).
      params: extra keyword arguments bound to `fn`.

    Examples:
      >>> import jaxmetrics as jm
      >>> terrain = jm.groups(lambda s: s["terrain"], ("flat", "rough"))
      >>> terrain.names
      ('flat', 'rough')
    """

    fn: Callable[..., Any]
    names: Sequence[str]
    params: Mapping[str, Any] = dataclasses.field(default_factory=dict)

    def __post_init__(self):
        if not callable(self.fn):
            raise TypeError(f"groups: fn must be callable, got {self.fn!r}.")
        if not isinstance(self.params, Mapping):
            raise TypeError("groups: params must be a dict of keyword arguments.")
        names = self.names
        if isinstance(names, str) or not isinstance(names, Sequence) or not names:
            raise ValueError(
                f"groups: names must be a non-empty sequence of group names, got {names!r}; "
                'e.g. jaxmetrics.groups(fn, ("flat", "rough")).'
            )
        for n in names:
            check_name(n, "groups")
            if "/" in n:
                raise ValueError(
                    f"groups: group name {n!r} contains '/'; a group is one tag component "
                    f"(<metric>/<group>/<stat>). Use e.g. {n.replace('/', '_')!r}."
                )
            if _is_statistic(n):
                raise ValueError(
                    f"groups: group name {n!r} is also a statistic's name, so "
                    f"'<metric>/{n}' would read as that statistic. Rename the group, "
                    f"e.g. {n + '_group'!r}."
                )
        if len(set(names)) != len(names):
            raise ValueError(f"groups: duplicate group names in {list(names)!r}.")
        object.__setattr__(self, "names", tuple(names))


def _is_statistic(name: str) -> bool:
    try:
        _statistics.get(name)
    except KeyError:
        return False
    return True


def groups(fn: Callable[..., Any], names: Sequence[str], **params: Any) -> Groups:
    """A grouping of envs for `Term(groups=...)` or `Metrics(groups=...)`: `fn` gives
    each env's group index, `names` the groups in index order (see `Groups`).

    Examples:
      >>> import jax.numpy as jnp, jaxmetrics as jm
      >>> metrics = jm.Metrics(
      ...     terms={"reward": jm.Term(lambda s: s["reward"], reduce="sum")},
      ...     groups=jm.groups(lambda s: s["task"], ("walk", "run")),
      ... )
      >>> state = metrics.init(num_envs=3)
      >>> step = {"reward": jnp.array([1.0, 2.0, 3.0]), "task": jnp.array([0, 1, 1])}
      >>> state = metrics.update(state, step, jnp.array([True, True, True]))
      >>> report = metrics.to_host(metrics.compute(state))
      >>> report["Episode_Metrics/reward"], report["Episode_Metrics/reward/run"]
      (2.0, 2.5)
    """
    return Groups(fn, names, params)


Stat = str | Ema | Window | Histogram | Quantiles


@dataclasses.dataclass(frozen=True)
class StatSpec:
    """The validated report statistics of one metric."""

    simple: frozenset[str]
    ema: Ema | None
    window: Window | None
    histogram: Histogram | None
    quantiles: Quantiles | None = None


def parse_stats(stats: Sequence[Stat], where: str) -> StatSpec:
    if isinstance(stats, (str, Ema, Window, Histogram, Quantiles)):
        stats = (stats,)
    simple: set[str] = set()
    found: dict[type, Any] = {}
    for s in stats:
        if isinstance(s, str):
            if s not in SIMPLE_STATS:
                hint = ""
                builder = {"percentile": "window", "quantile": "quantiles"}.get(s, s)
                if builder in ("ema", "window", "histogram", "quantiles"):
                    hint = f" Use jaxmetrics.{builder}(...) for it."
                raise ValueError(
                    f"{where}: unknown report statistic {s!r}; expected one of "
                    f"{SIMPLE_STATS} or jaxmetrics.ema/window/histogram/quantiles(...).{hint}"
                )
            simple.add(s)
        elif isinstance(s, (Ema, Window, Histogram, Quantiles)):
            if type(s) in found:
                raise ValueError(
                    f"{where}: at most one {type(s).__name__.lower()} statistic per metric, "
                    f"got {found[type(s)]!r} and {s!r}. Define a second term for another one."
                )
            found[type(s)] = check_quantiles(s, where) if isinstance(s, Quantiles) else s
        else:
            raise TypeError(
                f"{where}: a report statistic must be a string or jaxmetrics.ema/window/"
                f"histogram/quantiles(...), got {s!r} of type {type(s).__name__}."
            )
    return StatSpec(
        frozenset(simple),
        found.get(Ema),
        found.get(Window),
        found.get(Histogram),
        found.get(Quantiles),
    )


def check_policy(policy: str, where: str) -> str:
    if policy not in NONFINITE_POLICIES:
        raise ValueError(
            f"{where}: unknown nonfinite policy {policy!r}; expected one of {NONFINITE_POLICIES}."
        )
    return policy


def check_name(name: Any, where: str) -> str:
    """A metric, counter or group name: a non-empty string whose `/`-separated parts are
    all non-empty and none is `.` or `..`. Tags are paths (`Episode_Metrics/<name>/std`):
    MLflow refuses names that normalize to another path (`a//b`, `x/`, `a/./b`) and would
    drop every record of the run at flush time; TensorBoard and W&B would group them
    under a different path."""
    if not isinstance(name, str) or not name:
        raise ValueError(f"{where}: names must be non-empty strings, got {name!r}.")
    bad = [p for p in name.split("/") if p in ("", ".", "..")]
    if bad:
        raise ValueError(
            f"{where}: the name {name!r} has an empty, '.' or '..' part between slashes; "
            "tags are paths, and MLflow refuses names that normalize to another path. Use "
            f"{'/'.join(p for p in name.split('/') if p not in ('', '.', '..')) or 'x'!r} "
            "or another name."
        )
    return name


@dataclasses.dataclass(frozen=True)
class Term:
    """A metric term: a pure function evaluated once per env step.

    `fn(step_input, **params)` returns one value per env (shape `[num_envs]`, float, int or
    bool) or, when `outputs` is given, a dict with exactly those keys, each `[num_envs]`
    (several metrics from one function, sharing intermediates). An output `o` of term `t`
    is the metric `t/o`.

    Args:
      fn: the term function.
      reduce: episode reduction, one of "mean" (per-step average), "sum", "max", "min",
        "last", "std" or `jaxmetrics.discounted(gamma)`; for a multi-output term, one for
        all or a dict per output.
      stats: report statistics over finished episodes (strings and
        `jaxmetrics.ema/window/histogram/quantiles`).
      params: extra keyword arguments bound to `fn`.
      outputs: output names of a multi-output term (the keys of the returned dict).
      nonfinite: "skip" (default: leave NaN/inf steps out and count them), "propagate"
        or "raise" (raise at flush); None uses the `Metrics` default.
      groups: a `jaxmetrics.groups(...)`: every statistic is also kept per group;
        None uses the `Metrics` default (no groups unless `Metrics(groups=...)`).

    Examples:
      >>> import jax.numpy as jnp, jaxmetrics as jm
      >>> speed = jm.Term(lambda s: jnp.abs(s["qvel"]).sum(-1), reduce="max")
      >>> speed.reduce
      'max'
    """

    fn: Callable[..., Any]
    reduce: str | Discounted | Mapping[str, str | Discounted] = "mean"
    stats: Sequence[Stat] = DEFAULT_STATS
    params: Mapping[str, Any] = dataclasses.field(default_factory=dict)
    outputs: Sequence[str] | None = None
    nonfinite: str | None = None
    groups: Groups | None = None


@dataclasses.dataclass(frozen=True)
class Logged:
    """A value logged directly by training code (loss, KL, learning rate, ...).

    Each call of `Metrics.log` adds the given scalar (or every element of an array) as
    values weighing 1 each.

    Args:
      stats: report statistics over the logged values.
      nonfinite: see `Term`.

    Examples:
      >>> import jaxmetrics as jm
      >>> jm.Logged(stats=("mean", jm.ema(0.1))).stats
      ('mean', Ema(coeff=0.1))
    """

    stats: Sequence[Stat] = DEFAULT_STATS
    nonfinite: str | None = None


@dataclasses.dataclass(frozen=True)
class MetricSpec:
    """One row of a stream: a single reported metric after flattening terms."""

    name: str  # metric name, e.g. "reward/forward"
    term: str  # term (or logged) name it comes from
    reduce: str | Discounted | None  # episode reduction; None for logged values
    stats: StatSpec
    nonfinite: str
    group: str | None = None  # the group of a per-group row (`<metric>/<group>`)


def reported(stats: StatSpec) -> list[str]:
    """The statistics a metric with these report statistics has in `Metrics.compute`,
    in report order."""
    wants = {
        "simple": lambda s: s.name in stats.simple,
        "ema": lambda s: stats.ema is not None,
        "window": lambda s: stats.window is not None,
        "histogram": lambda s: stats.histogram is not None,
        "always": lambda s: True,
    }
    out = []
    for s in _statistics.STATISTICS:
        if s.source == "percentile" and stats.window is not None:
            out += [_statistics.percentile(p) for p in stats.window.percentiles]
        elif s.source == "quantiles" and stats.quantiles is not None:
            out += [_statistics.quantile(p) for p in stats.quantiles.levels]
        elif s.source in wants and wants[s.source](s):
            out.append(s.name)
    return out
