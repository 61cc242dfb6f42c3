"""`Report`: what `Metrics.compute` returns, a mapping tag -> statistic whose pytree
leaves are whole columns (one array per statistic over the metrics that have it).

A report has one tag per metric, group and statistic: thousands with many groups. As a
dict of one array per tag, every tag was an output of the jitted program (and a slice in
it), and XLA's compile time and memory grew faster than linearly with them: minutes at
1,000 groups. The columns are a few arrays whatever the number of groups; a tag's value
is cut from its column only when asked for, and `to_host` cuts them all on the host.
"""

import dataclasses
from collections.abc import Iterator, Mapping
from typing import Any

import jax
import numpy as np

from . import _count
from ._count import Count

Column = jax.Array | Count


@dataclasses.dataclass(frozen=True, eq=False)
class ReportLayout:
    """Where each tag of a report lies in its columns.

    Attributes:
      key: what determines the layout (the spec's identity and `include_running`):
        layouts, and so the pytree structures of reports, are equal when their keys are.
      tags: every tag, in report order.
      at: tag -> (column, row): its value is that row of that column.
      trailing: per column, the number of axes after its row axis (1 for histograms and
        window contents, else 0); leading axes (vmap, scan) come before the row axis.
    """

    key: tuple
    tags: tuple[str, ...]
    at: Mapping[str, tuple[int, int]]
    trailing: tuple[int, ...]

    def __eq__(self, other: object) -> bool:
        return isinstance(other, ReportLayout) and self.key == other.key

    def __hash__(self) -> int:
        return hash(self.key)


def _row(a: Any, j: int, trailing: int) -> Any:
    """Row `j` of the column array `a` (a JAX or numpy array, or the `ShapeDtypeStruct` of
    one from `jax.eval_shape`), its row axis `trailing` axes from the end."""
    axis = len(a.shape) - 1 - trailing
    if isinstance(a, jax.ShapeDtypeStruct):
        return jax.ShapeDtypeStruct(a.shape[:axis] + a.shape[axis + 1 :], a.dtype)
    return a[(slice(None),) * axis + (j,)]


@jax.tree_util.register_pytree_node_class
class Report(Mapping[str, Any]):
    """A report, as `Metrics.compute` returns it: tag -> statistic (an array, or a `Count`
    of exact counts), in the order of the tags.

    It reads like a dict (`report[tag]`, `in`, iteration, `len`, `items()`); as a pytree
    its leaves are one column per statistic, not one array per tag, so that a jitted
    `compute` has a few outputs whatever the number of metrics and groups, and a stack of
    reports (`vmap`, `lax.scan`) stacks the columns: `report[tag]` then has the stacked
    axes. `Metrics.to_host` turns it into a plain dict of host values.
    """

    __slots__ = ("columns", "layout")

    def __init__(self, layout: ReportLayout, columns: tuple[Any, ...]):
        self.layout = layout
        self.columns = columns

    def __getitem__(self, tag: str) -> Any:
        c, j = self.layout.at[tag]
        trailing = self.layout.trailing[c]
        return jax.tree.map(lambda a: _row(a, j, trailing), self.columns[c])

    def __contains__(self, tag: object) -> bool:
        return tag in self.layout.at

    def __iter__(self) -> Iterator[str]:
        return iter(self.layout.tags)

    def __len__(self) -> int:
        return len(self.layout.tags)

    def __repr__(self) -> str:
        return f"Report({dict(self)!r})"

    def tree_flatten(self) -> tuple[tuple[Any, ...], ReportLayout]:
        return self.columns, self.layout

    @classmethod
    def tree_unflatten(cls, layout: ReportLayout, columns: Any) -> "Report":
        return cls(layout, tuple(columns))


def to_host(report: Report) -> dict[str, Any]:
    """A fetched report (numpy columns, e.g. from `jax.device_get`) as tag -> host value:
    floats, exact Python ints, numpy arrays (int64 for counts) where a value is not a
    scalar, as `Metrics.to_host` gives them."""
    host = Report(
        report.layout,
        tuple(_count.to_int(c) if isinstance(c, Count) else np.asarray(c) for c in report.columns),
    )
    counts = [isinstance(c, Count) for c in report.columns]
    out: dict[str, Any] = {}
    for tag in host:
        v = host[tag]
        if np.ndim(v):
            out[tag] = v
        else:
            out[tag] = int(v) if counts[host.layout.at[tag][0]] else float(v)
    return out
