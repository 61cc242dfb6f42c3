"""Quantile sketches: exact counts of a period's values in logarithmic buckets.

DDSketch's layout (Masson, Rim and Lee, VLDB 2019): with `g = (1 + a) / (1 - a)`, bucket
`k` holds the magnitudes in `(lo g^(k-1), lo g^k]`, and its representative `2 lo g^k /
(g + 1)` is within relative `a` of every value in it. A row's counts are one `Count` pair
per slot, ordered by value, so a quantile is the representative of the first slot whose
cumulative count exceeds its rank:

    [x < -hi] [negative buckets, largest magnitude first] [-lo <= x < 0] [0] [0 < x <= lo]
    [positive buckets] [x > hi] [NaN]

The edges are computed in float64 on the host and rounded to the state's dtype once; a
value's bucket is found by comparing it with those rounded edges (a `log` gives the
bucket to within one, the comparison settles it), and each representative is the best
one for its rounded edges, rounded once. The internal accuracy is `a (1 - 2^-10)`, which
leaves room for those roundings: every representative is within the stated `a` of every
value of its bucket (`tests/core/test_quantiles.py` checks the tables). Values beyond the
magnitude range have no representative: a quantile that falls on them is NaN.
"""

import dataclasses
import functools
import math

import jax
import jax.numpy as jnp
import numpy as np

from ._count import Count
from ._spec import QUANTILE_MAGNITUDES

_SLACK = 1.0 - 2.0**-10
_GRID = 10**6  # levels are percentiles on a 1e-4 grid: q = P / 10^6, P an integer


@dataclasses.dataclass(frozen=True)
class SketchGroup:
    """The quantile rows of one accuracy; they share the bucket tables."""

    accuracy: float
    rows: tuple[int, ...]

    @property
    def buckets(self) -> int:
        """Buckets per sign (`N`); a row has `2 N + 6` slots."""
        return _buckets(self.accuracy)

    @property
    def slots(self) -> int:
        return 2 * self.buckets + 6


def _buckets(accuracy: float) -> int:
    a = accuracy * _SLACK
    lo, hi = QUANTILE_MAGNITUDES
    return math.ceil(math.log(hi / lo) / math.log((1 + a) / (1 - a)))


@functools.cache
def tables(accuracy: float, dtype: str) -> dict[str, np.ndarray | float]:
    """Host-side constants of a sketch in `dtype`: the rounded bucket edges (`edges[k]`,
    k = 0..N: bucket k covers `(edges[k-1], edges[k]]`), the magnitude slots' `lower`
    and `upper` bounds, and every slot's representative (`reps`, NaN where none)."""
    dt = np.dtype(dtype)
    a = accuracy * _SLACK
    log_g = math.log((1 + a) / (1 - a))
    n = _buckets(accuracy)
    lo = QUANTILE_MAGNITUDES[0]
    edges = (lo * np.exp(np.arange(n + 1) * log_g)).astype(dt)
    e64 = edges.astype(np.float64)
    rep = (2 * e64[:-1] * e64[1:] / (e64[:-1] + e64[1:])).astype(dt)  # bucket k = 1..N
    nan = np.full(1, np.nan, dt)
    reps = np.concatenate([nan, -rep[::-1], nan, np.zeros(1, dt), nan, rep, nan, nan])
    return {
        "edges": edges,
        "lower": np.concatenate([np.zeros(1, dt), edges]),
        "upper": np.concatenate([edges, np.full(1, np.inf, dt)]),
        "reps": reps,
        "log_lo": float(np.log(e64[0])),
        "inv_log_g": 1.0 / log_g,
    }


def slot(g: SketchGroup, values: jax.Array, mask: jax.Array) -> jax.Array:
    """The slot of each value `[R, B]`; masked-out values get `slots`, which matches none."""
    dt = values.dtype
    t = tables(g.accuracy, dt.name)
    n = g.buckets
    mag = jnp.abs(values)
    guess = jnp.ceil((jnp.log(mag) - t["log_lo"]) * t["inv_log_g"])
    guess = jnp.clip(jnp.nan_to_num(guess, nan=0.0, posinf=n + 1.0, neginf=0.0), 0, n + 1)
    s = guess.astype(jnp.int32)
    lower, upper = (jnp.asarray(t[k], dt) for k in ("lower", "upper"))
    s = s + (mag > upper[s]).astype(jnp.int32) - ((mag <= lower[s]) & (mag > 0)).astype(jnp.int32)
    out = jnp.where(values > 0, n + 3 + s, n + 1 - s)
    out = jnp.where(values == 0, n + 2, out)
    out = jnp.where(jnp.isnan(values), 2 * n + 5, out)
    return jnp.where(mask, out, g.slots)


def add(counts: Count, slots: jax.Array) -> Count:
    """Counts each slot of `slots[R, B]` (out-of-range slots are dropped) exactly.

    O(B) per call, whatever the number of slots: a scatter-add into the low words, and a
    carry into the high word of the slots whose low word wrapped.
    """
    rows = jnp.broadcast_to(jnp.arange(slots.shape[0], dtype=jnp.int32)[:, None], slots.shape)

    def at(x: jax.Array) -> jax.Array:
        return x.at[rows, slots].get(mode="fill", fill_value=0)

    lo = counts.lo.at[rows, slots].add(jnp.uint32(1), mode="drop")
    wrapped = (at(lo) < at(counts.lo)).astype(jnp.uint32)
    # Every value of one slot writes the same new high word, so `max` sets it once.
    hi = counts.hi.at[rows, slots].max(at(counts.hi) + wrapped, mode="drop")
    return Count(hi, lo)


def _exact_rank(p: jax.Array, m: jax.Array) -> jax.Array:
    """`floor(p * m / 10^6)` in uint32 arithmetic, exact for `p <= 10^6`, `m < 2^32`:
    `m = a 10^6 + b`, `b = b1 2^10 + b0`, and `2^10 / 10^6 = 16 / 15625`, so no
    intermediate exceeds 2^32."""
    a, b = m // _GRID, m % _GRID
    u, v = p * (b >> 10), p * (b & 1023)
    return p * a + 16 * (u // 15625) + (1024 * (u % 15625) + v) // _GRID


def quantiles(
    g: SketchGroup, counts: Count, levels: tuple[tuple[float, ...], ...], dt
) -> jax.Array:
    """`[rows, L]`: per row of the group, the value at each of its levels (percentiles),
    level `k` of row `j` at `[j, k]` (`L` the most levels of a row; a row's slots past its
    own levels hold nothing to read). The value is the representative of the slot holding
    the value of rank `floor(p/100 (n-1))`.

    Ranks are exact up to 2^32 values per period (uint32 arithmetic); beyond, they are
    rounded to float32 (2^-24 of the rank). NaN for an empty period, a period with a NaN
    value ("propagate"), or a rank on a value outside the magnitude range.
    """
    merge = lambda x, y: (x[0] + y[0] + (x[1] + y[1] < x[1]).astype(jnp.uint32), x[1] + y[1])  # noqa: E731
    cum_hi, cum_lo = jax.lax.associative_scan(merge, (counts.hi, counts.lo), axis=1)
    n_hi, n_lo = cum_hi[:, -1:], cum_lo[:, -1:]
    m_lo = n_lo - jnp.uint32(1)
    m_hi = n_hi - (n_lo == 0).astype(jnp.uint32)
    empty = (n_hi == 0) & (n_lo == 0)
    has_nan = (counts.hi[:, -1:] > 0) | (counts.lo[:, -1:] > 0)
    reps = jnp.asarray(tables(g.accuracy, jnp.dtype(dt).name)["reps"], dt)
    # Every row's levels as one [rows, L] array, so that the ops do not grow with the
    # rows (a grouped metric has one per group); short rows are padded with level 0.
    width = max(len(ps) for ps in levels)
    grid = [[round(x * _GRID / 100) for x in ps] + [0] * (width - len(ps)) for ps in levels]
    p = jnp.asarray(np.array(grid, np.uint32))
    big = m_hi > 0
    # Past 2^32 values: the rank from a float32 product, split into two words.
    m = m_hi.astype(jnp.float32) * 2.0**32 + m_lo.astype(jnp.float32)
    approx = jnp.floor(p.astype(jnp.float32) / _GRID * m)
    approx_hi = jnp.floor(approx / 2.0**32)
    k_hi = jnp.where(big, approx_hi.astype(jnp.uint32), jnp.uint32(0))
    approx_lo = (approx - approx_hi * 2.0**32).astype(jnp.uint32)
    k_lo = jnp.where(big, approx_lo, _exact_rank(p, m_lo))
    ch, cl = cum_hi[:, None, :], cum_lo[:, None, :]
    above = (ch > k_hi[..., None]) | ((ch == k_hi[..., None]) & (cl > k_lo[..., None]))
    value = reps[jnp.argmax(above, axis=2)]
    return jnp.where(empty | has_nan, jnp.nan, value)
