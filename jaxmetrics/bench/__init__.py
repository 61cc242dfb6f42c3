"""Benchmarks: what jaxmetrics costs, against the bare rollout and the alternatives.

Run `python -m jaxmetrics.bench --help`; results and how they were taken are in
docs/benchmarks.md. Needs the `brax` extra for the end-to-end scenarios.
"""

from ._cli import FULL as FULL
from ._cli import QUICK as QUICK
from ._cli import Config as Config
from ._cli import main as main
from ._cli import run as run
from ._report import Table as Table

__all__ = ["FULL", "QUICK", "Config", "Table", "main", "run"]
