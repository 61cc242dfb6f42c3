"""Per-group period statistics by segment reductions, against a float64 reference that keeps
one stream per group (a hand loop over steps and envs).

The group rows of a metric whose statistics are period statistics only are folded by
segment reductions over the group index; a grouped metric with an EMA or a window keeps one
row per group. The spec mixes both, with two groupings of different sizes, so that the
segment rows sit between rows folded as rows. Data far from zero is held to the period
statistics' own bounds (mean within 1e-6, std within 1e-4 of float64); a group index out
of range joins no group (only the overall row and `Counters/ungrouped`).
"""

import math
import re
from unittest import mock

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from jax.sharding import AxisType, NamedSharding
from jax.sharding import PartitionSpec as P
from reference import SIMPLE_STATS, RefStream, episode_value
from test_core_reductions import assert_stat_close

import jaxmetrics as jm
from benchmarks._hlo import COLLECTIVES
from jaxmetrics._core._stream import SegmentPlan

E, T = 12, 10
FIRST = ("f0", "f1", "f2", "f3", "f4")
SECOND = ("s0", "s1", "s2")
EMA_C, WINDOW = 0.3, 3
# name -> (row of the step input, reduction, statistics, grouping, nonfinite policy). Rows
# sort by reduction: sum, max, min, last; the window/EMA metric `w` (rows per group) sits
# between segment metrics.
TERMS = {
    "a": (0, "sum", SIMPLE_STATS, FIRST, "skip"),
    "w": (1, "max", ("mean", "count", jm.ema(EMA_C), jm.window(WINDOW)), FIRST, "skip"),
    "p": (2, "min", SIMPLE_STATS, SECOND, "propagate"),
    "x": (3, "last", SIMPLE_STATS, SECOND, "skip"),
}
FAR = ("w", "x")  # rows that get the offset: max and last keep the values exact


def _metrics() -> jm.Metrics:
    groupings = {
        FIRST: jm.groups(lambda s: s["g1"], FIRST),
        SECOND: jm.groups(lambda s: s["g2"], SECOND),
    }
    return jm.Metrics(
        terms={
            name: jm.Term(
                lambda s, k: s["x"][k],
                reduce=red,
                stats=stats,
                params={"k": k},
                groups=groupings[names],
                nonfinite=policy,
            )
            for name, (k, red, stats, names, policy) in TERMS.items()
        }
    )


METRICS = _metrics()


class Reference:
    """Per metric: an overall stream and one per group, fed in ascending env order."""

    def __init__(self, num_envs: int):
        self.streams = {}
        for m, (_, _, _, names, policy) in TERMS.items():
            kw = {"ema_coeff": EMA_C, "window": WINDOW} if m == "w" else {}
            for g in (None, *range(len(names))):
                self.streams[(m, g)] = RefStream(skip=policy == "skip", **kw)
        self.running = {m: [[] for _ in range(num_envs)] for m in TERMS}
        self.ungrouped = 0

    def step(self, x: np.ndarray, g1: np.ndarray, g2: np.ndarray, done: np.ndarray) -> None:
        for m, (k, red, _, names, policy) in TERMS.items():
            group = g1 if names is FIRST else g2
            for e in range(len(done)):
                g = int(group[e])
                targets = [None] + ([g] if 0 <= g < len(names) else [])
                v = float(x[k, e])
                if not math.isfinite(v):
                    for t in targets:
                        self.streams[(m, t)].nonfinite += 1
                self.running[m][e].append(v)
                if not done[e]:
                    continue
                ev = episode_value(self.running[m][e], red, skip_nonfinite=policy == "skip")
                self.running[m][e] = []
                if ev is None:
                    continue
                for t in targets:
                    if policy == "skip" and not math.isfinite(ev):
                        self.streams[(m, t)].nonfinite += 1
                    self.streams[(m, t)].add(ev)
        out = [((i < 0) | (i >= len(n))) & done for i, n in ((g1, FIRST), (g2, SECOND))]
        self.ungrouped += int(np.sum(out[0])) + int(np.sum(out[1]))

    def reset_period(self) -> None:
        for s in self.streams.values():
            s.reset_period()

    def check(self, host: dict) -> None:
        for (m, g), stream in self.streams.items():
            names = TERMS[m][3]
            name = m if g is None else f"{m}/{names[g]}"
            want = stream.report()
            for stat, w in want.items():
                tag = f"Episode_Metrics/{name}" + ("" if stat == "mean" else f"/{stat}")
                if stat == "histogram" or tag not in host:
                    continue
                got = host[tag]
                if (
                    m in FAR
                    and stat in ("mean", "std", "sum")
                    and want["count"]
                    and math.isfinite(w)
                ):
                    _assert_moment(got, w, want, stat, tag)
                else:
                    assert_stat_close(got, w, tag, propagate=TERMS[m][4] == "propagate")
        assert host["Counters/ungrouped"] == self.ungrouped


def _assert_moment(got: float, want: float, report: dict, stat: str, tag: str) -> None:
    """The period statistics' bounds (docs/semantics.md, "Numerics"): the mean within 1e-6
    of the mean (or of the spread, near zero), the sum within that times the count, and,
    for a spread of at least 1e-3 of the mean, the std within 1e-4 of itself; a narrower
    spread (a few values close together) within 2^-20 of the mean, a few float32 ulp."""
    mean, std = abs(report["mean"]), report["std"]
    if stat == "mean":
        assert abs(got - want) <= 1e-6 * max(mean, std), (tag, got, want)
    elif stat == "sum":
        assert abs(got - want) <= 1e-6 * max(mean, std) * report["count"], (tag, got, want)
    elif std >= 1e-3 * mean:
        assert abs(got - want) <= 1e-4 * std, (tag, got, want)
    else:
        assert abs(got - want) <= 2**-20 * mean, (tag, got, want)


def _scan(metrics):
    def body(state, inp):
        x, g1, g2, d, flush = inp
        state = metrics.update(state, {"x": x, "g1": g1, "g2": g2}, d)
        report = metrics.compute(state)
        state = jax.lax.cond(flush, metrics.reset_period, lambda s: s, state)
        return state, report

    return jax.jit(lambda s, *xs: jax.lax.scan(body, s, xs)[1])


_RUN = _scan(METRICS)
_RUN_MASKED = _scan(METRICS)  # traced with the group rows folded as masked rows

grid = st.integers(-800, 800).map(lambda k: k / 8 + 1 / 16)
# Group indices: mostly in range, some just out of it, some far out (the int32 extremes).
group_index = st.one_of(
    st.integers(-2, 6), st.sampled_from([-(2**31), 2**31 - 1, 1000]), st.integers(0, 4)
)


@st.composite
def rollouts(draw):
    n = T * len(TERMS) * E
    xs = np.asarray(draw(st.lists(grid, min_size=n, max_size=n)), np.float64)
    xs = xs.reshape(T, len(TERMS), E)
    offset = draw(st.sampled_from([0.0, 1.0, 1e4, -1e4, 1e6]))
    spread = draw(st.sampled_from([1e-3, 1e-1, 1.0])) * max(abs(offset), 1.0) / 100
    far = [TERMS[m][0] for m in FAR]
    xs[:, far] = offset + spread * xs[:, far]
    xs = xs.astype(np.float32)
    holes = np.asarray(draw(st.lists(st.integers(0, 15), min_size=n, max_size=n)))
    holes = holes.reshape(xs.shape)
    xs = np.where(holes == 0, np.float32(np.nan), xs)
    xs = np.where(holes == 1, np.float32(np.inf), xs)
    g1, g2 = (
        np.asarray(draw(st.lists(group_index, min_size=T * E, max_size=T * E)), np.int32)
        for _ in range(2)
    )
    dones = draw(st.lists(st.integers(0, 2), min_size=T * E, max_size=T * E))
    flushes = draw(st.lists(st.booleans(), min_size=T, max_size=T))
    return (
        xs,
        g1.reshape(T, E),
        g2.reshape(T, E),
        np.asarray(dones).reshape(T, E) == 0,
        np.asarray(flushes),
    )


def _check(state, xs, g1, g2, dones, flushes, sharding=None, run=_RUN):
    inputs = tuple(map(jnp.asarray, (xs, g1, g2, dones, flushes)))
    if sharding is not None:  # the env axis (last) split like the state's envs
        mesh = sharding.mesh
        inputs = (
            tuple(
                jax.device_put(a, NamedSharding(mesh, P(*(None,) * (a.ndim - 1), "env")))
                for a in inputs[:4]
            )
            + inputs[4:]
        )
    with np.errstate(all="ignore"):
        reports = jax.device_get(run(state, *inputs))
    ref = Reference(E)
    for t in range(T):
        ref.step(xs[t], g1[t], g2[t], dones[t])
        with np.errstate(all="ignore"):
            host = METRICS.to_host(jax.tree.map(lambda a, t=t: a[t], reports))
        ref.check(host)
        if flushes[t]:
            ref.reset_period()


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(rollouts())
def test_group_period_statistics_match_a_float64_reference(data):
    _check(METRICS.init(E), *data)


@settings(max_examples=5, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(rollouts())
def test_group_period_statistics_of_a_sharded_state_match_the_reference(data):
    mesh = jax.make_mesh((2,), ("env",), devices=jax.devices()[:2])
    sharding = NamedSharding(mesh, P("env"))
    _check(METRICS.init(E, sharding=sharding), *data, sharding=sharding)


@settings(max_examples=10, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(rollouts())
def test_group_period_statistics_as_masked_rows_match_the_reference(data):
    # An accelerator folds the group rows of a small batch as masked rows
    # (`SegmentPlan.serves`): the same numbers as the segments.
    with mock.patch.object(SegmentPlan, "serves", lambda *_: False):
        _check(METRICS.init(E), *data, run=_RUN_MASKED)


def test_segments_serve_every_batch_on_cpu_and_large_ones_elsewhere(monkeypatch):
    plan = METRICS._rows.ep_segments
    assert plan is not None and plan.rows > 0

    def scatters(serves: bool) -> int:
        g = jnp.zeros((E,), jnp.int32)
        step = {"x": jnp.zeros((len(TERMS), E), jnp.float32), "g1": g, "g2": g}
        with mock.patch.object(SegmentPlan, "serves", lambda *_: serves):
            jaxpr = jax.make_jaxpr(METRICS.update)(METRICS.init(E), step, g > 0)
        return str(jaxpr).count("scatter")

    assert scatters(True) > scatters(False)  # the switch picks the fold
    assert plan.serves(1)  # this suite runs on the CPU
    monkeypatch.setattr(jax, "default_backend", lambda: "gpu")
    seg = jm._core._stream._segments
    limit = seg.ACCELERATOR_MIN_ENTRIES
    assert plan.rows < seg.ACCELERATOR_MIN_GROUPS * len(plan.blocks)  # few groups: masked
    assert not plan.serves(1) and not plan.serves(limit)
    monkeypatch.setattr(seg, "ACCELERATOR_MIN_GROUPS", 1)
    assert not plan.serves(-(-limit // plan.rows) - 1)
    assert plan.serves(-(-limit // plan.rows))


def _shapes(hlo_text: str) -> list[tuple[int, ...]]:
    """The shape of every array in HLO text."""
    dims = re.findall(r"\b(?:pred|[suf]\d+|bf16)\[([\d,]*)\]", hlo_text)
    return [tuple(int(d) for d in s.split(",") if d) for s in dims]


def test_period_statistics_of_64_groups_hold_no_array_of_groups_times_envs():
    """The scaling, pinned: with 64 groups of period statistics the compiled step holds no
    array of 64 x envs elements or more (the report rows masked per group were
    metrics x 65 rows x envs); only [metrics, envs] batches and [rows] statistics."""
    groups, envs, metrics = 64, 256, 3
    names = tuple(f"g{i}" for i in range(groups))
    m = jm.Metrics(
        terms={
            f"m{k}": jm.Term(
                lambda s, k: s["x"][k], reduce=red, params={"k": k}, stats=SIMPLE_STATS
            )
            for k, red in enumerate(("sum", "mean", "max"))
        },
        groups=jm.groups(lambda s: s["g"], names),
    )

    def run(state, x, g, done):
        def body(s, inp):
            return m.update(s, {"x": inp[0], "g": inp[1]}, inp[2]), None

        return jax.lax.scan(body, state, (x, g, done))[0]

    args = (
        m.init(envs),
        jnp.zeros((4, metrics, envs), jnp.float32),
        jnp.zeros((4, envs), jnp.int32),
        jnp.zeros((4, envs), bool),
    )
    text = jax.jit(run).lower(*args).compile().as_text()
    shapes = _shapes(text)
    assert (metrics, envs) in shapes or (metrics * envs,) in shapes  # the batch is there
    big = [s for s in shapes if math.prod(s) >= groups * envs]
    assert big == [], big


@settings(max_examples=20, deadline=None)
@given(seed=st.integers(0, 2**16), offset=st.sampled_from([0.0, 1e4, -1e6]))
def test_both_scatter_forms_give_each_groups_batch_statistics(seed, offset):
    """`segment_batch`'s CPU form (a scatter per statistic) and its accelerator form (one
    per kind of combination) against numpy, per source and group, on one CPU."""
    from jaxmetrics._core._stream import _segments

    rng = np.random.default_rng(seed)
    sources, envs, groups = 3, 64, np.array([5, 2, 5], np.int32)
    values = (offset + rng.normal(size=(sources, envs))).astype(np.float32)
    values[rng.random(values.shape) < 0.05] = np.nan
    ok = (rng.random(values.shape) < 0.5) & np.isfinite(values)
    bad = (~np.isfinite(values)).astype(np.int32)
    group = rng.integers(-2, 7, size=values.shape).astype(np.int32)
    shift = np.where(rng.random((sources, 5)) < 0.5, 0, offset).astype(np.float32)
    args = tuple(map(jnp.asarray, (values, ok, bad, group, shift)))
    forms = [
        [np.asarray(a) for a in _segments._segment_batch(form, *args, groups)]
        for form in (_segments.scatter_each, _segments.scatter_stacked)
    ]
    for s in range(sources):
        for g in range(groups[s]):
            inside = group[s] == g
            x = values[s][inside & ok[s]].astype(np.float64)
            for k, bsum, bmin, bmax, mb, m2b, nbad in (
                [f[i][s, g] for i in range(7)] for f in forms
            ):
                assert k == len(x) and nbad == int(np.sum(bad[s][inside]))
                if not len(x):
                    assert bsum == 0 and bmin == np.inf and bmax == -np.inf
                    continue
                assert (bmin, bmax) == (x.min(), x.max())
                # A float32 sum: within its rounding of the values' magnitudes.
                assert abs(bsum - x.sum()) <= 1e-6 * np.abs(x).sum()
                spread = max(x.std(), 1e-6 * abs(x.mean()))
                # The mean less the shift, within float32 rounding of the mean.
                assert abs(mb + shift[s, g] - x.mean()) <= 1e-6 * max(abs(x.mean()), spread)
                np.testing.assert_allclose(m2b, np.sum((x - x.mean()) ** 2), rtol=1e-4, atol=1e-6)


@pytest.mark.parametrize("axis_type", [AxisType.Auto, AxisType.Explicit])
def test_both_scatter_forms_fold_env_shards_alone(axis_type):
    """Per env shard (`vmap` over a leading axis split over devices, as `update` folds a
    sharded state), each form gives the unsharded numbers, with no collective."""
    from jaxmetrics._core._stream import _segments

    rng = np.random.default_rng(0)
    shards, sources, envs, groups = 4, 2, 16, np.array([3, 2], np.int32)
    values = rng.normal(size=(shards, sources, envs)).astype(np.float32)
    ok = rng.random(values.shape) < 0.5
    bad = (rng.random(values.shape) < 0.1).astype(np.int32)
    group = rng.integers(-1, 4, size=values.shape).astype(np.int32)
    shift = rng.normal(size=(shards, sources, 3)).astype(np.float32)
    mesh = jax.make_mesh((shards,), ("env",), axis_types=(axis_type,), devices=jax.devices()[:4])
    for form in (_segments.scatter_each, _segments.scatter_stacked):
        run = jax.jit(jax.vmap(lambda *a, form=form: _segments._segment_batch(form, *a, groups)))
        want = jax.device_get(run(values, ok, bad, group, shift))
        with jax.set_mesh(mesh):
            args = [
                jax.device_put(a, NamedSharding(mesh, P("env")))
                for a in (values, ok, bad, group, shift)
            ]
            hlo = run.lower(*args).compile().as_text()
            assert not any(op in hlo for op in COLLECTIVES), hlo
            got = jax.device_get(run(*args))
        for g, w in zip(got, want):
            np.testing.assert_array_equal(g, w)
