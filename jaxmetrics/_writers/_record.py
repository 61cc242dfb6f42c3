"""What a writer receives: one `Record` per run per flush, and the `Writer` protocol."""

import dataclasses
import os
from collections.abc import Mapping, Sequence
from typing import Any, NamedTuple, Protocol, runtime_checkable

import numpy as np

from .._metrics import TagInfo


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
      wall_time: seconds since the epoch when the flush (or emit callback) happened.
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


def fs_path(value: Any, who: str, name: str, kind: str) -> str:
    """`value` as a non-empty filesystem path string, or an error naming the argument."""
    try:
        path = os.fspath(value)
    except TypeError:
        raise TypeError(f"{who}: {name} must be a {kind}, got {value!r}.") from None
    if not isinstance(path, str) or not path:
        raise ValueError(f"{who}: {name} must be a non-empty {kind}, got {value!r}.")
    return path
