"""JSON lines: one machine-readable record per run per flush, appended."""

import json
import os
from collections.abc import Sequence
from typing import Any

from .._report import Record
from .._tags import TagInfo
from ._paths import fs_path


def record_to_json(record: Record) -> dict[str, Any]:
    """The JSON object `JsonlWriter` writes for a record."""
    return {
        "step": record.step,
        "wall_time": record.wall_time,
        "scalars": dict(record.scalars),
        "histograms": {
            tag: {
                "edges": h.edges.tolist(),
                "counts": h.counts.tolist(),
                "underflow": h.underflow,
                "overflow": h.overflow,
            }
            for tag, h in record.histograms.items()
        },
        "windows": {tag: w.tolist() for tag, w in record.windows.items()},
    }


class JsonlWriter:
    """Appends one JSON object per record to `path` (JSON lines).

    Each line is `{"step", "wall_time", "scalars": {tag: value}, "histograms": {tag:
    {"edges", "counts", "underflow", "overflow"}}, "windows": {tag: [values]}}`. Values
    are exact (float64, counts as integers) and never NaN, so every line is strict JSON.
    Lines are appended with one `write` each on an unbuffered file, so a crash leaves at
    most a partial last line, and a resumed run appends to the same file.

    Args:
      path: the file; its directory is created if missing. Checked here: an invalid or
        unwritable path raises `ValueError` naming it.

    Examples:
      >>> import json, os, tempfile, jaxmetrics as jm
      >>> path = os.path.join(tempfile.mkdtemp(), "metrics.jsonl")
      >>> metrics = jm.Metrics(logged=["loss"])
      >>> state = metrics.log(metrics.init(1), {"loss": 0.5})
      >>> with jm.Logger(metrics, [jm.JsonlWriter(path)]) as logger:
      ...     state = logger.flush(state, step=1)
      >>> with open(path) as f:
      ...     json.loads(f.readline())["scalars"]["Train/loss"]
      0.5
    """

    def __init__(self, path: str | os.PathLike):
        p = fs_path(path, "JsonlWriter", "path", "file path")
        self.path = p
        try:
            parent = os.path.dirname(p)
            if parent:
                os.makedirs(parent, exist_ok=True)
            self._file = open(p, "ab", buffering=0)  # noqa: SIM115 (closed in close())
        except (OSError, ValueError) as e:
            raise ValueError(
                f"JsonlWriter: cannot open {p!r} for appending: {e}. Pass a writable file path."
            ) from None

    def open(self, tags: Sequence[TagInfo]) -> None:
        """Nothing to prepare: every line is self-describing."""

    def write(self, record: Record) -> None:
        """Appends the record as one line."""
        line = json.dumps(record_to_json(record), allow_nan=False, separators=(",", ":"))
        data = memoryview((line + "\n").encode())
        while data:
            data = data[self._file.write(data) :]

    def close(self) -> None:
        """Closes the file."""
        self._file.close()
