"""Every episode reduction and every report statistic against the float64 Python reference.

Values, `done` patterns and flush cadences are random (hypothesis); the report is compared
after *every* step, under `jit` + `lax.scan`, with `reset_period` applied through `lax.cond`.
"""

import dataclasses
import functools
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


@pytest.mark.parametrize("path", ["jnp", "kernel", "segments"])
def test_counts_of_one_step_past_a_byte_are_exact(monkeypatch, path):
    # The per-entry non-finite flags and the per-env counted rows reach the fold as uint8
    # (`Metrics.update`): one step of 700 envs, each NaN and ending, in groups with some
    # indices out of range, must count every one. Against numpy on the inputs, on the
    # jnp path, the CUDA kernel's (interpret mode) and the segment reductions'.
    from jaxmetrics._core import _stream

    n, names = 700, ("a", "b", "c")
    stats = ("count", "max") if path == "segments" else ("count", jm.ema(0.1))
    metrics = jm.Metrics(
        terms={"x": jm.Term(lambda s: s[0], reduce="mean", stats=stats)},
        groups=jm.groups(lambda s: s[1], names),
    )
    if path == "kernel":
        fold = _stream.add_with_counts
        monkeypatch.setattr(_stream, "add_with_counts", functools.partial(fold, interpret=True))
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
def test_fused_kernel_matches_a_python_loop(rows, batch, size, seed):
    # The CUDA kernel (`_stream._kernel`), run in Pallas' interpret mode since CI has no GPU,
    # against float64 numpy and a loop over each row in arrival order: the batch's
    # statistics and counted sums, the EMA's weighted sum and a ring written one arrival at a
    # time. Rows cover no EMA (c = 0), c = 1 (0^0 = 1), a seeding row, far-from-zero
    # values, empty rows, and rows in and out of the ring; batches of one block and of
    # two, whose last block overlaps the first.
    check_fused_kernel(rows, batch, size, seed)


@pytest.mark.parametrize(
    ("rows", "batch", "size", "seed"),
    # Seeds drawn for masks of every density: every entry, 50%, 2%, 50%, none.
    [(2, 1000, 16, 2), (2, 1000, 5, 6), (1, 1023, 5, 6), (2, 513, 16, 1), (2, 999, 1, 1)],
)
def test_fused_kernel_reads_a_row_in_blocks(rows, batch, size, seed):
    # A batch of one program that is not a power of two is read in two blocks, the second
    # overlapping the first (in all but one entry at 513): the arrival ranks, the moments
    # and the ring writes across blocks, against the same loop.
    from jaxmetrics._core._stream import _chunks

    assert _chunks.chunking(rows, batch, False, ranked=True) == (batch, 1, False)
    assert _chunks.blocking(batch)[1] == 2
    check_fused_kernel(rows, batch, size, seed)


@pytest.mark.parametrize(
    ("rows", "batch", "size", "seed"),
    # Seeds drawn for masks of these densities: 50%, every entry, 50%, every entry, 2%, 50%,
    # 2%.
    [
        (2, 3000, 700, 3),
        (2, 4097, 16, 1),
        (2, 8192, 6000, 2),
        (3, 24576, 5000, 2),
        (2, 65536, 16, 0),
        (2, 65536, 4100, 4),
        (1, 9000, 2000, 4),
    ],
)
def test_fused_kernel_folds_a_long_row_in_chunks(rows, batch, size, seed):
    # Past 2,048 entries a row is folded by one program per chunk: each chunk's arrival
    # ranks count the row's later chunks, rings larger than a chunk take arrivals from
    # several, the last chunk of a row that chunks do not divide overlaps the one before
    # (3,000: in 72 entries; 4,097: in all but one), and the chunks' moments are combined;
    # against the same loop.
    from jaxmetrics._core._stream import _chunks

    assert _chunks.chunking(rows, batch, False, ranked=True)[1] > 1
    check_fused_kernel(rows, batch, size, seed)


@pytest.mark.parametrize(
    ("rows", "batch", "size", "chunks", "seed"),
    # Masks 50% full, full, 2% full, 50% full, drawn per 1,024 entries at 65,536.
    [
        (2, 8192, 2048, 4, 3),
        (1, 16385, 4096, 5, 1),
        (3, 24577, 4096, 7, 4),
        (1, 65536, 4096, 16, 2),
    ],
)
def test_fused_kernel_folds_long_rows_without_ranks_in_larger_chunks(
    rows, batch, size, chunks, seed
):
    # Ungrouped period statistics (no EMA, no ring) need no chunk counts: chunks twice
    # the ranked rows' size, the last one overlapping the one before where they do not
    # divide the row (16,385 and 24,577), their moments combined; against the loop.
    from jaxmetrics._core._stream import _chunks

    assert _chunks.chunking(rows, batch, False, ranked=False) == (size, chunks, False)
    check_fused_kernel(rows, batch, 3, seed, ranked=False, pieces=1024 if batch > 60000 else None)


@pytest.mark.parametrize(
    ("rows", "batch", "groups", "size", "seed"),
    # Seeds drawn for group indices in few groups, uniform, all in one group, uniform over
    # 64 groups of 40 entries (most empty); in chunks counted in the kernel: uniform at
    # 2,048 (every entry) and 3,000 entries (16 groups); in chunks counted by XLA: 65 rows
    # of 2,100 (uniform over 64 groups; masks full and 2%) and past 4,096 (few, one,
    # uniform). The other masks are half full, or full at 4,097.
    [(2, 64, 3, 5, 4), (1, 300, 8, 16, 0), (2, 100, 2, 5, 6), (1, 40, 64, 3, 7)]
    + [(2, 2048, 3, 16, 2), (1, 3000, 16, 700, 7), (1, 2100, 64, 5, 1), (1, 2100, 64, 5, 3)]
    + [(1, 4097, 3, 700, 2), (1, 9000, 5, 16, 0), (1, 9000, 2, 3000, 6)],
)
def test_fused_kernel_reads_group_rows_from_the_ungrouped_batch(rows, batch, groups, size, seed):
    # Group rows (`Selected`) read from the source rows and the group index, each masked
    # to its group in the kernel: against the loop over the rows masked in numpy, with
    # few and many groups, empty groups, every entry in one group, out-of-range group
    # indices, counted rows in part of the rows, batches of one and two blocks and of
    # several chunks.
    check_fused_kernel(rows, batch, size, seed, groups)


@pytest.mark.parametrize(
    ("rows", "batch", "groups", "seed"),
    # One program per row; chunks that would be counted in the kernel (3,000 entries, 1
    # group: 4 rows x 3 chunks) and by XLA (2,100 entries, 64 groups; past 4,096).
    [(2, 300, 3, 0), (1, 3000, 1, 7), (1, 2100, 64, 1), (2, 4097, 3, 2), (1, 9000, 2, 6)],
)
def test_fused_kernel_folds_group_rows_without_ranks(rows, batch, groups, seed):
    # Period statistics alone (no EMA, no ring) need no arrival rank: a chunk folds its
    # own entries, whatever the row's other chunks hold, and reads no chunk counts.
    check_fused_kernel(rows, batch, 3, seed, groups, ranked=False)


@pytest.mark.parametrize(
    ("rows", "batch", "groups", "ranked", "seed"),
    # Chunked rows: 64 groups over 2,100 entries (with ranks: EMA, ring; chunks counted
    # by XLA) and 4,097 (with ranks and without); 4 x 65 rows, whose chunks `combine`
    # reduces over. Seeds drawn for uniform group indices and masks 2% full, so that a
    # flag alone reaches some chunks.
    [(1, 2100, 64, True, 3), (1, 4097, 64, False, 0), (2, 4097, 64, True, 2)]
    + [(4, 2100, 64, True, 9)],
)
def test_fused_kernel_folds_sparse_group_rows_from_the_batch(rows, batch, groups, ranked, seed):
    # Group rows read from the batch, most of their chunks empty at these masks: with
    # flags on 0.5% of the entries, chunks that a flag alone reaches must count it, and
    # the empty chunks' partial statistics must combine into their rows' (against the
    # float64 loop). Counted rows on the first two rows only, as a spec's episode
    # tallies are.
    check_fused_kernel(rows, batch, 5, seed, groups, ranked=ranked, flags=0.005, counted_rows=2)


@pytest.mark.parametrize(
    ("batch", "groups", "size", "seed", "flags", "ranked"),
    # Seeds drawn for masks 2% full with flags on 0.5% of the entries (a list of one
    # block: 32 entries at 300, 64 at 2,100, 128 at 4,097), flags alone (an empty mask),
    # and masks half full or full with flags on half the entries (lists of several
    # blocks, in chunks of 256 and 1,024 entries, the last one overlapping the one
    # before; 40 entries: two chunks of 32 that overlap); group indices uniform, or in a
    # few groups.
    [(300, 8, 5, 8, 0.005, True), (2100, 64, 5, 3, 0.005, True), (4097, 64, 700, 0, 0.005, True)]
    + [(2100, 64, 5, 9, 0.005, True), (4097, 64, 3, 0, 0.005, False)]
    + [(300, 3, 5, 1, None, True), (2100, 3, 16, 4, None, True), (4097, 2, 3000, 2, None, True)]
    + [(40, 64, 3, 7, None, True)],
)
def test_fused_kernel_reads_group_rows_from_the_lists_of_reached_entries(
    batch, groups, size, seed, flags, ranked
):
    # Each group row read from its source row's list of reached entries (`_reached`): a
    # list of one block, loaded once for every pass, and lists of several, read in a loop;
    # the counted rows summed over every entry, reached or not; against the float64 loop.
    check_fused_kernel(1, batch, size, seed, groups, ranked=ranked, flags=flags, listed=True)


@pytest.mark.parametrize(
    ("rows", "batch", "size", "seed"), [(2, 24577, 100, 0), (1, 65536, 7, 1), (3, 40000, 5, 2)]
)
def test_fused_kernel_reads_long_rows_from_the_chunks_segments_of_their_lists(
    rows, batch, size, seed
):
    # Ungrouped rows read from their lists, whose chunks (2,048 and 4,096 entries here,
    # `_reached.SEGMENTS`) each list their entries in a segment of their own: the mask's
    # density drawn per run of 3,000 entries, so that segments are empty, sparse and full
    # side by side; against the float64 loop.
    check_fused_kernel(rows, batch, size, seed, pieces=3000, listed=True)


@pytest.mark.parametrize(
    ("sources", "batch", "density"),
    [(3, 300, 0.02), (2, 3000, 0.5), (1, 4097, 1.0), (2, 65, 0.0), (1, 2048, 0.02)]
    + [(1, 24577, 0.3)],  # chunks of 2,048 (`_reached.SEGMENTS`)
)
@pytest.mark.parametrize("grouped", [False, True])
def test_reached_entries_are_listed_in_order_and_counted_rows_summed(
    sources, batch, density, grouped
):
    # The lists hold each source row's entries, each chunk's in entry order in its own
    # segment (the last chunk at 300, 3,000 and 4,097 overlapping the one before), counted
    # per chunk: with group rows the masked-in or flagged entries' indices, without them
    # the masked-in entries' values, each chunk's flags summed beside them. The listing's
    # kernel sums every counted row whole. Against numpy.
    from jaxmetrics._core import _stream
    from jaxmetrics._core._stream import _reached

    rng = np.random.default_rng(batch)
    ok = rng.random((sources, batch)) < density
    bad = np.where(rng.random((sources, batch)) < 0.2, rng.integers(1, 3, (sources, batch)), 0)
    values = rng.standard_normal((sources, batch)).astype(np.float32)
    counted = rng.integers(0, 3, (5, batch)).astype(np.int32)

    def lists(values, ok, bad, counted):
        batch = _stream.Selected.every(values, ok, bad.astype(jnp.uint8))
        if grouped:
            ids = jnp.zeros((1, values.shape[1]), jnp.int32)
            batch = dataclasses.replace(batch, ids=ids, kind=(0,) * sources)
        return _reached.reached(batch, counted, interpret=True)

    (listed, counts, flags), sums = jax.jit(lists)(values, ok, bad, counted)
    assert (flags is None) == grouped
    size = _reached.chunk(batch)
    assert counts.shape == (sources, -(-batch // size))
    for r in range(sources):
        entries = np.flatnonzero(ok[r] | (bad[r] != 0) if grouped else ok[r])
        for c in range(counts.shape[1]):
            mine = (np.arange(batch) >= c * size) & (np.arange(batch) < (c + 1) * size)
            want = entries[mine[entries]]
            assert int(counts[r, c]) == len(want)
            segment = np.asarray(listed[r, c * size : c * size + len(want)])
            np.testing.assert_array_equal(segment, want if grouped else values[r, want])
            if not grouped:
                assert int(flags[r, c]) == int(bad[r, mine].sum())
    np.testing.assert_array_equal(_reached.summed(sums), counted.sum(axis=1))


@pytest.mark.parametrize(
    ("rows", "batch", "size", "seed", "chunks", "itself"),
    [
        (1, 4096, 16, 0, 4, True),
        (1, 4096, 3000, 1, 4, True),
        (3, 3000, 1100, 2, 3, True),
        (7, 1025, 5, 3, 2, True),
        (2, 2048, 1, 4, 2, True),
        (1, 1024, 16, 5, 1, False),
        (10, 4096, 16, 6, 4, True),
        (32, 4096, 3, 9, 4, True),
        (33, 4096, 3, 10, 1, False),
        (42, 3000, 3, 11, 3, True),
        (43, 3000, 3, 12, 1, False),
        (1, 4097, 2000, 7, 5, True),
        (2, 12289, 5000, 13, 13, True),
        (13, 12288, 3, 14, 12, True),
        (14, 12288, 3, 15, 12, False),
        (2, 16384, 5000, 16, 8, True),
        (20, 16384, 3, 17, 8, True),
        (21, 16384, 3, 18, 8, False),
        (2, 24577, 5000, 8, 13, True),
    ],
)
def test_fused_kernel_chunks_rows_past_1024_entries(rows, batch, size, seed, chunks, itself):
    # Past 1,024 entries a row is chunked (up to 4,096 entries, while that makes at most
    # 128 programs); each chunk's program counts the row's mask around it itself (in one
    # block, or two at 3,000, 1,025, 4,097 and 12,289) up to 4,096 entries, and past it
    # while that makes at most 160 programs (13 rows of 12 chunks, not 14; at 16,384 chunks
    # of 2,048, 20 rows of 8, not 21; 24,577, which `update` reads from the lists, in 13
    # chunks of 2,048), else it reads the chunks' counts. Masks drawn per 1,024 entries as
    # empty, full or in between, so that whole chunks are empty or full; rings smaller than
    # a chunk, and larger than several.
    from jaxmetrics._core._stream import _chunks

    got = _chunks.chunking(rows, batch, False, ranked=True)
    assert (got.n, got.counted_here) == (chunks, itself)
    check_fused_kernel(rows, batch, size, seed, pieces=1024)


def check_fused_kernel(
    rows,
    batch,
    size,
    seed,
    groups=0,
    pieces=None,
    ranked=True,
    flags=None,
    counted_rows=None,
    listed=False,
):
    """The kernel against a loop over each row (see the tests above); without an EMA and
    a ring where not `ranked` (its chunks then need no rank). `flags`: the density of
    non-finite flags (else half); `counted_rows`: at most that many counted rows (else
    about one per row and pack). With `groups`, the
    batch's rows are each of `rows` source rows over every entry and then masked to each
    of `groups` groups (`Selected`), the group index drawn uniformly (out of range on
    either side included), all in one group, or in a few groups (the others empty); the
    loop reads the rows masked in numpy. `pieces`: the mask's density drawn per run of
    that many entries of a row (else one density for the whole batch). `listed`: group
    rows read from the lists of reached entries (`_reached`), else from the batch."""
    from jaxmetrics._core import _stream
    from jaxmetrics._core._stream import _kernel

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
    # A ring of the rows drawn into it, in random order; its `pos` indexed by stream row.
    # The ring keeps a row's newest `size` arrivals, the oldest of them at `pos`.
    members = [r for r in range(rows) if rng.random() < 0.7] or [rows - 1]
    ring_row = np.full(rows, -1, np.int32)
    ring_row[members] = rng.permutation(len(members))
    data = rng.integers(0, 2**32, (len(members), size, 2), dtype=np.uint32)
    pos = rng.integers(0, size, rows).astype(np.int32)

    def fold(m, v, bad, i, t, ta, w, o, sh, d, p):
        ema = _kernel.EmaIn(coeff, w, o) if ranked else None
        rings = (_kernel.RingIn(d, p, ring_row, np.arange(rows)),) if ranked else ()
        table = (tuple(int(a) for a in b) for b in (src, kind, group))
        selected = _stream.Selected(v, m, bad, i, *table)
        return _kernel.fold(selected, sh, t, ta, packs, ema, rings, True, listed=listed)

    args = (ok, x, flags_in, ids, steps, counted, ema_w, ema_off, shift, data, pos)
    stats, rings, *_ = jax.device_get(jax.jit(fold)(*map(jnp.asarray, args)))
    want_counted = np.zeros(rows * packs, np.int64)
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
            np.testing.assert_allclose(
                float(stats.ema[r]), want, rtol=1e-5, atol=1e-6 * scale + 1e-30, err_msg=str(r)
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
        np.testing.assert_array_equal(np.asarray(rings[0]), want_ring)
    else:
        assert stats.ema is None and rings == ()


@pytest.mark.parametrize(
    ("num_envs", "dtype", "fused"),
    [(3000, "float32", True), (4096, "float32", True), (16, "float32", False)]
    + [(4097, "float32", True), (65536, "float32", True), (65537, "float32", False)]
    + [(3000, "float64", False)],
)
def test_fused_kernel_serves_float32_batches_of_32_to_65536(monkeypatch, num_envs, dtype, fused):
    # The kernel holds float32 only: a float64 state, and batches under the kernel's
    # smallest or past its largest, take the jnp path.
    from jaxmetrics._core import _stream
    from jaxmetrics._core._stream import _kernel

    assert _kernel.fits(num_envs, dtype) == fused
    fold = _stream.add_with_counts
    monkeypatch.setattr(_stream, "add_with_counts", functools.partial(fold, interpret=True))
    term = jm.Term(lambda x: x, reduce="mean", stats=("mean", jm.ema(0.1), jm.window(5)))
    with jax.enable_x64(dtype == "float64"):
        metrics = jm.Metrics(terms={"a": term}, dtype=jnp.dtype(dtype))
        x, done = jnp.zeros(num_envs, dtype), jnp.zeros(num_envs, bool)
        jaxpr = jax.make_jaxpr(metrics.update)(metrics.init(num_envs), x, done)
    assert ("pallas_call" in str(jaxpr)) == fused


@pytest.mark.parametrize(
    ("num_envs", "ema", "kernels"),
    [(4096, False, 0), (4097, False, 1), (65536, False, 1), (4096, True, 1), (16384, True, 1)]
    + [(16385, True, 2), (65536, True, 2)],
)
def test_period_statistics_alone_fold_in_the_kernel_past_4096_envs_without_lists(
    monkeypatch, num_envs, ema, kernels
):
    # Ungrouped period statistics are XLA's one reduction up to 4,096 envs and the
    # kernel's past it, whose chunks need no lists of reached entries at any size (one
    # Pallas call); with an EMA the kernel serves every size, and past 16,384 envs
    # reads the rows from the lists (a second call, the listing's).
    from jaxmetrics._core import _stream

    fold = _stream.add_with_counts
    monkeypatch.setattr(_stream, "add_with_counts", functools.partial(fold, interpret=True))
    stats = ("mean", "std", "min", "max", jm.histogram(10, (0.0, 1.0)))
    term = jm.Term(lambda x: x, reduce="mean", stats=stats + ((jm.ema(0.1),) if ema else ()))
    metrics = jm.Metrics(terms={"a": term, "b": jm.Term(lambda x: 2 * x, reduce="sum")})
    x, done = jnp.zeros(num_envs, jnp.float32), jnp.zeros(num_envs, bool)
    jaxpr = str(jax.make_jaxpr(metrics.update)(metrics.init(num_envs), x, done))
    assert jaxpr.count("pallas_call") == kernels


@pytest.mark.parametrize(
    ("num_envs", "groups", "history", "in_kernel"),
    [(300, 0, False, True), (1024, 0, False, True), (3000, 0, False, False)]
    + [(4097, 0, False, False), (16385, 0, False, True), (300, 3, False, True)]
    + [(300, 0, True, False)],
)
def test_the_fused_kernel_updates_the_rows_fields_where_each_row_is_one_program(
    monkeypatch, num_envs, groups, history, in_kernel
):
    # The per-row fields are updated by the program that folds the row where each row is
    # one (up to 1,024 entries, and rows read from the lists: group rows, and ranked rows
    # past 16,384 entries): `_update.update` runs on `[1, 1]` blocks there, and not on the
    # `[R]` fields. Chunked rows, and a spec whose EMA keeps its newest values for exact
    # merges (rings XLA advances; a reporting state's), take XLA's update of the `[R]`
    # fields.
    from jaxmetrics._core import _fresh, _stream
    from jaxmetrics._core._stream import _update

    fold = _stream.add_with_counts
    monkeypatch.setattr(_stream, "add_with_counts", functools.partial(fold, interpret=True))
    shapes = []
    update = _update.update
    monkeypatch.setattr(_update, "update", lambda f, *a: shapes.append(f.m2.shape) or update(f, *a))
    term = jm.Term(lambda x: x[0], reduce="mean", stats=("mean", jm.ema(0.1), jm.window(5)))
    grouping = jm.groups(lambda x: x[1], tuple(f"g{i}" for i in range(groups))) if groups else None
    metrics = jm.Metrics(terms={"a": term}, groups=grouping)
    state = metrics.init(num_envs)
    if history:
        state = _fresh.fresh(metrics._rows, num_envs, 1, ema_history=True)
    x = (jnp.zeros(num_envs, jnp.float32), jnp.zeros(num_envs, jnp.int32))
    jax.make_jaxpr(metrics.update)(state, x, jnp.zeros(num_envs, bool))
    # (A row read from its list is folded in one block or in a loop of them: two traces.)
    assert set(shapes) == ({(1, 1)} if in_kernel else {(1 + groups,)})


@pytest.mark.parametrize(("batch", "density"), [(300, 0.3), (4097, 0.02), (4097, 1.0)])
def test_fused_kernel_counts_listed_rows_into_histograms_by_programs_of_their_own(batch, density):
    # Ungrouped rows read from the lists, each selecting a source row other than its own
    # index (rows 0..2 select sources 2, 0 and 3 of four): the programs past the rows'
    # count each (row, histogram row) pair's entries from its source row's list, two
    # histograms of other bins and ranges (rows 0 and 2 in one, row 1 in the other).
    # Entries that only a non-finite flag lists are not counted, NaN in no slot, the
    # infinities under and over the range; against numpy's float64 histograms.
    from jaxmetrics._core import _stream
    from jaxmetrics._core._stream import _hists, _kernel
    from jaxmetrics._core._stream._state import HistGroup

    rng = np.random.default_rng(batch)
    src = (2, 0, 3)
    ok = rng.random((4, batch)) < density
    x = rng.normal(size=(4, batch)).astype(np.float32)
    x[:, :3] = np.nan, np.inf, -np.inf
    flagged = rng.random((4, batch)) < 0.05
    specs = ((5, (0, 2), (-1.0, -0.5), (1.0, 2.0)), (40, (1,), (-2.0,), (2.0,)))
    hist_rows, hists = [], []
    for bins, rows, lo, hi in specs:
        row = np.full(3, -1, np.int32)
        row[list(rows)] = np.arange(len(rows))
        hist_rows.append(_hists.HistRows.of(HistGroup(bins, rows, lo, hi), row))
        zero = np.zeros((len(rows), bins + 2), np.uint32)
        hists.append((zero.astype(np.int32), zero, zero))

    def fold(ok, x, bad, hists):
        ids = jnp.zeros((0, batch), jnp.int32)
        selected = _stream.Selected(x, ok, bad, ids, src, (-1,) * 3, (0,) * 3)
        _, _, counted, _ = _kernel.fold(
            selected,
            jnp.zeros(3, jnp.float32),
            jnp.zeros(3, jnp.uint32),
            jnp.zeros((0, batch), jnp.int32),
            0,
            interpret=True,
            listed=True,
            hists=tuple(_hists.HistIn(*h) for h in hists),
            hist_rows=tuple(hist_rows),
        )
        return counted

    counted = jax.jit(fold)(ok, x, flagged.astype(np.uint8), hists)
    for (bins, rows, lo, hi), h in zip(specs, counted):
        np.testing.assert_array_equal(h.counted, 0)
        np.testing.assert_array_equal(h.hi, 0)
        for i, r in enumerate(rows):
            v = x[src[r]][ok[src[r]]].astype(np.float64)
            v = v[~np.isnan(v)]
            inner = np.histogram(v, np.linspace(lo[i], hi[i], bins + 1))[0]
            want = np.r_[np.sum(v < lo[i]), inner, np.sum(v > hi[i])]
            np.testing.assert_array_equal(np.asarray(h.lo[i], np.int64), want, err_msg=str(r))


@pytest.mark.parametrize(
    ("num_envs", "groups", "listed"),
    [(300, 0, False), (4097, 0, False), (300, 2, True)]
    # Rows read from their lists without groups: their histograms counted by programs
    # of their own, a (row, histogram row) pair each, as past 16,384 envs.
    + [(300, 0, True), (4097, 0, True)],
)
def test_fused_kernel_carries_histogram_counts_into_the_high_word(
    monkeypatch, num_envs, groups, listed
):
    # A histogram's counts are two uint32 words: the kernel adds a step's counts to the
    # low words and carries into the high word where one wraps. From low words 2 below
    # 2^32, the counts after two steps against numpy's histogram of the finite values in
    # float64, as 64-bit integers; and the state as the jnp path leaves it.
    from jaxmetrics._core import _stream
    from jaxmetrics._core._stream import _reached

    monkeypatch.setattr(_reached, "listed", lambda *_: listed)

    edges = np.linspace(-1.0, 1.0, 6)
    # With an EMA, which the kernel folds (a histogram alone takes XLA's kernels).
    stats = (jm.histogram(5, (-1.0, 1.0)), jm.ema(0.1))
    term = jm.Term(lambda x: x[0], reduce="last", stats=stats)
    grouping = jm.groups(lambda x: x[1], ("a", "b")) if groups else None
    metrics = jm.Metrics(terms={"a": term}, groups=grouping)
    rng = np.random.default_rng(3)
    xs = rng.normal(size=(2, num_envs)).astype(np.float32)
    xs[0, :3] = np.inf, -np.inf, np.nan
    gs = rng.integers(0, 2, (2, num_envs)).astype(np.int32)
    near = 2**32 - 2

    def start():
        def wrap(path, leaf):
            key = jax.tree_util.keystr(path)
            return jnp.full_like(leaf, near) if "hists" in key and key.endswith(".lo") else leaf

        return jax.tree_util.tree_map_with_path(wrap, metrics.init(num_envs))

    def run():
        done = jnp.ones(num_envs, bool)
        step = jax.jit(metrics.update)
        s = step(start(), (jnp.asarray(xs[0]), jnp.asarray(gs[0])), done)
        return step(s, (jnp.asarray(xs[1]), jnp.asarray(gs[1])), done)

    plain = run()
    fold = _stream.add_with_counts
    monkeypatch.setattr(_stream, "add_with_counts", functools.partial(fold, interpret=True))
    fused = run()
    for (path, a), b in zip(jax.tree_util.tree_leaves_with_path(plain), jax.tree.leaves(fused)):
        if not jnp.issubdtype(a.dtype, jnp.floating):
            np.testing.assert_array_equal(a, b, err_msg=jax.tree_util.keystr(path))
    words = {
        jax.tree_util.keystr(k).rsplit(".", 1)[1]: np.asarray(v, np.uint64)
        for k, v in jax.tree_util.tree_leaves_with_path(fused)
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


@pytest.mark.parametrize(
    ("num_envs", "steps", "groups", "ranked", "listed"),
    [
        (64, 30, 0, True, False),
        (300, 10, 0, True, False),
        (3000, 10, 0, True, False),
        (3000, 10, 3, False, False),
    ]
    + [(4097, 10, 0, True, False), (12288, 10, 0, True, False), (300, 10, 3, True, False)]
    + [(4097, 10, 3, True, False), (300, 10, 3, False, False), (4097, 10, 3, False, False)]
    + [(300, 10, 3, True, True), (4097, 10, 3, False, True), (4097, 10, 0, True, True)]
    + [(12288, 10, 0, False, False)],
)
def test_fused_kernel_folds_a_rollout_like_the_jnp_path(
    monkeypatch, num_envs, steps, groups, ranked, listed
):
    # The whole update with the kernel (interpret mode) against the jnp path that CPUs and
    # sharded states take, over a rollout with episodes ending, non-finite values, two
    # EMAs, two window sizes and two histograms: every count, ring slot and histogram bin
    # of the state equal, every reported number to float32 rounding (the batch's sums
    # are taken in another order). Batches of one block, of two, and of several chunks;
    # with `groups`, each metric also per group (indices out of range included), its
    # group rows read by the kernel from the ungrouped batch; not `ranked`: the period
    # statistics only, which the kernel folds for group rows and past 4,096 envs; `listed`:
    # the rows read from the lists of reached entries (`_reached`, with group rows or past
    # 16,384 envs without), else from the batch.
    from jaxmetrics._core import _stream
    from jaxmetrics._core._stream import _reached

    monkeypatch.setattr(_reached, "listed", lambda *_: listed)

    stats = {
        "a": ("mean", jm.ema(0.05), jm.window(7)),
        "b": ("std", jm.ema(0.5), jm.window(3, percentiles=(50,))),
        "c": ("max", jm.histogram(5, (-1.0, 1.0)), jm.window(7)),
        "d": ("min", jm.histogram(40, (-2.0, 2.0))),
    }
    if not ranked:
        stats = {"a": ("mean", "sum"), "b": ("std", "min"), "c": ("max",)}
        stats["d"] = ("min", jm.histogram(40, (-2.0, 2.0)))
        # As rows, as on a GPU at these sizes: a CPU takes them as segments, no kernel.
        monkeypatch.setattr(_stream.SegmentPlan, "serves", lambda *_: False)
    names = tuple(f"g{i}" for i in range(groups))
    metrics = jm.Metrics(
        terms={
            k: jm.Term(lambda x, i: x[0][i], reduce="mean", stats=v, params={"i": i})
            for i, (k, v) in enumerate(stats.items())
        },
        groups=jm.groups(lambda x: x[1], names) if groups else None,
    )
    rng = np.random.default_rng(7)
    xs = rng.normal(size=(steps, 4, num_envs)).astype(np.float32)
    xs[3, 0, :5], xs[5, 2, 7], xs[8, 1, 9] = np.nan, np.inf, -np.inf
    dones = rng.random((steps, num_envs)) < 0.3
    gs = rng.integers(-1, groups + 1, (steps, num_envs)).astype(np.int32)

    def run():
        def body(s, inp):
            return metrics.update(s, inp[:2], inp[2]), None

        scan = jax.jit(lambda s, *inputs: jax.lax.scan(body, s, inputs)[0])
        return scan(metrics.init(num_envs), *map(jnp.asarray, (xs, gs, dones)))

    plain = run()
    fold = _stream.add_with_counts
    monkeypatch.setattr(_stream, "add_with_counts", functools.partial(fold, interpret=True))
    state = metrics.init(num_envs)
    assert "pallas_call" in str(jax.make_jaxpr(metrics.update)(state, (xs[0], gs[0]), dones[0]))
    fused = run()
    for (path, a), b in zip(jax.tree_util.tree_leaves_with_path(plain), jax.tree.leaves(fused)):
        if not jnp.issubdtype(a.dtype, jnp.floating):
            np.testing.assert_array_equal(a, b, err_msg=jax.tree_util.keystr(path))
    want, got = (metrics.to_host(metrics.compute(s)) for s in (plain, fused))
    assert want.keys() == got.keys()
    for tag in want:
        # A sum near zero keeps its addends' rounding: a few ulps of partial sums near 10
        # (3 groups at 3,000 envs: 1.7e-6 off in a sum of 0.04).
        atol = 1e-5 if tag.endswith("/sum") else 1e-6
        np.testing.assert_allclose(got[tag], want[tag], rtol=2e-6, atol=atol, err_msg=tag)


@pytest.mark.parametrize(
    ("constant", "value", "num_envs", "groups", "ranked", "chunks"),
    [
        # Chunks of 2,048 with ranks, 4,096 without (`LARGER_CHUNKS`), here from 8,192.
        ("LARGER_CHUNKS", 8192, 12288, 0, True, (2048, 6, True)),
        ("LARGER_CHUNKS", 8192, 12288, 0, False, (4096, 3, False)),
        # Group rows chunked at any number of rows (`GROUPS_CHUNKED`), here past 8 programs.
        ("PROGRAMS", 8, 3000, 3, False, (1024, 3, False)),
        # The chunks combined by reductions (`COMBINED_BY_REDUCTIONS`), here from 1 row.
        ("COMBINED_BY_REDUCTIONS", 1, 4097, 0, True, (1024, 5, True)),
        ("COMBINED_BY_REDUCTIONS", 1, 4097, 3, False, (1024, 5, False)),
    ],
)
def test_fused_kernel_folds_the_large_regimes_like_the_jnp_path(
    monkeypatch, constant, value, num_envs, groups, ranked, chunks
):
    # The fold paths that take more entries or rows than a rollout in interpret mode
    # affords, their threshold lowered to the rollout's batch: the same rollout against
    # the jnp path, after checking that its batch takes the path (`chunks`: `Chunking`).
    from jaxmetrics._core._stream import _chunks

    monkeypatch.setattr(_chunks, constant, value)
    rows = 4 * (1 + groups)  # the rollout's four metrics, each per group too
    assert _chunks.chunking(rows, num_envs, groups > 0, ranked=ranked) == chunks
    test_fused_kernel_folds_a_rollout_like_the_jnp_path(
        monkeypatch, num_envs, 10, groups, ranked, False
    )
