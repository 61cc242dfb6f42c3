"""Writers behind one small protocol (`jaxmetrics.Writer`); each imports its backend only
when created."""

from ._console import ConsoleWriter as ConsoleWriter
from ._jsonl import ForeignFileError as ForeignFileError
from ._jsonl import JsonlWriter as JsonlWriter
from ._memory import MemoryWriter as MemoryWriter
from ._mlflow import MLflowWriter as MLflowWriter
from ._tensorboard import TensorBoardWriter as TensorBoardWriter
from ._wandb import WandbWriter as WandbWriter
