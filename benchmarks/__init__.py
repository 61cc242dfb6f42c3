"""Benchmarks: what jaxmetrics costs, against the bare rollout and the alternatives.

Not part of the installed package: run them from a checkout's root, `python -m benchmarks
--help`. Results and how they were taken are in docs/benchmarks.md. The end-to-end,
many-device and trainer benchmarks need the `brax` extra (the Playground one `playground`).
"""

from ._cli import FULL as FULL
from ._cli import QUICK as QUICK
from ._cli import Config as Config
from ._cli import main as main
from ._cli import run as run
from ._report import Table as Table

__all__ = ["FULL", "QUICK", "Config", "Table", "main", "run"]
