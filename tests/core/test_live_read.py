"""`Metrics.read`: the live statistics a curriculum reads in-graph, after every step of a
scan, against a float64 hand loop of the finished episodes so far, per group; under `vmap`
over seeds and with the envs sharded over 2 and 4 devices; and what it compiles to.

The reference keeps an overall stream and one per group (an episode joins the group its
env is in on the step it ends), fed in ascending env index, as `Metrics` defines it.
"""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from jax.sharding import AxisType, NamedSharding
from jax.sharding import PartitionSpec as P
from reference import RefStream, episode_value

import jaxmetrics as jm
from benchmarks._hlo import collectives, loop_body_ops

E, T, WINDOW, EMA_C = 8, 12, 5, 0.3
NAMES = ("easy", "mid", "hard")
# (statistic, the reference's key): window_count is the window's length.
READS = ("mean", "count", "ema", "window_mean", "window_std", "window_count", "window_p50")
METRICS = jm.Metrics(
    terms={
        "ret": jm.Term(
            lambda s: s["x"],
            reduce="sum",
            stats=("mean", "count", jm.ema(EMA_C), jm.window(WINDOW, (50,))),
        ),
        "success_rate": jm.success_rate(lambda s: s["x"] > 0, window_size=WINDOW, ema_coeff=EMA_C),
    },
    groups=jm.groups(lambda s: s["level"], NAMES),
)
FLAG_READS = ("mean", "count", "ema", "window_mean", "window_count")


def reference(xs, levels, dones, flushes):
    """Per step, per (metric, group or None), the float64 statistics of the episodes
    finished so far (period statistics since the last flush before that step)."""
    kw = dict(ema_coeff=EMA_C, window=WINDOW, percentiles=(50,))
    keys = [(m, g) for m in ("ret", "success_rate") for g in (None, *range(len(NAMES)))]
    streams = {k: RefStream(**kw) for k in keys}
    running = {m: [[] for _ in range(E)] for m in ("ret", "success_rate")}
    out = []
    for t in range(T):
        for e in range(E):
            x = float(xs[t, e])
            for m, red, v in (("ret", "sum", x), ("success_rate", "last", float(x > 0))):
                running[m][e].append(v)
                if dones[t, e]:
                    ev = episode_value(running[m][e], red, skip_nonfinite=True)
                    running[m][e] = []
                    g = int(levels[t, e])
                    for k in [(m, None)] + ([(m, g)] if 0 <= g < len(NAMES) else []):
                        streams[k].add(ev)
        step = {}
        for k, s in streams.items():
            r = s.report()
            r["window_count"] = len(s.window)
            step[k] = r
        out.append(step)
        if flushes[t]:
            for s in streams.values():
                s.reset_period()
    return out


def scan_reads(state, xs, levels, dones, flushes):
    """After every step (before its flush), every read of both metrics, overall and by
    group."""

    def body(state, inp):
        x, level, done, flush = inp
        state = METRICS.update(state, {"x": x, "level": level}, done)
        got = {}
        for m, stats in (("ret", READS), ("success_rate", FLAG_READS)):
            for stat in stats:
                got[m, stat, False] = METRICS.read(state, m, stat)
                got[m, stat, True] = METRICS.read(state, m, stat, by_group=True)
        state = jax.lax.cond(flush, METRICS.reset_period, lambda s: s, state)
        return state, got

    return jax.lax.scan(body, state, (xs, levels, dones, flushes))[1]


def assert_follow(got, want):
    for (m, stat, by_group), values in got.items():
        values = np.asarray(values, np.float64)
        assert values.shape == ((T, len(NAMES)) if by_group else (T,)), (m, stat, by_group)
        for t in range(T):
            groups = range(len(NAMES)) if by_group else [None]
            for j, g in enumerate(groups):
                v = values[t, j] if by_group else values[t]
                w = float(want[t][m, g][stat])
                where = f"{m}/{stat} group {g} after step {t}"
                if math.isnan(w):
                    assert math.isnan(v), where
                else:
                    assert v == pytest.approx(w, rel=2e-6, abs=2e-6), where


grid = st.integers(-40, 40).map(lambda k: k / 4)


@st.composite
def rollouts(draw):
    xs = np.asarray(draw(st.lists(grid, min_size=T * E, max_size=T * E)), np.float32)
    # Levels 0..2 and one out of range (3): its episodes count only overall.
    levels = np.asarray(draw(st.lists(st.integers(0, 3), min_size=T * E, max_size=T * E)))
    dones = np.asarray(draw(st.lists(st.integers(0, 2), min_size=T * E, max_size=T * E))) == 0
    flushes = np.asarray(draw(st.lists(st.booleans(), min_size=T, max_size=T)))
    return (
        xs.reshape(T, E),
        levels.reshape(T, E).astype(np.int32),
        dones.reshape(T, E),
        flushes,
    )


_reads = jax.jit(lambda *a: scan_reads(METRICS.init(E), *a))


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(data=rollouts())
def test_reads_follow_the_finished_episodes_after_every_step(data):
    assert_follow(jax.device_get(_reads(*data)), reference(*data))


def test_reads_under_vmap_over_seeds_follow_each_seed():
    rng = np.random.default_rng(3)
    seeds = 3
    xs = rng.integers(-8, 9, (seeds, T, E)).astype(np.float32) / 2
    levels = rng.integers(0, 4, (seeds, T, E)).astype(np.int32)
    dones = rng.random((seeds, T, E)) < 0.4
    flushes = rng.random((seeds, T)) < 0.3
    init = jax.vmap(lambda _: METRICS.init(E))(jnp.arange(seeds))
    got = jax.device_get(jax.jit(jax.vmap(scan_reads))(init, xs, levels, dones, flushes))
    for i in range(seeds):
        mine = {k: v[i] for k, v in got.items()}
        assert_follow(mine, reference(xs[i], levels[i], dones[i], flushes[i]))


@pytest.mark.parametrize("devices", [2, 4])
def test_reads_of_a_state_sharded_over_devices_are_the_whole_run_s(devices):
    # Windows and EMAs of a sharded state are read in the global order: by step, then
    # ascending env index across the shards; the reads are the one-device run's.
    mesh = jax.make_mesh((devices,), ("env",), (AxisType.Auto,), devices=jax.devices()[:devices])
    envs = NamedSharding(mesh, P(None, "env"))
    rng = np.random.default_rng(devices)
    xs = rng.integers(-8, 9, (T, E)).astype(np.float32) / 2
    levels = rng.integers(0, 4, (T, E)).astype(np.int32)
    dones = rng.random((T, E)) < 0.5
    dones[3] = True  # every env at once: more than the window holds
    flushes = rng.random(T) < 0.3
    state = METRICS.init(E, sharding=NamedSharding(mesh, P("env")))
    run = jax.jit(scan_reads)
    placed = [jax.device_put(a, envs) for a in (xs, levels, dones)]
    got = jax.device_get(run(state, *placed, flushes))
    assert_follow(got, reference(xs, levels, dones, flushes))


def test_reading_one_statistic_compiles_to_that_statistic_only():
    # A curriculum reads every step: the report's other statistics (the window's sort
    # for its percentile, the histograms) must not be computed for it, and a state of
    # one device reads without a collective.
    def step_ops(read):
        def body(state, x):
            state = METRICS.update(state, {"x": x, "level": jnp.zeros(E, jnp.int32)}, x > 0)
            return state, read(state)

        def loop(state, xs):
            return jax.lax.scan(body, state, xs)

        xs = jnp.zeros((4, E), jnp.float32)
        ops = loop_body_ops(jax.jit(loop).lower(METRICS.init(E), xs).compile().as_text())
        return ops, sum(ops.values())

    _, update = step_ops(lambda s: None)
    whole, with_report = step_ops(METRICS.compute)
    read, with_read = step_ops(
        lambda s: METRICS.read(s, "success_rate", "window_mean", by_group=True)
    )
    assert whole.get("sort")  # the window percentile: what the check could find
    assert not read.get("sort")
    assert with_read - update < (with_report - update) / 4, (update, with_read, with_report)
    assert not collectives(read)


def test_reads_equal_the_report_of_the_same_state():
    rng = np.random.default_rng(0)
    state = METRICS.init(E)
    for _ in range(6):
        step = {"x": rng.normal(size=E).astype(np.float32), "level": rng.integers(0, 3, E)}
        state = METRICS.update(state, step, rng.random(E) < 0.5)
    report = METRICS.to_host(METRICS.compute(state))
    for stat, suffix in (("mean", ""), ("ema", "/ema"), ("window_p50", "/window_p50")):
        for j, g in enumerate(NAMES):
            tag = f"Episode_Metrics/ret/{g}{suffix}"
            got = float(METRICS.read(state, "ret", stat, by_group=True)[j])
            assert got == report[tag] or (math.isnan(got) and math.isnan(report[tag])), tag
    assert float(METRICS.read(state, "episodes", "total")) == report["Counters/episodes"]
    assert float(METRICS.read(state, "ret/mid", "count")) == report["Episode_Metrics/ret/mid/count"]


def test_bad_reads_name_the_metric_and_the_fix_at_trace_time():
    state = METRICS.init(E)
    jitted = jax.jit(METRICS.read, static_argnums=(1, 2), static_argnames=("by_group",))
    with pytest.raises(ValueError, match=r"no metric 'retrun'.*'ret', 'ret/easy'"):
        jitted(state, "retrun", "mean")
    with pytest.raises(ValueError, match=r"'success_rate' has no statistic 'std'.*stats="):
        jitted(state, "success_rate", "std")
    with pytest.raises(ValueError, match=r"'ret/easy' has no groups"):
        jitted(state, "ret/easy", "mean", by_group=True)
    ungrouped = jm.Metrics(terms={"r": jm.Term(lambda s: s)})
    with pytest.raises(ValueError, match=r"no statistic 'window_count'.*jm.window"):
        ungrouped.read(ungrouped.init(2), "r", "window_count")
    with pytest.raises(ValueError, match=r"leading axes \(3,\).*jax.vmap\(metrics.read\)"):
        METRICS.read(jax.vmap(lambda _: METRICS.init(E))(jnp.arange(3)), "ret")
    with pytest.raises(TypeError, match="expected a MetricsState"):
        METRICS.read({"x": 1}, "ret")
