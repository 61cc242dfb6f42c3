"""Per-group statistics against a float64 reference that keeps one stream per group.

The reference is a hand loop: an episode joins the stream of the group its env is in on
the step it ends (and the metric's overall stream); a non-finite step counts in the group
its env is in on that step. Group indices out of range join the overall stream only and
count in `Counters/ungrouped`.
"""

import math
import re

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from jax.sharding import AxisType, NamedSharding
from jax.sharding import PartitionSpec as P
from reference import RefStream, episode_value
from test_core_reductions import EMA_C, HIST, PCTS, STATS, WINDOW, assert_stat_close, compare

import jaxmetrics as jm
from benchmarks._hlo import collectives, loop_body_ops

E, T = 8, 10
NAMES = ("flat", "rough", "stairs")
REDUCTIONS = {"r_sum": "sum", "r_max": "max"}


def make_metrics():
    terms = {
        name: jm.Term(lambda s, k: s["x"][k], reduce=red, stats=STATS, params={"k": k})
        for k, (name, red) in enumerate(REDUCTIONS.items())
    }
    return jm.Metrics(terms=terms, groups=jm.groups(lambda s: s["group"], NAMES))


METRICS = make_metrics()


class RefGroups:
    """Per metric: an overall stream and one per group, fed in ascending env order."""

    def __init__(self, num_envs: int, names=NAMES):
        kw = dict(ema_coeff=EMA_C, window=WINDOW, percentiles=PCTS, hist=HIST)
        self.names = names
        self.streams = {
            (m, g): RefStream(**kw) for m in REDUCTIONS for g in (None, *range(len(names)))
        }
        self.running = {m: [[] for _ in range(num_envs)] for m in REDUCTIONS}
        self.ungrouped = 0
        self.num_envs = num_envs

    def step(self, x: np.ndarray, group: np.ndarray, done: np.ndarray) -> None:
        for k, (m, red) in enumerate(REDUCTIONS.items()):
            for e in range(self.num_envs):
                g = int(group[e])
                targets = [None] + ([g] if 0 <= g < len(self.names) else [])
                v = float(x[k, e])
                if not math.isfinite(v):
                    for t in targets:
                        self.streams[(m, t)].nonfinite += 1
                self.running[m][e].append(v)
                if not done[e]:
                    continue
                ev = episode_value(self.running[m][e], red, skip_nonfinite=True)
                self.running[m][e] = []
                if ev is None:
                    continue
                for t in targets:
                    if not math.isfinite(ev):
                        self.streams[(m, t)].nonfinite += 1
                    self.streams[(m, t)].add(ev)
        self.ungrouped += int(np.sum(done & ((group < 0) | (group >= len(self.names)))))

    def reset_period(self) -> None:
        for s in self.streams.values():
            s.reset_period()

    def check(self, host: dict, skip=()) -> None:
        for (m, g), stream in self.streams.items():
            name = m if g is None else f"{m}/{self.names[g]}"
            want = {k: v for k, v in stream.report().items() if k not in skip}
            compare(METRICS, host, want, "Episode_Metrics", name)
        assert host["Counters/ungrouped"] == self.ungrouped


grid = st.integers(-800, 800).map(lambda k: k / 8 + 1 / 16)


@st.composite
def grouped_rollouts(draw):
    n = T * len(REDUCTIONS) * E
    xs = np.asarray(draw(st.lists(grid, min_size=n, max_size=n)), np.float32)
    xs = xs.reshape(T, len(REDUCTIONS), E)
    holes = np.asarray(draw(st.lists(st.integers(0, 12), min_size=n, max_size=n)))
    xs = np.where(holes.reshape(xs.shape) == 0, np.float32(np.nan), xs)
    # Mostly valid groups, some out of range on either side.
    groups = draw(st.lists(st.integers(-1, len(NAMES)), min_size=T * E, max_size=T * E))
    dones = draw(st.lists(st.integers(0, 2), min_size=T * E, max_size=T * E))
    flushes = draw(st.lists(st.booleans(), min_size=T, max_size=T))
    return (
        xs,
        np.asarray(groups, np.int32).reshape(T, E),
        np.asarray(dones).reshape(T, E) == 0,
        np.asarray(flushes),
    )


def _scan(metrics):
    def body(state, inp):
        x, g, d, flush = inp
        state = metrics.update(state, {"x": x, "group": g}, d)
        report = metrics.compute(state)
        state = jax.lax.cond(flush, metrics.reset_period, lambda s: s, state)
        return state, report

    return jax.jit(lambda s, *xs: jax.lax.scan(body, s, xs)[1])


_RUN = _scan(METRICS)


def check_rollout(state, xs, groups, dones, flushes, mesh=None):
    inputs = tuple(map(jnp.asarray, (xs, groups, dones, flushes)))
    if mesh is not None:  # the env axis (last) split like the state's envs
        inputs = (
            tuple(
                jax.device_put(a, NamedSharding(mesh, P(*(None,) * (a.ndim - 1), "env")))
                for a in inputs[:3]
            )
            + inputs[3:]
        )
    reports = jax.device_get(_RUN(state, *inputs))
    ref = RefGroups(E)
    for t in range(T):
        ref.step(xs[t], groups[t], dones[t])
        ref.check(METRICS.to_host(jax.tree.map(lambda a, t=t: a[t], reports)))
        if flushes[t]:
            ref.reset_period()


@settings(max_examples=30, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(grouped_rollouts())
def test_every_statistic_is_kept_per_group_at_the_step_the_episode_ends(data):
    check_rollout(METRICS.init(E), *data)


@settings(max_examples=5, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(grouped_rollouts())
def test_groups_of_a_sharded_state_match_the_reference(data):
    mesh = jax.make_mesh((4,), ("env",), axis_types=(AxisType.Auto,), devices=jax.devices()[:4])
    sharding = NamedSharding(mesh, P("env"))
    check_rollout(METRICS.init(E, sharding=sharding), *data, mesh=mesh)


def test_merged_states_keep_groups_exact():
    """Two workers' grouped states merged = one run over both env batches."""
    rng = np.random.default_rng(3)
    xs = rng.normal(size=(T, 2, 2 * E)).astype(np.float32)
    groups = rng.integers(-1, 4, size=(T, 2 * E)).astype(np.int32)
    dones = rng.random((T, 2 * E)) < 0.4
    update = jax.jit(METRICS.update)
    halves = []
    for part in (slice(0, E), slice(E, 2 * E)):
        s = METRICS.init(E)
        for t in range(T):
            s = update(s, {"x": xs[t][:, part], "group": groups[t, part]}, dones[t, part])
        halves.append(s)
    host = METRICS.to_host(METRICS.compute(METRICS.merge(*halves)))
    ref = RefGroups(2 * E)
    for t in range(T):
        ref.step(xs[t], groups[t], dones[t])
    # The EMA of states merged without EMA history is the workers' average (documented).
    ref.check(host, skip=("ema",))


def test_term_groups_override_the_spec_default_and_groupings_are_independent():
    task = jm.groups(lambda s: s["task"], ("walk", "run"))
    level = jm.groups(lambda s: s["level"], ("easy", "hard"))
    m = jm.Metrics(
        terms={
            "a": jm.Term(lambda s: s["x"], reduce="sum", stats=("mean", "count")),
            "b": jm.Term(lambda s: s["x"], reduce="sum", stats=("count",), groups=level),
        },
        groups=task,
    )
    step = {
        "x": jnp.array([1.0, 2.0, 3.0, 4.0]),
        "task": jnp.array([0, 1, 1, 5]),
        "level": jnp.array([1, 1, 0, 1]),
    }
    state = m.update(m.init(4), step, jnp.array([True, True, True, True]))
    host = m.to_host(m.compute(state))
    assert host["Episode_Metrics/a/walk"] == 1.0 and host["Episode_Metrics/a/run"] == 2.5
    assert host["Episode_Metrics/a"] == 2.5 and host["Episode_Metrics/a/count"] == 4
    assert host["Episode_Metrics/b/easy/count"] == 1 and host["Episode_Metrics/b/hard/count"] == 3
    assert "Episode_Metrics/b/walk/count" not in host
    assert host["Counters/ungrouped"] == 1  # env 3's task 5; every level is in range
    assert [i.tag for i in m.tags if i.metric.startswith("a")] == [
        "Episode_Metrics/a",
        "Episode_Metrics/a/count",
        "Episode_Metrics/a/nonfinite",
        "Episode_Metrics/a/walk",
        "Episode_Metrics/a/walk/count",
        "Episode_Metrics/a/walk/nonfinite",
        "Episode_Metrics/a/run",
        "Episode_Metrics/a/run/count",
        "Episode_Metrics/a/run/nonfinite",
    ]


def test_group_indices_may_be_bool_or_host_ints_of_any_width():
    m = jm.Metrics(
        terms={"r": jm.Term(lambda s: s["x"], reduce="sum", stats=("count",))},
        groups=jm.groups(lambda s: s["g"], ("no", "yes")),
    )
    x = jnp.ones(3)
    done = jnp.ones(3, bool)
    for g, want in (
        (jnp.array([True, False, True]), (1, 2, 0)),
        (np.array([1, 0, 2**40], np.int64), (1, 1, 1)),  # 2^40 is out of range, not 0
        (np.array([1, 1, -(2**40)], np.int64), (0, 2, 1)),
    ):
        host = m.to_host(m.compute(m.update(m.init(3), {"x": x, "g": g}, done)))
        got = tuple(
            host[t]
            for t in (
                "Episode_Metrics/r/no/count",
                "Episode_Metrics/r/yes/count",
                "Counters/ungrouped",
            )
        )
        assert got == want


def test_running_values_and_logger_records_have_the_group_tags():
    m = jm.Metrics(
        terms={"r": jm.Term(lambda s: s["x"], reduce="sum", stats=("mean",))},
        groups=jm.groups(lambda s: s["g"], ("a", "b")),
    )
    writer = jm.MemoryWriter()
    with jm.Logger(m, [writer], include_running=True) as logger:
        state = m.update(
            m.init(2),
            {"x": jnp.array([1.0, 2.0]), "g": jnp.array([1, 0])},
            jnp.array([True, False]),
        )
        logger.flush(state, step=1)
    (rec,) = writer.records
    assert rec.scalars["Episode_Metrics/r/b"] == 1.0
    assert "Episode_Metrics/r/a" not in rec.scalars  # no episode of group a: NaN, not written
    assert rec.scalars["Episode_Metrics/r/running"] == 2.0
    running = [t for t in rec.scalars if t.endswith("/running")]
    assert running == ["Episode_Metrics/r/running"]  # running values are per metric only


@pytest.mark.parametrize(
    "names, match",
    [
        ("flat", r"non-empty sequence"),
        ((), r"non-empty sequence"),
        (("a", "a"), r"duplicate group names"),
        (("a/b",), r"contains '/'"),
        (("std",), r"also a statistic's name"),
        (("window_p50",), r"also a statistic's name"),
        (("",), r"non-empty strings"),
    ],
)
def test_bad_group_names_are_refused_with_the_fix(names, match):
    with pytest.raises(ValueError, match=match):
        jm.groups(lambda s: s, names)


def test_groups_that_are_not_a_grouping_are_refused():
    with pytest.raises(TypeError, match=r"term 'r': groups must be jaxmetrics.groups"):
        jm.Metrics(terms={"r": jm.Term(lambda s: s, groups=("a", "b"))})
    with pytest.raises(TypeError, match=r"Metrics\(groups=...\) takes"):
        jm.Metrics(terms={"r": lambda s: s}, groups=lambda s: s)
    with pytest.raises(TypeError, match=r"fn must be callable"):
        jm.groups("task", ("a",))


def test_group_tags_that_collide_after_sanitization_are_refused():
    grouping = jm.groups(lambda s: s, ("hard mode", "hard_mode"))
    with pytest.raises(ValueError, match=r"tag collision.*hard_mode"):
        jm.Metrics(terms={"r": jm.Term(lambda s: s, groups=grouping)})
    with pytest.raises(ValueError, match=r"tag collision"):
        jm.Metrics(
            terms={
                "r": jm.Term(lambda s: s, groups=jm.groups(lambda s: s, ("x",))),
                "r/x": jm.Term(lambda s: s),
            }
        )


@pytest.mark.parametrize(
    "group_fn, err, match",
    [
        (
            lambda s: s.astype(jnp.float32),
            TypeError,
            r"groups \['a', 'b'\] of term 'r'.*dtype float32",
        ),
        (lambda s: jnp.zeros((3, 1), jnp.int32), ValueError, r"shape \(3, 1\).*one index per env"),
        (lambda s: None, TypeError, r"groups \['a', 'b'\] of term 'r'.*None"),
    ],
)
def test_bad_group_indices_are_refused_at_trace_time(group_fn, err, match):
    m = jm.Metrics(
        terms={"r": lambda s: s.astype(jnp.float32)}, groups=jm.groups(group_fn, ("a", "b"))
    )
    with pytest.raises(err, match=match):
        jax.jit(m.update)(m.init(3), jnp.arange(3), jnp.ones(3, bool))


def test_ungrouped_is_a_builtin_counter_only_with_groups():
    plain = jm.Metrics(terms={"r": lambda s: s})
    assert "ungrouped" not in plain.counter_names
    grouped = jm.Metrics(terms={"r": lambda s: s}, groups=jm.groups(lambda s: s, ("a",)))
    assert grouped.counter_names[:3] == ("env_steps", "episodes", "ungrouped")
    with pytest.raises(ValueError, match=r"'ungrouped' is counted by update"):
        grouped.increment(grouped.init(2), "ungrouped")
    with pytest.raises(ValueError, match=r"built in"):
        jm.Metrics(
            terms={"r": lambda s: s}, counters=("ungrouped",), groups=jm.groups(lambda s: s, ("a",))
        )
    assert jm.Metrics(terms={"r": lambda s: s}, counters=("ungrouped",)).counter_names[-1] == (
        "ungrouped"
    )


def test_group_names_are_part_of_the_spec_identity():
    a = jm.Metrics(terms={"r": lambda s: s}, groups=jm.groups(lambda s: s, ("a", "b")))
    b = jm.Metrics(terms={"r": lambda s: s}, groups=jm.groups(lambda s: s, ("a", "c")))
    with pytest.raises(ValueError, match=r"different Metrics spec"):
        b.compute(a.init(2))


def test_window_percentile_values_per_group_follow_arrival_order():
    """Windows per group keep the newest values of that group only (ascending env index
    within a step)."""
    m = jm.Metrics(
        terms={"r": jm.Term(lambda s: s["x"], reduce="last", stats=(jm.window(2),))},
        groups=jm.groups(lambda s: s["g"], ("a", "b")),
    )
    state = m.init(4)
    for x, g in (([1, 2, 3, 4], [0, 1, 0, 1]), ([5, 6, 7, 8], [1, 1, 0, 0])):
        step = {"x": jnp.asarray(x, jnp.float32), "g": jnp.asarray(g)}
        state = m.update(state, step, jnp.ones(4, bool))
    host = m.to_host(m.compute(state))
    np.testing.assert_array_equal(host["Episode_Metrics/r/a/window_values"], [7.0, 8.0])
    np.testing.assert_array_equal(host["Episode_Metrics/r/b/window_values"], [5.0, 6.0])
    np.testing.assert_array_equal(host["Episode_Metrics/r/window_values"], [7.0, 8.0])
    assert_stat_close(host["Episode_Metrics/r/b/window_mean"], 5.5, "window_mean")


@pytest.mark.parametrize("axis_type", [AxisType.Auto, AxisType.Explicit])
def test_grouped_step_loop_has_no_cross_device_collectives(axis_type):
    """Groups split rows, never envs: a sharded grouped state still folds shard-locally,
    and gives the unsharded result."""
    mesh = jax.make_mesh((4,), ("env",), axis_types=(axis_type,), devices=jax.devices()[:4])
    rng = np.random.default_rng(5)
    xs = rng.normal(size=(T, 2, 16)).astype(np.float32)
    groups = rng.integers(-1, 4, size=(T, 16)).astype(np.int32)
    dones = rng.random((T, 16)) < 0.3

    def run(sharding):
        def go(xs, groups, dones):
            state = METRICS.init(16, sharding=sharding)
            body = lambda s, a: (METRICS.update(s, {"x": a[0], "group": a[1]}, a[2]), None)  # noqa: E731
            return jax.lax.scan(body, state, (xs, groups, dones))[0]

        return jax.jit(go)

    with jax.set_mesh(mesh):
        args = [
            jax.device_put(a, NamedSharding(mesh, P(*(None,) * (a.ndim - 1), "env")))
            for a in (xs, groups, dones)
        ]
        sharded = run(NamedSharding(mesh, P("env")))
        ops = loop_body_ops(sharded.lower(*args).compile().as_text())
        assert ops and collectives(ops) == {}, collectives(ops)
        got = METRICS.to_host(METRICS.compute(sharded(*args)))
    want = METRICS.to_host(METRICS.compute(run(None)(xs, groups, dones)))
    assert got.keys() == want.keys()
    for tag, w in want.items():
        np.testing.assert_allclose(np.asarray(got[tag], np.float64), w, rtol=2e-6, err_msg=tag)


def _many_groups(n: int, stats=("mean", "std", "count")) -> jm.Metrics:
    return jm.Metrics(
        terms={"r": jm.Term(lambda s: s["x"], reduce="sum", stats=stats)},
        groups=jm.groups(lambda s: s["g"], tuple(f"g{i}" for i in range(n))),
    )


def _ops(text: str) -> int:
    return len(re.findall(r"\bstablehlo\.\w+", text))


FULL_STATS = (*STATS, jm.quantiles((50, 99)))


@pytest.mark.parametrize("stats", [("mean", "std", "count"), FULL_STATS])
def test_compute_lowers_to_the_same_program_at_any_number_of_groups(stats):
    """Groups are an axis of the report's columns: ops and outputs one per group made
    compile time grow faster than the groups (4 s at 100 groups, minutes at 1,000)."""

    def lowered(n):
        m = _many_groups(n, stats)
        return jax.jit(m.compute).lower(m.init(4)).as_text()

    few, many = lowered(10), lowered(1000)
    assert _ops(many) == _ops(few)
    assert len(many) < 1.5 * len(few)  # static row indices are the only growth


def test_thousands_of_groups_match_a_float64_reference():
    n, envs, steps = 2000, 4096, 6
    rng = np.random.default_rng(11)
    xs = rng.normal(3.0, 2.0, size=(steps, envs)).astype(np.float32)
    groups = rng.integers(-3, n + 3, size=(steps, envs)).astype(np.int32)
    dones = rng.random((steps, envs)) < 0.5
    m = _many_groups(n)

    def go(xs, groups, dones):
        body = lambda s, a: (m.update(s, {"x": a[0], "g": a[1]}, a[2]), None)  # noqa: E731
        return m.compute(jax.lax.scan(body, m.init(envs), (xs, groups, dones))[0])

    host = m.to_host(jax.jit(go)(xs, groups, dones))

    # Each episode's sum, in the group its env is in on the step the episode ends.
    running = np.zeros(envs)
    values, ends = [], []
    for t in range(steps):
        running += xs[t]
        values.append(running[dones[t]])
        ends.append(groups[t][dones[t]])
        running[dones[t]] = 0.0
    every, g = np.concatenate(values), np.concatenate(ends)
    inside = (g >= 0) & (g < n)
    v, g = every[inside], g[inside]
    count = np.bincount(g, minlength=n)
    mean = np.bincount(g, weights=v, minlength=n) / np.maximum(count, 1)
    std = np.sqrt(np.bincount(g, weights=(v - mean[g]) ** 2, minlength=n) / np.maximum(count, 1))
    empty = count == 0
    assert empty.any() and not empty.all()  # both kinds of groups are checked

    def column(stat):
        suffix = "" if stat == "mean" else f"/{stat}"
        return np.array([host[f"Episode_Metrics/r/g{i}{suffix}"] for i in range(n)])

    np.testing.assert_array_equal(column("count"), count)
    for stat, want in (("mean", mean), ("std", std)):
        got = column(stat)
        assert np.isnan(got[empty]).all(), stat
        np.testing.assert_allclose(got[~empty], want[~empty], rtol=1e-5, atol=1e-5, err_msg=stat)
    assert host["Counters/ungrouped"] == int((~inside).sum())
    assert host["Episode_Metrics/r/count"] == every.size
    np.testing.assert_allclose(host["Episode_Metrics/r"], every.mean(), rtol=1e-5)
