"""The path checks shared by the writers that write files."""

import os
from typing import Any


def fs_path(value: Any, who: str, name: str, kind: str) -> str:
    """`value` as a non-empty filesystem path string, or an error naming the argument."""
    try:
        path = os.fspath(value)
    except TypeError:
        raise TypeError(f"{who}: {name} must be a {kind}, got {value!r}.") from None
    if not isinstance(path, str) or not path:
        raise ValueError(f"{who}: {name} must be a non-empty {kind}, got {value!r}.")
    return path


def writable_dir(value: Any, who: str, name: str) -> str:
    """`value` as a directory that exists (created if missing) and is writable, or an
    error naming the argument, before anything is written."""
    path = fs_path(value, who, name, "path")
    try:
        os.makedirs(path, exist_ok=True)
    except (OSError, ValueError) as e:
        raise ValueError(
            f"{who}: cannot create {name} {path!r}: {e}. Pass a writable directory."
        ) from None
    if not os.access(path, os.W_OK | os.X_OK):
        raise ValueError(f"{who}: {name} {path!r} is not writable. Pass a writable one.")
    return path
