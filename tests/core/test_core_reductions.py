"""Every episode reduction and every report statistic against the float64 Python reference.

Values, `done` patterns and flush cadences are random (hypothesis); the report is compared
after *every* step, under `jit` + `lax.scan`, with `reset_period` applied through `lax.cond`.
"""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from reference import SIMPLE_STATS, RefEpisodes, RefStream

import jaxmetrics as jm

REDUCTIONS = ("mean", "sum", "max", "min", "last", "std")
E, T = 5, 10  # 5 envs finishing at once overflow the window of 3
EMA_C = 0.3
WINDOW = 3
PCTS = (0.0, 25.0, 50.0, 90.0, 100.0)
HIST = (8, -50.0, 50.0)
STATS = (
    *SIMPLE_STATS,
    jm.ema(EMA_C),
    jm.window(WINDOW, PCTS),
    jm.histogram(HIST[0], HIST[1:]),
)


def make_metrics(nonfinite="skip"):
    terms = {
        f"r_{red}": jm.Term(lambda x, k: x[k], reduce=red, stats=STATS, params={"k": k})
        for k, red in enumerate(REDUCTIONS)
    }
    return jm.Metrics(terms=terms, logged=["a", "b"], nonfinite=nonfinite)


METRICS = {p: make_metrics(p) for p in ("skip", "propagate")}
# The logged-value programs, jitted once for every hypothesis example.
LOGGED = {
    p: (jax.jit(m.log), jax.jit(m.compute), jax.jit(m.reset_period)) for p, m in METRICS.items()
}


def _slice(report, t):
    return {k: jax.tree.map(lambda a: a[t], v) for k, v in report.items()}


def assert_stat_close(got, want, where, propagate=False):
    if isinstance(got, jm.Count):
        np.testing.assert_array_equal(got, want, err_msg=where)
        return
    got = np.asarray(got, np.float64)
    want = np.asarray(want, np.float64)
    if propagate:
        np.testing.assert_array_equal(~np.isfinite(got), ~np.isfinite(want), err_msg=where)
        ok = np.isfinite(want)
        got, want = got[ok], want[ok]
    finite = np.abs(want[np.isfinite(want)])
    scale = max(1.0, float(finite.max(initial=0.0)))
    np.testing.assert_allclose(
        got, want, rtol=2e-5, atol=2e-5 * scale, equal_nan=True, err_msg=where
    )


def compare(metrics, host, ref_report, prefix, name, propagate=False, only=None):
    for stat, want in ref_report.items():
        if only is not None and stat not in only:
            continue
        tag = f"{prefix}/{name}" if stat == "mean" else f"{prefix}/{name}/{stat}"
        if stat == "histogram" and propagate:
            continue
        assert tag in host, tag
        assert_stat_close(host[tag], want, tag, propagate)


DEFAULT_LOGGED_STATS = ("mean", "std", "min", "max", "count", "nonfinite")
grid = st.integers(-800, 800).map(lambda k: k / 8 + 1 / 16)  # never on a histogram edge


@st.composite
def rollouts(draw, nonfinite=False):
    vals = draw(st.lists(grid, min_size=T * 6 * E, max_size=T * 6 * E))
    xs = np.asarray(vals, np.float32).reshape(T, 6, E)
    if nonfinite:
        bad = draw(
            st.lists(
                st.sampled_from([0.0, np.nan, np.inf, -np.inf]),
                min_size=T * 6 * E,
                max_size=T * 6 * E,
            )
        )
        bad = np.asarray(bad, np.float32).reshape(T, 6, E)
        use = draw(st.lists(st.booleans(), min_size=T * 6 * E, max_size=T * 6 * E))
        use = np.asarray(use).reshape(T, 6, E) & (np.random.default_rng(0).random((T, 6, E)) < 0.3)
        xs = np.where(use & (bad != 0), bad, xs)
    pattern = draw(st.sampled_from(["random", "all", "none", "env0_every_step", "sparse"]))
    if pattern == "random":
        dones = np.asarray(draw(st.lists(st.booleans(), min_size=T * E, max_size=T * E)))
    elif pattern == "all":
        dones = np.ones(T * E, bool)
    elif pattern == "none":
        dones = np.zeros(T * E, bool)
    elif pattern == "env0_every_step":
        dones = np.tile(np.arange(E) == 0, T)
    else:
        dones = np.asarray(draw(st.lists(st.integers(0, 7), min_size=T * E, max_size=T * E))) == 0
    flushes = np.asarray(draw(st.lists(st.booleans(), min_size=T, max_size=T)))
    return xs, dones.reshape(T, E), flushes


_RUN_CACHE: dict[str, object] = {}


def run_jitted(policy, xs, dones, flushes):
    m = METRICS[policy]
    if policy not in _RUN_CACHE:

        def body(state, inp):
            x, d, flush = inp
            state = m.update(state, x, d)
            report = m.compute(state)
            state = jax.lax.cond(flush, m.reset_period, lambda s: s, state)
            return state, report

        _RUN_CACHE[policy] = jax.jit(lambda xs, d, f: jax.lax.scan(body, m.init(E), (xs, d, f))[1])
    out = _RUN_CACHE[policy](jnp.asarray(xs), jnp.asarray(dones), jnp.asarray(flushes))
    return jax.device_get(out)


def assert_reports_follow_reference(metrics, reports, xs, dones, flushes, reductions, skip=True):
    """Reports after every step (stacked on a leading axis) against the float64 reference
    fed the same rollout; `xs[t, k]` feeds term `r_<reductions[k]>`."""
    steps, num_envs = dones.shape
    ref = RefEpisodes(
        num_envs,
        {f"r_{r}": r for r in reductions},
        skip=skip,
        ema_coeff=EMA_C,
        window=WINDOW,
        percentiles=PCTS,
        hist=HIST,
    )
    for t in range(steps):
        ref.step({f"r_{r}": xs[t, k] for k, r in enumerate(reductions)}, dones[t])
        host = metrics.to_host(_slice(reports, t))
        for name, stream in ref.streams.items():
            compare(metrics, host, stream.report(), "Episode_Metrics", name, not skip)
        assert host["Counters/episodes"] == int(dones[: t + 1].sum())
        assert host["Counters/env_steps"] == (t + 1) * num_envs
        if flushes[t]:
            ref.reset_period()


def check_rollout(policy, xs, dones, flushes):
    reports = run_jitted(policy, xs, dones, flushes)
    assert_reports_follow_reference(
        METRICS[policy], reports, xs, dones, flushes, REDUCTIONS, skip=policy != "propagate"
    )


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(rollouts())
def test_episode_reductions_and_report_stats_match_reference(data):
    check_rollout("skip", *data)


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(rollouts(nonfinite=True))
def test_nonfinite_values_skipped_and_counted(data):
    check_rollout("skip", *data)


@settings(max_examples=15, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(rollouts(nonfinite=True))
def test_nonfinite_propagate_policy_makes_statistics_nonfinite(data):
    check_rollout("propagate", *data)


@pytest.mark.parametrize("path", ["rows", "segments"])
def test_counts_of_one_step_past_a_byte_are_exact(path):
    # The per-entry non-finite flags and the per-env counted rows reach the fold as uint8
    # (`Metrics.update`): one step of 700 envs, each NaN and ending, in groups with some
    # indices out of range, must count every one. Against numpy on the inputs, with the
    # group rows folded as rows and by the segment reductions.
    n, names = 700, ("a", "b", "c")
    stats = ("count", "max") if path == "segments" else ("count", jm.ema(0.1))
    metrics = jm.Metrics(
        terms={"x": jm.Term(lambda s: s[0], reduce="mean", stats=stats)},
        groups=jm.groups(lambda s: s[1], names),
    )
    rng = np.random.default_rng(11)
    ids = rng.integers(-1, len(names) + 1, n).astype(np.int32)
    x = np.full(n, np.nan, np.float32)
    x[::7] = 1.0  # finite, in an episode that has no other step: no flag
    state = jax.jit(metrics.update)(
        metrics.init(n), (jnp.asarray(x), jnp.asarray(ids)), jnp.ones(n, bool)
    )
    host = metrics.to_host(metrics.compute(state))
    prefix = metrics.prefixes["episode"]
    bad = ~np.isfinite(x)
    assert host[f"{prefix}/x/nonfinite"] == int(bad.sum()) > 255
    assert host[f"{prefix}/x/count"] == int((~bad).sum())
    for g, name in enumerate(names):
        assert host[f"{prefix}/x/{name}/nonfinite"] == int((bad & (ids == g)).sum())
    assert host["Counters/episodes"] == host["Counters/env_steps"] == n
    assert host["Counters/ungrouped"] == int(((ids < 0) | (ids >= len(names))).sum())


@settings(max_examples=30, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    st.lists(
        st.tuples(grid, st.lists(grid, min_size=3, max_size=3), st.booleans()),
        min_size=1,
        max_size=12,
    )
)
def test_logged_values_match_reference(steps):
    m = METRICS["skip"]
    log, compute, reset = LOGGED["skip"]
    spec = m.metric_specs["a"].stats
    assert spec.window is None  # logged values here use the default statistics
    ref = {n: RefStream() for n in ("a", "b")}
    state = m.init(E)
    for a, b, flush in steps:
        state = log(state, {"a": jnp.float32(a), "b": jnp.asarray(b, jnp.float32)})
        ref["a"].add(a)
        for v in b:
            ref["b"].add(v)
        host = m.to_host(compute(state))
        for n, r in ref.items():
            compare(m, host, r.report(), "Train", n, only=DEFAULT_LOGGED_STATS)
        if flush:
            state = reset(state)
            for r in ref.values():
                r.reset_period()


def test_logging_one_name_leaves_the_others_untouched():
    m = jm.Metrics(logged=["a", "b"])
    state = m.log(m.init(0), {"a": 1.0, "b": 2.0})
    state = m.log(state, {"a": 3.0})
    host = m.to_host(m.compute(state))
    assert host["Train/a"] == 2.0 and host["Train/a/count"] == 2
    assert host["Train/b"] == 2.0 and host["Train/b/count"] == 1


def test_logged_nonfinite_counted_and_left_out():
    m = jm.Metrics(logged=["loss"])
    state = m.log(m.init(0), {"loss": jnp.asarray([1.0, jnp.nan, 3.0, jnp.inf])})
    host = m.to_host(m.compute(state))
    assert host["Train/loss"] == 2.0
    assert host["Train/loss/count"] == 2
    assert host["Train/loss/nonfinite"] == 2


def test_mean_of_episodes_not_mean_of_batch_means():
    # DESIGN.md: 3 episodes of 0 then 1 of 1 is 0.25 (mjlab's logger says 0.5).
    m = jm.Metrics(terms={"success": jm.Term(lambda s: s, reduce="last")})
    state = m.init(3)
    state = m.update(state, jnp.zeros(3), jnp.ones(3, bool))
    state = m.update(state, jnp.asarray([1.0, 0.0, 0.0]), jnp.asarray([True, False, False]))
    host = m.to_host(m.compute(state))
    assert host["Episode_Metrics/success"] == 0.25
    assert host["Episode_Metrics/success/count"] == 4


def test_window_keeps_last_n_in_env_order_when_4096_envs_finish_at_once():
    n_env = 4096
    m = jm.Metrics(
        terms={
            "x": jm.Term(
                lambda s: s, reduce="last", stats=(jm.window(100, (10, 50, 90)), jm.ema(0.01))
            )
        }
    )
    rng = np.random.default_rng(1)
    vals = [rng.normal(size=n_env).astype(np.float32) for _ in range(2)]
    state = m.init(n_env)
    update = jax.jit(m.update)
    ref = RefStream(ema_coeff=0.01, window=100, percentiles=(10, 50, 90))
    for v in vals:
        state = update(state, jnp.asarray(v), jnp.ones(n_env, bool))
        for e in range(n_env):
            ref.add(float(v[e]))
    host = m.to_host(m.compute(state))
    want = ref.report()
    np.testing.assert_array_equal(host["Episode_Metrics/x/window_values"], vals[1][-100:])
    for stat in ("window_mean", "window_std", "window_p10", "window_p50", "window_p90", "ema"):
        assert math.isclose(
            host[f"Episode_Metrics/x/{stat}"], want[stat], rel_tol=1e-5, abs_tol=1e-6
        ), stat


def test_ema_seeded_by_first_value_and_carried_across_periods():
    m = jm.Metrics(logged={"v": jm.Logged(stats=(jm.ema(0.5), "mean"))})
    state = m.log(m.init(0), {"v": 4.0})
    assert m.to_host(m.compute(state))["Train/v/ema"] == 4.0  # seeded, no bias correction
    state = m.reset_period(state)
    host = m.to_host(m.compute(state))
    assert host["Train/v/ema"] == 4.0 and math.isnan(host["Train/v"])
    state = m.log(state, {"v": 2.0})
    assert m.to_host(m.compute(state))["Train/v/ema"] == 3.0


def test_ema_coefficient_one_tracks_the_last_value():
    m = jm.Metrics(logged={"v": jm.Logged(stats=(jm.ema(1.0),))})
    state = m.log(m.init(0), {"v": jnp.asarray([1.0, 5.0, 7.0])})
    assert m.to_host(m.compute(state))["Train/v/ema"] == 7.0


@pytest.mark.parametrize("seed", range(4))
def test_window_mean_and_std_of_values_far_from_zero_match_float64(seed):
    # Near 1e6 a float32 mean of the window rounds by up to a few hundredths; its square
    # added to the variance put the std off by up to 1e-3 of itself.
    rng = np.random.default_rng(seed)
    metrics = jm.Metrics(
        terms={"x": jm.Term(lambda x: x, reduce="last", stats=("mean", jm.window(64)))}
    )
    x = (np.float32(1e6) + rng.normal(0, 1.5, 64)).astype(np.float32)
    state = jax.jit(metrics.update)(metrics.init(64), jnp.asarray(x), jnp.ones(64, bool))
    host = metrics.to_host(metrics.compute(state))
    want = x.astype(np.float64)
    np.testing.assert_allclose(host["Episode_Metrics/x/window_mean"], want.mean(), rtol=1e-7)
    np.testing.assert_allclose(host["Episode_Metrics/x/window_std"], want.std(), rtol=1e-5)


@pytest.mark.parametrize(
    "values",
    [[1.0, np.inf], [np.inf, 1.0, 2.0], [-np.inf, 3.0], [np.inf, -np.inf], [1.0, np.nan, 2.0]],
)
def test_window_mean_of_values_with_infinities_is_numpys(values):
    # A window that propagates non-finite values: its mean is numpy's, inf where an inf
    # is among finite values (deviations from a non-finite mean once made it NaN).
    m = jm.Metrics(logged={"v": jm.Logged(stats=(jm.window(4),), nonfinite="propagate")})
    state = m.init(0)
    for x in values:
        state = m.log(state, {"v": jnp.float32(x)})
    got = m.to_host(m.compute(state))["Train/v/window_mean"]
    with np.errstate(invalid="ignore"):  # inf - inf
        want = np.mean(np.asarray(values, np.float64))
    np.testing.assert_array_equal(got, want)


@pytest.mark.parametrize("order", [(0, 1, 2), (1, 0, 2), (2, 1, 0)])
def test_window_mean_sums_as_if_exact(order):
    # float32: 1e8 + 1 rounds to 1e8, so a plain sum of the window says 0; numpy's float64
    # mean of the same float32 values is 1/3.
    m = jm.Metrics(logged={"v": jm.Logged(stats=(jm.window(3),))})
    values = np.asarray([1e8, 1.0, -1e8], np.float32)[list(order)]
    state = m.log(m.init(0), {"v": jnp.asarray(values)})
    got = m.to_host(m.compute(state))["Train/v/window_mean"]
    np.testing.assert_allclose(got, values.astype(np.float64).mean(), rtol=1e-7)


def test_window_persists_across_periods():
    m = jm.Metrics(logged={"v": jm.Logged(stats=("count", jm.window(4)))})
    state = m.init(0)
    for v in range(6):
        state = m.reset_period(m.log(state, {"v": float(v)}))
    host = m.to_host(m.compute(state))
    assert host["Train/v/count"] == 0
    np.testing.assert_array_equal(host["Train/v/window_values"], [2.0, 3.0, 4.0, 5.0])


def test_empty_period_reports_count_zero_and_nan():
    m = jm.Metrics(
        terms={
            "x": jm.Term(
                lambda s: s,
                stats=("mean", "std", "min", "max", "sum", "count", jm.window(3, (50,))),
            )
        }
    )
    host = m.to_host(m.compute(m.init(2)))
    assert host["Episode_Metrics/x/count"] == 0
    assert host["Episode_Metrics/x/sum"] == 0.0
    for stat in ("", "/std", "/min", "/max", "/window_mean", "/window_p50"):
        assert math.isnan(host[f"Episode_Metrics/x{stat}"]), stat


def test_running_episodes_reported_only_when_asked():
    m = jm.Metrics(terms={"x": jm.Term(lambda s: s, reduce="sum")})
    state = m.update(m.init(2), jnp.asarray([1.0, 2.0]), jnp.asarray([False, False]))
    assert "Episode_Metrics/x/running" not in m.compute(state)
    host = m.to_host(m.compute(state, include_running=True))
    assert host["Episode_Metrics/x/running"] == 1.5
    assert math.isnan(host["Episode_Metrics/x"])


@pytest.mark.parametrize("dtype", [jnp.bool_, jnp.int32, jnp.uint8, jnp.float16, jnp.float32])
def test_bool_and_int_outputs_accepted(dtype):
    m = jm.Metrics(terms={"x": jm.Term(lambda s: s.astype(dtype), reduce="sum")})
    state = m.update(m.init(3), jnp.asarray([1.0, 0.0, 1.0]), jnp.ones(3, bool))
    assert m.to_host(m.compute(state))["Episode_Metrics/x/max"] == 1.0


@settings(max_examples=30, deadline=None)
@given(st.lists(st.integers(0, 12), min_size=1, max_size=40), st.integers(1, 3))
def test_both_histogram_counting_paths_match_numpy(slots, rows):
    # The CPU lowering scatters, accelerators compare-and-count (lax.platform_dependent):
    # both are checked here, since CI has no accelerator. Slot 11 and 12 match no bin.
    from jaxmetrics._core._stream import slot_counts_compare, slot_counts_scatter

    slot = np.tile(np.asarray(slots, np.int32), (rows, 1))
    slot[1:] = (slot[1:] + np.arange(1, rows)[:, None]) % 13
    into = np.arange(rows * 11, dtype=np.int32).reshape(rows, 11)  # counted on top of
    want = into + np.stack([np.bincount(r[r < 11], minlength=11) for r in slot])
    for fn in (slot_counts_scatter, slot_counts_compare):
        np.testing.assert_array_equal(jax.jit(fn)(jnp.asarray(slot), jnp.asarray(into)), want)


@settings(max_examples=40, deadline=None)
@given(
    st.integers(1, 3).flatmap(
        lambda r: st.integers(0, 200).flatmap(
            lambda n: st.lists(
                st.lists(st.booleans(), min_size=n, max_size=n), min_size=r, max_size=r
            )
        )
    )
)
def test_arrival_ranks_count_the_later_entries_of_each_row(rows):
    # The window slots and EMA weights come from these ranks; they are computed in two
    # levels (blocks of entries, then blocks), checked here against a Python count.
    from jaxmetrics._core import _stream

    mask = np.array(rows, dtype=bool).reshape(len(rows), -1)
    after, k = jax.jit(_stream.arrivals_after)(jnp.asarray(mask))
    for r, row in enumerate(mask):
        assert int(k[r]) == int(row.sum())
        for j in np.flatnonzero(row):
            assert int(after[r, j]) == int(row[j + 1 :].sum())


@settings(max_examples=25, deadline=None)
@given(
    st.integers(1, 4),
    st.sampled_from([32, 64, 256, 40, 100, 300]),
    st.sampled_from([1, 5, 16]),
    st.integers(0, 2**32 - 1),
)
def test_a_batch_fold_matches_a_python_loop(rows, batch, size, seed):
    # The fold of one batch (`_stream._fold`) against float64 numpy and a loop over each
    # row in arrival order: the batch's statistics and counted sums, the EMA's weighted sum
    # and a window's ring written one arrival at a time. Rows cover no EMA, c = 1 (0^0 =
    # 1), a seeding row, far-from-zero values, empty rows, and rows in and out of the ring.
    check_batch_fold(rows, batch, size, seed)


@pytest.mark.parametrize(
    ("rows", "batch", "size", "seed"),
    # Seeds drawn for masks of these densities: every entry, 50%, 2%, 2%.
    [(2, 4097, 16, 1), (2, 8192, 6000, 2), (2, 65536, 16, 0), (1, 9000, 2000, 4)],
)
def test_a_long_batch_fold_matches_a_python_loop(rows, batch, size, seed):
    # Batches of thousands of entries, whose arrival ranks count many words of the mask,
    # and rings larger than a step's arrivals; against the same loop.
    check_batch_fold(rows, batch, size, seed)


@pytest.mark.parametrize(
    ("rows", "batch", "groups", "size", "seed"),
    # Seeds drawn for group indices in few groups, uniform, all in one group, uniform over
    # 64 groups of 40 entries (most empty), and past 4,096 entries uniform over two groups.
    [(2, 64, 3, 5, 4), (1, 300, 8, 16, 0), (2, 100, 2, 5, 6), (1, 40, 64, 3, 7)]
    + [(1, 9000, 2, 3000, 6)],
)
def test_a_batch_fold_of_group_rows_matches_a_python_loop(rows, batch, groups, size, seed):
    # Group rows (`Selected`) selected from the source rows and the group index, each
    # masked to its group: against the loop over the rows masked in numpy, with few and
    # many groups, empty groups, every entry in one group, out-of-range group indices and
    # counted rows in part of the rows.
    check_batch_fold(rows, batch, size, seed, groups)


@pytest.mark.parametrize(
    ("rows", "batch", "groups", "ranked", "seed"),
    # Seeds drawn for uniform group indices and masks 2% full.
    [(1, 2100, 64, True, 3), (1, 4097, 64, False, 0), (2, 300, 3, False, 21)],
)
def test_a_batch_fold_of_sparse_group_rows_counts_flags_alone(rows, batch, groups, ranked, seed):
    # Flags on 0.5% of the entries, so that a flag alone reaches some rows, which must
    # count it; with and without an EMA and a ring (the period statistics alone need no
    # arrival rank). Counted rows on the first two rows only, as a spec's episode tallies
    # are.
    check_batch_fold(rows, batch, 5, seed, groups, ranked=ranked, flags=0.005, counted_rows=2)


def check_batch_fold(
    rows, batch, size, seed, groups=0, pieces=None, ranked=True, flags=None, counted_rows=None
):
    """The fold of one batch (`_fold._fold` of the rows a `Selected` selects) against a loop
    over each row (see the tests above); without an EMA and a window where not `ranked`.
    `flags`: the density of non-finite flags (else half); `counted_rows`: at most that many
    counted rows (else about one per row and pack). With `groups`, the batch's rows are
    each of `rows` source rows over every entry and then masked to each of `groups` groups
    (`Selected`), the group index drawn uniformly (out of range on either side included),
    all in one group, or in a few groups (the others empty); the loop reads the rows masked
    in numpy. `pieces`: the mask's density drawn per run of that many entries of a row
    (else one density for the whole batch)."""
    from jaxmetrics._core import _spec, _stream
    from jaxmetrics._core._stream import _fold

    rng = np.random.default_rng(seed)
    sources = rows
    densities = [0.0, 0.02, 0.5, 1.0]
    if pieces is None:
        ok = rng.random((sources, batch)) < rng.choice(densities)
    else:
        runs = rng.choice(densities, (sources, -(-batch // pieces)))
        ok = rng.random((sources, batch)) < np.repeat(runs, pieces, axis=1)[:, :batch]
    level = rng.choice([1e4, 1e6])
    x = (level + rng.normal(size=(sources, batch))).astype(np.float32)
    flags_in = rng.integers(0, 2, (sources, batch), dtype=np.int32)
    if flags is not None:
        thin = np.random.default_rng([seed, 1]).random((sources, batch))
        flags_in = (thin < flags).astype(np.int32)
    src, kind, group = np.arange(sources), np.full(sources, -1), np.zeros(sources, int)
    ids = np.zeros((0, batch), np.int32)
    if groups:
        how = rng.integers(0, 3)
        if how == 0:
            gid = rng.integers(-1, groups + 1, batch)
        elif how == 1:
            gid = np.full(batch, rng.integers(0, groups))
        else:
            gid = rng.choice(rng.integers(-1, groups, 2), batch)
        ids = np.stack([rng.integers(0, groups, batch), gid]).astype(np.int32)
        src = np.repeat(np.arange(sources), 1 + groups)
        kind = np.tile(np.r_[-1, np.ones(groups, int)], sources)
        group = np.tile(np.r_[0, np.arange(groups)], sources)
        rows = len(src)
    match = np.ones((rows, batch), bool)
    if groups:
        match = (kind[:, None] < 0) | (ids[np.maximum(kind, 0)] == group[:, None])
    mask, values, nonfinite = ok[src] & match, x[src], flags_in[src] * match
    packs = int(rng.integers(0, 3))
    counted = rng.integers(0, 3, (rng.integers(max(0, rows * packs - 1), rows * packs + 1), batch))
    counted = counted[:counted_rows].astype(np.int32)
    coeff = rng.choice([0.0, 0.01, 0.3, 1.0], rows).astype(np.float32)
    ema_w = rng.choice([0.0, 1.0], rows).astype(np.float32)  # 0: unseeded
    ema_off, shift = (level + rng.normal(size=(2, rows))).astype(np.float32)
    shift *= rng.random(rows) < 0.5  # 0: a period's first batch, moments from far off
    steps = rng.integers(0, 2**32, rows, dtype=np.uint32)
    # A window over the rows drawn into it, its ring rows in row order; its `pos` has every
    # row. The ring keeps a row's newest `size` arrivals, the oldest of them at `pos`.
    members = [r for r in range(rows) if rng.random() < 0.7] or [rows - 1]
    ring_row = np.full(rows, -1, np.int32)
    ring_row[members] = np.arange(len(members))
    data = rng.integers(0, 2**32, (len(members), size, 2), dtype=np.uint32)
    pos = rng.integers(0, size, rows).astype(np.int32)

    def row_stats(r):
        stats = ["mean"]
        if ranked and coeff[r] > 0:
            stats.append(jm.ema(float(coeff[r])))
        if ranked and ring_row[r] >= 0:
            stats.append(jm.window(size))
        return _spec.parse_stats(stats, f"row {r}")

    specs = [_spec.MetricSpec(f"r{r}", f"r{r}", "mean", row_stats(r), "skip") for r in range(rows)]
    plan = _stream.StreamPlan.build(specs, jnp.float32)

    def fold(m, v, bad, i, t, ta, w, o, sh, d, p):
        s = _stream.init(plan)._replace(ema_w=w, ema_off=o, steps=t)
        if ranked:
            s = s._replace(windows=(s.windows[0]._replace(data=d, pos=p),))
        table = (tuple(int(a) for a in b) for b in (src, kind, group))
        selected = _stream.Selected(v, m, bad, i, *table)
        return _fold._fold_dense(plan, s, selected, sh, ta)

    args = (ok, x, flags_in, ids, steps, counted, ema_w, ema_off, shift, data, pos)
    stats, _, windows, *_ = jax.device_get(jax.jit(fold)(*map(jnp.asarray, args)))
    want_counted = np.zeros(-(-counted.shape[0] // rows) * rows, np.int64)
    want_counted[: counted.shape[0]] = counted.sum(axis=1)
    np.testing.assert_array_equal(stats.counted_sums, want_counted)
    np.testing.assert_array_equal(stats.nonfinite, nonfinite.sum(axis=1))
    np.testing.assert_array_equal(stats.count, mask.sum(axis=1))

    want_ring = data.copy()
    for r in range(rows):
        idx = np.flatnonzero(mask[r])
        c = float(coeff[r])
        seeding = ema_w[r] == 0 and c > 0
        off = float(ema_off[r] if ema_w[r] > 0 else shift[r])
        want, scale = 0.0, 0.0
        p = int(pos[r])
        for n, j in enumerate(idx):
            later = len(idx) - 1 - n
            w = (1 - c) ** later * (1.0 if seeding and n == 0 else c)
            want += w * (float(values[r, j]) - off)
            scale += abs(w) * abs(float(values[r, j]) - off)
            if ring_row[r] >= 0 and later < size:
                want_ring[ring_row[r], p] = (values[r, j : j + 1].view(np.uint32)[0], steps[r])
                p = (p + 1) % size
        if ranked:
            # Without an EMA row (every `coeff` 0) there is no weighted sum: each row's is 0.
            got = 0.0 if stats.ema is None else float(stats.ema[r])
            np.testing.assert_allclose(
                got, want, rtol=1e-5, atol=1e-6 * scale + 1e-30, err_msg=str(r)
            )
        x = values[r, idx].astype(np.float64)
        assert (stats.min[r], stats.max[r]) == (x.min(initial=np.inf), x.max(initial=-np.inf))
        np.testing.assert_allclose(stats.sum[r], x.sum(), rtol=1e-6)
        d = x - float(shift[r])
        mean_d = d.mean() if len(x) else 0.0
        # Deviations from a shift near the values are exact in float32 (Sterbenz); from a
        # shift of 0, the mean is as good as float32 holds the values (up to 1e6).
        np.testing.assert_allclose(stats.mean_dev[r], mean_d, rtol=2e-7, atol=1e-6)
        np.testing.assert_allclose(stats.m2[r], ((d - mean_d) ** 2).sum(), rtol=1e-5, atol=1e-6)
    if ranked:
        np.testing.assert_array_equal(np.asarray(windows[0]), want_ring)
    else:
        assert stats.ema is None and windows == ()


@pytest.mark.parametrize(("num_envs", "groups"), [(300, 0), (4097, 0), (300, 2)])
def test_histogram_counts_carry_into_the_high_word(num_envs, groups):
    # A histogram's counts are two uint32 words: a step's counts are added to the low
    # words with a carry into the high word where one wraps. From low words 2 below 2^32,
    # the counts after two steps against numpy's histogram of the finite values in
    # float64, as 64-bit integers.
    edges = np.linspace(-1.0, 1.0, 6)
    term = jm.Term(lambda x: x[0], reduce="last", stats=(jm.histogram(5, (-1.0, 1.0)),))
    grouping = jm.groups(lambda x: x[1], ("a", "b")) if groups else None
    metrics = jm.Metrics(terms={"a": term}, groups=grouping)
    rng = np.random.default_rng(3)
    xs = rng.normal(size=(2, num_envs)).astype(np.float32)
    xs[0, :3] = np.inf, -np.inf, np.nan
    gs = rng.integers(0, 2, (2, num_envs)).astype(np.int32)
    near = 2**32 - 2

    def wrap(path, leaf):
        key = jax.tree_util.keystr(path)
        return jnp.full_like(leaf, near) if "hists" in key and key.endswith(".lo") else leaf

    state = jax.tree_util.tree_map_with_path(wrap, metrics.init(num_envs))
    done = jnp.ones(num_envs, bool)
    step = jax.jit(metrics.update)
    for t in range(2):
        state = step(state, (jnp.asarray(xs[t]), jnp.asarray(gs[t])), done)
    words = {
        jax.tree_util.keystr(k).rsplit(".", 1)[1]: np.asarray(v, np.uint64)
        for k, v in jax.tree_util.tree_leaves_with_path(state)
        if "hists" in jax.tree_util.keystr(k)
    }
    # Non-finite values are counted apart (`nonfinite`), in no slot.
    finite = xs[np.isfinite(xs)].astype(np.float64)
    want = np.r_[np.sum(finite < -1), np.histogram(finite, edges)[0], np.sum(finite > 1)]
    total = (words["hi"] * 2**32 + words["lo"]).reshape(-1, 7)  # 1 + groups rows
    np.testing.assert_array_equal(total[0], near + want.astype(np.uint64))
    if groups:
        np.testing.assert_array_equal(total[1:].sum(axis=0), 2 * near + want.astype(np.uint64))
    assert total[0].max() > 2**32
