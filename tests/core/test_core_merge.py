"""merge: count-weighted, exact where it can be, associative, with empty() as identity."""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from reference import SIMPLE_STATS, RefStream

import jaxmetrics as jm

WINDOW = 4
STATS = (
    *SIMPLE_STATS,
    jm.ema(0.2),
    jm.window(WINDOW, (50,)),
    jm.histogram(6, (-30.0, 30.0)),
)
METRICS = jm.Metrics(
    terms={"x": jm.Term(lambda s: s, reduce="sum", stats=STATS)},
    logged={"v": jm.Logged(stats=STATS)},
)
log = jax.jit(METRICS.log)
merge = jax.jit(METRICS.merge)
compute = jax.jit(METRICS.compute)

grid = st.integers(-400, 400).map(lambda k: k / 8 + 1 / 16)
worker = st.lists(grid, min_size=0, max_size=9)


def fed(values):
    state = METRICS.init(0)
    if values:
        state = log(state, {"v": jnp.asarray(values, jnp.float32)})
    return state


def host(state):
    return METRICS.to_host(compute(state))


def close(a, b, tag):
    np.testing.assert_allclose(
        np.asarray(a, np.float64),
        np.asarray(b, np.float64),
        rtol=1e-5,
        atol=1e-4,
        equal_nan=True,
        err_msg=tag,
    )


def assert_reports_close(ra, rb):
    assert ra.keys() == rb.keys()
    for tag in ra:
        close(ra[tag], rb[tag], tag)


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(worker, worker)
def test_merge_matches_reference_over_both_workers(va, vb):
    got = host(merge(fed(va), fed(vb)))
    ref = RefStream(window=WINDOW, percentiles=(50,), hist=(6, -30.0, 30.0))
    for v in va + vb:
        ref.add(v)
    want = ref.report()
    for stat in (
        "mean",
        "std",
        "min",
        "max",
        "sum",
        "count",
        "histogram",
        "window_values",
        "window_mean",
        "window_p50",
    ):
        tag = "Train/v" if stat == "mean" else f"Train/v/{stat}"
        close(got[tag], want[stat], tag)
    # EMA of disjoint workers: the average of the seeded workers' EMAs.
    emas = []
    for vals in (va, vb):
        r = RefStream(ema_coeff=0.2)
        for v in vals:
            r.add(v)
        if vals:
            emas.append(r.report()["ema"])
    close(got["Train/v/ema"], np.mean(emas) if emas else math.nan, "ema")


@settings(max_examples=30, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(worker)
def test_merge_with_empty_is_identity(va):
    s = fed(va)
    assert_reports_close(host(merge(s, METRICS.empty())), host(s))
    assert_reports_close(host(merge(METRICS.empty(), s)), host(s))


@settings(max_examples=30, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(worker, worker, worker)
def test_merge_is_associative(va, vb, vc):
    a, b, c = fed(va), fed(vb), fed(vc)
    assert_reports_close(host(merge(merge(a, b), c)), host(merge(a, merge(b, c))))


def test_merged_episode_states_concatenate_envs_and_keep_running():
    a = METRICS.update(METRICS.init(3), jnp.asarray([1.0, 2.0, 3.0]), jnp.asarray([1, 0, 0]))
    b = METRICS.update(METRICS.init(2), jnp.asarray([10.0, 20.0]), jnp.asarray([0, 1]))
    m = METRICS.merge(a, b)
    assert m.running.steps.shape == (1, 5)
    m = METRICS.update(m, jnp.asarray([1.0, 1.0, 1.0, 1.0, 1.0]), jnp.ones(5, bool))
    h = METRICS.to_host(METRICS.compute(m))
    # episodes: 1 (a env0), 20 (b env1), then 1, 3, 4, 11, 1
    want = np.asarray([1.0, 20.0, 1.0, 3.0, 4.0, 11.0, 1.0])
    assert h["Episode_Metrics/x/count"] == 7
    assert math.isclose(h["Episode_Metrics/x"], want.mean(), rel_tol=1e-6)
    assert h["Counters/env_steps"] == 10 and h["Counters/episodes"] == 7


def _ema64(values, c):
    """The sequential EMA (seeded by the first value) of `values` in order, in float64."""
    e = None
    for v in values:
        e = float(v) if e is None else c * float(v) + (1 - c) * e
    return e


def test_mixed_merges_of_sharded_and_unsharded_states_follow_the_documented_rule(env_sharded):
    # A sharded state keeps each EMA's newest values (its shards merge exactly); an
    # unsharded one keeps none. Merged, the sharded side's EMA must not be taken alone
    # (merge(a, b) would read 1.0 here) or misweighted (merge(b, a): 3.667): docs/semantics.md
    # ("Merge") allows the sequential EMA or the average of the workers' EMAs, and the
    # average it is.
    c = 0.5
    m = jm.Metrics(terms={"x": jm.Term(lambda x: x, stats=("count", jm.ema(c)))})
    done = jnp.ones(2, bool)
    rng = np.random.default_rng(3)
    steps = [rng.normal(0, 10, (3, 2)).astype(np.float32) for _ in range(3)]

    update, merge, compute = (jax.jit(f) for f in (m.update, m.merge, m.compute))

    def run(state, xs):
        for x in xs:
            state = update(state, jnp.asarray(x), done)
        return state

    s1 = run(m.init(2, sharding=env_sharded), steps[0])
    s2 = run(m.init(2), steps[1])
    s3 = run(m.init(2, sharding=env_sharded), steps[2])
    report = lambda s: m.to_host(compute(s))  # noqa: E731
    ema = lambda s: report(s)["Episode_Metrics/x/ema"]  # noqa: E731
    e1, e2, e3 = (_ema64(x.reshape(-1), c) for x in steps)  # each worker in env order

    assert ema(merge(s1, s2)) == pytest.approx((e1 + e2) / 2, rel=1e-5)
    assert ema(merge(s2, s1)) == pytest.approx((e1 + e2) / 2, rel=1e-5)
    three = (e1 + e2 + e3) / 3
    assert ema(merge(merge(s1, s2), s3)) == pytest.approx(three, rel=1e-5)
    assert ema(merge(s1, merge(s2, s3))) == pytest.approx(three, rel=1e-5)
    assert report(merge(merge(s1, s2), s3))["Episode_Metrics/x/count"] == 18
    # Two states with history merge sequentially: s3's values after s1's of each step.
    both = np.stack([steps[0], steps[2]], axis=1).reshape(-1)
    assert ema(merge(s1, s3)) == pytest.approx(_ema64(both, c), rel=1e-5)
