"""The cross-seed summary run: per tag and step, statistics of the seeds' values.

`Logger(runs=N, seeds_summary=[...])` writes, beside each seed's run, one more run whose
records summarize the seeds (rliable's recommendations for reporting RL results: an
interquartile mean and an interval, not a mean alone). `SeedsSummary` joins the seeds'
records by step as the writer thread writes them and turns each complete step into one
summary `Record`.

Pure Python, numpy and `scipy.special` (a JAX dependency): no JAX here.
"""

import math
from collections.abc import Sequence
from typing import Any

import numpy as np

from .._core import _statistics, _tags
from .._core._tags import TagInfo
from ._record import Record

CONFIDENCE = 0.95
"""The level of the Student-t interval of the mean across seeds."""

# The summary statistics, in the order a summary record lists them per seed tag.
STATS = tuple(s.name for s in _statistics.STATISTICS if s.source == "seeds")

# What is summarized: a scalar statistic or count of a run's record. Histograms, window
# contents, rare-event counts (written only once non-zero) and timers are left out.
_SUMMARIZED = ("float", "exact")


def iqm(values: np.ndarray) -> float:
    """The interquartile mean: the mean of `values` with `floor(n / 4)` of the smallest
    and as many of the largest left out (rliable's `scipy.stats.trim_mean(x, 0.25)`; for
    n < 4 it is the mean).

    Examples:
      >>> import numpy as np
      >>> from jaxmetrics._host._seed_statistics import iqm
      >>> iqm(np.array([1.0, 2.0, 3.0, 4.0, 100.0]))     # 5 seeds: 1 cut at each end
      3.0
    """
    x = np.sort(np.asarray(values, np.float64))
    k = x.size // 4
    return float(np.mean(x[k : x.size - k]))


def summarize(values: Sequence[float]) -> dict[str, float | int]:
    """The summary statistics of one tag at one step over the seeds' finite values.

    Returns `seeds_count` (seeds with a finite value), `seeds_mean`, `seeds_min`,
    `seeds_max` and `seeds_iqm` from one value on, and from two on `seeds_std` (sample
    std, ddof 1) and the Student-t 95% interval of the mean, `mean -/+ t(0.975, n - 1)
    * std / sqrt(n)` (`seeds_ci_lower`, `seeds_ci_upper`). Nothing for no finite value.

    Examples:
      >>> from jaxmetrics._host._seed_statistics import summarize
      >>> s = summarize([1.0, 2.0, 3.0, float("nan")])
      >>> s["seeds_count"], s["seeds_mean"], round(s["seeds_ci_upper"], 4)
      (3, 2.0, 4.4841)
    """
    x = np.asarray(values, np.float64)
    x = x[np.isfinite(x)]
    n = int(x.size)
    if n == 0:
        return {}
    mean = float(np.mean(x))
    out: dict[str, float | int] = {"seeds_mean": mean}
    half = 0.0  # set, and read, where n > 1
    if n > 1:
        from scipy.special import stdtrit  # the Student t quantile; scipy comes with jax

        std = float(np.std(x, ddof=1))
        half = float(stdtrit(n - 1, 0.5 + CONFIDENCE / 2)) * std / math.sqrt(n)
        out["seeds_std"] = std
    out["seeds_min"] = float(np.min(x))
    out["seeds_max"] = float(np.max(x))
    out["seeds_iqm"] = iqm(x)
    if n > 1:
        out["seeds_ci_lower"] = mean - half
        out["seeds_ci_upper"] = mean + half
    out["seeds_count"] = n
    return out


def summary_tags(tags: Sequence[TagInfo]) -> tuple[TagInfo, ...]:
    """The summary run's tag table, from the seeds' (a logger's `tags`): for every scalar
    tag `T`, `T` itself (the mean across seeds, so that TensorBoard draws it in the
    seeds' chart) and `T/seeds_std`, ..., `T/seeds_count`, in group "seeds" with `T` as
    the metric.

    Raises:
      ValueError: two summary tags are equal once TensorBoard has sanitized them (e.g. a
        metric named `x/seeds_std`).
    """
    out = [
        TagInfo(t.tag + _statistics.get(stat).suffix, "seeds", t.tag, stat)
        for t in tags
        if _statistics.get(t.stat).host in _SUMMARIZED
        for stat in STATS
    ]
    _tags.check_unique((i.tag, f"seeds summary {i.stat} of {i.metric!r}") for i in out)
    return tuple(out)


class SeedsSummary:
    """Joins the seeds' records by step and makes the summary records.

    A step's summary is made once every seed has written a record at that step, or has
    moved past it (a seed whose period did not end there, with per-seed `when` in
    `Logger.emit`, is missing at that step); `drain` makes the rest. A seed whose value
    of a tag is missing or not finite at a step is left out of that tag's statistics.

    Args:
      tags: the summary tag table (`summary_tags`).
      runs: the number of seeds.
    """

    def __init__(self, tags: Sequence[TagInfo], runs: int):
        self._seed_tags = list(dict.fromkeys(i.metric for i in tags))
        self._runs = runs
        self._pending: dict[int, dict[int, Record]] = {}
        self._last: list[int | None] = [None] * runs

    def add(self, run: int, record: Record) -> list[Record]:
        """Takes one seed's record; returns the summary records now complete, in step
        order."""
        step = record.step
        out = []
        if run in self._pending.get(step, {}):  # a second record of this seed at `step`
            out += self._finish(lambda s: s <= step)
        self._pending.setdefault(step, {})[run] = record
        last = self._last[run]
        self._last[run] = step if last is None else max(last, step)
        return out + self._finish(self._complete)

    def drain(self) -> list[Record]:
        """The summary records of every step still waiting for seeds, in step order."""
        return self._finish(lambda s: True)

    def _complete(self, step: int) -> bool:
        group = self._pending[step]
        return all(
            r in group or (last is not None and last > step) for r, last in enumerate(self._last)
        )

    def _finish(self, done: Any) -> list[Record]:
        out = []
        for step in sorted(self._pending):
            if not done(step):
                break
            out.append(self._record(step, self._pending.pop(step)))
        return out

    def _record(self, step: int, group: dict[int, Record]) -> Record:
        scalars: dict[str, float | int] = {}
        for tag in self._seed_tags:
            values = [r.scalars[tag] for r in group.values() if tag in r.scalars]
            for stat, v in summarize(values).items():
                scalars[tag + _statistics.get(stat).suffix] = v
        wall_time = max(r.wall_time for r in group.values())
        return Record(step, wall_time, scalars, {}, {})
