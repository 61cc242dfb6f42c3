"""The argument checks shared by the writers: paths, directories, hyperparameters."""

import os
from collections.abc import Mapping
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


def check_hparams(hparams: Any, who: str, kind: str = "") -> dict[str, bool | int | float | str]:
    """`hparams` (None: none) as a dict of names to bool/int/float/str, or an error naming
    `who` and the offending entry; `kind` says what the backend makes of them."""
    if hparams is None:
        return {}
    if not isinstance(hparams, Mapping):
        raise TypeError(f"{who}: hparams must be a dict, got {hparams!r}.")
    for k, v in hparams.items():
        if not isinstance(k, str) or not isinstance(v, bool | int | float | str):
            raise TypeError(
                f"{who}: hparam {k!r}={v!r}: names must be strings and values bool, int, "
                f"float or str{kind}."
            )
    return dict(hparams)
