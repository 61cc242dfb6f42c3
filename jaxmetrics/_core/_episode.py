"""Per-env episode accumulators, stacked over metrics: three `[rows, num_envs]` arrays.

Every reduction keeps its running episode in the same three arrays (`EpisodeState`):
a step counter and two float slots whose meaning depends on the row's reduction
(`SLOTS`). One elementwise pass updates every row, selecting per row what its
reduction computes, so the whole fold of a step is one fused kernel whatever the mix
of reductions, and XLA can update the accumulators in place. Rows are ordered by
reduction (`ORDER`). The step on which an episode ends is folded in before the
episode value is read; then that env's accumulators reset.

A discounted row keeps a compensated sum of `gamma^t x_t`, where `t` is the episode's
step index (`EpisodeState.length`, one per env: every step counts, folded or not).
`gamma^t` is recomputed from `t` on every step as `exp(t ln gamma)`, with `ln gamma`
taken in float64 on the host and split so that the float32 products with `t` are exact
(`_discounted`): no running product to drift (a running product of float32 gammas
drifts to 7e-5 relative after 10^4 steps of 0.9999), and no rounding of `t ln gamma`
(`tests/core/test_discounted.py`).
"""

import dataclasses
import math
from collections.abc import Sequence
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from ._numerics import kahan_add, two_sum
from ._reductions import Discounted

ORDER = ("mean", "std", "sum", "max", "min", "last", "discounted")

# Per reduction: what the slots `value` and `aux` hold, and their values at episode start.
SLOTS = {
    "mean": ("Welford mean", 0.0, "unused", 0.0),
    "std": ("Welford mean", 0.0, "Welford sum of squared deviations", 0.0),
    "sum": ("sum", 0.0, "Kahan compensation of the sum", 0.0),
    "max": ("max", -np.inf, "unused", 0.0),
    "min": ("min", np.inf, "unused", 0.0),
    "last": ("last value", np.nan, "unused", 0.0),
    "discounted": ("sum of gamma^t x_t", 0.0, "Kahan compensation of the sum", 0.0),
}


class EpisodeState(NamedTuple):
    """Running episodes of every env; what `value` and `aux` hold per row is `SLOTS`."""

    steps: jax.Array  # [M, E] int32: steps folded into the running episode (finite ones)
    value: jax.Array  # [M, E] float: the reduction's running value (see SLOTS)
    aux: jax.Array  # [M, E] float: its auxiliary slot (see SLOTS), 0 where unused
    length: jax.Array  # [D, E] int32: the episode's steps so far, folded or not; D = 1
    # where the spec has discounted rows (their `t`), else 0


@dataclasses.dataclass(frozen=True)
class EpisodePlan:
    """The reduction of each row (rows sorted by `ORDER`)."""

    sizes: tuple[int, ...]  # per reduction in ORDER
    dtype: jnp.dtype
    log_gammas: tuple[float, ...] = ()  # ln(gamma) of each discounted row, in row order

    @classmethod
    def build(cls, reductions: Sequence[str | Discounted], dtype) -> "EpisodePlan":
        names = [r.name if isinstance(r, Discounted) else r for r in reductions]
        logs = tuple(math.log(r.gamma) for r in reductions if isinstance(r, Discounted))
        return cls(tuple(names.count(k) for k in ORDER), jnp.dtype(dtype), logs)

    @property
    def rows(self) -> int:
        return sum(self.sizes)

    @property
    def kinds(self) -> tuple[str, ...]:
        return tuple(k for k, n in zip(ORDER, self.sizes) for _ in range(n))

    def column(self, fn) -> np.ndarray:
        """`[rows, 1]` numpy column of `fn(reduction)` per row (a constant in-graph)."""
        return np.array([fn(k) for k in self.kinds], dtype=np.float64).reshape(-1, 1)

    def is_(self, *names: str) -> np.ndarray:
        """`[rows, 1]` bool column: whether each row's reduction is one of `names`."""
        return np.array([k in names for k in self.kinds], dtype=bool).reshape(-1, 1)


def _start(plan: EpisodePlan) -> tuple[np.ndarray, np.ndarray]:
    return plan.column(lambda k: SLOTS[k][1]), plan.column(lambda k: SLOTS[k][3])


def init(plan: EpisodePlan, num_envs: int) -> EpisodeState:
    a0, b0 = _start(plan)
    shape = (plan.rows, num_envs)
    return EpisodeState(
        jnp.zeros(shape, jnp.int32),
        jnp.broadcast_to(jnp.asarray(a0, plan.dtype), shape),
        jnp.broadcast_to(jnp.asarray(b0, plan.dtype), shape),
        jnp.zeros((1 if plan.log_gammas else 0, num_envs), jnp.int32),
    )


def _values(plan: EpisodePlan, steps, a, b) -> jax.Array:
    """Each row's episode value from its slots (meaningful where steps > 0)."""
    n = jnp.maximum(steps, 1).astype(plan.dtype)
    std = jnp.sqrt(b / n) if plan.sizes[1] else a
    compensated = plan.is_("sum", "discounted")
    return jnp.where(plan.is_("std"), std, jnp.where(compensated, a - b, a))


def _discounted(plan: EpisodePlan, ep: EpisodeState, x, fold) -> tuple[jax.Array, jax.Array]:
    """The discounted rows' new sum and compensation (computed on every row)."""
    log_g = np.zeros((plan.rows, 1))
    log_g[plan.is_("discounted")[:, 0], 0] = plan.log_gammas
    # t ln gamma as a float32 pair (hi + lo): ln gamma = lg1 + lg2, lg1 with 12 significant
    # bits, and t = t_hi + t_lo with t_lo < 2^12, so t_hi lg1 and t_lo lg1 are exact for
    # t < 2^24; error-free sums carry what the rounded exponent loses, and gamma^t =
    # exp(hi) (1 + lo). A plain exp(float32(t) float32(ln gamma)) is off by |t ln gamma|
    # 2^-24 relative, past 1e-6 for a sparse reward late in a long episode. (A product of
    # exps would not do: XLA rewrites exp(a) exp(b) as exp(a + b).)
    mant, expo = np.frexp(log_g)
    lg1 = np.ldexp(np.round(mant * 4096.0) / 4096.0, expo)
    lg2 = log_g - lg1
    t = ep.length
    t_lo = t & 4095
    t_hi = (t - t_lo).astype(plan.dtype)
    t_lo, t = t_lo.astype(plan.dtype), t.astype(plan.dtype)
    lg1, lg2 = jnp.asarray(lg1, plan.dtype), jnp.asarray(lg2, plan.dtype)
    hi, lo1 = two_sum(t_hi * lg1, t_lo * lg1)
    hi, lo2 = two_sum(hi, t * lg2)
    factor = jnp.exp(hi) * (1 + (lo1 + lo2))
    # gamma^t * inf is inf even where gamma^t underflowed to 0 (only "propagate" folds it).
    term = jnp.where(jnp.isfinite(x), factor * x, x)
    return kahan_add(ep.value, ep.aux, jnp.where(fold, term, 0))


def step(
    plan: EpisodePlan, ep: EpisodeState, x: jax.Array, fold: jax.Array, done: jax.Array
) -> tuple[EpisodeState, jax.Array, jax.Array]:
    """Folds one step `x[M, E]` (where `fold[M, E]`) into the running episodes.

    Returns the new state, the episode values `[M, E]` as of this step (meaningful where
    `done`), and whether each env's episode has any folded step (`[M, E]` bool).
    """
    steps = ep.steps + fold.astype(jnp.int32)
    a, b = ep.value, ep.aux
    # Every reduction's update on every row, each row then keeps its own (a select per
    # reduction, not a kernel per block of rows).
    nw = jnp.maximum(steps, 1).astype(plan.dtype)
    # An infinite mean stays infinite under finite steps or the same infinity (as numpy's
    # mean does) instead of turning into NaN through inf - inf; only "propagate" lets
    # infinities in at all.
    stays = jnp.isinf(a) & (jnp.isfinite(x) | (x == a))
    delta = jnp.where(fold & ~stays, x - a, 0)
    mean = a + delta / nw
    m2 = b + jnp.where(fold, delta * (x - mean), 0)
    total, comp = kahan_add(a, b, jnp.where(fold, x, 0))
    vmax = jnp.where(fold, jnp.maximum(a, x), a)
    vmin = jnp.where(fold, jnp.minimum(a, x), a)
    last = jnp.where(fold, x, a)
    is_ = plan.is_
    new_a = jnp.where(
        is_("mean", "std"),
        mean,
        jnp.where(
            is_("sum"), total, jnp.where(is_("max"), vmax, jnp.where(is_("min"), vmin, last))
        ),
    )
    new_b = jnp.where(is_("std"), m2, jnp.where(is_("sum"), comp, b))
    if plan.log_gammas:
        dsum, dcomp = _discounted(plan, ep, x, fold)
        new_a = jnp.where(is_("discounted"), dsum, new_a)
        new_b = jnp.where(is_("discounted"), dcomp, new_b)
    values = _values(plan, steps, new_a, new_b)
    d = done[None, :]
    a0, b0 = _start(plan)
    # Start values as constant columns, so the reset keeps each field's sharding.
    reset = EpisodeState(
        jnp.where(d, 0, steps),
        jnp.where(d, jnp.asarray(a0, plan.dtype), new_a),
        jnp.where(d, jnp.asarray(b0, plan.dtype), new_b),
        jnp.where(d, 0, ep.length + 1),
    )
    return reset, values, steps > 0


def running(plan: EpisodePlan, ep: EpisodeState) -> jax.Array:
    """Current value of every running episode `[M, E]` (NaN where it has no step yet)."""
    return jnp.where(ep.steps > 0, _values(plan, ep.steps, ep.value, ep.aux), jnp.nan)
