"""Period quantiles `jm.quantiles(levels, accuracy)` against numpy's exact quantiles
(method "lower") with the accuracy bound asserted: negative values, zeros, mixed signs,
magnitudes from 1e-9 to 1e9, under `jit` + `lax.scan`, merged over a 4-device sharded
state and by `Metrics.merge`; the sketch's tables, exact counts and ranks; bad input.
"""

import math
from fractions import Fraction

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from jax.sharding import AxisType, NamedSharding
from jax.sharding import PartitionSpec as P

import jaxmetrics as jm
from jaxmetrics._core import _sketch
from jaxmetrics._core._count import Count

# Levels at which numpy's float64 rank equals the exact one (see test_rank_is_exact...).
LEVELS = (0, 1, 10, 25, 50, 75, 90, 99, 99.9, 100)
ACCURACY = 0.01
E, T = 8, 6


def assert_within(host, prefix, values, accuracy=ACCURACY, levels=LEVELS):
    """Each level within `accuracy` of numpy's exact quantile, or NaN where that quantile
    is outside the sketch's (float32-rounded) magnitude range."""
    edges = _sketch.tables(accuracy, "float32")["edges"]
    values = np.asarray(values, np.float64)
    for p in levels:
        got = host[f"{prefix}/q{p:g}"]
        want = float(np.percentile(values, p, method="lower"))
        if want != 0 and not edges[0] < abs(want) <= edges[-1]:
            assert math.isnan(got), (p, got, want)
        else:
            assert abs(got - want) <= accuracy * abs(want), (p, got, want)


magnitudes = st.floats(-9, 9).map(lambda e: 10.0**e)
value = st.one_of(
    st.just(0.0),
    magnitudes,
    magnitudes.map(lambda v: -v),
    st.floats(-1000, 1000, width=32, allow_subnormal=False),  # XLA flushes subnormals to 0
    st.sampled_from([1.0, -1.0, 1e-9, -1e-9, 1e9, -1e9]),
)


@st.composite
def rollouts(draw):
    xs = draw(st.lists(value, min_size=T * E, max_size=T * E))
    xs = np.asarray(xs, np.float32).reshape(T, E)
    dones = np.asarray(draw(st.lists(st.booleans(), min_size=T * E, max_size=T * E)))
    return xs, dones.reshape(T, E)


METRICS = jm.Metrics(
    terms={"x": jm.Term(lambda x: x, reduce="last", stats=("count", jm.quantiles(LEVELS)))},
    logged={"v": jm.Logged(stats=(jm.quantiles(LEVELS, accuracy=0.05),))},
)
MESH = jax.make_mesh((4,), ("env",), axis_types=(AxisType.Auto,), devices=jax.devices()[:4])
_RUNS = {}


def rollout(sharded):
    if sharded not in _RUNS:
        m = METRICS
        sharding = NamedSharding(MESH, P("env")) if sharded else None

        def go(xs, dones):
            body = lambda s, a: (m.update(s, *a), None)  # noqa: E731
            return m.compute(jax.lax.scan(body, m.init(E, sharding=sharding), (xs, dones))[0])

        _RUNS[sharded] = jax.jit(go)
    return _RUNS[sharded]


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(rollouts())
def test_episode_quantiles_within_the_accuracy_of_numpy_also_sharded(data):
    xs, dones = data
    finished = xs[dones]  # "last" of a one-step view: every ended episode's last value...
    # ...is its value on the step it ended: the values at `dones`, in any order.
    reports = []
    for sharded in (False, True):
        placed = (xs, dones)
        if sharded:
            placed = jax.device_put(placed, NamedSharding(MESH, P(None, "env")))
        reports.append(METRICS.to_host(rollout(sharded)(*placed)))
    one, four = reports
    assert one["Episode_Metrics/x/count"] == len(finished)
    for p in LEVELS:  # a sharded sketch merges to the very same counts
        tag = f"Episode_Metrics/x/q{p:g}"
        assert one[tag] == four[tag] or (math.isnan(one[tag]) and math.isnan(four[tag]))
    if len(finished):
        assert_within(one, "Episode_Metrics/x", finished)
    else:
        assert all(math.isnan(one[f"Episode_Metrics/x/q{p:g}"]) for p in LEVELS)


# Chunks of three lengths: each length is one compile of `log`.
chunk = st.sampled_from([1, 7, 50]).flatmap(lambda n: st.lists(value, min_size=n, max_size=n))


LOG = jax.jit(METRICS.log)
MERGED_REPORT = jax.jit(lambda a, b: METRICS.compute(METRICS.merge(a, b)))


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.lists(chunk, min_size=2, max_size=4))
def test_logged_quantiles_and_merge_of_two_states(chunks):
    m, log = METRICS, LOG
    a, b = m.init(0), m.init(0)
    for i, c in enumerate(chunks):
        if i % 2:
            b = log(b, {"v": jnp.asarray(c, jnp.float32)})
        else:
            a = log(a, {"v": jnp.asarray(c, jnp.float32)})
    every = np.concatenate([np.asarray(c, np.float32) for c in chunks])
    merged = m.to_host(MERGED_REPORT(a, b))
    assert_within(merged, "Train/v", every, accuracy=0.05)


@pytest.mark.parametrize("accuracy", [0.001, 0.005, 0.01, 0.02, 0.05, 0.1, 0.3, 0.9, 0.999])
@pytest.mark.parametrize("dtype", ["float32", "float64"])
def test_every_representative_is_within_the_accuracy_of_its_whole_bucket(accuracy, dtype):
    t = _sketch.tables(accuracy, dtype)
    edges = t["edges"]
    assert edges[0] <= 1e-9 and edges[-1] >= 1e9
    n = len(edges) - 1
    reps = t["reps"][n + 3 + 1 : 2 * n + 4].astype(np.float64)  # positive buckets 1..N
    assert np.all(t["reps"][1 : n + 1] == -t["reps"][n + 4 : 2 * n + 4][::-1])
    lows = np.nextafter(edges[:-1], np.inf).astype(np.float64)  # smallest value in each
    highs = edges[1:].astype(np.float64)
    err = np.maximum((reps - lows) / lows, (highs - reps) / highs)
    assert err.max() <= accuracy, err.max()


def test_memory_is_slots_times_8_bytes_and_the_slot_count_is_documented():
    g = _sketch.SketchGroup(0.01, (0,))
    assert g.slots == 4156  # 2 x 2075 buckets + 6: docs/semantics.md says so
    state = jm.Metrics(logged={"v": jm.Logged(stats=(jm.quantiles(),))}).init(0)
    (counts,) = state.logged.sketches
    assert counts.hi.shape == (1, 4156) and counts.hi.dtype == jnp.uint32
    assert counts.hi.nbytes + counts.lo.nbytes == 4156 * 8
    assert _sketch.SketchGroup(0.001, (0,)).slots == 41_494


def test_zero_negative_and_out_of_range_values_land_in_their_slots():
    g = _sketch.SketchGroup(0.01, (0,))
    n = g.buckets
    x = jnp.asarray([[0.0, -0.0, 1e-10, -1e-10, 2e9, -2e9, jnp.nan, 1e-9, 1e9, -1.0, 5.0]])
    mask = jnp.ones(x.shape, bool).at[0, -1].set(False)
    got = np.asarray(_sketch.slot(g, x, mask))[0]
    assert list(got[:7]) == [n + 2, n + 2, n + 3, n + 1, 2 * n + 4, 0, 2 * n + 5]
    assert got[7] == n + 3  # 1e-9 rounds to the float32 edge below it: underflow
    assert n + 3 < got[8] <= 2 * n + 4 and 0 <= got[9] < n + 1 and got[10] == g.slots


def test_out_of_range_quantiles_are_nan_and_counted_so_the_logger_warns():
    m = jm.Metrics(logged={"v": jm.Logged(stats=("count", jm.quantiles((0, 50, 100))))})
    s = m.log(m.init(0), {"v": jnp.asarray([2e9, 1.0, 2.0, 3.0, 1e-12], jnp.float32)})
    host = m.to_host(m.compute(s))
    assert math.isnan(host["Train/v/q0"]) and math.isnan(host["Train/v/q100"])
    assert abs(host["Train/v/q50"] - 2.0) <= 0.02
    assert host["Train/v/nonfinite"] == 2
    assert [(i.tag, c) for i, _, c in m.nonfinite(host)] == [("Train/v/nonfinite", 2)]


def test_propagate_policy_nan_makes_every_quantile_nan():
    m = jm.Metrics(logged={"v": jm.Logged(stats=(jm.quantiles((0, 50)),), nonfinite="propagate")})
    s = m.log(m.init(0), {"v": jnp.asarray([1.0, 2.0, 3.0])})
    assert m.to_host(m.compute(s))["Train/v/q0"] == pytest.approx(1.0, rel=0.01)
    host = m.to_host(m.compute(m.log(s, {"v": jnp.nan})))
    assert math.isnan(host["Train/v/q0"]) and math.isnan(host["Train/v/q50"])


def test_quantiles_reset_with_the_period():
    m = jm.Metrics(logged={"v": jm.Logged(stats=(jm.quantiles((50,)),))})
    s = m.reset_period(m.log(m.init(0), {"v": jnp.asarray([100.0, 100.0])}))
    assert math.isnan(m.to_host(m.compute(s))["Train/v/q50"])
    s = m.log(s, {"v": 5.0})
    assert m.to_host(m.compute(s))["Train/v/q50"] == pytest.approx(5.0, rel=0.01)


def test_rank_is_exact_numpy_lower_computes_it_in_float64():
    # p = 29 of 0..100: the exact rank is 29; numpy 2.4's float64 (0.29 * 100 = 28.999...) gives
    # 28 (numpy 2.0 computes the index otherwise and gives 29).
    m = jm.Metrics(logged={"v": jm.Logged(stats=(jm.quantiles((29, 90)),))})
    values = np.arange(1, 102, dtype=np.float32)  # ranks 0..100 hold 1..101
    host = m.to_host(m.compute(m.log(m.init(0), {"v": values})))
    exact = values[math.floor(Fraction(29, 100) * (len(values) - 1))]
    assert exact == 30.0  # rank 29
    assert host["Train/v/q29"] == pytest.approx(exact, rel=0.01)
    assert host["Train/v/q90"] == pytest.approx(np.percentile(values, 90, method="lower"), 0.01)


@settings(max_examples=200, deadline=None)
@given(st.integers(0, 10**6), st.integers(0, 2**32 - 1))
def test_uint32_rank_is_exact(p, m):
    got = int(_sketch._exact_rank(jnp.uint32(p), jnp.uint32(m)))
    assert got == math.floor(Fraction(p * m, 10**6))


def test_counts_carry_past_2_32_and_ranks_past_2_32_values():
    g = _sketch.SketchGroup(0.01, (0,))
    n = g.buckets
    one = n + 3 + 1 + int(np.ceil(np.log(1e9) / np.log(1.0202)))  # some positive bucket
    lo = jnp.zeros((1, g.slots), jnp.uint32).at[0, one].set(jnp.uint32(2**32 - 1))
    counts = _sketch.add(Count(jnp.zeros_like(lo), lo), jnp.asarray([[one, one, g.slots]]))
    assert (int(counts.hi[0, one]), int(counts.lo[0, one])) == (1, 1)
    # 2^32 + 1 values of ~1 and 2^31 huge ones: the median is ~1, the maximum overflows.
    counts = Count(counts.hi, counts.lo.at[0, 2 * n + 4].set(2**31))
    q50, q100 = _sketch.quantiles(g, counts, ((50.0, 100.0),), jnp.float32)[0]
    assert 0.98 <= float(q50) <= 1.02 and math.isnan(float(q100))


@pytest.mark.parametrize(
    "q, match",
    [
        (jm.quantiles(accuracy=0), r"logged value 'v': quantiles\(accuracy=...\) must be a num"),
        (jm.quantiles(accuracy=1.0), "in \\[0.001, 1\\), got 1.0"),
        (jm.quantiles(accuracy=1e-4), "got 0.0001"),
        (jm.quantiles(accuracy="0.01"), "got '0.01'"),
        (jm.quantiles(accuracy=None), "got None"),
        (jm.quantiles(()), r"non-empty sequence of percentiles in \[0, 100\], got \(\)"),
        (jm.quantiles(50), "got 50. Use e.g. jaxmetrics.quantiles"),
        (jm.quantiles((50, 150)), r"at most 4 decimals, got 150 in \(50, 150\)"),
        (jm.quantiles((-1,)), "got -1"),
        (jm.quantiles(("50",)), "got '50'"),
        (jm.quantiles((99.99999,)), "got 99.99999"),
        (jm.quantiles((50, 90, 50)), r"distinct, got \(50, 90, 50\); list each once"),
    ],
)
def test_bad_quantiles_name_the_metric_and_the_fix(q, match):
    with pytest.raises(ValueError, match=match):
        jm.Metrics(logged={"v": jm.Logged(stats=(q,))})


def test_other_misuse_is_refused_with_the_fix():
    with pytest.raises(ValueError, match=r"term 'x': at most one quantiles statistic"):
        jm.Metrics(terms={"x": jm.Term(lambda s: s, stats=(jm.quantiles(), jm.quantiles()))})
    with pytest.raises(ValueError, match=r"Use jaxmetrics.quantiles\(...\) for it"):
        jm.Metrics(terms={"x": jm.Term(lambda s: s, stats=("quantile",))})
    with pytest.raises(ValueError, match="group name 'q50' is also a statistic's name"):
        jm.groups(lambda s: s, ("q50", "rest"))  # <m>/q50 would read as a quantile
    with pytest.raises(ValueError, match="tag collision: .*'Episode_Metrics/x/q50'"):
        jm.Metrics(
            terms={
                "x": jm.Term(lambda s: s, stats=(jm.quantiles((50,)),)),
                "x/q50": jm.Term(lambda s: s),
            }
        )


def test_levels_accuracy_are_part_of_the_spec_identity_and_the_logger_writes_floats():
    def make(a):
        return jm.Metrics(logged={"v": jm.Logged(stats=(jm.quantiles((50,), accuracy=a),))})

    ids = [make(a).init(0).spec._fields for a in (0.01, 0.01, 0.02)]
    assert ids[0] == ids[1] != ids[2]
    m = make(0.01)
    writer = jm.MemoryWriter()
    with jm.Logger(m, [writer]) as logger:
        assert [i.stat for i in logger.tags if i.metric == "v"] == ["q50", "nonfinite"]
        logger.flush(m.log(m.init(0), {"v": 3.0}), step=1)
    (record,) = writer.records
    assert isinstance(record.scalars["Train/v/q50"], float)


def test_grouped_quantiles_are_kept_per_group():
    m = jm.Metrics(
        terms={
            "x": jm.Term(
                lambda s: s["x"],
                reduce="last",
                stats=("count", jm.quantiles((0, 50, 100))),
                groups=jm.groups(lambda s: s["g"], ("a", "b")),
            )
        }
    )
    rng = np.random.default_rng(3)
    xs = rng.normal(size=(20, 6)).astype(np.float32)
    gs = rng.integers(0, 2, (20, 6))
    dones = rng.random((20, 6)) < 0.5
    s = m.init(6)
    for x, g, d in zip(xs, gs, dones):
        s = m.update(s, {"x": jnp.asarray(x), "g": jnp.asarray(g)}, jnp.asarray(d))
    host = m.to_host(m.compute(s))
    assert_within(host, "Episode_Metrics/x", xs[dones], levels=(0, 50, 100))
    for k, name in enumerate(("a", "b")):
        values = xs[dones & (gs == k)]
        assert host[f"Episode_Metrics/x/{name}/count"] == len(values) > 0
        assert_within(host, f"Episode_Metrics/x/{name}", values, levels=(0, 50, 100))
