"""The compiled side of a `Logger`: the report program of a spec, shared by its loggers.

Per spec, number of runs and `include_running`: the `Packer` of the report (its layout
from shapes alone, so the host side works before any trace), the in-graph `compute`
(state -> packed report, what `emit` and `record` run) and the flush program (compute
and `reset_period` in one jitted call, compiled once per mesh and state shardings).

They are kept in a `WeakKeyDictionary` keyed by the `Metrics` object: every Logger of a
spec shares them (a new Logger compiles nothing new), and they go when the spec does.
The spec's `MetricsState.spec` identity cannot be the key: it is shared by equal specs
and never freed. No cached value may hold the `Metrics` strongly, or its entry would
never go: the programs reach it through a weak reference (a Logger that runs them holds
its spec).
"""

import functools
import weakref
from collections.abc import Callable
from typing import Any, NamedTuple

import jax

from .._core import _stream, _tags
from .._core._metrics import Metrics
from .._core._metrics_state import MetricsState
from .._core._report import Report
from .._core._sharding import mesh_of, placed, replicated
from .._core._tags import TagInfo
from ._record import derived_tags
from ._transfer import Packer

Packed = tuple[jax.Array, jax.Array]  # (floats [F], counts uint32 [2, K]), see `Packer`


class StateShardings:
    """A state's tree of shardings as a key of the compiled flush (compared by value)."""

    def __init__(self, tree: MetricsState):
        self.fresh = _uncarried(tree.finished)  # the shardings of what a flush makes afresh
        leaves, treedef = jax.tree.flatten(tree)
        self._key = (tuple(leaves), treedef)

    def __eq__(self, other: object) -> bool:
        return isinstance(other, StateShardings) and self._key == other._key

    def __hash__(self) -> int:
        return hash(self._key)


class ReportPrograms(NamedTuple):
    """The report programs of one spec, number of runs and `include_running`.

    Attributes:
      packer: packs and unpacks the report.
      compute: in-graph, one run's state -> its packed report.
      report_and_reset: host, a concrete state (`[runs]` leading axis for several runs)
        -> `(report, finished, logged)`: the packed report as one array (`[runs]` of
        `Packer.joined`) and the reset statistics, by the jitted program compiled for the
        state's mesh and shardings.
    """

    packer: Packer
    compute: Callable[[MetricsState], Packed]
    report_and_reset: Callable[[MetricsState], tuple[jax.Array, Any, Any]]


_CACHE: weakref.WeakKeyDictionary[Metrics, dict[tuple[int, bool], ReportPrograms]] = (
    weakref.WeakKeyDictionary()
)


def report_programs(metrics: Metrics, runs: int, include_running: bool) -> ReportPrograms:
    """The report programs of `metrics` (built once, then shared)."""
    per_spec = _CACHE.setdefault(metrics, {})
    key = (runs, include_running)
    if key not in per_spec:
        per_spec[key] = _build(metrics, runs, include_running)
    return per_spec[key]


def tag_table(metrics: Metrics, include_running: bool) -> tuple[TagInfo, ...]:
    """A logger's static tags: the spec's, running values on request, derived ones."""
    running = [
        _tags.info(metrics.prefixes["episode"], "episode", name, "running")
        for name, spec in metrics.metric_specs.items()
        if include_running and spec.reduce is not None and spec.group is None
    ]
    return metrics.tags + tuple(running) + tuple(derived_tags(metrics.tags))


def _build(metrics: Metrics, runs: int, include_running: bool) -> ReportPrograms:
    metrics_ref = weakref.ref(metrics)

    def report(state: MetricsState) -> Report:
        return metrics_ref().compute(state, include_running=include_running)  # type: ignore[union-attr]

    shapes = jax.eval_shape(lambda: report(metrics.init(1)))
    infos = [i for i in tag_table(metrics, include_running) if i.tag in shapes]
    # Each statistic's tags side by side: the packed arrays are then a few runs of the
    # report's columns (a gather each, `Packer.pack`), not a piece per tag.
    layout = [i.tag for i in sorted(infos, key=lambda i: i.stat)]
    packer = Packer(shapes, [i.tag for i in infos], metrics.dtype, layout)

    def compute(state: MetricsState) -> Packed:
        return packer.pack(report(state))

    def compute_reset(state: MetricsState) -> tuple[jax.Array, Any, Any]:
        # Only what the new period makes afresh: a jitted call's every output is a new
        # buffer, so the fields it carries on would be copied at every flush.
        new = metrics_ref().reset_period(state)  # type: ignore[union-attr]
        words = packer.joined(compute(state))
        return words, _uncarried(new.finished), _uncarried(new.logged)

    batched = compute_reset if runs == 1 else jax.vmap(compute_reset)

    @functools.cache
    def compiled(mesh: jax.sharding.Mesh | None, shardings: Any) -> Callable[..., Any]:
        # On a sharded state's mesh: the packed report whole on every device, so that
        # every process can read its copy (O(metrics) bytes cross devices), and the
        # reset statistics split as they came in, so the next steps stay shard-local.
        def run(state: MetricsState) -> tuple[jax.Array, Any, Any]:
            words, finished, logged = batched(state)
            if mesh is None:
                return words, finished, logged
            return replicated(words, mesh), placed(finished, shardings.fresh), logged

        return jax.jit(run)

    def report_and_reset(state: MetricsState) -> tuple[jax.Array, Any, Any]:
        mesh = mesh_of(state)
        shardings = (
            None if mesh is None else StateShardings(jax.tree.map(lambda x: x.sharding, state))
        )
        words, finished, logged = compiled(mesh, shardings)(state)
        return words, _carried(finished, state.finished), _carried(logged, state.logged)

    return ReportPrograms(packer, compute, report_and_reset)


def _uncarried(s: _stream.StreamState | None) -> _stream.StreamState | None:
    return None if s is None else _stream.uncarried(s)


def _carried(new: _stream.StreamState | None, old: Any) -> _stream.StreamState | None:
    return None if new is None else _stream.carried(new, old)
