"""jaxmetrics: a JAX-functional metrics pytree for jitted, vectorized RL environments.

Please don't use symbols from the private `_*` modules: everything public is re-exported here.
"""

from ._count import Count as Count
from ._metrics import Metrics as Metrics
from ._metrics import NonFiniteError as NonFiniteError
from ._metrics import TagInfo as TagInfo
from ._spec import Ema as Ema
from ._spec import Histogram as Histogram
from ._spec import Logged as Logged
from ._spec import Term as Term
from ._spec import Window as Window
from ._spec import ema as ema
from ._spec import histogram as histogram
from ._spec import window as window
from ._state import MetricsState as MetricsState
from ._step import Transition as Transition
from ._step import wrap_step as wrap_step

__version__ = "0.1.0"

__all__ = [
    "Count",
    "Ema",
    "Histogram",
    "Logged",
    "Metrics",
    "MetricsState",
    "NonFiniteError",
    "TagInfo",
    "Term",
    "Transition",
    "Window",
    "ema",
    "histogram",
    "window",
    "wrap_step",
]
