"""What every scenario measures: the 10-term spec, the hand-written floor, host loggers.

The spec mixes every episode reduction (sum, mean, std, max, min, last) and every
report statistic (mean/std/min/max/sum/count, EMA, window with percentiles, histogram).
The floor is the least any in-graph logger can do: per env a running episode sum, and
at episode ends a per-metric total and an episode count (what Brax's `episode_metrics`
give). The host loggers are what people write instead: per-episode reductions in numpy,
or per env in Python dicts, fed with values copied to the host on every step.
"""

import collections
from collections.abc import Callable, Sequence
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

import jaxmetrics as jm
from jaxmetrics._core._reductions import Discounted
from jaxmetrics._core._spec import Ema, Histogram, Window

# Episode reduction of each of the 10 pattern terms; term i of N uses PATTERN[i % 10].
PATTERN = ("sum", "sum", "mean", "std", "max", "min", "mean", "last", "mean", "mean")


def pattern_stats(i: int, window: int, hist_range: tuple[float, float]) -> tuple[Any, ...]:
    """Report statistics of pattern term `i`: every term counts, some do much more."""
    k = i % 10
    extra: dict[int, tuple[Any, ...]] = {
        0: ("std", "min", "max", "sum", jm.ema(0.01)),
        1: ("sum",),
        2: ("std", jm.window(window, percentiles=(50, 90))),
        4: ("max", jm.histogram(20, hist_range)),
        5: ("min",),
        6: ("std", jm.ema(0.05)),
        7: (jm.window(window),),
        9: (jm.histogram(20, hist_range),),
    }
    return ("mean", "count", *extra.get(k, ()))


def _row(x: jax.Array, i: int) -> jax.Array:
    return x[i]


def _group_of(x: jax.Array, n: int) -> jax.Array:
    # Row 0 is uniform in [0, 1): each env lands in a random group on every step.
    return jnp.minimum((x[0] * n).astype(jnp.int32), n - 1)


def random_spec(
    num_terms: int, window: int = 100, features: str = "full", groups: int = 0
) -> jm.Metrics:
    """Terms `m0..m{N-1}` reading row `i % 10` of a `[10, num_envs]` step input.

    `features` trims the spec for the ablation table: "sum" (every term sum-reduced,
    mean+sum+count only), "simple" (mixed reductions, simple stats only), "ema", "window",
    "histogram" (simple plus that one kind), "discounted_quantiles" (simple, with the two
    sum terms discounted by 0.99 and the two histogram terms' histograms replaced by
    `quantiles((50, 90, 99))`), "full" (everything). `groups > 0` keeps every statistic
    per group too, the group of an env drawn from row 0 on every step.
    """
    terms = {}
    for i in range(num_terms):
        reduce, stats = _trim(i, pattern_stats(i, window, (0.0, 1.0)), features)
        terms[f"m{i}"] = jm.Term(_row, reduce=reduce, stats=stats, params={"i": i % 10})
    grouping = None
    if groups:
        grouping = jm.groups(_group_of, tuple(f"g{k}" for k in range(groups)), n=groups)
    return jm.Metrics(terms=terms, groups=grouping)


def _trim(
    i: int, stats: tuple[Any, ...], features: str
) -> tuple[str | Discounted, tuple[Any, ...]]:
    """Pattern term `i`'s reduction and statistics, trimmed to `features`."""
    if features == "sum":
        return "sum", ("mean", "sum", "count")
    if features == "discounted_quantiles":
        simple = tuple(s for s in stats if isinstance(s, str))
        if any(isinstance(s, Histogram) for s in stats):
            simple += (jm.quantiles((50, 90, 99)),)
        return (jm.discounted(0.99) if PATTERN[i % 10] == "sum" else PATTERN[i % 10]), simple
    if features != "full":
        keep = {"ema": Ema, "window": Window, "histogram": Histogram}.get(features)
        stats = tuple(s for s in stats if isinstance(s, str) or (keep and isinstance(s, keep)))
    return PATTERN[i % 10], stats


def random_values(x: jax.Array, num_terms: int) -> jax.Array:
    """The `[N, num_envs]` values the floor sees: the same rows the spec's terms read."""
    return jnp.stack([x[i % 10] for i in range(num_terms)])


class FloorState(NamedTuple):
    """The hand-written floor: in-graph sum + count, nothing else."""

    ep_sum: jax.Array  # [M, E] float32: running episode sums
    total: jax.Array  # [M] float32: sum of finished episodes' sums
    episodes: jax.Array  # [] int32: finished episodes


def floor_init(num_metrics: int, num_envs: int) -> FloorState:
    return FloorState(
        jnp.zeros((num_metrics, num_envs), jnp.float32),
        jnp.zeros((num_metrics,), jnp.float32),
        jnp.zeros((), jnp.int32),
    )


def floor_update(s: FloorState, values: jax.Array, done: jax.Array) -> FloorState:
    ep = s.ep_sum + values.astype(jnp.float32)
    d = done.astype(jnp.bool_)[None, :]
    total = s.total + jnp.sum(jnp.where(d, ep, 0.0), axis=1)
    episodes = s.episodes + jnp.sum(done.astype(jnp.int32))
    return FloorState(jnp.where(d, 0.0, ep), total, episodes)


class LayoutFloorState(NamedTuple):
    """The floor over jaxmetrics' episode layout: the three `[M, E]` accumulators of
    `jaxmetrics._core._episode.EpisodeState` (a step count and two float slots), here a
    Welford mean and M2 per episode, and the finished episodes' means summed."""

    steps: jax.Array  # [M, E] int32
    mean: jax.Array  # [M, E] float32: running episode means
    m2: jax.Array  # [M, E] float32: their sums of squared deviations
    total: jax.Array  # [M] float32: sum of finished episodes' means
    episodes: jax.Array  # [] int32: finished episodes


def layout_floor_init(num_metrics: int, num_envs: int) -> LayoutFloorState:
    shape = (num_metrics, num_envs)
    zeros = jnp.zeros(shape, jnp.float32)
    return LayoutFloorState(
        jnp.zeros(shape, jnp.int32),
        zeros,
        zeros,
        jnp.zeros((num_metrics,), jnp.float32),
        jnp.zeros((), jnp.int32),
    )


def _row_sums(a: jax.Array) -> jax.Array:
    """`a[M, E]` summed over E, past 4,096 entries in parts of 256 and then the parts:
    summed whole in the accumulators' kernel, a row of 8,192 or 16,384 entries is one
    program of XLA's (as it was in `jaxmetrics._core._stream.batch_one_pass`, which reduces the
    same way). The barrier keeps XLA from merging the two sums back into one."""
    rows, width = a.shape
    if width <= 4096:
        return jnp.sum(a, axis=1)
    parts = -(-width // 256)
    padded = jnp.pad(a, ((0, 0), (0, parts * 256 - width)))
    partial = jax.lax.optimization_barrier(jnp.sum(padded.reshape(rows, parts, 256), axis=2))
    return jnp.sum(partial, axis=1)


def layout_floor_update(
    s: LayoutFloorState, values: jax.Array, done: jax.Array
) -> LayoutFloorState:
    steps = s.steps + 1
    x = values.astype(jnp.float32)
    delta = x - s.mean
    mean = s.mean + delta / steps.astype(jnp.float32)
    m2 = s.m2 + delta * (x - mean)
    d = done.astype(jnp.bool_)[None, :]
    total = s.total + _row_sums(jnp.where(d, mean, 0.0))
    episodes = s.episodes + jnp.sum(done.astype(jnp.int32))
    return LayoutFloorState(
        jnp.where(d, 0, steps),
        jnp.where(d, 0.0, mean),
        jnp.where(d, 0.0, m2),
        total,
        episodes,
    )


def sum_metrics(metrics: jm.Metrics) -> list[int]:
    """Indices (in definition order) of the sum-reduced metrics: those the floor matches."""
    return [i for i, s in enumerate(metrics.metric_specs.values()) if s.reduce == "sum"]


def compare_with_floor(metrics: jm.Metrics, report: dict[str, Any], floor: FloorState) -> dict:
    """Do jaxmetrics and the floor report the same counts and episode sums?

    Every metric's `/count` must equal the floor's episode count; every sum-reduced
    metric's `/sum` must equal the floor's total (to float32 summation order).
    """
    names = list(metrics.metric_specs)
    prefix = metrics.prefixes["episode"]
    episodes = int(floor.episodes)
    counts = [int(report[f"{prefix}/{n}/count"]) for n in names]
    sums = {names[i]: float(report[f"{prefix}/{names[i]}/sum"]) for i in sum_metrics(metrics)}
    totals = {names[i]: float(floor.total[i]) for i in sum_metrics(metrics)}
    rel = max((abs(sums[n] - totals[n]) / max(abs(totals[n]), 1e-30) for n in sums), default=0.0)
    return {
        "episodes": episodes,
        "counts": counts,
        "counts_equal": all(c == episodes for c in counts),
        "sum_metrics": len(sums),
        "jaxmetrics_sums": sums,
        "floor_totals": totals,
        "max_rel_diff_sum": rel,
    }


# ---------------------------------------------------------------- rollout terms (Brax)


def _reward(s):
    return s.reward


def _abs_reward(s):
    return jnp.abs(s.reward)


def _qvel_max(s):
    return jnp.max(jnp.abs(s.pipeline_state.qd), axis=-1)


def _obs_min(s):
    return jnp.min(s.obs, axis=-1)


def _obs_norm(s):
    return jnp.sqrt(jnp.sum(s.obs * s.obs, axis=-1))


def _obs0(s):
    return s.obs[..., 0]


def _alive(s):
    return 1.0 - s.done


def _qvel_mean(s):
    return jnp.mean(jnp.abs(s.pipeline_state.qd), axis=-1)


# (name, fn, histogram range) in pattern order; generic over Brax envs (no env-specific
# metrics keys), so the same spec runs on `ant` and on the cheap `inverted_pendulum`.
ROLLOUT_TERMS: tuple[tuple[str, Callable[[Any], jax.Array], tuple[float, float]], ...] = (
    ("reward", _reward, (0.0, 1.0)),
    ("abs_reward", _abs_reward, (0.0, 1.0)),
    ("reward_mean", _reward, (0.0, 1.0)),
    ("reward_std", _reward, (0.0, 1.0)),
    ("qvel_max", _qvel_max, (0.0, 50.0)),
    ("obs_min", _obs_min, (0.0, 1.0)),
    ("obs_norm", _obs_norm, (0.0, 1.0)),
    ("obs0_last", _obs0, (0.0, 1.0)),
    ("alive", _alive, (0.0, 1.0)),
    ("qvel_mean", _qvel_mean, (0.0, 20.0)),
)


def _of_transition(fn: Callable[[Any], jax.Array]) -> Callable[[Any], jax.Array]:
    def term(t):
        return fn(t.state)

    return term


def rollout_terms(
    window: int = 100, transition: bool = False, features: str = "full"
) -> dict[str, jm.Term]:
    """The 10 terms over a Brax `State` (read after `env.step`), or with `transition`
    over the `jaxmetrics.brax.Transition` that `MetricsWrapper` gives terms. `features`
    trims them as in `random_spec`."""
    terms = {}
    for i, (name, fn, hist) in enumerate(ROLLOUT_TERMS):
        reduce, stats = _trim(i, pattern_stats(i, window, hist), features)
        terms[name] = jm.Term(_of_transition(fn) if transition else fn, reduce=reduce, stats=stats)
    return terms


def rollout_spec(window: int = 100, transition: bool = False, features: str = "full") -> jm.Metrics:
    """The spec of `rollout_terms`."""
    return jm.Metrics(terms=rollout_terms(window, transition, features))


def rollout_values(state: Any) -> jax.Array:
    """The same 10 per-step values, stacked `[10, num_envs]` float32, for the others."""
    return jnp.stack([fn(state).astype(jnp.float32) for _, fn, _ in ROLLOUT_TERMS])


# ---------------------------------------------------------------- host-side loggers


class NumpyEpisodeLogger:
    """A per-episode host logger, vectorized over envs with numpy.

    Same reductions as the spec (`reductions[m]` per metric); finished episodes go into
    per-metric lists (the period) and 100-deep deques (the window). Fed one step at a time.
    """

    def __init__(self, reductions: Sequence[str], num_envs: int, window: int = 100):
        self.reductions = tuple(reductions)
        m = len(self.reductions)
        self.steps = np.zeros(num_envs, np.int64)
        self.sum = np.zeros((m, num_envs))
        self.sumsq = np.zeros((m, num_envs))
        self.max = np.full((m, num_envs), -np.inf)
        self.min = np.full((m, num_envs), np.inf)
        self.last = np.full((m, num_envs), np.nan)
        self.period: list[list[float]] = [[] for _ in range(m)]
        self.window = [collections.deque(maxlen=window) for _ in range(m)]

    def update(self, values: Any, done: Any) -> None:
        v = np.asarray(values, np.float64)
        d = np.asarray(done).astype(bool)
        self.steps += 1
        self.sum += v
        self.sumsq += v * v
        np.maximum(self.max, v, out=self.max)
        np.minimum(self.min, v, out=self.min)
        self.last[...] = v
        if not d.any():
            return
        idx = np.flatnonzero(d)
        n = self.steps[idx].astype(np.float64)
        for m, r in enumerate(self.reductions):
            s = self.sum[m, idx]
            if r == "sum":
                ep = s
            elif r == "mean":
                ep = s / n
            elif r == "std":
                ep = np.sqrt(np.maximum(self.sumsq[m, idx] / n - (s / n) ** 2, 0.0))
            else:
                ep = {"max": self.max, "min": self.min, "last": self.last}[r][m, idx]
            self.period[m].extend(ep.tolist())
            self.window[m].extend(ep.tolist())
        self.steps[idx] = 0
        self.sum[:, idx] = 0.0
        self.sumsq[:, idx] = 0.0
        self.max[:, idx] = -np.inf
        self.min[:, idx] = np.inf

    @property
    def episodes(self) -> int:
        return len(self.period[0]) if self.period else 0

    def totals(self) -> list[float]:
        return [float(np.sum(p)) for p in self.period]


class DictEpisodeLogger:
    """A per-env Python logger in the style of RLlib's `MetricsLogger` fed per env.

    One dict of running values per env, updated in a Python loop over envs and metrics.
    """

    def __init__(self, names: Sequence[str], reductions: Sequence[str], num_envs: int):
        self.names = tuple(names)
        self.reductions = dict(zip(self.names, reductions))
        self.running: list[dict[str, list[float]]] = [
            {n: [] for n in self.names} for _ in range(num_envs)
        ]
        self.period: dict[str, list[float]] = {n: [] for n in self.names}

    def update(self, values: Any, done: Any) -> None:
        v = np.asarray(values).tolist()
        d = np.asarray(done).astype(bool).tolist()
        for e, run in enumerate(self.running):
            for m, name in enumerate(self.names):
                run[name].append(v[m][e])
            if d[e]:
                for name, vals in run.items():
                    self.period[name].append(_reduce_list(self.reductions[name], vals))
                    vals.clear()

    @property
    def episodes(self) -> int:
        return len(self.period[self.names[0]]) if self.names else 0

    def totals(self) -> list[float]:
        return [float(np.sum(self.period[n])) for n in self.names]


def _reduce_list(r: str, vals: list[float]) -> float:
    if r == "sum":
        return sum(vals)
    if r == "mean":
        return sum(vals) / len(vals)
    if r == "std":
        return float(np.std(vals))
    if r == "max":
        return max(vals)
    if r == "min":
        return min(vals)
    return vals[-1]
