"""The report's trip to the host, packed in-graph into two flat arrays.

A report holds ~10 small statistics per metric (and per group); copying and fetching
each one costs a dispatch and a Python call per leaf, which dominates a flush long before
the bytes do. `pack` concatenates every float statistic into one vector and every exact count (the
`Count` hi/lo words) into one `[2, K]` uint32 array, and `joined` makes those one uint32
array, so a flush moves one.
`unpack` restores the host report (floats, exact Python ints, numpy arrays), like
`Metrics.to_host`.
"""

import math
from collections.abc import Iterable, Sequence
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from .._core import _count
from .._core._count import Count
from .._core._report import Report


class _Slot(NamedTuple):
    tag: str
    is_count: bool
    offset: int
    shape: tuple[int, ...]


class Packer:
    """Packs the reports of one spec; the layout is fixed when the packer is built.

    Args:
      report: the report's shapes: `jax.eval_shape` of `Metrics.compute`, a `Report` of
        `jax.ShapeDtypeStruct` columns.
      order: the tags in the order `unpack` returns them (every tag of `report`).
      dtype: the float dtype of the packed statistics.
      layout: the tags in the order they lie in the packed arrays (default `order`).

    Attributes:
      num_floats: F, the length of the packed floats.
      num_counts: K, the columns of the packed counts.
      dtype: the float dtype of the packed statistics.
    """

    def __init__(
        self,
        report: Report,
        order: Sequence[str],
        dtype: Any,
        layout: Sequence[str] | None = None,
    ):
        layout = order if layout is None else layout
        if sorted(order) != sorted(report) or sorted(layout) != sorted(report):
            raise ValueError("Packer: `order` and `layout` must list every tag of the report once.")
        self.dtype = jnp.dtype(dtype)
        # A tag's shape is its column's less the row axis: read off the columns, not cut
        # from them tag by tag (tens of thousands of tags with many groups).
        counted = [isinstance(c, Count) for c in report.columns]
        shapes = [tuple(jax.tree.leaves(c)[0].shape[1:]) for c in report.columns]
        slots, size = {}, {False: 0, True: 0}
        # The packed arrays as runs of tags of one column, each run one gather of static
        # rows: a few ops whatever the number of tags (a slice per tag was thousands).
        runs: dict[bool, list[tuple[int, list[int]]]] = {False: [], True: []}
        for tag in layout:
            c, j = report.layout.at[tag]
            kind = counted[c]
            slots[tag] = _Slot(tag, kind, size[kind], shapes[c])
            size[kind] += math.prod(shapes[c])
            if runs[kind] and runs[kind][-1][0] == c:
                runs[kind][-1][1].append(j)
            else:
                runs[kind].append((c, [j]))
        self._slots = tuple(slots[tag] for tag in order)
        self.num_floats, self.num_counts = size[False], size[True]
        self._runs = {k: [(c, np.asarray(at, np.int32)) for c, at in v] for k, v in runs.items()}
        self._report_layout = report.layout
        self._shapes = _shapes(report)

    def pack(self, report: Report) -> tuple[jax.Array, jax.Array]:
        """In-graph: `(floats [F], counts uint32 [2, K])`.

        Raises:
          ValueError: the report's tags or shapes differ from the layout.
        """
        if not isinstance(report, Report) or report.layout != self._report_layout:
            raise ValueError(self._DIFFERS)
        if _shapes(report) != self._shapes:
            raise ValueError(self._DIFFERS)

        def taken(column: jax.Array, at: np.ndarray) -> jax.Array:
            whole = np.array_equal(at, np.arange(column.shape[0]))
            return jnp.ravel(column if whole else column[at])

        floats = [taken(report.columns[c], at).astype(self.dtype) for c, at in self._runs[False]]
        counts = [[taken(a, at) for a in report.columns[c]] for c, at in self._runs[True]]
        f = jnp.concatenate(floats) if floats else jnp.zeros((0,), self.dtype)
        c = (
            jnp.stack([jnp.concatenate(words) for words in zip(*counts)])
            if counts
            else jnp.zeros((2, 0), jnp.uint32)
        )
        return f, c

    def joined(self, packed: tuple[jax.Array, jax.Array]) -> jax.Array:
        """In-graph: `pack`'s floats and counts as one uint32 array `[F * w + 2K]` (w the
        words of a float), so that a flush copies one array to the host, not two."""
        floats, counts = packed
        bits = jax.lax.bitcast_convert_type(floats, jnp.uint32).reshape(-1)
        return jnp.concatenate([bits, counts.reshape(-1)])

    def parted(self, words: np.ndarray | jax.Array) -> tuple[np.ndarray, np.ndarray]:
        """Host: `joined`'s inverse, over any leading axes: `(floats [..., F], counts
        [..., 2, K])`."""
        words = np.asarray(words)
        n = self.num_floats * self.dtype.itemsize // 4
        floats = np.ascontiguousarray(words[..., :n]).view(self.dtype)
        return floats, words[..., n:].reshape(*words.shape[:-1], 2, self.num_counts)

    _DIFFERS = (
        "the report's layout differs from the one the Logger was built for; a Logger "
        "serves one Metrics spec (and one include_running setting)."
    )

    def totals(self, counts: Any, runs: int) -> list[dict[str, int]]:
        """Host: per run, every scalar count (the counters' totals among them) from packed
        counts of shape `[runs, 2, K]` (or `[2, K]` for one run)."""
        c = np.reshape(np.asarray(counts), (runs, 2, -1))
        tags = [s.tag for s in self._slots if s.is_count and s.shape == ()]
        return [self.unpack(None, c[r], tags) for r in range(runs)]

    def any_nonzero(self, counts: np.ndarray, tags: Iterable[str]) -> bool:
        """Host: whether any of the count `tags` is non-zero in one element's counts."""
        wanted = set(tags)
        cols = [
            i
            for s in self._slots
            if s.is_count and s.tag in wanted
            for i in range(s.offset, s.offset + math.prod(s.shape))
        ]
        return bool(counts[:, cols].any())

    def unpack(
        self, floats: np.ndarray | None, counts: np.ndarray, tags: Iterable[str] | None = None
    ) -> dict[str, Any]:
        """Host: the report (or only `tags`) from one element's packed arrays; scalars
        become floats, counts exact Python ints (int64 arrays when not scalar)."""
        wanted = None if tags is None else set(tags)
        out: dict[str, Any] = {}
        for s in self._slots:
            if wanted is not None and s.tag not in wanted:
                continue
            n = math.prod(s.shape)
            if s.is_count:
                part = counts[:, s.offset : s.offset + n]
                out[s.tag] = _count.to_int(
                    Count(part[0].reshape(s.shape), part[1].reshape(s.shape))
                )
            else:
                assert floats is not None
                a = floats[s.offset : s.offset + n].reshape(s.shape)
                out[s.tag] = float(a) if a.ndim == 0 else a
        return out


def _shapes(report: Report) -> list[tuple[int, ...]]:
    return [tuple(a.shape) for a in jax.tree.leaves(report)]
