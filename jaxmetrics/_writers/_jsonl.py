"""JSON lines: one machine-readable record per run per flush, appended."""

import json
import os
import re
import stat
import threading
from collections.abc import Sequence
from typing import Any

from .._core._tags import TagInfo
from .._core._validate import is_int
from .._host._record import Record
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
    drops a partial last line when it is provably this writer's record cut by a crash (never
    acknowledged by `Logger.wait`): it does not parse as JSON, and it starts as this
    writer's lines do (`{"step":<int>,"`), or it follows whole records of this writer. The
    file's mode and, for a symlinked path, the link are kept. A file holding anything else
    (another program's JSON, text) is refused with `jaxmetrics.ForeignFileError` and left
    untouched.

    Args:
      path: the file; its directory is created if missing. Checked here: an invalid or
        unwritable path raises `ValueError` naming it, a file that is not this writer's
        JSON lines `ForeignFileError` (a `ValueError`).
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
            _check_regular(p)
            self._key = _claim(p)
        except ForeignFileError:
            raise
        except (OSError, ValueError) as e:
            raise ValueError(
                f"JsonlWriter: cannot open {p!r} for appending: {e}. Pass a writable file path."
            ) from None
        try:
            _repair(p, purge_step)
            self._file = AppendFile(p)
        except BaseException as e:
            _release(self._key)
            if isinstance(e, (OSError, ValueError)) and not isinstance(e, ForeignFileError):
                raise ValueError(
                    f"JsonlWriter: cannot open {p!r} for appending: {e}. Pass a writable file path."
                ) from None
            raise

    def open(self, tags: Sequence[TagInfo]) -> None:
        """Nothing to prepare: every line is self-describing."""

    def write(self, record: Record) -> None:
        """Appends the record as one line."""
        line = json.dumps(record_to_json(record), allow_nan=False, separators=(",", ":"))
        self._file.append((line + "\n").encode())

    def close(self) -> None:
        """Closes the file (another JsonlWriter may then open it)."""
        try:
            self._file.close()
        finally:
            _release(self._key)


_KEYS = ("step", "wall_time", "scalars", "histograms", "windows")
_HEAD = b'{"step":'  # how every line this writer writes starts (see `write`)
_CUT_HEAD = re.compile(rb'\{"step":-?\d+,"')  # compact separators: no other writer's look


# The files JsonlWriters of this process hold open: lines of two writers (two runs given
# one path) would interleave with nothing to tell them apart.
_OPEN: set[str] = set()
_OPEN_LOCK = threading.Lock()


def _check_regular(path: str) -> None:
    """Refuses an existing path that is not a regular file (opening a FIFO for writing
    blocks until a reader comes; a directory or a device is no log)."""
    try:
        mode = os.stat(path).st_mode
    except FileNotFoundError:
        return
    if not stat.S_ISREG(mode):
        raise ValueError("it exists and is not a regular file (a FIFO, a device or a folder)")


def _claim(path: str) -> str:
    key = os.path.realpath(path)  # one file, whatever the links that name it
    with _OPEN_LOCK:
        if key in _OPEN:
            raise ValueError(
                "another JsonlWriter of this process has it open (two runs given one path "
                "would interleave their lines); give each run its own file, e.g. "
                "lambda run: [JsonlWriter(f'{root}/run_{run}.jsonl')]"
            )
        _OPEN.add(key)
    return key


def _release(key: str) -> None:
    with _OPEN_LOCK:
        _OPEN.discard(key)


class ForeignFileError(ValueError):
    """`JsonlWriter` was given a file that holds something other than its own records (the
    file is left untouched)."""


def _parses(data: bytes) -> bool:
    try:
        json.loads(data)
    except ValueError:
        return False
    return True


def _is_cut_record(tail: bytes, after_records: bool) -> bool:
    """Whether an unterminated last line is provably a record of this writer cut short (it
    writes a line and its newline in one call, so a whole JSON value is never its cut)."""
    if _parses(tail):
        return False
    if _CUT_HEAD.match(tail):
        return True
    # Cut inside the head (`{`, `{"st`, `{"step":1`): only after this writer's records.
    return after_records and (_HEAD.startswith(tail) or tail.startswith(_HEAD))


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
            raise ForeignFileError(
                f"JsonlWriter: {path!r} exists and its line {i + 1} is not a JsonlWriter "
                "record; the file was left untouched. Pass the path of a new file or of "
                "this writer's own JSON lines."
            )
    tail = data[len(whole) :]
    if tail and not _is_cut_record(tail, bool(lines)):
        raise ForeignFileError(
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
