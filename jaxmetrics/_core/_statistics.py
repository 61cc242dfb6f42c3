"""The registry of statistics: every `TagInfo.stat` the library writes, in report order.

Tag suffixes (`_tags`), the statistics a metric reports (`_spec.reported`), how a host record
holds each value (`_host._record`) and the console's columns derive from `STATISTICS`; nothing
else lists statistic names. (`_stream.compute` produces the in-graph values under these
names; `tests/test_layering.py` checks that the two agree.)
"""

from typing import NamedTuple


class Statistic(NamedTuple):
    """One statistic.

    Attributes:
      name: `TagInfo.stat`; a template for the window percentile and the quantile
        families (see `percentile` and `quantile`).
      suffix: what follows `<prefix>/<metric>` in its tag ("" for the mean).
      source: what asks for it. "simple": its name among a metric's `stats`; "ema",
        "window", "percentile", "histogram", "quantiles": the matching
        `jaxmetrics.ema/window/histogram/quantiles(...)`; "always": every metric;
        "running": `include_running`; "counter": every counter; "logger": added by the
        `Logger` from another tag; "seeds": the `Logger`'s cross-seed summary run
        (`_host._seed_statistics`), of a seed tag.
      host: what a `Record` holds. "float": a float, left out when not finite;
        "exact": an exact int; "sparse": an exact int written from its first non-zero
        value on; "histogram": `HistogramData`; "window": the finite window contents.
      column: the `ConsoleWriter` column it is shown in (None: the last column).
      overflow: when the value counts as an overflow of the dtype (added to the metric's
        `nonfinite` count and not written; see `_stream.compute`). "period": not
        finite although the period has values (non-finite values were left out, so the
        statistic itself overflowed); "inf": infinite (values near the dtype's limit);
        None: never.
    """

    name: str
    suffix: str
    source: str
    host: str
    column: str | None = None
    overflow: str | None = None


_PERCENTILE = "window_p{p}"
_QUANTILE = "q{p}"
LEVEL_DECIMALS = 4
"""Percentile levels (window percentiles, quantiles) have at most this many decimals, so
that each has an exact tag."""

STATISTICS = (
    Statistic("mean", "", "simple", "float", "mean", overflow="period"),
    Statistic("std", "/std", "simple", "float", "std", overflow="period"),
    Statistic("min", "/min", "simple", "float", "min"),
    Statistic("max", "/max", "simple", "float", "max"),
    Statistic("sum", "/sum", "simple", "float", overflow="period"),
    Statistic("count", "/count", "simple", "exact", "count"),
    Statistic("ema", "/ema", "ema", "float", overflow="inf"),
    Statistic("window_mean", "/window_mean", "window", "float", overflow="inf"),
    Statistic("window_std", "/window_std", "window", "float", overflow="inf"),
    Statistic("window_min", "/window_min", "window", "float", overflow="inf"),
    Statistic("window_max", "/window_max", "window", "float", overflow="inf"),
    Statistic("window_values", "/window_values", "window", "window"),
    Statistic(_PERCENTILE, "/" + _PERCENTILE, "percentile", "float", overflow="inf"),
    Statistic("histogram", "/histogram", "histogram", "histogram"),
    Statistic(_QUANTILE, "/" + _QUANTILE, "quantiles", "float", overflow="period"),
    Statistic("nonfinite", "/nonfinite", "always", "sparse"),
    Statistic("running", "/running", "running", "float"),
    Statistic("total", "", "counter", "exact", "count"),
    Statistic("per_sec", "/per_sec", "logger", "float"),
    Statistic("histogram/underflow", "/histogram/underflow", "logger", "sparse"),
    Statistic("histogram/overflow", "/histogram/overflow", "logger", "sparse"),
    # The summary run's tag of the mean across seeds is the seeds' own tag.
    Statistic("seeds_mean", "", "seeds", "float", "mean"),
    Statistic("seeds_std", "/seeds_std", "seeds", "float", "std"),
    Statistic("seeds_min", "/seeds_min", "seeds", "float", "min"),
    Statistic("seeds_max", "/seeds_max", "seeds", "float", "max"),
    Statistic("seeds_iqm", "/seeds_iqm", "seeds", "float"),
    Statistic("seeds_ci_lower", "/seeds_ci_lower", "seeds", "float"),
    Statistic("seeds_ci_upper", "/seeds_ci_upper", "seeds", "float"),
    Statistic("seeds_count", "/seeds_count", "seeds", "exact", "count"),
)

SIMPLE_STATS = tuple(s.name for s in STATISTICS if s.source == "simple")
"""The statistics named by a plain string in `stats=`."""

COLUMNS = tuple(dict.fromkeys(s.column for s in STATISTICS if s.column is not None))
"""The console's columns, in order."""

_BY_NAME = {s.name: s for s in STATISTICS}
# A family member's name is its template's prefix followed by a number.
_FAMILIES = {t.split("{", 1)[0]: t for t in (_PERCENTILE, _QUANTILE)}


def level(p: float) -> str:
    """A percentile level as tags write it: exact to `LEVEL_DECIMALS` decimals, no trailing
    zeros, no exponent (`50`, `99.9`, `0.0001`, `12.3457`)."""
    text = f"{p:.{LEVEL_DECIMALS}f}".rstrip("0").rstrip(".")
    return "0" if text == "-0" else text


def is_level(p: float) -> bool:
    """Whether `p` is a percentile in [0, 100] with at most `LEVEL_DECIMALS` decimals."""
    scaled = p * 10**LEVEL_DECIMALS
    return 0 <= p <= 100 and abs(scaled - round(scaled)) <= 1e-6


def percentile(p: float) -> str:
    """The statistic name of window percentile `p`: `window_p50`, `window_p99.9`."""
    return _PERCENTILE.format(p=level(p))


def quantile(p: float) -> str:
    """The statistic name of period quantile `p` (a percentile): `q50`, `q99.9`."""
    return _QUANTILE.format(p=level(p))


def get(name: str) -> Statistic:
    """The registry entry of `name` (a window percentile or a quantile resolves to its
    family).

    Raises:
      KeyError: for a name that is not a statistic.
    """
    found = _BY_NAME.get(name)
    for prefix, template in _FAMILIES.items():
        if found is None and name.startswith(prefix) and name[len(prefix) :][:1].isdigit():
            return _BY_NAME[template]._replace(name=name, suffix="/" + name)
    if found is None:
        raise KeyError(f"{name!r} is not a jaxmetrics statistic.")
    return found
