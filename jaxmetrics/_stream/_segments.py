"""Per-group period statistics by segment reductions over the group index.

A grouped metric reports one stream row per group beside its overall row. Rows whose
statistics are period statistics only (count, sum, mean, std, min, max, non-finite
counts) need no ordered data per row: one pass over the metric's `[envs]` values, each
env's value added into the slot of its group (a scatter into `[groups]`), gives every
group's batch statistics at a cost that does not grow with the number of groups. The
other rows (the overall rows, and group rows with an EMA, a window, a histogram or a
sketch) are folded as rows (`_fold.add_with_counts`), and both halves' fields are put back
in the stream's row order: the state keeps its layout.

The segment rows' batch statistics are those of `_fold.batch_two_pass` (count, sum, min,
max, then the moments around the running mean, or the batch's mean for an empty
period), per group: the same numbers the rows' masked reduction gives, to float32
rounding.
"""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from .._count import Count
from .._sharding import gathered
from ._fold import add_with_counts, counts_width, period_update
from ._state import StreamPlan, StreamState

# The [R] fields `period_update` changes; the segment rows' other [R] fields (EMA,
# window positions) stay as they are.
PERIOD_FIELDS = ("count", "mean", "m2", "m2_c", "sum", "sum_c", "min", "max", "nonfinite", "steps")
_OTHER_ROW_FIELDS = ("ema", "ema_off", "ema_w", "ema_n")


@dataclasses.dataclass(frozen=True)
class SegmentPlan:
    """Which rows of a stream are folded by segment reductions.

    `blocks`: per segment source (a row of the segment inputs), the stream row of its
    first group and its number of groups; its groups are that many consecutive rows.
    `dense`: the other rows, folded as rows by `dense_plan`, a plan of those rows alone
    (they hold every EMA, window, histogram and sketch row of the stream)."""

    blocks: tuple[tuple[int, int], ...]
    dense: tuple[int, ...]
    dense_plan: StreamPlan

    @classmethod
    def build(cls, plan: StreamPlan, blocks: tuple[tuple[int, int], ...]) -> "SegmentPlan":
        segment = {first + j for first, n in blocks for j in range(n)}
        dense = tuple(r for r in range(len(plan.rows)) if r not in segment)
        return cls(blocks, dense, StreamPlan.build([plan.rows[r] for r in dense], plan.dtype))

    @property
    def width(self) -> int:
        """Group slots per source: the most groups of any source."""
        return max(n for _, n in self.blocks)

    @property
    def groups(self) -> np.ndarray:
        """Per source, its number of groups (int32)."""
        return np.array([n for _, n in self.blocks], np.int32)


def _take(x: jax.Array, at: np.ndarray) -> jax.Array:
    # One gather of static indices (XLA fuses it into its neighbours), where slices of
    # each run of rows are one more kernel each.
    return jnp.take(x, at, axis=0, indices_are_sorted=True, unique_indices=True)


def _dense_rows(sp: SegmentPlan, x: jax.Array) -> jax.Array:
    """The dense rows of a stream field `x[R]`."""
    return _take(x, np.asarray(sp.dense, np.int32))


def _segment_rows(sp: SegmentPlan, x: jax.Array) -> jax.Array:
    """The segment rows of a stream field `x[R]` as `[sources, width]` (slots past a
    source's groups repeat its last group and are never read back)."""
    at = [[a + min(j, n - 1) for j in range(sp.width)] for a, n in sp.blocks]
    return _take(x, np.asarray(at, np.int32).reshape(-1)).reshape(len(sp.blocks), sp.width)


def _assembled(sp: SegmentPlan, dense: jax.Array, segment: jax.Array) -> jax.Array:
    """A stream field `[R]` from its dense rows `[R_d]` and segment rows
    `[sources, width]`, in the stream's row order."""
    at = np.zeros(len(sp.dense) + sum(n for _, n in sp.blocks), np.int32)
    at[list(sp.dense)] = np.arange(len(sp.dense))
    for i, (first, n) in enumerate(sp.blocks):
        at[first : first + n] = len(sp.dense) + i * sp.width + np.arange(n)
    flat = jnp.concatenate([dense, segment.reshape(-1)])
    return jnp.take(flat, at, axis=0, unique_indices=True)


def _tree(f, *xs):
    return jax.tree.map(f, *xs)


def add_segmented(
    plan: StreamPlan,
    sp: SegmentPlan,
    s: StreamState,
    values: jax.Array,
    mask: jax.Array,
    nonfinite: jax.Array,
    counted: jax.Array,
    counts: Count,
    segments: tuple[jax.Array, jax.Array, jax.Array, jax.Array],
    fused: bool = False,
) -> tuple[StreamState, Count]:
    """`_fold.add_with_counts` for a stream with segment rows: `values`, `mask` and
    `nonfinite` (`[R_d, B]`) are the dense rows' batch; `segments` are the segment
    sources' `values`, `ok` (folded), `bad` (non-finite counts) and group index
    (`[sources, B]`; an index out of a source's range joins none of its groups)."""
    dense_state = s._replace(
        **{f: _tree(lambda x: _dense_rows(sp, x), getattr(s, f)) for f in PERIOD_FIELDS},
        **{f: _dense_rows(sp, getattr(s, f)) for f in _OTHER_ROW_FIELDS},
        windows=tuple(
            w._replace(pos=_dense_rows(sp, w.pos), filled=_dense_rows(sp, w.filled))
            for w in s.windows
        ),
    )
    # The counts ride on the dense rows' fold, padded to its own width (the entries past
    # the counted rows stay zero).
    full = counts.lo.shape[0]
    width = counts_width(sp.dense_plan, counted.shape[0])
    pad = max(width - full, 0)
    mine = _tree(lambda c: jnp.pad(c, (0, pad))[:width], counts)
    dense, mine = add_with_counts(
        sp.dense_plan, dense_state, values, mask, nonfinite, counted, mine, fused
    )
    counts = _tree(lambda c, m: jnp.concatenate([m, c[width:]])[:full], counts, mine)

    seg_state = s._replace(
        **{f: _tree(lambda x: _segment_rows(sp, x), getattr(s, f)) for f in PERIOD_FIELDS}
    )
    shift = seg_state.mean
    batch = segment_batch(*(gathered(a) for a in segments), sp.groups, shift)
    seg = period_update(seg_state, *batch, shift)

    def assembled(f: str):
        if f in PERIOD_FIELDS:
            return _tree(lambda d, g: _assembled(sp, d, g), getattr(dense, f), getattr(seg, f))
        return _assembled(sp, getattr(dense, f), _segment_rows(sp, getattr(s, f)))

    def ring_field(d: jax.Array, old: jax.Array) -> jax.Array:
        return _assembled(sp, d, _segment_rows(sp, old))

    new = dense._replace(
        **{f: assembled(f) for f in PERIOD_FIELDS + _OTHER_ROW_FIELDS},
        windows=tuple(
            d._replace(pos=ring_field(d.pos, w.pos), filled=ring_field(d.filled, w.filled))
            for d, w in zip(dense.windows, s.windows)
        ),
    )
    return new, counts


def segment_batch(
    values: jax.Array,
    ok: jax.Array,
    bad: jax.Array,
    group: jax.Array,
    groups: np.ndarray,
    shift: jax.Array,
) -> tuple[jax.Array, ...]:
    """Per source and group (`[sources, width]`): the batch's count, sum, min, max, the
    mean and squared deviations of its values less `shift`, and its non-finite count,
    of the entries of `values[sources, B]` where `ok` whose `group` is that group.
    `_fold.batch_two_pass` per group, each pass one scatter per statistic into the
    group slots; `bad` (int32) counts for the entry's group whether or not it is `ok`."""
    dt = values.dtype
    sources, width = shift.shape
    size = sources * width
    # One flat slot per source and group (an index pair per entry scatters at half the
    # speed on a CPU); `size` is past every slot: entries scattered there are dropped.
    first = jnp.arange(0, size, width, dtype=jnp.int32)[:, None]
    inside = (group >= 0) & (group < jnp.asarray(groups)[:, None])
    slot = jnp.where(inside, first + group, size).reshape(-1)
    at = jnp.where(ok.reshape(-1), slot, size)

    def scatter(x: jax.Array, where: jax.Array, fill, how: str) -> jax.Array:
        into = jnp.full((size,), fill, x.dtype)
        out = getattr(into.at[where], how)(x.reshape(-1), mode="drop")
        return out.reshape(sources, width)

    k = scatter(jnp.ones_like(at), at, 0, "add")
    bsum = scatter(values, at, 0, "add")
    bmin = scatter(values, at, jnp.inf, "min")
    bmax = scatter(values, at, -jnp.inf, "max")
    nbad = scatter(bad, slot, 0, "add")
    kd = jnp.maximum(k, 1).astype(dt)
    pivot = jnp.where(shift != 0, shift, bsum / kd)
    d = values - pivot.reshape(-1).at[at].get(mode="fill", fill_value=0).reshape(values.shape)
    s1 = scatter(d, at, 0, "add")
    s2 = scatter(d * d, at, 0, "add")
    mb = s1 / kd
    m2b = jnp.maximum(s2 - s1 * mb, 0)
    return k, bsum, bmin, bmax, mb + (pivot - shift), m2b, nbad
