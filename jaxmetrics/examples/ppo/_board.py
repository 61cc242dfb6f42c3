"""The console board: a progress bar per seed with the headline metrics, fed as a writer."""

import time
from collections.abc import Sequence
from typing import Any

import jaxmetrics as jm

HEADLINE = (
    ("return", "Episode_Metrics/episode_return/window_mean"),
    ("length", "Episode_Metrics/episode_length/window_mean"),
    ("v_loss", "Train/value_loss"),
    ("kl", "Train/approx_kl"),
    ("steps/s", "Counters/env_steps/per_sec"),
)
"""What the progress bar shows: (label, tag); the return and length are over the last
100 episodes."""


class ProgressWriter:
    """A `jaxmetrics.Writer` that draws a progress bar per run with the headline metrics.

    One `ProgressBoard` is shared by the writers of all runs. Records arrive on the
    logger's writer thread, so the bar moves in every mode: after each host flush, on
    each in-graph emit, and as a report history is written.
    """

    def __init__(self, board: "ProgressBoard", run: int, label: str):
        self._board, self._run, self._label = board, run, label
        self.last: dict[str, float | int] = {}

    def open(self, tags: Sequence[jm.TagInfo]) -> None:
        """Adds this run's bar."""
        self._board.add(self._run, self._label)

    def write(self, record: jm.Record) -> None:
        """Moves the bar to the record's step and shows its headline values."""
        for _, tag in HEADLINE:
            if tag in record.scalars:
                self.last[tag] = record.scalars[tag]
        shown = "  ".join(
            f"{label} {_format(self.last[tag])}" for label, tag in HEADLINE if tag in self.last
        )
        self._board.update(self._run, record.step, shown)

    def close(self) -> None:
        """Nothing to release (the board is stopped by its owner)."""


def _format(v: float | int) -> str:
    return f"{v:,.0f}" if abs(v) >= 1000 else f"{v:.3g}"


class ProgressBoard:
    """Progress bars (rich) for several runs; plain lines when rich is missing or off.

    Args:
      total: the x-axis value at the end (env steps).
      enabled: draw anything at all.
    """

    def __init__(self, total: int, enabled: bool = True):
        self._total, self._enabled = total, enabled
        self._progress: Any = None
        self._tasks: dict[int, Any] = {}
        self._last_print = 0.0
        if enabled:
            try:
                from rich.progress import (
                    BarColumn,
                    MofNCompleteColumn,
                    Progress,
                    TextColumn,
                    TimeElapsedColumn,
                )
            except ImportError:  # the `console` extra is optional: fall back to prints
                return
            self._progress = Progress(
                TextColumn("{task.description}"),
                BarColumn(),
                MofNCompleteColumn(),
                TimeElapsedColumn(),
                TextColumn("{task.fields[shown]}"),
            )
            self._progress.start()

    def add(self, run: int, label: str) -> None:
        if self._progress is not None:
            self._tasks[run] = self._progress.add_task(label, total=self._total, shown="compiling")

    def update(self, run: int, step: int, shown: str) -> None:
        if not self._enabled:
            return
        if self._progress is not None:
            self._progress.update(self._tasks[run], completed=step, shown=shown)
            return
        now = time.monotonic()
        if now - self._last_print > 2.0 or step >= self._total:
            self._last_print = now
            print(f"[run {run}] step {step:,}/{self._total:,}  {shown}", flush=True)

    def stop(self) -> None:
        if self._progress is not None:
            self._progress.stop()
