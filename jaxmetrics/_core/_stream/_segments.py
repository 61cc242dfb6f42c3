"""Per-group period statistics by segment reductions over the group index.

A grouped metric reports one stream row per group beside its overall row. Rows whose
statistics are period statistics only (count, sum, mean, std, min, max, non-finite
counts) need no ordered data per row: one pass over the metric's `[envs]` values, each
env's value added into the slot of its group (a scatter into `[groups]`), gives every
group's batch statistics at a cost that does not grow with the number of groups. The
other rows (the overall rows, and group rows with an EMA, a window, a histogram or a
sketch) are reduced as rows (`_fold`, over a plan of those rows alone), and both halves'
batch statistics are put in the stream's row order before the one update of the
per-row fields: the state keeps its layout, and that update stays elementwise in it.

The segment rows' batch statistics are those of `_fold.batch_two_pass` (count, sum, min,
max, then the moments around the running mean, or the batch's mean for an empty
period), per group: the same numbers the rows' masked reduction gives, to float32
rounding.
"""

import dataclasses
from collections.abc import Callable
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from ._state import StreamPlan, StreamState
from ._update import Batch

ACCELERATOR_MIN_ENTRIES = 2**22
"""Segment rows x envs from which an accelerator folds group rows as segments: on a GPU
through XLA's kernels the segments lost at 4,096 envs and won with 64 groups of 10 sources
at 16,384 envs (10.5 million entries; docs/benchmarks.md, "Why the fast paths", 816ce47).
Not measured on a TPU or a ROCm GPU."""
ACCELERATOR_MIN_GROUPS = 64
"""Groups per source (on average) from which an accelerator folds them as segments: with
few groups the scatters' atomic adds contend (the same row of docs/benchmarks.md; 816ce47,
db0cbf9). Not measured on a TPU or a ROCm GPU."""


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
    def rows(self) -> int:
        """The segment rows: every source's groups."""
        return sum(n for _, n in self.blocks)

    def serves(self, num_envs: int) -> bool:
        """Whether a batch of `num_envs` envs folds the segment rows by segment reductions
        here (at trace time), or as masked rows like the others.

        On a CPU a masked row costs a pass over the envs, so segments always win. On an
        accelerator one masked reduction reads every row in one kernel, while the segment
        path's scatters are kernels of their own whose atomic adds contend when few groups
        share the envs: there segments won only with many groups over a large batch."""
        if jax.default_backend() == "cpu":
            return True
        many = self.rows >= ACCELERATOR_MIN_GROUPS * len(self.blocks)
        return many and self.rows * num_envs >= ACCELERATOR_MIN_ENTRIES

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


def _assembled(sp: SegmentPlan, dense: jax.Array, segment: jax.Array) -> jax.Array:
    """A stream field `[R]` from its dense rows `[R_d]` and segment rows
    `[sources, width]`, in the stream's row order."""
    at = np.zeros(len(sp.dense) + sum(n for _, n in sp.blocks), np.int32)
    at[list(sp.dense)] = np.arange(len(sp.dense))
    for i, (first, n) in enumerate(sp.blocks):
        at[first : first + n] = len(sp.dense) + i * sp.width + np.arange(n)
    flat = jnp.concatenate([dense, segment.reshape(-1)])
    return jnp.take(flat, at, axis=0, unique_indices=True)


def dense_state(sp: SegmentPlan, s: StreamState) -> StreamState:
    """`s` as a state of `sp.dense_plan`: its [R] fields (and window positions) at the
    dense rows; rings, histograms and sketches (dense rows only) as they are."""

    def rows(x: jax.Array) -> jax.Array:
        return _dense_rows(sp, x)

    per_row = ("count", "mean", "m2", "m2_c", "sum", "sum_c", "min", "max", "nonfinite")
    per_row += ("ema", "ema_off", "ema_w", "ema_n", "steps")
    return s._replace(
        **{f: jax.tree.map(rows, getattr(s, f)) for f in per_row},
        windows=tuple(w._replace(pos=rows(w.pos), filled=rows(w.filled)) for w in s.windows),
    )


def segment_rows(sp: SegmentPlan, x: jax.Array) -> jax.Array:
    """The segment rows of a stream field `x[R]` as `[sources, width]` (slots past a
    source's groups repeat its last group and are never read back)."""
    at = [[a + min(j, n - 1) for j in range(sp.width)] for a, n in sp.blocks]
    return _take(x, np.asarray(at, np.int32).reshape(-1)).reshape(len(sp.blocks), sp.width)


def joined(
    sp: SegmentPlan, dense: Batch, grouped: tuple[jax.Array, ...], c: int, width: int
) -> Batch:
    """Every row's batch statistics (`_update.Batch`, `[R]`; counted sums `[width]`) from
    the dense rows' (`dense`, counted sums of the `c` counted rows first) and the segment
    rows' (`grouped`, `segment_batch`'s seven); segment rows have no EMA sum."""
    both = [_assembled(sp, d, g) for d, g in zip(dense[:7], grouped)]
    ema = dense.ema
    if ema is not None:
        ema = _assembled(sp, ema, jnp.zeros((len(sp.blocks), sp.width), ema.dtype))
    counted = jnp.pad(dense.counted_sums[:c], (0, width - c))
    return Batch(*both, ema=ema, counted_sums=counted)


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
    `_fold.batch_two_pass` per group, each pass a few scatters into the group slots;
    `bad` (integers) counts for the entry's group whether or not it is `ok`.

    A CPU scatters one statistic at a time (`scatter_each`: a scatter of several
    channels is slower per statistic there); elsewhere the statistics of a pass that
    combine alike share one scatter (`scatter_stacked`: on a GPU each scatter is a kernel
    launch of its own, and the launches are the cost; docs/benchmarks.md). Both give
    the same numbers, so the form follows the default backend at trace time (a
    `platform_dependent` choice between them is refused under `vmap` over a sharded
    state: its branches' outputs come out split differently)."""
    form = scatter_each if jax.default_backend() == "cpu" else scatter_stacked
    return _segment_batch(form, values, ok, bad, group, shift, groups)


Scatter = Callable[[str, Any, jax.Array, int, tuple[jax.Array, ...]], list[jax.Array]]


def scatter_each(
    how: str, fill: Any, where: jax.Array, size: int, xs: tuple[jax.Array, ...]
) -> list[jax.Array]:
    """Per `x` of `xs` (each flat, like `where`): `[size]` filled with `fill`, its entries
    combined into slot `where` by `how` ("add", "min", "max"); slots past `size` dropped."""
    return [getattr(jnp.full((size,), fill, x.dtype).at[where], how)(x, mode="drop") for x in xs]


def scatter_stacked(
    how: str, fill: Any, where: jax.Array, size: int, xs: tuple[jax.Array, ...]
) -> list[jax.Array]:
    """`scatter_each` as one scatter of the `xs` stacked as channels."""
    x = jnp.stack(xs, axis=1)
    out = getattr(jnp.full((size, len(xs)), fill, x.dtype).at[where], how)(x, mode="drop")
    return [out[:, i] for i in range(len(xs))]


def _segment_batch(
    scatter: Scatter,
    values: jax.Array,
    ok: jax.Array,
    bad: jax.Array,
    group: jax.Array,
    shift: jax.Array,
    groups: np.ndarray,
) -> tuple[jax.Array, ...]:
    dt = values.dtype
    sources, width = shift.shape
    size = sources * width
    # One flat slot per source and group (an index pair per entry scatters slower on a
    # CPU: docs/benchmarks.md); `size` is past every slot: entries scattered there are
    # dropped.
    first = jnp.arange(0, size, width, dtype=jnp.int32)[:, None]
    inside = (group >= 0) & (group < jnp.asarray(groups)[:, None])
    slot = jnp.where(inside, first + group, size).reshape(-1)
    at = jnp.where(ok.reshape(-1), slot, size)
    flat = values.reshape(-1)

    def slots(x: jax.Array) -> jax.Array:
        return x.reshape(sources, width)

    # The count as a float beside the sum (exact to 2^24 entries a batch row; `ok`, which
    # is 1 wherever an entry is not dropped, keeps the channels split alike over a mesh),
    # the min as the max of the negated values (negation is exact).
    ones = ok.reshape(-1).astype(dt)
    kf, bsum = map(slots, scatter("add", 0, at, size, (ones, flat)))
    bmax, neg_min = map(slots, scatter("max", -jnp.inf, at, size, (flat, -flat)))
    (nbad,) = map(slots, scatter("add", 0, slot, size, (bad.reshape(-1).astype(jnp.int32),)))
    k, bmin = kf.astype(jnp.int32), -neg_min
    kd = jnp.maximum(k, 1).astype(dt)
    pivot = jnp.where(shift != 0, shift, bsum / kd)
    d = flat - pivot.reshape(-1).at[at].get(mode="fill", fill_value=0)
    s1, s2 = map(slots, scatter("add", 0, at, size, (d, d * d)))
    mb = s1 / kd
    m2b = jnp.maximum(s2 - s1 * mb, 0)
    return k, bsum, bmin, bmax, mb + (pivot - shift), m2b, nbad
