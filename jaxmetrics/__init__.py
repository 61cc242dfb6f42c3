"""jaxmetrics: a JAX-functional metrics pytree for jitted, vectorized RL environments.

Please don't use symbols from the private `_*` modules: everything public is re-exported here.
"""

from ._core._checkpoint import MetricsCheckpoint as MetricsCheckpoint
from ._core._count import Count as Count
from ._core._metrics import Metrics as Metrics
from ._core._metrics_state import MetricsState as MetricsState
from ._core._reductions import discounted as discounted
from ._core._report import Report as Report
from ._core._spec import Logged as Logged
from ._core._spec import Term as Term
from ._core._spec import ema as ema
from ._core._spec import groups as groups
from ._core._spec import histogram as histogram
from ._core._spec import quantiles as quantiles
from ._core._spec import window as window
from ._core._success import success_rate as success_rate
from ._core._tags import TagInfo as TagInfo
from ._host._history import History as History
from ._host._logger import Logger as Logger
from ._host._logger import NonFiniteError as NonFiniteError
from ._host._logger import ReportsLostError as ReportsLostError
from ._host._logger import WriterError as WriterError
from ._host._logger import WriterTimeoutError as WriterTimeoutError
from ._host._record import HistogramData as HistogramData
from ._host._record import Record as Record
from ._host._record import Writer as Writer
from ._host._wrap_step import Transition as Transition
from ._host._wrap_step import wrap_step as wrap_step
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
    "Record",
    "Report",
    "TagInfo",
    "TensorBoardWriter",
    "Term",
    "Transition",
    "WandbWriter",
    "Writer",
    "WriterError",
    "WriterTimeoutError",
    "discounted",
    "ema",
    "groups",
    "histogram",
    "quantiles",
    "success_rate",
    "window",
    "wrap_step",
]
