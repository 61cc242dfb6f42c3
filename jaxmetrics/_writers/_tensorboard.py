"""TensorBoard event files through tensorboardX (imported when the writer is created)."""

import os
import uuid
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from .. import _tags
from .._report import HistogramData, Record
from .._tags import TagInfo
from .._validate import is_int
from ._paths import fs_path

_HPARAM_TYPES = (bool, int, float, str)


def _check_dir(logdir: Any, who: str) -> str:
    path = fs_path(logdir, who, "logdir", "path")
    try:
        os.makedirs(path, exist_ok=True)
    except (OSError, ValueError) as e:
        raise ValueError(
            f"{who}: cannot create log directory {path!r}: {e}. Pass a writable directory."
        ) from None
    if not os.access(path, os.W_OK | os.X_OK):
        raise ValueError(f"{who}: log directory {path!r} is not writable. Pass a writable one.")
    return path


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
    whatever was written survives a crash of the process. The event file is created by
    `open` (when the `Logger` starts, or at a `ProgressFn`'s first call), so a run that
    fails before leaves none.

    Args:
      logdir: the run directory; created if missing. It is checked here: an invalid or
        unwritable path raises `ValueError` naming it, before training starts.
      hparams: hyperparameters (name -> bool/int/float/str) for the HParams dashboard.
      hparam_metrics: tags the HParams dashboard shows; only with `hparams`.
      window_bins: bins of the window-contents histograms.
      std_bands: write the mean ± std bands for the Custom Scalars tab.

    Raises:
      ValueError: bad `logdir`, `window_bins` or hparams.
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
    ):
        if not is_int(window_bins) or window_bins < 1:
            raise ValueError(
                f"TensorBoardWriter: window_bins must be an int >= 1, got {window_bins!r}."
            )
        if not isinstance(std_bands, bool):
            raise TypeError(f"TensorBoardWriter: std_bands must be a bool, got {std_bands!r}.")
        if hparams is not None:
            if not isinstance(hparams, Mapping):
                raise TypeError(f"TensorBoardWriter: hparams must be a dict, got {hparams!r}.")
            for k, v in hparams.items():
                if not isinstance(k, str) or not isinstance(v, _HPARAM_TYPES):
                    raise TypeError(
                        f"TensorBoardWriter: hparam {k!r}={v!r}: names must be strings and "
                        "values bool, int, float or str."
                    )
        elif hparam_metrics is not None:
            raise ValueError("TensorBoardWriter: hparam_metrics needs hparams.")
        if hparam_metrics is not None and (
            isinstance(hparam_metrics, str) or not all(isinstance(t, str) for t in hparam_metrics)
        ):
            raise TypeError(
                f"TensorBoardWriter: hparam_metrics must be a list of tags, got {hparam_metrics!r}."
            )
        self.logdir = _check_dir(logdir, "TensorBoardWriter")
        self._hparams = dict(hparams) if hparams is not None else None
        self._hparam_metrics = None if hparam_metrics is None else list(hparam_metrics)
        self._bins = window_bins
        self._std_bands = std_bands

        from tensorboardX import summary
        from tensorboardX.event_file_writer import EventsWriter
        from tensorboardX.proto.event_pb2 import Event
        from tensorboardX.proto.summary_pb2 import HistogramProto, Summary

        self._summary, self._EventsWriter, self._Event, self._Hist, self._Summary = (
            summary,
            EventsWriter,
            Event,
            HistogramProto,
            Summary,
        )
        self._events: Any = None
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
        # does not drain; the synchronous EventsWriter below flushes (and fsyncs) for real.
        # The suffix keeps two writers opened in the same second from sharing a file name.
        try:
            self._events = self._EventsWriter(
                os.path.join(self.logdir, "events"), f".{os.getpid()}.{uuid.uuid4().hex[:8]}"
            )
        except OSError as e:
            raise ValueError(
                f"TensorBoardWriter: cannot create an event file in {self.logdir!r}: {e}."
            ) from None
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
            self._events.write_event(self._Event(summary=s))
        self._events.flush()

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
        self._events.write_event(event)
        self._events.flush()

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
        if self._hparams is not None:
            _, _, sei = self._summary.hparams(self._hparams, {})
            self._events.write_event(self._Event(summary=sei))
        self._events.close()
