"""JSON lines: one machine-readable record per run per flush, appended."""

import json
import os
from collections.abc import Sequence
from typing import Any

from .._report import Record
from .._tags import TagInfo
from .._validate import is_int
from ._append import AppendFile
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

    The file only ever holds whole lines: each is written and fsync'ed on its own, and a
    write that fails part-way (a full disk) is cut back before the error reaches the
    `Logger`, so later lines start on a line of their own. Opening an existing file
    drops a partial last line (a record cut by a crash: never acknowledged by
    `Logger.wait`), keeping the file's mode and, for a symlinked path, the link. A file
    holding anything else (another program's JSON, text) is refused and left untouched.

    Args:
      path: the file; its directory is created if missing. Checked here: an invalid or
        unwritable path, or a file that is not this writer's JSON lines, raises
        `ValueError` naming it.
      purge_step: when resuming a run from a checkpoint taken at an earlier step: lines
        with a step >= `purge_step` are dropped from the existing file (rewritten
        atomically), so the resumed run's records replace them instead of following
        them (the same rule as `TensorBoardWriter(purge_step=...)`).

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

    def __init__(self, path: str | os.PathLike, *, purge_step: int | None = None):
        p = fs_path(path, "JsonlWriter", "path", "file path")
        if purge_step is not None and (not is_int(purge_step) or purge_step < 0):
            raise ValueError(
                f"JsonlWriter: purge_step must be an int >= 0 or None, got {purge_step!r}."
            )
        self.path = p
        try:
            parent = os.path.dirname(p)
            if parent:
                os.makedirs(parent, exist_ok=True)
            _repair(p, purge_step)
            self._file = AppendFile(p)
        except _ForeignFile:
            raise
        except (OSError, ValueError) as e:
            raise ValueError(
                f"JsonlWriter: cannot open {p!r} for appending: {e}. Pass a writable file path."
            ) from None

    def open(self, tags: Sequence[TagInfo]) -> None:
        """Nothing to prepare: every line is self-describing."""

    def write(self, record: Record) -> None:
        """Appends the record as one line."""
        line = json.dumps(record_to_json(record), allow_nan=False, separators=(",", ":"))
        self._file.append((line + "\n").encode())

    def close(self) -> None:
        """Closes the file."""
        self._file.close()


_KEYS = ("step", "wall_time", "scalars", "histograms", "windows")
_HEAD = b'{"step":'  # how every line this writer writes starts (see `write`)


class _ForeignFile(ValueError):
    """The existing file holds something other than this writer's records."""


def _is_record(line: bytes) -> bool:
    try:
        obj = json.loads(line)
    except ValueError:
        return False
    return isinstance(obj, dict) and tuple(obj) == _KEYS


def _repair(path: str, purge_step: int | None) -> None:
    """Drops a partial last line (a record cut by a crash), and with `purge_step` every
    line from that step on. A file that holds anything but this writer's records is left
    untouched and refused; a repair keeps the file's mode, and a symlinked path its link."""
    try:
        with open(path, "rb") as f:
            data = f.read()
    except FileNotFoundError:
        return
    whole = data[: data.rfind(b"\n") + 1]
    lines = whole.splitlines(keepends=True)
    for i, line in enumerate(lines):
        if not _is_record(line):
            raise _ForeignFile(
                f"JsonlWriter: {path!r} exists and its line {i + 1} is not a JsonlWriter "
                "record; the file was left untouched. Pass the path of a new file or of "
                "this writer's own JSON lines."
            )
    tail = data[len(whole) :]
    ours = tail.startswith(_HEAD) or _HEAD.startswith(tail)  # cut after or inside its head
    if tail and (not ours or _is_record(tail)):
        # A whole record without its newline was never cut by this writer (it writes
        # the line and its newline in one call): someone else's text.
        raise _ForeignFile(
            f"JsonlWriter: {path!r} exists and ends in an unterminated line that is not a "
            "JsonlWriter record cut short; the file was left untouched. Pass the path of a "
            "new file or of this writer's own JSON lines."
        )
    if purge_step is not None:
        lines = [line for line in lines if json.loads(line)["step"] < purge_step]
    keep = b"".join(lines)
    if keep == data:
        return
    target = os.path.realpath(path)  # replace the file a symlink points to, not the link
    mode = os.stat(target).st_mode & 0o7777
    tmp = f"{target}.{os.getpid()}.tmp"
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, mode)
    with os.fdopen(fd, "wb") as f:
        f.write(keep)
        f.flush()
        os.fsync(f.fileno())
    os.chmod(tmp, mode)  # the umask narrowed the mode os.open was given
    os.replace(tmp, target)
