"""An append-only file that holds whole records only, whatever the disk does.

A full disk (or a quota, or a file size limit) can take part of a record and refuse the
rest. Appended to afterwards, such a file holds a broken record in the middle: a JSON
line merged with the next one, an event file that TensorBoard stops reading there. Here
every record goes out with `os.write` calls on an unbuffered descriptor and is fsync'ed;
if any of that fails, the file is cut back to its last whole record before the error is
raised, and if even that fails, it is cut back before the next record is written.
"""

import os


class AppendFile:
    """Appends byte records to `path` (created if missing), each whole or not at all.

    Attributes:
      path: the file.
      size: bytes of whole records in the file.
    """

    def __init__(self, path: str):
        self.path = path
        self._fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_APPEND, 0o644)
        self.size = os.fstat(self._fd).st_size
        self._torn = False  # a failed append may have left a partial record past `size`

    def append(self, data: bytes) -> None:
        """Writes `data` at the end and syncs it to disk.

        Raises:
          OSError: the write or the sync failed; the file then ends with its last whole
            record again (or will, before the next append).
        """
        if self._torn:
            os.ftruncate(self._fd, self.size)
            self._torn = False
        view = memoryview(data)
        try:
            while view:
                view = view[os.write(self._fd, view) :]
            os.fsync(self._fd)
        except OSError:
            self._torn = True
            try:
                os.ftruncate(self._fd, self.size)
                self._torn = False
            except OSError:
                pass  # retried before the next append
            raise
        self.size += len(data)

    def close(self) -> None:
        """Closes the file (cut back to whole records first, if an append left a part)."""
        try:
            if self._torn:
                os.ftruncate(self._fd, self.size)
        finally:
            os.close(self._fd)
