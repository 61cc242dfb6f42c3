"""Per-env episode accumulators, stacked over metrics and grouped by reduction.

Rows are ordered by reduction (`ORDER`), so each reduction works on one contiguous
block `[rows, num_envs]`. The step on which an episode ends is folded in before the
episode value is read; then that env's accumulators reset.

A discounted row keeps its episode's step index `t` and a compensated sum of
`gamma^t x_t`. `gamma^t` is recomputed from `t` on every step as `exp(t ln gamma)`, with
`ln gamma` taken in float64 on the host: no running product to drift, and a float32
`ln gamma` is far more precise than a float32 `gamma` near 1 (a running product of
float32 gammas drifts to 7e-5 relative after 10^4 steps of 0.9999; this stays within
1e-6 of float64, `tests/test_discounted.py`).
"""

import dataclasses
import math
from collections.abc import Sequence
from typing import NamedTuple

import jax
import jax.numpy as jnp

from ._numerics import kahan_add
from ._reductions import Discounted

ORDER = ("mean", "std", "sum", "max", "min", "last", "discounted")


class EpisodeState(NamedTuple):
    """Running episodes of every env. Row blocks follow `ORDER`."""

    steps: jax.Array  # [M, E] int32: steps folded into the running episode (finite ones)
    mean: jax.Array  # [M_mean + M_std, E] float: Welford mean
    m2: jax.Array  # [M_std, E] float: Welford sum of squared deviations
    sum: jax.Array  # [M_sum, E] float, Kahan-compensated by sum_c
    sum_c: jax.Array  # [M_sum, E] float
    max: jax.Array  # [M_max, E] float, -inf at episode start
    min: jax.Array  # [M_min, E] float, +inf at episode start
    last: jax.Array  # [M_last, E] float, NaN at episode start
    disc: jax.Array  # [M_disc, E] float: sum of gamma^t x_t, Kahan-compensated by disc_c
    disc_c: jax.Array  # [M_disc, E] float
    disc_t: jax.Array  # [M_disc, E] int32: steps of the episode so far, folded or not


@dataclasses.dataclass(frozen=True)
class EpisodePlan:
    """How many rows each reduction has (rows are sorted by `ORDER`)."""

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

    def block(self, name: str) -> slice:
        i = ORDER.index(name)
        start = sum(self.sizes[:i])
        return slice(start, start + self.sizes[i])


# Value of each EpisodeState field at the start of an episode.
_START = EpisodeState(
    steps=0,
    mean=0.0,
    m2=0.0,
    sum=0.0,
    sum_c=0.0,
    max=-jnp.inf,
    min=jnp.inf,
    last=jnp.nan,
    disc=0.0,
    disc_c=0.0,
    disc_t=0,
)


def init(plan: EpisodePlan, num_envs: int) -> EpisodeState:
    n = dict(zip(ORDER, plan.sizes))
    rows = EpisodeState(
        steps=plan.rows,
        mean=n["mean"] + n["std"],
        m2=n["std"],
        sum=n["sum"],
        sum_c=n["sum"],
        max=n["max"],
        min=n["min"],
        last=n["last"],
        disc=n["discounted"],
        disc_c=n["discounted"],
        disc_t=n["discounted"],
    )
    dtypes = EpisodeState(jnp.int32, *(plan.dtype,) * 9, jnp.int32)
    return EpisodeState(*(jnp.full((r, num_envs), v, dt) for r, v, dt in zip(rows, _START, dtypes)))


def step(
    plan: EpisodePlan, ep: EpisodeState, x: jax.Array, fold: jax.Array, done: jax.Array
) -> tuple[EpisodeState, jax.Array, jax.Array]:
    """Folds one step `x[M, E]` (where `fold[M, E]`) into the running episodes.

    Returns the new state, the episode values `[M, E]` as of this step (meaningful where
    `done`), and whether each env's episode has any folded step (`[M, E]` bool).
    """
    steps = ep.steps + fold.astype(jnp.int32)
    b = plan.block
    welford = slice(b("mean").start, b("std").stop)
    xw, fw = x[welford], fold[welford]
    nw = jnp.maximum(steps[welford], 1).astype(plan.dtype)
    # An infinite mean stays infinite under finite steps or the same infinity (as numpy's
    # mean does) instead of turning into NaN through inf - inf; only "propagate" lets
    # infinities in at all.
    stays = jnp.isinf(ep.mean) & (jnp.isfinite(xw) | (xw == ep.mean))
    delta = jnp.where(fw & ~stays, xw - ep.mean, 0)
    mean = ep.mean + delta / nw
    std_in_w = slice(b("std").start - welford.start, b("std").stop - welford.start)
    m2 = ep.m2 + jnp.where(fw[std_in_w], delta[std_in_w] * (xw - mean)[std_in_w], 0)

    xs, fs = x[b("sum")], fold[b("sum")]
    t, sum_c = kahan_add(ep.sum, ep.sum_c, jnp.where(fs, xs, 0))

    vmax = jnp.where(fold[b("max")], jnp.maximum(ep.max, x[b("max")]), ep.max)
    vmin = jnp.where(fold[b("min")], jnp.minimum(ep.min, x[b("min")]), ep.min)
    last = jnp.where(fold[b("last")], x[b("last")], ep.last)

    xd, fd = x[b("discounted")], fold[b("discounted")]
    log_g = jnp.asarray(plan.log_gammas, plan.dtype).reshape(-1, 1)
    factor = jnp.exp(ep.disc_t.astype(plan.dtype) * log_g)
    # gamma^t * inf is inf even where gamma^t underflowed to 0 (only "propagate" folds it).
    term = jnp.where(jnp.isfinite(xd), factor * xd, xd)
    disc, disc_c = kahan_add(ep.disc, ep.disc_c, jnp.where(fd, term, 0))

    nstd = jnp.maximum(steps[b("std")], 1).astype(plan.dtype)
    values = jnp.concatenate(
        [
            mean[: plan.sizes[0]],
            jnp.sqrt(m2 / nstd),
            t - sum_c,
            vmax,
            vmin,
            last,
            disc - disc_c,
        ],
        axis=0,
    )
    new = EpisodeState(steps, mean, m2, t, sum_c, vmax, vmin, last, disc, disc_c, ep.disc_t + 1)
    d = done[None, :]
    # Start values as scalars (not fresh arrays), so the reset keeps each field's sharding.
    reset = EpisodeState(*(jnp.where(d, v0, v) for v0, v in zip(_START, new)))
    return reset, values, steps > 0


def running(plan: EpisodePlan, ep: EpisodeState) -> jax.Array:
    """Current value of every running episode `[M, E]` (NaN where it has no step yet)."""
    b = plan.block
    nstd = jnp.maximum(ep.steps[b("std")], 1).astype(plan.dtype)
    values = jnp.concatenate(
        [
            ep.mean[: plan.sizes[0]],
            jnp.sqrt(ep.m2 / nstd),
            ep.sum - ep.sum_c,
            ep.max,
            ep.min,
            ep.last,
            ep.disc - ep.disc_c,
        ],
        axis=0,
    )
    return jnp.where(ep.steps > 0, values, jnp.nan)
