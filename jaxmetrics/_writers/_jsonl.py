"""JSON lines: one machine-readable record per run per flush, appended."""

import functools
import json
import os
import re
import stat
import threading
from collections.abc import Sequence
from typing import Any, NamedTuple

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
    `Logger`, so later lines start on a line of their own. Opening an existing file checks
    that each of its lines is byte for byte one this writer writes: its keys in its order,
    compact separators, its values' shapes. A crash can leave the last record unfinished
    (never acknowledged by `Logger.wait`): whole but for its newline, it gets the newline;
    cut shorter, it is dropped when that is provably this writer's record: the start of a
    line this writer writes, after whole records of this writer or holding its first two
    keys (`{"step":<int>,"wall_time":`). Such a repair is made in place, so the file's mode,
    a symlinked path's link and other hard links to it are kept. A file holding anything
    else (another program's JSON, text) is refused with `jaxmetrics.ForeignFileError` and
    left untouched.

    Args:
      path: the file; its directory is created if missing. Checked here: an invalid or
        unwritable path raises `ValueError` naming it, a file that is not this writer's
        JSON lines `ForeignFileError` (a `ValueError`).
      purge_step: when resuming a run from a checkpoint taken at an earlier step: lines
        with a step >= `purge_step` are dropped from the existing file, so the resumed
        run's records replace them instead of following them (the same rule as
        `TensorBoardWriter(purge_step=...)`). Last lines are cut off in place; lines
        followed by kept ones make an atomic rewrite, a new file (other hard links to
        the old one keep it).

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
            self._key = _identity(p)
            _claim(self._key)
        except (OSError, ValueError) as e:
            raise ValueError(
                f"JsonlWriter: cannot open {p!r} for appending: {e}. Pass a writable file path."
            ) from None
        try:
            self._key = _repair(p, purge_step, self._key)
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
        self._file.append(_line(record_to_json(record)))

    def close(self) -> None:
        """Closes the file (another JsonlWriter may then open it)."""
        try:
            self._file.close()
        finally:
            _release(self._key)


def _line(obj: dict[str, Any]) -> bytes:
    """The line `write` writes for `obj`, `record_to_json`'s object."""
    return (json.dumps(obj, allow_nan=False, separators=(",", ":")) + "\n").encode()


class _Language(NamedTuple):
    """A regular language as two regexes: `whole` matches its strings, `cut` any of their
    prefixes (the empty one too). Both are built from one description, so a cut line is
    judged by the same format as a whole one."""

    whole: bytes
    cut: bytes


def _byte(cls: bytes) -> _Language:
    """One byte out of a regex character class."""
    return _Language(cls, b"(?:" + cls + b")?")


def _lit(text: bytes) -> _Language:
    return _seq(*(_byte(re.escape(bytes([b]))) for b in text))


def _seq(*parts: _Language) -> _Language:
    # A cut of `ab` is a whole `a` and a cut of `b`, or a cut of `a`.
    cut = parts[-1].cut
    for part in reversed(parts[:-1]):
        cut = b"(?:" + part.whole + cut + b"|" + part.cut + b")"
    return _Language(b"".join(part.whole for part in parts), cut)


def _alt(*options: _Language) -> _Language:
    return _Language(
        b"(?:" + b"|".join(o.whole for o in options) + b")",
        b"(?:" + b"|".join(o.cut for o in options) + b")",
    )


def _maybe(part: _Language) -> _Language:
    return _Language(b"(?:" + part.whole + b")?", part.cut)


def _many(part: _Language) -> _Language:
    """Zero or more `part`s."""
    return _Language(b"(?:" + part.whole + b")*", b"(?:" + part.whole + b")*" + part.cut)


def _list(item: _Language) -> _Language:
    """A JSON array of `item`s, compact (as `json.dumps(..., separators=(",", ":"))`)."""
    return _seq(_lit(b"["), _maybe(_seq(item, _many(_seq(_lit(b","), item)))), _lit(b"]"))


# The bytes `write` writes: json.dumps' ints and floats (repr: `1.0`, `1e-05`; never NaN or
# inf), and strings in ASCII (a quote, a backslash and bytes outside " "..."~" escaped).
_DIGIT = _byte(rb"[0-9]")
_INT = _seq(_maybe(_lit(b"-")), _alt(_lit(b"0"), _seq(_byte(rb"[1-9]"), _many(_DIGIT))))
_NUMBER = _seq(
    _INT,
    _maybe(_seq(_lit(b"."), _DIGIT, _many(_DIGIT))),
    _maybe(_seq(_lit(b"e"), _byte(rb"[+-]"), _DIGIT, _many(_DIGIT))),
)
_HEX = _byte(rb"[0-9a-f]")
_ESCAPE = _seq(_lit(b"\\"), _alt(_byte(rb'["\\bfnrt]'), _seq(_lit(b"u"), _HEX, _HEX, _HEX, _HEX)))
_STRING = _seq(_lit(b'"'), _many(_alt(_byte(rb"[ !#-\[\]-~]"), _ESCAPE)), _lit(b'"'))


def _object(value: _Language) -> _Language:
    """A JSON object of string keys to `value`s, compact."""
    pair = _seq(_STRING, _lit(b":"), value)
    return _seq(_lit(b"{"), _maybe(_seq(pair, _many(_seq(_lit(b","), pair)))), _lit(b"}"))


# A line's first two keys: the least a line cut short must hold, with no whole line of this
# writer before it, to be told from other programs' JSON (`{"step":3,"` starts theirs too).
_FIRST_KEYS = _seq(_lit(b'{"step":'), _INT, _lit(b',"wall_time":'))
_HISTOGRAM = _seq(
    *(_lit(b'{"edges":'), _list(_NUMBER), _lit(b',"counts":'), _list(_INT)),
    *(_lit(b',"underflow":'), _INT, _lit(b',"overflow":'), _INT, _lit(b"}")),
)
_RECORD_LINE = _seq(  # record_to_json's object, as `write` writes it
    *(_FIRST_KEYS, _NUMBER, _lit(b',"scalars":'), _object(_NUMBER)),
    *(_lit(b',"histograms":'), _object(_HISTOGRAM)),
    *(_lit(b',"windows":'), _object(_list(_NUMBER)), _lit(b"}\n")),
)
_WHOLE = re.compile(_RECORD_LINE.whole)
_HEAD = re.compile(_FIRST_KEYS.whole)


@functools.cache
def _cut() -> re.Pattern[bytes]:
    # Compiled when a file first ends in a cut line, not at import: the pattern is large.
    return re.compile(_RECORD_LINE.cut)


# The files JsonlWriters of this process hold open, by (st_dev, st_ino): lines of two
# writers (two runs given one file, through one path or two) would interleave with nothing
# to tell them apart.
_OPEN: set[tuple[int, int]] = set()
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


def _identity(path: str) -> tuple[int, int]:
    """The file's (st_dev, st_ino), created if missing: one file whatever the paths
    (symlinks, hard links) that name it."""
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_APPEND, 0o644)
    try:
        st = os.fstat(fd)
    finally:
        os.close(fd)
    return st.st_dev, st.st_ino


def _claim(key: tuple[int, int]) -> None:
    with _OPEN_LOCK:
        if key in _OPEN:
            raise ValueError(
                "another JsonlWriter of this process has it open, through this path or "
                "another link to the file (two runs given one file would interleave their "
                "lines); give each run its own file, e.g. "
                "lambda run: [JsonlWriter(f'{root}/run_{run}.jsonl')]"
            )
        _OPEN.add(key)


def _release(key: tuple[int, int]) -> None:
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


def _is_record(line: bytes) -> bool:
    """Whether `line` is byte for byte a line `write` writes: of its format, and with the
    values it holds written as json.dumps writes them (no tag twice, `1.0` not `1.00`)."""
    return _WHOLE.fullmatch(line) is not None and _line(json.loads(line)) == line


def _foreign(path: str, what: str, fix: str) -> ForeignFileError:
    return ForeignFileError(
        f"JsonlWriter: {path!r} exists and {what}; the file was left untouched. {fix}"
    )


_FIX = "Pass the path of a new file or of this writer's own JSON lines."


def _records(path: str, data: bytes) -> list[bytes]:
    """The file's records, its last one ended if a crash cut only its newline and dropped
    if a crash cut it shorter; `ForeignFileError` if the file is not provably this
    writer's (it is never changed then)."""
    whole = data[: data.rfind(b"\n") + 1]
    lines = whole.splitlines(keepends=True)
    for i, line in enumerate(lines):
        if not _is_record(line):
            raise _foreign(path, f"its line {i + 1} is not a JsonlWriter record", _FIX)
    tail = data[len(whole) :]
    if not tail:
        return lines
    # `write` writes a line and its newline in one call, so an unterminated whole JSON
    # value is this writer's only if it is a whole record of it.
    if _parses(tail):
        if not _is_record(tail + b"\n"):
            raise _foreign(
                path, "ends in an unterminated line that is not a JsonlWriter record", _FIX
            )
        return [*lines, tail + b"\n"]
    if not _cut().fullmatch(tail):
        raise _foreign(
            path,
            "ends in an unterminated line that is neither a JsonlWriter record nor the start "
            "of one",
            _FIX,
        )
    if not lines and not _HEAD.match(tail):
        raise _foreign(
            path,
            f"holds only an unterminated line of {len(tail)} bytes that starts like a "
            "JsonlWriter record but is too short to prove it one (other programs' JSON "
            "starts so too)",
            "If it is this writer's file, cut by a crash in its first record, delete it; "
            "else pass the path of a new file.",
        )
    return lines


def _repair(path: str, purge_step: int | None, key: tuple[int, int]) -> tuple[int, int]:
    """Ends or drops an unfinished last record (see `_records`), and with `purge_step`
    drops every line from that step on. Returns the identity of the file now at `path`,
    which is this writer's claim: `key`, or a rewritten file's (claimed before it
    replaces the old one, so no second writer can find it unclaimed)."""
    with open(path, "rb") as f:
        data = f.read()
    lines = _records(path, data)
    if purge_step is not None:
        lines = [line for line in lines if json.loads(line)["step"] < purge_step]
    keep = b"".join(lines)
    if keep == data:
        return key
    if data.startswith(keep) or keep == data + b"\n":
        # Cutting off the last bytes or ending the last line is done in place: the file
        # keeps its mode, and stays the one file its hard links and this writer's claim name.
        fd = os.open(path, os.O_WRONLY | os.O_APPEND)
        try:
            if len(keep) < len(data):
                os.ftruncate(fd, len(keep))
            else:
                os.write(fd, b"\n")
            os.fsync(fd)
        finally:
            os.close(fd)
        return key
    # Lines purged from before kept ones: a rewrite, atomic so that a crash leaves the old
    # file or the new one whole.
    target = os.path.realpath(path)  # replace the file a symlink points to, not the link
    mode = os.stat(target).st_mode & 0o7777
    tmp = f"{target}.{os.getpid()}.tmp"
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, mode)
    with os.fdopen(fd, "wb") as f:
        f.write(keep)
        f.flush()
        os.fsync(f.fileno())
        st = os.fstat(f.fileno())
    os.chmod(tmp, mode)  # the umask narrowed the mode os.open was given
    new = (st.st_dev, st.st_ino)
    _claim(new)
    try:
        os.replace(tmp, target)
    except BaseException:
        _release(new)
        raise
    _release(key)
    return new
