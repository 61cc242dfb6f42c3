"""Bad input fails at spec-build or trace time, naming the culprit and the fix."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxmetrics as jm


def ident(s):
    return s


@pytest.mark.parametrize(
    "kwargs, match",
    [
        (
            {"terms": {"x": jm.Term(ident, reduce="avg")}},
            r"term 'x': unknown episode reduction 'avg'",
        ),
        (
            {"terms": {"x": jm.Term(ident, stats=("median",))}},
            r"term 'x': unknown report statistic 'median'",
        ),
        ({"terms": {"x": jm.Term(ident, stats=("ema",))}}, r"Use jaxmetrics.ema\(...\)"),
        (
            {"terms": {"x": jm.Term(ident, stats=(jm.window(3), jm.window(5)))}},
            r"at most one window",
        ),
        (
            {"terms": {"x": jm.Term(ident, nonfinite="ignore")}},
            r"term 'x': unknown nonfinite policy 'ignore'",
        ),
        (
            {"logged": {"loss": jm.Logged(stats=(3,))}},
            r"logged value 'loss': a report statistic must be",
        ),
        ({"logged": "loss"}, r"logged must be a dict or a list of names"),
        ({"terms": {"x": 3}}, r"term 'x': expected jaxmetrics.Term or a function"),
        ({"terms": {"x": jm.Term(ident, outputs="ab")}}, r"outputs must be a non-empty sequence"),
        ({"terms": {"x": jm.Term(ident, outputs=("a", "a"))}}, r"duplicate output names"),
        ({"terms": {"x": jm.Term(ident, reduce={"a": "sum"})}}, r"a dict `reduce` needs `outputs`"),
        (
            {"terms": {"x": jm.Term(ident, outputs=("a",), reduce={"b": "sum"})}},
            r"unknown outputs \['b'\]",
        ),
        ({"terms": {"x": ident}, "counters": ("episodes",)}, r"built in"),
        ({"counters": ("a", "a")}, r"duplicate counter names"),
        ({"nonfinite": "drop"}, r"Metrics\(nonfinite=...\): unknown nonfinite policy"),
        ({"dtype": jnp.int32}, r"must be a float dtype"),
        ({"dtype": jnp.bfloat16}, r"Metrics\(dtype=bfloat16\): .* Use float32"),
        ({"dtype": jnp.float16}, r"Metrics\(dtype=float16\): .* Use float32"),
    ],
)
def test_bad_spec_rejected_when_built(kwargs, match):
    with pytest.raises((ValueError, TypeError), match=match):
        jm.Metrics(**kwargs)


@pytest.mark.parametrize(
    "make, match",
    [
        (lambda: jm.window(0), r"window size must be a positive int, got 0"),
        (lambda: jm.window(-3), r"window size must be a positive int"),
        (lambda: jm.window(2.5), r"window size must be a positive int"),
        (lambda: jm.window(2**20 + 1), r"window\(1048577\) needs 8.0 MiB per metric"),
        (
            lambda: jm.window(2**31),
            r"window size 2147483648 is over 1048576 .*16,384.0 MiB per metric",
        ),
        (lambda: jm.window(10, percentiles=(101,)), r"percentiles must be numbers in \[0, 100\]"),
        (lambda: jm.ema(0.0), r"ema coefficient must be a number in \(0, 1\], got 0.0"),
        (lambda: jm.ema(1.5), r"ema coefficient must be a number in \(0, 1\]"),
        (lambda: jm.histogram(0, (0, 1)), r"histogram bins must be a positive int"),
        (lambda: jm.histogram(10, (1, 1)), r"histogram range needs lo < hi"),
        (lambda: jm.histogram(10, (0, float("inf"))), r"two finite numbers"),
    ],
)
def test_bad_statistic_parameters_rejected(make, match):
    with pytest.raises(ValueError, match=match):
        make()


@pytest.mark.parametrize(
    "terms, match",
    [
        # outputs of a term named "x" and a statistic of "x" would write the same tag
        (
            {"x": jm.Term(ident, stats=("std",)), "x/std": ident},
            r"tag collision.*Episode_Metrics/x/std",
        ),
        # distinct names that TensorBoard sanitizes to the same tag
        ({"a b": ident, "a_b": ident}, r"tag collision.*TensorBoard turns"),
    ],
)
def test_colliding_tags_rejected_when_built(terms, match):
    with pytest.raises(ValueError, match=match):
        jm.Metrics(terms=terms)


N = 8


@pytest.mark.parametrize(
    "fn, match",
    [
        (
            lambda s: s[:, None],
            r"term 'x' returned shape \(8, 1\); expected \(num_envs,\)=\(8,\): drop the trailing axis with .squeeze\(-1\)",
        ),
        (
            lambda s: jnp.sum(s),
            r"returned shape \(\); .*it returned a scalar; broadcast it with jnp.full",
        ),
        (lambda s: jnp.stack([s, s], -1), r"reduce the extra axes"),
        (lambda s: s[:3], r"returned shape \(3,\)"),
        (lambda s: s.astype(jnp.complex64), r"term 'x': got dtype complex64; give float"),
        (lambda s: "fast", r"term 'x': got 'fast' \(numpy dtype <U4\); give float, int or bool"),
        (lambda s: None, r"term 'x': got None; give float, int or bool values"),
        (lambda s: {"a": s}, r"term 'x' returned a dict .* Term\(fn, outputs=\['a'\]\)"),
    ],
)
def test_bad_term_output_rejected_at_trace_time(fn, match):
    m = jm.Metrics(terms={"x": fn})
    with pytest.raises((ValueError, TypeError), match=match):
        jax.jit(m.update)(m.init(N), jnp.zeros(N), jnp.zeros(N, bool))


def test_multi_output_term_must_return_its_declared_keys():
    m = jm.Metrics(terms={"t": jm.Term(lambda s: {"a": s}, outputs=("a", "b"))})
    with pytest.raises(
        ValueError, match=r"term 't' returned keys \['a'\]; its outputs are \['a', 'b'\]"
    ):
        m.update(m.init(N), jnp.zeros(N), jnp.zeros(N, bool))
    m = jm.Metrics(terms={"t": jm.Term(lambda s: s, outputs=("a",))})
    with pytest.raises(TypeError, match=r"declares outputs \['a'\] but returned"):
        m.update(m.init(N), jnp.zeros(N), jnp.zeros(N, bool))


def test_bad_done_rejected():
    m = jm.Metrics(terms={"x": ident})
    with pytest.raises(
        ValueError, match=r"done must be a bool array of shape \(num_envs,\)=\(8,\)"
    ):
        m.update(m.init(N), jnp.zeros(N), jnp.zeros((N, 1), bool))


@pytest.mark.parametrize("done", [[0.1] * N, [jnp.nan] * N, [-1.0] * N, [1.0] * N])
def test_float_done_rejected_at_trace_time(done):
    # 0.1, NaN and -1 used to count as episode ends without a word.
    m = jm.Metrics(terms={"x": ident})
    with pytest.raises(TypeError, match=r"done has dtype float32; .*state.done.astype\(bool\)"):
        jax.jit(m.update)(m.init(N), jnp.zeros(N), jnp.asarray(done, jnp.float32))


def test_integer_done_means_nonzero():
    m = jm.Metrics(terms={"x": ident})
    done = jnp.asarray([0, 1, 2, -1, 0, 0, 0, 0], jnp.int32)
    s = m.update(m.init(N), jnp.arange(N, dtype=jnp.float32), done)
    host = m.to_host(m.compute(s))
    assert host["Counters/episodes"] == 3
    assert host["Episode_Metrics/x"] == pytest.approx((1 + 2 + 3) / 3)


def test_update_of_the_merge_identity_names_the_fix():
    m = jm.Metrics(terms={"x": ident})
    for empty in (m.init(0), m.empty()):
        with pytest.raises(ValueError, match=r"this state has no envs: .* Use init\(num_envs\)"):
            m.update(empty, jnp.zeros(0), jnp.zeros(0, bool))


def test_bad_log_and_increment_rejected():
    m = jm.Metrics(logged=["loss"], counters=["updates"])
    s = m.init(0)
    with pytest.raises(ValueError, match=r"log: unknown logged names \['los'\]; declare them"):
        m.log(s, {"los": 1.0})
    with pytest.raises(ValueError, match=r"increment: unknown counter 'update'"):
        m.increment(s, "update")
    with pytest.raises(TypeError, match=r"`by` must be a scalar int"):
        m.increment(s, "updates", 1.5)
    with pytest.raises(ValueError, match=r"`by` must be in \[-2\^31, 2\^32\)"):
        m.increment(s, "updates", 2**32)
    for bad, match in (
        (None, r"log: 'loss': got None"),
        ("a", r"log: 'loss': got 'a' \(numpy dtype <U1\)"),
        ([object()], r"log: 'loss': got list of non-numbers"),
    ):
        with pytest.raises(TypeError, match=match):
            m.log(s, {"loss": bad})


def test_log_of_an_empty_array_logs_nothing():
    m = jm.Metrics(logged=["loss", "kl"])
    s = m.log(m.init(0), {"loss": jnp.zeros((0,)), "kl": jnp.asarray([2.0, 4.0])})
    s = jax.jit(m.log)(s, {"loss": jnp.zeros((0, 3))})
    host = m.to_host(m.compute(s))
    assert host["Train/loss/count"] == 0
    assert host["Train/kl/count"] == 2 and host["Train/kl"] == 3.0


def test_state_from_another_spec_rejected():
    a = jm.Metrics(terms={"x": ident})
    b = jm.Metrics(terms={"x": ident, "y": ident})
    with pytest.raises(ValueError, match=r"built by a different Metrics spec"):
        b.update(a.init(N), jnp.zeros(N), jnp.zeros(N, bool))
    # Same shapes, other names or statistics: once relabelled without a word.
    same_shape = [
        jm.Metrics(terms={"y": ident}),
        jm.Metrics(terms={"x": jm.Term(ident, reduce="sum")}),
        jm.Metrics(terms={"x": ident}, episode_prefix="Ep"),
        jm.Metrics(logged=["loss"]),
    ]
    for other in same_shape:
        for fn in (
            lambda s, o=other: o.compute(s),
            lambda s, o=other: jax.jit(o.compute)(s),
            lambda s, o=other: o.merge(s, s),
            lambda s, o=other: jax.jit(o.update)(s, jnp.zeros(N), jnp.zeros(N, bool)),
        ):
            with pytest.raises(ValueError, match=r"built by a different Metrics spec"):
                fn(a.init(N))
    with pytest.raises(ValueError, match=r"built by a different Metrics spec"):
        jm.Metrics(logged=["kl"]).log(jm.Metrics(logged=["loss"]).init(0), {"kl": 1.0})
    # The same configuration built twice (e.g. in a resumed process) is the same spec.
    again = jm.Metrics(terms={"x": ident})
    assert again.to_host(again.compute(a.init(N)))["Episode_Metrics/x/count"] == 0
    with pytest.raises(TypeError, match=r"expected a MetricsState"):
        a.compute({"not": "a state"})


def test_init_rejects_bad_num_envs():
    m = jm.Metrics(terms={"x": ident})
    with pytest.raises(TypeError, match=r"num_envs must be an int"):
        m.init(4.0)
    with pytest.raises(ValueError, match=r"num_envs must be >= 0"):
        m.init(-1)


def test_nonfinite_policies_at_flush():
    m = jm.Metrics(
        terms={
            "warned": ident,
            "raised": jm.Term(ident, nonfinite="raise"),
            "quiet": jm.Term(ident, nonfinite="propagate"),
        }
    )
    s = m.update(m.init(2), jnp.asarray([jnp.nan, 1.0]), jnp.ones(2, bool))
    host = m.to_host(m.compute(s))
    # The spec reports what it saw and each metric's policy; it neither warns nor raises.
    found = [(i.tag, policy, n) for i, policy, n in m.nonfinite(host)]
    assert found == [
        ("Episode_Metrics/warned/nonfinite", "skip", 1),
        ("Episode_Metrics/raised/nonfinite", "raise", 1),
        ("Episode_Metrics/quiet/nonfinite", "propagate", 1),
    ]
    assert m.nonfinite(m.to_host(m.compute(m.init(2)))) == []
    assert host["Episode_Metrics/raised"] == 1.0  # left out, as under "skip"
    # The logger applies the policies: "skip" warns, "raise" raises, naming run and step.
    memory = jm.MemoryWriter()
    with pytest.raises(jm.NonFiniteError, match=r"step 3, run 0: term 'raised': 1 non") as err:
        with pytest.warns(RuntimeWarning, match=r"step 3, run 0: term 'warned': 1 non"):
            with jm.Logger(m, [memory]) as logger:
                logger.flush(s, 3)
    assert "quiet" not in str(err.value)
    assert [r.step for r in memory.records] == [3]


@pytest.mark.parametrize("name", ["a//b", "x/", "/x", "a/./b", "a/../b"])
def test_names_that_are_not_clean_paths_are_refused_at_build_time(name):
    # MLflow refuses tags that normalize to another path, at flush time, for every record.
    with pytest.raises(ValueError, match=r"empty, '\.' or '\.\.' part between slashes"):
        jm.Metrics(logged=[name])
    with pytest.raises(ValueError, match=r"part between slashes"):
        jm.Metrics(terms={name: jm.Term(lambda x: x)})
    with pytest.raises(ValueError, match=r"part between slashes"):
        jm.Metrics(logged=["ok"], counters=[name])
    with pytest.raises(ValueError, match=r"Metrics\(logged_prefix=\.\.\.\).*part between slashes"):
        jm.Metrics(logged=["ok"], logged_prefix=name)
    logger = jm.Logger(jm.Metrics(logged=["ok"]), [])
    with pytest.raises(ValueError, match=r"Logger.timer.*part between slashes"):
        logger.timer(name)
    logger.close()


def test_a_bare_string_of_stats_is_one_statistic():
    m = jm.Metrics(
        logged={"x": jm.Logged(stats="mean")}, terms={"r": jm.Term(lambda x: x, stats="max")}
    )
    assert sorted(i.tag for i in m.tags if i.group != "counter" and i.stat != "nonfinite") == [
        "Episode_Metrics/r/max",
        "Train/x",
    ]


def test_a_stack_of_states_is_refused_where_one_state_is_expected():
    # A state stacked over seeds (vmapped init) passed whole to compute would merge the
    # seeds as if they were env shards of one run: a wrong number with no error.
    m = jm.Metrics(terms={"r": jm.Term(lambda r: r)}, logged=["loss"], counters=["c"])
    rewards = np.array([[1.0, 2.0, 3.0], [10.0, 20.0, 30.0]], np.float32)
    done = jnp.array([True, False, True])

    def run(r):
        return m.update(m.init(3), jnp.asarray(r), done)

    stacked = jax.vmap(run)(rewards)
    for fn, args in (
        ("compute", (stacked,)),
        ("update", (stacked, jnp.ones(3), done)),
        ("reset_period", (stacked,)),
        ("merge", (stacked, stacked)),
    ):
        with pytest.raises(ValueError, match=rf"{fn}: this state has leading axes \(2,\)"):
            getattr(m, fn)(*args)
    per_seed = jax.vmap(m.compute)(stacked)
    means = np.asarray(per_seed["Episode_Metrics/r"])
    np.testing.assert_allclose(means, [(r[0] + r[2]) / 2 for r in rewards.astype(np.float64)])


@pytest.mark.parametrize("make", [lambda ps: jm.window(8, percentiles=ps), jm.quantiles])
def test_percentile_levels_have_exact_tags_and_more_than_4_decimals_are_refused(make):
    def spec(levels):
        return jm.Metrics(logged={"x": jm.Logged(stats=(make(levels),))})

    for bad in [(12.34567,), (1e-5,), (12.34567, 12.34568)]:
        with pytest.raises(ValueError, match=r"at most 4 decimals, got "):
            spec(bad)
    metrics = spec((12.3456, 12.3457, 1e-4, -0.0, 99.9, 100))
    levels = [t.stat.split("_p")[-1].lstrip("q") for t in metrics.tags if t.stat[-1].isdigit()]
    assert levels == ["12.3456", "12.3457", "0.0001", "0", "99.9", "100"]


def test_a_window_percentile_of_minus_zero_is_the_0th_percentile():
    metrics = jm.Metrics(logged={"x": jm.Logged(stats=(jm.window(4, percentiles=(-0.0, 50)),))})
    state = metrics.log(metrics.init(1), {"x": jnp.array([3.0, 1.0, 2.0], jnp.float32)})
    report = metrics.compute(state)  # raised KeyError: 'window_p-0'
    assert float(report["Train/x/window_p0"]) == 1.0
    assert float(report["Train/x/window_p50"]) == np.percentile([3.0, 1.0, 2.0], 50)
