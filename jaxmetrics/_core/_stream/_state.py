"""The stream's state (`StreamState`), its static plan (`StreamPlan`), and the ring
buffers that keep the newest values of windows and EMA histories with their arrival steps."""

import dataclasses
import math
from collections.abc import Sequence
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax.typing import DTypeLike

from .. import _count
from .._count import Count
from .._sketch import SketchGroup
from .._spec import MetricSpec


class Ring(NamedTuple):
    """Ring buffers of the newest `size` arrivals of some rows, with their arrival steps.

    The value with arrival order j (0 oldest ... size-1 newest, right-aligned) is at
    slot (pos + j) mod size, valid when j >= size - filled.

    A slot holds its value's bits and its stamp side by side (`ring_words` words of the
    stream's dtype, then the stamp), so that a step writes both in one scatter: stamps
    of their own would cost a second pass over the rings.
    """

    data: jax.Array  # [rows, size, ring_words(dtype) + 1] uint32: value bits, then stamp
    pos: jax.Array  # [rows] int32, next slot to write
    filled: jax.Array  # [rows] int32 in [0, size]

    @property
    def size(self) -> int:
        return self.data.shape[-2]

    def values(self, dt: DTypeLike) -> jax.Array:
        """`[..., rows, size]` values of dtype `dt` (the stream's)."""
        return _from_words(self.data[..., :-1], dt)

    @property
    def stamps(self) -> jax.Array:
        """`[..., rows, size]` uint32: the stream's `steps` when each value arrived."""
        return self.data[..., -1]


def ring_words(dt: DTypeLike) -> int:
    """uint32 words that hold one value of the stream's dtype `dt` (float32 or float64)."""
    return jnp.dtype(dt).itemsize // 4


def _to_words(x: jax.Array) -> jax.Array:
    """`x[...]` (float32 or float64) as `uint32[..., ring_words(x.dtype)]`, bit for bit."""
    w = jax.lax.bitcast_convert_type(x, jnp.uint32)
    return w if x.dtype.itemsize == 8 else w[..., None]


def _from_words(w: jax.Array, dt: DTypeLike) -> jax.Array:
    """`_to_words`' inverse."""
    return jax.lax.bitcast_convert_type(w if jnp.dtype(dt).itemsize == 8 else w[..., 0], dt)


def packed(values: jax.Array, stamps: jax.Array) -> jax.Array:
    """`Ring.data` of `values` and their uint32 `stamps` (same shape)."""
    return jnp.concatenate([_to_words(values), stamps.astype(jnp.uint32)[..., None]], axis=-1)


class StreamState(NamedTuple):
    """Report statistics of R metrics; see the module docstring for what resets when."""

    count: Count  # [R] uint32 pair: values in this period (shadows tuple.count)  # pyright: ignore[reportIncompatibleMethodOverride]
    mean: jax.Array  # [R] float: Welford/Chan running mean of the period
    m2: jax.Array  # [R] float: sum of squared deviations, Kahan-compensated by m2_c
    m2_c: jax.Array  # [R] float
    sum: jax.Array  # [R] float: period sum, Kahan-compensated by sum_c
    sum_c: jax.Array  # [R] float
    min: jax.Array  # [R] float, +inf when empty
    max: jax.Array  # [R] float, -inf when empty
    nonfinite: Count  # [R] uint32 pair: non-finite values left out in this period
    # EMA fields have every row (0 where a row has no EMA), so that the whole update of
    # the per-row statistics after a batch is one elementwise pass over [R] arrays.
    ema: jax.Array  # [R] float: the EMA minus `ema_off`: its trailing part
    ema_off: jax.Array  # [R] float: the EMA's leading part (the EMA is ema_off + ema)
    ema_w: jax.Array  # [R] float: 0 unseeded, else number of merged seeded workers
    ema_n: jax.Array  # [R] int32: values the EMA has seen (saturates at 2^31 - 1)
    ema_rings: tuple[Ring, ...]  # one per EmaGroup: the newest values, for exact merges
    # [R] uint32: arrival steps so far (wraps; only differences are used). Every row
    # advances together; kept per row so that its update is one more [R] field.
    steps: jax.Array
    # One per distinct window size; its `pos` and `filled` have every stream row (`[R]`,
    # 0 outside the group) so that they are updated with the other [R] fields.
    windows: tuple[Ring, ...]
    hists: tuple[Count, ...]  # one per distinct bin count: [R_h, bins + 2] incl. under/overflow
    # Like `hists`, int32 and zero between steps: a step's counts are scattered into it in
    # place, added to `hists` and zeroed in that same kernel (a scatter into a fresh zero
    # array costs one more kernel per step, the fill).
    hist_steps: tuple[jax.Array, ...]
    sketches: tuple[Count, ...]  # one per distinct quantile accuracy: [R_q, slots] (`_sketch`)


@dataclasses.dataclass(frozen=True)
class WindowGroup:
    size: int
    rows: tuple[int, ...]


@dataclasses.dataclass(frozen=True)
class EmaGroup:
    """EMA rows of one coefficient; `history` is how many newest values make it exact.

    A value that has `h` newer ones weighs at most `(1-c)^h` in the EMA; with
    `h = history` that is below 2^-32 (capped at `MAX_EMA_HISTORY` values), so merging
    workers by folding their newest `history` values in arrival order, on top of any
    estimate of the older EMA within the range of the values, is exact to 2^-32 of that
    range: below float32's resolution.
    """

    coeff: float
    rows: tuple[int, ...]  # indices into the stream's EMA rows (not its rows)

    @property
    def history(self) -> int:
        if self.coeff >= 1.0:
            return 1
        return min(MAX_EMA_HISTORY, math.ceil(32 * math.log(2) / -math.log1p(-self.coeff)))


MAX_EMA_HISTORY = 1 << 16
"""The most newest values an EMA keeps per row for exact merges (`EmaGroup.history`): a bound
on the ring's memory, not a speed choice (`MIN_MERGED_EMA` says what it costs in exactness)."""
MIN_MERGED_EMA = -math.expm1(-32 * math.log(2) / MAX_EMA_HISTORY)
"""The smallest EMA coefficient whose merge is exact to 2^-32 of the range: below it the
`MAX_EMA_HISTORY` newest values kept per worker leave the older EMA a weight above 2^-32
(about 3.385e-4)."""


@dataclasses.dataclass(frozen=True)
class HistGroup:
    bins: int
    rows: tuple[int, ...]
    lo: tuple[float, ...]
    hi: tuple[float, ...]


@dataclasses.dataclass(frozen=True)
class StreamPlan:
    """Static layout of a stream, derived from its metric specs."""

    rows: tuple[MetricSpec, ...]
    ema_rows: tuple[int, ...]
    ema_coeffs: tuple[float, ...]
    ema_groups: tuple[EmaGroup, ...]
    windows: tuple[WindowGroup, ...]
    hists: tuple[HistGroup, ...]
    dtype: jnp.dtype
    sketches: tuple[SketchGroup, ...] = ()

    @property
    def ranked_rows(self) -> tuple[int, ...]:
        """Rows whose statistics depend on arrival order (EMA, windows)."""
        return tuple(sorted(set(self.ema_rows).union(*(g.rows for g in self.windows))))

    def stream_rows(self, g: EmaGroup) -> tuple[int, ...]:
        """The stream rows of EMA group `g` (its `rows` index the EMA rows)."""
        return tuple(self.ema_rows[j] for j in g.rows)

    def ema_by_row(self, fill: float) -> tuple[np.ndarray, np.ndarray]:
        """Per stream row: whether it has an EMA, and its coefficient (`fill` if not)."""
        coeff = dict(zip(self.ema_rows, self.ema_coeffs))
        rows = range(len(self.rows))
        return np.array([i in coeff for i in rows]), np.array([coeff.get(i, fill) for i in rows])

    @classmethod
    def build(cls, rows: Sequence[MetricSpec], dtype: DTypeLike) -> "StreamPlan":
        rows = tuple(rows)
        ema_rows = tuple(i for i, r in enumerate(rows) if r.stats.ema is not None)
        coeffs = tuple(float(rows[i].stats.ema.coeff) for i in ema_rows)  # type: ignore[union-attr]
        ema_groups = tuple(
            EmaGroup(c, tuple(j for j, cj in enumerate(coeffs) if cj == c))
            for c in sorted(set(coeffs))
        )
        sizes = sorted({r.stats.window.size for r in rows if r.stats.window is not None})
        windows = tuple(
            WindowGroup(
                n,
                tuple(i for i, r in enumerate(rows) if r.stats.window and r.stats.window.size == n),
            )
            for n in sizes
        )
        bins = sorted({r.stats.histogram.bins for r in rows if r.stats.histogram is not None})
        hists = []
        for b in bins:
            idx = tuple(
                i
                for i, r in enumerate(rows)
                if r.stats.histogram is not None and r.stats.histogram.bins == b
            )
            hists.append(
                HistGroup(
                    b,
                    idx,
                    tuple(rows[i].stats.histogram.range[0] for i in idx),  # type: ignore[union-attr]
                    tuple(rows[i].stats.histogram.range[1] for i in idx),  # type: ignore[union-attr]
                )
            )
        accuracies = sorted({r.stats.quantiles.accuracy for r in rows if r.stats.quantiles})
        sketches = tuple(
            SketchGroup(
                a,
                tuple(
                    i
                    for i, r in enumerate(rows)
                    if r.stats.quantiles and r.stats.quantiles.accuracy == a
                ),
            )
            for a in accuracies
        )
        return cls(
            rows, ema_rows, coeffs, ema_groups, windows, tuple(hists), jnp.dtype(dtype), sketches
        )


def _ring(rows: int, size: int, dt: DTypeLike) -> Ring:
    return Ring(
        jnp.zeros((rows, size, ring_words(dt) + 1), jnp.uint32),
        jnp.zeros((rows,), jnp.int32),
        jnp.zeros((rows,), jnp.int32),
    )


def init(plan: StreamPlan, ema_history: bool = False) -> StreamState:
    """An empty stream. `ema_history` keeps each EMA row's newest values (its group's
    `history`), which makes merging EMAs of disjoint workers exact; without it a merged
    EMA is the average of the workers' EMAs."""
    r, dt = len(plan.rows), plan.dtype
    zeros = jnp.zeros((r,), dt)
    e = r
    return StreamState(
        count=_count.zeros((r,)),
        mean=zeros,
        m2=zeros,
        m2_c=zeros,
        sum=zeros,
        sum_c=zeros,
        min=jnp.full((r,), jnp.inf, dt),
        max=jnp.full((r,), -jnp.inf, dt),
        nonfinite=_count.zeros((r,)),
        ema=jnp.zeros((e,), dt),
        ema_off=jnp.zeros((e,), dt),
        ema_w=jnp.zeros((e,), dt),
        ema_n=jnp.zeros((e,), jnp.int32),
        ema_rings=tuple(
            _ring(len(g.rows), g.history if ema_history else 0, dt) for g in plan.ema_groups
        ),
        steps=jnp.zeros((r,), jnp.uint32),
        windows=tuple(
            _ring(len(g.rows), g.size, dt)._replace(
                pos=jnp.zeros((r,), jnp.int32), filled=jnp.zeros((r,), jnp.int32)
            )
            for g in plan.windows
        ),
        hists=tuple(_count.zeros((len(g.rows), g.bins + 2)) for g in plan.hists),
        hist_steps=tuple(jnp.zeros((len(g.rows), g.bins + 2), jnp.int32) for g in plan.hists),
        sketches=tuple(_count.zeros((len(g.rows), g.slots)) for g in plan.sketches),
    )


# The fields a new period keeps: EMA, windows and the arrival step run across periods.
CARRIED = ("ema", "ema_off", "ema_w", "ema_n", "ema_rings", "steps", "windows")


def reset_period(plan: StreamPlan, s: StreamState) -> StreamState:
    """Clears the period statistics; EMA, windows and the arrival step carry on."""
    return carried(init(plan), s)


def carried(new: StreamState, old: StreamState) -> StreamState:
    """`new` with `old`'s `CARRIED` fields (the very arrays)."""
    return new._replace(**{f: getattr(old, f) for f in CARRIED})


def uncarried(s: StreamState) -> StreamState:
    """`s` with its `CARRIED` fields None: what a new period makes afresh."""
    return s._replace(**dict.fromkeys(CARRIED))


def weight_dtype(dt: jnp.dtype) -> jnp.dtype:
    # Counts and weights need float32's range even for a float16/bfloat16 state.
    return jnp.dtype(jnp.float64) if dt == jnp.float64 else jnp.dtype(jnp.float32)


def take_rows(rows: tuple[int, ...], x: jax.Array) -> jax.Array:
    if rows == tuple(range(x.shape[0])):
        return x
    # Static row slices, not a gather: keeps the env axis' sharding unambiguous.
    return jnp.stack([x[i] for i in rows])


INT32_MAX = np.int32(np.iinfo(np.int32).max)
"""Where `ema_n` (int32) saturates instead of wrapping."""
UINT32_MAX = np.uint32(np.iinfo(np.uint32).max)
"""The newest arrival's key in a ring merge (`_merge`): keys count down from it by age."""


def window_ring(g: WindowGroup, w: Ring) -> Ring:
    """The ring of window group `g` with its own rows' `pos` and `filled` ([R_w])."""
    return w._replace(pos=take_rows(g.rows, w.pos), filled=take_rows(g.rows, w.filled))


def widened_ring(g: WindowGroup, ring: Ring, rows: int) -> Ring:
    """`_window`'s inverse: `pos` and `filled` spread to every row (0 outside `g`)."""
    at = {r: j for j, r in enumerate(g.rows)}

    def spread(x: jax.Array) -> jax.Array:
        zero = jnp.zeros_like(x[0])
        return jnp.stack([x[at[i]] if i in at else zero for i in range(rows)])

    return ring._replace(pos=spread(ring.pos), filled=spread(ring.filled))


def rotated(r: Ring) -> Ring:
    """`r` rotated so that slot j holds arrival order j (oldest first, right-aligned; `pos`
    0), over any leading axes."""
    n = r.size
    if n == 0:
        return r
    j = jnp.arange(n, dtype=jnp.int32).reshape((1,) * r.pos.ndim + (n,))
    slot = (r.pos[..., None] + j) % n
    return Ring(
        jnp.take_along_axis(r.data, slot[..., None], axis=-2), jnp.zeros_like(r.pos), r.filled
    )


def ordered(w: Ring, steps: jax.Array, dt: DTypeLike) -> tuple[jax.Array, jax.Array, jax.Array]:
    """Ring contents right-aligned in arrival order (oldest first): values, their ages
    in arrival steps (`steps - stamp`, `steps` per ring row), and validity."""
    r = rotated(w)
    j = jnp.arange(w.size, dtype=jnp.int32)[None, :]
    return r.values(dt), steps[:, None] - r.stamps, j >= (w.size - w.filled)[:, None]
