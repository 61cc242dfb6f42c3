"""The path check shared by the writers that write files."""

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
