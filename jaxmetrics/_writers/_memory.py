"""In memory, for notebooks: a long-format pandas DataFrame and a one-line plot."""

import threading
from collections.abc import Sequence
from typing import Any

from .._core import _tags
from .._core._tags import TagInfo
from .._host._record import Record


class MemoryWriter:
    """Keeps every record in memory; `dataframe()` gives them in long format.

    pandas is imported when the writer is created, matplotlib when `plot` is first called.
    Read it after `Logger.wait()` or `Logger.close()` to see every flush so far.

    Examples:
      >>> import jaxmetrics as jm
      >>> metrics = jm.Metrics(logged=["loss"])
      >>> memory = jm.MemoryWriter()
      >>> with jm.Logger(metrics, [memory]) as logger:
      ...     for step in range(3):
      ...         state = metrics.log(metrics.init(1), {"loss": float(step)})
      ...         _ = logger.flush(state, step)
      >>> df = memory.dataframe()
      >>> df[df.tag == "Train/loss"].value.tolist()
      [0.0, 1.0, 2.0]
    """

    def __init__(self):
        import pandas  # noqa: F401  (fail here, not at the first read, if it is missing)

        self._records: list[Record] = []
        self._lock = threading.Lock()

    def open(self, tags: Sequence[TagInfo]) -> None:
        """Nothing to prepare."""

    def write(self, record: Record) -> None:
        """Keeps the record."""
        with self._lock:
            self._records.append(record)

    def close(self) -> None:
        """Nothing to release: the records stay readable."""

    @property
    def records(self) -> list[Record]:
        """Every record so far, in write order (histograms and windows included)."""
        with self._lock:
            return list(self._records)

    def dataframe(self) -> Any:
        """Scalars as a long-format DataFrame: columns `step` (int64), `tag` (str) and
        `value` (float64), one row per scalar per record, in write order."""
        import pandas as pd

        rows = [(r.step, t, float(v)) for r in self.records for t, v in r.scalars.items()]
        df = pd.DataFrame(rows, columns=["step", "tag", "value"])
        return df.astype({"step": "int64", "tag": "object", "value": "float64"})

    def plot(self, *tags: str, ax: Any = None, band: bool = True) -> Any:
        """Plots tags against step on one matplotlib Axes (created if not given).

        With `band`, a tag whose `<tag>/std` was also recorded is drawn inside a shaded
        mean ± std band. Returns the Axes.
        """
        import matplotlib.pyplot as plt

        if not tags:
            raise ValueError("MemoryWriter.plot: name at least one tag, e.g. plot('Train/loss').")
        df = self.dataframe()
        known = set(df.tag)
        missing = [t for t in tags if t not in known]
        if missing:
            raise ValueError(
                f"MemoryWriter.plot: no values recorded for {missing}; recorded tags: "
                f"{sorted(known)}."
            )
        if ax is None:
            _, ax = plt.subplots()
        for tag in tags:
            s = df[df.tag == tag]
            (line,) = ax.plot(s.step, s.value, label=tag)
            std_tag = _tags.tag("", tag, "std")  # the std of the metric whose mean is `tag`
            if band and std_tag in known:
                std = df[df.tag == std_tag].set_index("step").value
                m = s.set_index("step").value
                m, std = m.align(std, join="inner")
                ax.fill_between(m.index, m - std, m + std, color=line.get_color(), alpha=0.2)
        ax.set_xlabel("step")
        ax.legend()
        return ax
