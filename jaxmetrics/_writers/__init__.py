"""Writers behind one small protocol; each imports its backend only when created."""

from ._console import ConsoleWriter as ConsoleWriter
from ._jsonl import JsonlWriter as JsonlWriter
from ._memory import MemoryWriter as MemoryWriter
from ._record import HistogramData as HistogramData
from ._record import Record as Record
from ._record import Writer as Writer
from ._tensorboard import TensorBoardWriter as TensorBoardWriter
