"""A batch's stream rows as selections of source rows: each row one source row of the
batch, over every entry or masked to the entries of one group.

A grouped metric reports one stream row per group beside its overall row, each the
metric's values masked to that group's envs. Kept as the source rows, the group index
and a static table of which source and group each row selects, the batch that a step
hands the fold (and splits into env shards) is no bigger with groups than without; the
fold reads the rows as arrays (`dense`), each masked to its group.
"""

import dataclasses
import functools
from collections.abc import Callable, Sequence

import jax
import jax.numpy as jnp
import numpy as np

from ._state import take_rows


@functools.partial(
    jax.tree_util.register_dataclass,
    data_fields=["values", "ok", "bad", "ids"],
    meta_fields=["src", "kind", "group"],
)
@dataclasses.dataclass(frozen=True)
class Selected:
    """Row r of the batch is source row `src[r]` of `values` (`[S, B]`), masked in where
    `ok` and, for `kind[r] >= 0`, where grouping `kind[r]`'s index (`ids[kind[r]]`,
    `[K, B]` int32) is `group[r]`; its non-finite flags (`bad`, integers) count in the same
    entries of that group whether or not they are `ok`. `kind[r] == -1`: every entry."""

    values: jax.Array
    ok: jax.Array
    bad: jax.Array
    ids: jax.Array
    src: tuple[int, ...]
    kind: tuple[int, ...]
    group: tuple[int, ...]

    @classmethod
    def every(cls, values: jax.Array, mask: jax.Array, nonfinite: jax.Array) -> "Selected":
        """Each source row as it is: rows `[R, B]` with their own mask and flags."""
        rows = values.shape[0]
        # No grouping, laid out like the values (an env axis split over devices stays so).
        ids = values[:0].astype(jnp.int32)
        return cls(values, mask, nonfinite, ids, tuple(range(rows)), (-1,) * rows, (0,) * rows)

    @property
    def grouped(self) -> bool:
        return any(k >= 0 for k in self.kind)

    def take(self, rows: tuple[int, ...]) -> "Selected":
        """The selection of `rows` (static) only."""
        pick = lambda a: tuple(a[r] for r in rows)  # noqa: E731
        return dataclasses.replace(
            self, src=pick(self.src), kind=pick(self.kind), group=pick(self.group)
        )

    def arrays(self, fn: Callable[[jax.Array], jax.Array]) -> "Selected":
        """`fn` applied to each source array and the group index."""
        return dataclasses.replace(
            self, values=fn(self.values), ok=fn(self.ok), bad=fn(self.bad), ids=fn(self.ids)
        )

    def group_index(self, kinds: Sequence[int] | np.ndarray) -> jax.Array:
        """Per grouping in `kinds` (-1: none), its group index (`[n, B]` int32); 0 for
        every entry where none, so that a row of every entry is group 0 of it."""
        ids = jnp.concatenate([self.ids, jnp.zeros_like(self.ids[:1])])
        kinds = np.asarray(kinds, np.int32)
        return jnp.take(ids, np.where(kinds < 0, self.ids.shape[0], kinds), axis=0)

    def dense(self) -> tuple[jax.Array, jax.Array, jax.Array]:
        """The rows as arrays `[R, B]`: values, mask and non-finite flags."""
        if not self.grouped:
            values, ok, bad = (take_rows(self.src, a) for a in (self.values, self.ok, self.bad))
            return values, ok, bad
        src = np.asarray(self.src, np.int32)
        take = lambda a: jnp.take(a, src, axis=0)  # noqa: E731
        match = self.group_index(self.kind) == jnp.asarray(self.group, jnp.int32)[:, None]
        return take(self.values), take(self.ok) & match, jnp.where(match, take(self.bad), 0)
