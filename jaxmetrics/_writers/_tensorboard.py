"""TensorBoard event files through tensorboardX (imported when the writer is created)."""

import os
import socket
import struct
import time
import uuid
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from .._core import _tags
from .._core._tags import TagInfo
from .._core._validate import is_int
from .._host._record import HistogramData, Record
from ._append import AppendFile
from ._paths import check_hparams, writable_dir


class TensorBoardWriter:
    """Writes TensorBoard event files into `logdir` (one run).

    What it writes, per record:

    - a scalar for every scalar tag of the record (empty statistics are not in a record,
      so nothing is ever written as a fake 0). TensorBoard stores scalars as float32:
      counters past 2^24 show rounded there (they are exact in `JsonlWriter` and
      `MemoryWriter`);
    - `<metric>/histogram`: the histogram statistic's in-range bins, with the spec's
      edges (`Metrics.histogram_edges`); `sum`/`sum_squares` are taken at bin centres.
      Under/overflow counts are the scalars `<metric>/histogram/underflow|overflow`;
    - `<metric>/window_values`: a `window_bins`-bin histogram of the window contents,
      with their exact min, max, sum and sum of squares;
    - with `std_bands=True`: `Margin/<mean tag>/lower|upper` (mean -/+ std) for every
      metric that reports both a mean and a std, with a custom-scalars layout (written
      once) that draws each mean in a mean ± std band ("Custom Scalars" tab). Off by
      default: TensorBoard also lists these helper scalars in its Scalars tab, two per
      metric, under "Margin";
    - on request, an hparams session: `hparams` with the `hparam_metrics` tags (default:
      every mean tag).

    Tags are TensorBoard-sanitized (the spec already rejects tags that would collide).
    Events of one record go out as one event, flushed and fsync'ed on every write, so
    whatever was written survives a crash of the process; a write that fails part-way
    (a full disk) is cut back before the error reaches the `Logger`, so the file stays
    readable past it. The event file is created by `open` (when the `Logger` starts, or
    at a `ProgressFn`'s first call), so a run that fails before leaves none.

    Args:
      logdir: the run directory; created if missing. It is checked here: an invalid or
        unwritable path raises `ValueError` naming it, before training starts.
      hparams: hyperparameters (name -> bool/int/float/str) for the HParams dashboard.
      hparam_metrics: tags the HParams dashboard shows; only with `hparams`.
      window_bins: bins of the window-contents histograms.
      std_bands: write the mean ± std bands for the Custom Scalars tab.
      purge_step: when resuming a run in the same `logdir` from a checkpoint taken at an
        earlier step: TensorBoard hides every event of this run with a step >=
        `purge_step` written before (tensorboardX's `SummaryWriter(purge_step=...)`
        semantics: a session-start event at that step), so the resumed run's points
        replace them instead of drawing the curve back over itself.

    Raises:
      ValueError: bad `logdir`, `window_bins`, `purge_step` or hparams.
      TypeError: hparam values of another type, or a `std_bands` that is not a bool.
    """

    def __init__(
        self,
        logdir: str | os.PathLike,
        *,
        hparams: Mapping[str, bool | int | float | str] | None = None,
        hparam_metrics: Sequence[str] | None = None,
        window_bins: int = 30,
        std_bands: bool = False,
        purge_step: int | None = None,
    ):
        if not is_int(window_bins) or window_bins < 1:
            raise ValueError(
                f"TensorBoardWriter: window_bins must be an int >= 1, got {window_bins!r}."
            )
        if purge_step is not None and (not is_int(purge_step) or purge_step < 0):
            raise ValueError(
                f"TensorBoardWriter: purge_step must be an int >= 0 or None, got {purge_step!r}."
            )
        if not isinstance(std_bands, bool):
            raise TypeError(f"TensorBoardWriter: std_bands must be a bool, got {std_bands!r}.")
        if hparams is not None:
            check_hparams(hparams, "TensorBoardWriter")
        elif hparam_metrics is not None:
            raise ValueError("TensorBoardWriter: hparam_metrics needs hparams.")
        if hparam_metrics is not None and (
            isinstance(hparam_metrics, str) or not all(isinstance(t, str) for t in hparam_metrics)
        ):
            raise TypeError(
                f"TensorBoardWriter: hparam_metrics must be a list of tags, got {hparam_metrics!r}."
            )
        self.logdir = writable_dir(logdir, "TensorBoardWriter", "logdir")
        self._hparams = dict(hparams) if hparams is not None else None
        self._hparam_metrics = None if hparam_metrics is None else list(hparam_metrics)
        self._bins = window_bins
        self._std_bands = std_bands
        self._purge_step = purge_step

        # The generated protobuf modules define their messages at import time, out of the
        # type checker's sight.
        from tensorboardX import summary
        from tensorboardX.proto.event_pb2 import Event, SessionLog  # pyright: ignore[reportAttributeAccessIssue]
        from tensorboardX.proto.summary_pb2 import HistogramProto, Summary  # pyright: ignore[reportAttributeAccessIssue]
        from tensorboardX.record_writer import masked_crc32c

        self._summary, self._Event, self._SessionLog, self._Hist, self._Summary = (
            summary,
            Event,
            SessionLog,
            HistogramProto,
            Summary,
        )
        self._crc = masked_crc32c
        self._events: AppendFile | None = None
        self._bands: dict[str, tuple[str, str, str]] = {}

    def open(self, tags: Sequence[TagInfo]) -> None:
        """Creates the event file and writes the mean ± std layout and the hparams
        session, where asked for.

        Raises:
          ValueError: the event file cannot be created in `logdir`.
        """
        by_metric = {(i.group, i.metric): {} for i in tags}
        for i in tags:
            by_metric[(i.group, i.metric)][i.stat] = i.tag
        layout: dict[str, dict[str, list]] = {}
        for (group, _), stats in by_metric.items():
            if self._std_bands and "mean" in stats and "std" in stats:
                mean = stats["mean"]
                self._bands[mean] = (
                    stats["std"],
                    _tags.band(mean, "lower"),
                    _tags.band(mean, "upper"),
                )
                category = mean.split("/", 1)[0] if "/" in mean else group
                layout.setdefault(f"{category} (mean ± std)", {})[_tags.sanitize(mean)] = [
                    "Margin",
                    [_tags.sanitize(t) for t in (mean, *self._bands[mean][1:])],
                ]
        _tags.check_unique(
            [(i.tag, f"tag {i.tag!r}") for i in tags]
            + [(t, f"band of {m!r}") for m, b in self._bands.items() for t in b[1:]]
        )
        # tensorboardX's SummaryWriter hands events to a background queue that its flush()
        # does not drain; events here go to disk synchronously, fsync'ed, whole or not at
        # all. TensorBoard reads a run's files in name order: the time in nanoseconds puts
        # a resumed run's file (and its purge) after the earlier ones of the same second.
        name = (
            f"events.out.tfevents.{time.time_ns()}.{socket.gethostname()}."
            f"{os.getpid()}.{uuid.uuid4().hex[:8]}"
        )
        try:
            self._events = AppendFile(os.path.join(self.logdir, name))
            self._write_event(self._Event(wall_time=time.time(), file_version="brain.Event:2"))
        except OSError as e:
            raise ValueError(
                f"TensorBoardWriter: cannot create an event file in {self.logdir!r}: {e}."
            ) from None
        if self._purge_step is not None:
            # TensorBoard drops this run's earlier events from this step on.
            start = self._SessionLog(status=self._SessionLog.START)
            self._write_event(
                self._Event(wall_time=time.time(), step=self._purge_step, session_log=start)
            )
        summaries = []
        if layout:
            summaries.append(self._summary.custom_scalars(layout))
        if self._hparams is not None:
            metrics = self._hparam_metrics
            if metrics is None:
                metrics = [i.tag for i in tags if i.stat == "mean"]
            exp, ssi, _ = self._summary.hparams(
                self._hparams, {_tags.sanitize(t): 0.0 for t in metrics}
            )
            summaries += [exp, ssi]
        for s in summaries:
            self._write_event(self._Event(wall_time=time.time(), summary=s))

    def _write_event(self, event: Any) -> None:
        data = event.SerializeToString()
        header = struct.pack("<Q", len(data))
        assert self._events is not None
        self._events.append(
            header
            + struct.pack("<I", self._crc(header))
            + data
            + struct.pack("<I", self._crc(data))
        )

    def write(self, record: Record) -> None:
        """Writes one record as one event and flushes it to disk."""
        values = []
        Value = self._Summary.Value
        for tag, v in record.scalars.items():
            values.append(Value(tag=_tags.sanitize(tag), simple_value=float(v)))
        for mean, (std, lower, upper) in self._bands.items():
            if mean in record.scalars and std in record.scalars:
                m, s = float(record.scalars[mean]), float(record.scalars[std])
                values.append(Value(tag=_tags.sanitize(lower), simple_value=m - s))
                values.append(Value(tag=_tags.sanitize(upper), simple_value=m + s))
        for tag, h in record.histograms.items():
            proto = self._histogram_stat(h)
            if proto is not None:
                values.append(Value(tag=_tags.sanitize(tag), histo=proto))
        for tag, w in record.windows.items():
            values.append(Value(tag=_tags.sanitize(tag), histo=self._histogram_of(w)))
        event = self._Event(
            wall_time=record.wall_time, step=record.step, summary=self._Summary(value=values)
        )
        self._write_event(event)

    def _histogram_stat(self, h: HistogramData) -> Any:
        counts = np.asarray(h.counts, np.float64)
        num = counts.sum()
        if num == 0:
            return None
        centres = 0.5 * (h.edges[:-1] + h.edges[1:])
        # TensorBoard draws bucket i over (limit[i-1], limit[i]] with `min` as the first
        # left edge and `max` as the last right edge, so these give exactly the spec's bins.
        return self._Hist(
            min=float(h.edges[0]),
            max=float(h.edges[-1]),
            num=float(num),
            sum=float(counts @ centres),
            sum_squares=float(counts @ (centres * centres)),
            bucket_limit=h.edges[1:].tolist(),
            bucket=counts.tolist(),
        )

    def _histogram_of(self, values: np.ndarray) -> Any:
        counts, edges = np.histogram(values, bins=self._bins)
        return self._Hist(
            min=float(values.min()),
            max=float(values.max()),
            num=float(values.size),
            sum=float(values.sum()),
            sum_squares=float(values @ values),
            bucket_limit=edges[1:].tolist(),
            bucket=counts.astype(np.float64).tolist(),
        )

    def close(self) -> None:
        """Ends the hparams session (if any) and closes the event file (if opened)."""
        if self._events is None:
            return
        try:
            if self._hparams is not None:
                _, _, sei = self._summary.hparams(self._hparams, {})
                self._write_event(self._Event(wall_time=time.time(), summary=sei))
        finally:
            self._events.close()
