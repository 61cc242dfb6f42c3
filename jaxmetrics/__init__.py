"""jaxmetrics: a JAX-functional metrics pytree for jitted, vectorized RL environments.

Please don't use symbols from the private `_*` modules: everything public is re-exported here.
"""

from ._checkpoint import MetricsCheckpoint as MetricsCheckpoint
from ._count import Count as Count
from ._history import History as History
from ._logger import Logger as Logger
from ._logger import NonFiniteError as NonFiniteError
from ._logger import ReportsLostError as ReportsLostError
from ._logger import WriterError as WriterError
from ._logger import WriterTimeoutError as WriterTimeoutError
from ._metrics import Metrics as Metrics
from ._reductions import Discounted as Discounted
from ._reductions import discounted as discounted
from ._report import HistogramData as HistogramData
from ._report import Record as Record
from ._report import Writer as Writer
from ._spec import Ema as Ema
from ._spec import Groups as Groups
from ._spec import Histogram as Histogram
from ._spec import Logged as Logged
from ._spec import Quantiles as Quantiles
from ._spec import Term as Term
from ._spec import Window as Window
from ._spec import ema as ema
from ._spec import groups as groups
from ._spec import histogram as histogram
from ._spec import quantiles as quantiles
from ._spec import window as window
from ._state import MetricsState as MetricsState
from ._tags import TagInfo as TagInfo
from ._wrap_step import Transition as Transition
from ._wrap_step import wrap_step as wrap_step
from ._writers import ConsoleWriter as ConsoleWriter
from ._writers import ForeignFileError as ForeignFileError
from ._writers import JsonlWriter as JsonlWriter
from ._writers import MemoryWriter as MemoryWriter
from ._writers import MLflowWriter as MLflowWriter
from ._writers import TensorBoardWriter as TensorBoardWriter
from ._writers import WandbWriter as WandbWriter

__version__ = "0.1.0"

__all__ = [
    "ConsoleWriter",
    "ForeignFileError",
    "Count",
    "Discounted",
    "Ema",
    "Groups",
    "Histogram",
    "HistogramData",
    "History",
    "JsonlWriter",
    "Logged",
    "Logger",
    "MLflowWriter",
    "MemoryWriter",
    "Metrics",
    "MetricsCheckpoint",
    "MetricsState",
    "NonFiniteError",
    "ReportsLostError",
    "Quantiles",
    "Record",
    "TagInfo",
    "TensorBoardWriter",
    "Term",
    "Transition",
    "WandbWriter",
    "Window",
    "Writer",
    "WriterError",
    "WriterTimeoutError",
    "discounted",
    "ema",
    "groups",
    "histogram",
    "quantiles",
    "window",
    "wrap_step",
]
