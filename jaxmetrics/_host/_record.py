"""From a host report to a `Record`: what writers receive, and the rules of what is written.

A host report is tag -> value (floats, exact ints, numpy arrays), as `Metrics.to_host`
gives it. Per run, `RecordBuilder` turns each one into a `Record`: empty statistics (NaN)
are left out, exact counts stay Python ints, histograms and window contents get their own
fields, rare-event counts (`/nonfinite`, histogram tails) appear from their first
non-zero value on, and counters get their growth per second (`/per_sec`). Both the
`Logger` and `jaxmetrics.brax.ProgressFn` build their records here.

Pure Python and numpy: writers import this module without importing JAX.
"""

import dataclasses
import math
from collections.abc import Iterable, Mapping, Sequence
from typing import Any, NamedTuple, Protocol, runtime_checkable

import numpy as np

from .._core import _statistics, _tags
from .._core._tags import TagInfo


class HistogramData(NamedTuple):
    """A histogram statistic on the host.

    Attributes:
      edges: float64 `[bins + 1]` bin edges (`Metrics.histogram_edges`).
      counts: int64 `[bins]` in-range counts; the right edge belongs to the last bin.
      underflow: values below `edges[0]`.
      overflow: values above `edges[-1]`.
    """

    edges: np.ndarray
    counts: np.ndarray
    underflow: int
    overflow: int


@dataclasses.dataclass(frozen=True)
class Record:
    """One run's report at one step, ready to write.

    Empty statistics are already left out: no NaN ever reaches a writer, a histogram is
    present only when it counted something, a window only when it holds a finite value.

    Attributes:
      step: the x-axis value given to `Logger.flush` / `Logger.emit`.
      wall_time: seconds since the epoch when the report reached the host (for a flush,
        when the device had computed it; for an emit, the callback).
      scalars: tag -> value, in tag-table order. Counts and counters are exact Python ints,
        everything else a float.
      histograms: tag -> `HistogramData`, for `<metric>/histogram` tags.
      windows: tag -> float64 array of the finite window contents, oldest first, for
        `<metric>/window_values` tags.
    """

    step: int
    wall_time: float
    scalars: Mapping[str, float | int]
    histograms: Mapping[str, HistogramData]
    windows: Mapping[str, np.ndarray]


@runtime_checkable
class Writer(Protocol):
    """What a `Logger` drives. All calls come from the logger's writer thread, in order.

    `open` is called once with the logger's static tag table before the first `write`
    (writers may prepare layouts from it); timer tags are not in it, since timers are
    named at first use. `close` is called once, after the last `write`.
    """

    def open(self, tags: Sequence[TagInfo]) -> None: ...

    def write(self, record: Record) -> None: ...

    def close(self) -> None: ...


def check_writers(writers: Any, who: str) -> list[Writer]:
    """`writers` as a list, or an error naming `who` and the fix.

    Raises:
      TypeError: for a single writer (not in a list), or an element that is not a writer.
    """
    if isinstance(writers, Writer) or not isinstance(writers, Iterable):
        raise TypeError(f"{who}: writers must be a list of writers; wrap the writer in [...].")
    out = list(writers)
    for w in out:
        if not isinstance(w, Writer):
            raise TypeError(
                f"{who}: {w!r} is not a writer: it needs open(tags), write(record) and "
                "close() methods (see jaxmetrics.Writer)."
            )
    return out


def close_quietly(*groups: Any) -> None:
    """Closes the writers made before a construction error (that error is what matters,
    not theirs): each argument a writer, or a sequence of writers."""
    for group in groups:
        for w in [group] if isinstance(group, Writer) or not isinstance(group, Sequence) else group:
            close = getattr(w, "close", None)
            if callable(close):
                try:
                    close()
                except Exception:  # noqa: BLE001, S110
                    pass


def derived_tags(tags: Iterable[TagInfo]) -> list[TagInfo]:
    """The tags a record adds to a report's: counters' `/per_sec` and histogram tails."""
    out = []
    for i in tags:
        if i.stat == "total":
            out.append(_tags.derived(i, "per_sec"))
        elif i.stat == "histogram":
            out += [_tags.derived(i, f"histogram/{end}") for end in ("underflow", "overflow")]
    return out


class RecordBuilder:
    """Turns one run's host reports into `Record`s, in order.

    It remembers what spans records: the previous counter totals (for `/per_sec`) and
    which rare-event counts have been non-zero.

    Args:
      edges: histogram tag -> bin edges (`Metrics.histogram_edges`).
    """

    def __init__(self, edges: Mapping[str, np.ndarray]):
        self._edges = edges
        self._seen_nonzero: set[str] = set()
        self._prev: tuple[float, dict[str, int]] | None = None

    def __call__(
        self,
        values: Iterable[tuple[TagInfo, Any]],
        step: int,
        wall_time: float,
        timers: Mapping[str, float],
        *,
        new_point: bool = True,
    ) -> Record:
        """The record of one report.

        Args:
          values: (tag info, host value) pairs, in tag-table order.
          step: the x-axis value.
          wall_time: when the report reached the host (seconds since the epoch).
          timers: timer tag -> seconds, appended to the scalars.
          new_point: whether this report is a new point in time for the counters' rates:
            each counter's `/per_sec` is its growth since the previous new point over the
            wall time between the two (none for the first, nor for a report that is not
            a new point).
        """
        scalars: dict[str, float | int] = {}
        hists: dict[str, HistogramData] = {}
        windows: dict[str, np.ndarray] = {}
        totals: dict[str, int] = {}
        for info, v in values:
            host = _statistics.get(info.stat).host
            if host == "histogram":
                c = np.asarray(v, np.int64)
                if c.sum() > 0:
                    hists[info.tag] = HistogramData(
                        self._edges[info.tag], c[1:-1], int(c[0]), int(c[-1])
                    )
                under, over = derived_tags([info])
                self._sparse(scalars, under.tag, int(c[0]))
                self._sparse(scalars, over.tag, int(c[-1]))
            elif host == "window":
                w = np.asarray(v, np.float64)
                w = w[np.isfinite(w)]
                if w.size:
                    windows[info.tag] = w
            elif host == "sparse":
                self._sparse(scalars, info.tag, int(v))
            elif host == "exact":
                scalars[info.tag] = int(v)
                if info.stat == "total" and new_point:
                    totals[info.tag] = int(v)
                    rate = self._rate(info.tag, int(v), wall_time)
                    if rate is not None:
                        scalars[_tags.derived(info, "per_sec").tag] = rate
            else:
                f = float(v)
                if math.isfinite(f):
                    scalars[info.tag] = f
        if totals:
            self._prev = (wall_time, totals)
        scalars.update(timers)
        return Record(step, wall_time, scalars, hists, windows)

    def start(self, wall_time: float, totals: Mapping[str, int]) -> None:
        """Counts rates from these counter totals at `wall_time` (a resumed run's)."""
        self._prev = (wall_time, dict(totals))

    def _sparse(self, scalars: dict[str, float | int], tag: str, n: int) -> None:
        # Zero counts of rare events are written only once the event has happened.
        if n or tag in self._seen_nonzero:
            self._seen_nonzero.add(tag)
            scalars[tag] = n

    def _rate(self, tag: str, total: int, wall_time: float) -> float | None:
        if self._prev is None or wall_time <= self._prev[0] or tag not in self._prev[1]:
            return None
        prev_time, prev = self._prev
        return (total - prev[tag]) / (wall_time - prev_time)
