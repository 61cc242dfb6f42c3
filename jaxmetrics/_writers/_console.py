"""A compact table per record on a terminal or in CI logs (rich, imported on creation)."""

from collections.abc import Sequence
from typing import IO

from .._core import _statistics, _tags
from .._core._tags import TagInfo
from .._core._validate import is_int
from .._host._record import Record


def _fmt(v: float | int) -> str:
    return str(v) if isinstance(v, int) else f"{v:.4g}"


class ConsoleWriter:
    """Prints one table per record: a row per metric, columns mean/std/min/max/count,
    every other statistic as `stat=value` in a last column.

    Counters show their total in the count column (and `per_sec`), timers their seconds
    in the mean column. Colours only on a
    terminal; plain text in CI logs and files.

    Args:
      file: where to print (default: standard output at print time).
      every: print every `every`-th record only.
      width: table width in characters (default: the terminal's, or 100).
    """

    def __init__(self, file: IO[str] | None = None, *, every: int = 1, width: int | None = None):
        if not is_int(every) or every < 1:
            raise ValueError(f"ConsoleWriter: every must be an int >= 1, got {every!r}.")
        from rich.console import Console

        self._console = Console(file=file, width=width or None, soft_wrap=False)
        if width is None and not self._console.is_terminal:
            self._console.width = 100
        self._every = every
        self._seen = 0
        self._rows: dict[str, tuple[str, str]] = {}

    def open(self, tags: Sequence[TagInfo]) -> None:
        """Groups the tags into one row per metric (the tag without its stat suffix)."""
        for i in tags:
            column = _statistics.get(i.stat).column
            self._rows[i.tag] = (_tags.metric_tag(i), i.stat if column is None else column)

    def write(self, record: Record) -> None:
        """Prints the record's scalars as a table."""
        self._seen += 1
        if (self._seen - 1) % self._every:
            return
        from rich.table import Table

        rows: dict[str, dict[str, str]] = {}
        for tag, v in record.scalars.items():
            row, stat = self._rows.get(tag, (tag, "mean"))  # timers: seconds as "mean"
            rows.setdefault(row, {})[stat] = _fmt(v)
        table = Table(title=f"step {record.step}", title_justify="left", box=None, pad_edge=False)
        table.add_column("metric", overflow="fold")
        for c in _statistics.COLUMNS:
            table.add_column(c, justify="right")
        table.add_column("more", overflow="fold")
        for row, stats in rows.items():
            more = " ".join(f"{k}={v}" for k, v in stats.items() if k not in _statistics.COLUMNS)
            table.add_row(row, *(stats.get(c, "") for c in _statistics.COLUMNS), more)
        self._console.print(table)

    def close(self) -> None:
        """Nothing to release."""
