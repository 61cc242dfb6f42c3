"""Type checks shared by argument validation (the messages stay with each argument)."""

from typing import Any

import numpy as np


def is_int(value: Any) -> bool:
    """A Python or numpy integer; `True`/`False` are not (bool is an int subclass)."""
    return isinstance(value, (int, np.integer)) and not isinstance(value, bool)


def is_number(value: Any) -> bool:
    """An int (see `is_int`) or a float."""
    return is_int(value) or isinstance(value, (float, np.floating))
