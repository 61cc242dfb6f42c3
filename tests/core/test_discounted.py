"""The discounted-return episode reduction `jm.discounted(gamma)` against a float64 Python
unroll: random values (non-finite ones included), `done` patterns and discounts, under
`jit` + `lax.scan`; 10^4-step float32 episodes; merge, sharding and the spec's identity.
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

import jaxmetrics as jm

E, T = 4, 12
GAMMAS = (0.5, 0.9, 0.99, 1.0)


def discounted_returns(values, dones, gamma, skip=True):
    """Every finished episode's discounted return, in report order (by step, then env),
    unrolled by hand in float64; t counts every step, and a skipped non-finite one adds
    nothing. None for an episode with no step folded in (it is not reported)."""
    values = np.asarray(values, np.float64)
    out = []
    total = [0.0] * values.shape[1]
    t = [0] * values.shape[1]
    folded = [0] * values.shape[1]
    for step in range(values.shape[0]):
        for e in range(values.shape[1]):
            x = float(values[step, e])
            if math.isfinite(x) or not skip:
                total[e] += gamma ** t[e] * x if math.isfinite(x) else x
                folded[e] += 1
            t[e] += 1
            if dones[step, e]:
                out.append(total[e] if folded[e] else None)
                total[e], t[e], folded[e] = 0.0, 0, 0
    return out


def spec(nonfinite="skip"):
    return jm.Metrics(
        terms={
            f"g{k}": jm.Term(
                lambda x: x,
                reduce=jm.discounted(g),
                stats=("count", jm.window(T * E)),
                nonfinite=nonfinite,
            )
            for k, g in enumerate(GAMMAS)
        }
    )


SPECS = {p: spec(p) for p in ("skip", "propagate")}
_RUNS = {}


def run(policy, xs, dones):
    m = SPECS[policy]
    if policy not in _RUNS:

        def body(state, inp):
            return m.update(state, *inp), None

        def go(xs, dones):
            state = jax.lax.scan(body, m.init(E), (xs, dones))[0]
            return m.compute(state, include_running=True)

        _RUNS[policy] = jax.jit(go)
    return m.to_host(_RUNS[policy](jnp.asarray(xs), jnp.asarray(dones)))


values = st.floats(-100, 100, width=32)
bad = st.sampled_from([np.nan, np.inf, -np.inf])


@st.composite
def rollouts(draw):
    xs = np.asarray(
        draw(st.lists(st.one_of(values, values, values, bad), min_size=T * E, max_size=T * E)),
        np.float32,
    ).reshape(T, E)
    dones = np.asarray(draw(st.lists(st.booleans(), min_size=T * E, max_size=T * E)))
    return xs, dones.reshape(T, E)


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(rollouts(), st.sampled_from(["skip", "propagate"]))
def test_discounted_returns_match_a_float64_unroll(data, policy):
    xs, dones = data
    host = run(policy, xs, dones)
    for k, g in enumerate(GAMMAS):
        want = discounted_returns(xs, dones, g, skip=policy == "skip")
        if policy == "skip":  # episodes without a finite step are not reported
            want = [v for v in want if v is not None]
        got = host[f"Episode_Metrics/g{k}/window_values"]
        got = got[~np.isnan(got)] if policy == "skip" else got[-len(want) :]
        assert host[f"Episode_Metrics/g{k}/count"] == len(want)
        want = np.asarray(want, np.float64)
        np.testing.assert_allclose(got, want, rtol=1e-5, atol=1e-4, err_msg=f"gamma={g}")


def test_a_skipped_step_still_advances_t():
    # t = 0, 1, 2: the NaN at t = 1 adds nothing and the last step keeps gamma^2.
    m = jm.Metrics(terms={"r": jm.Term(lambda x: x, reduce=jm.discounted(0.5))})
    s = m.init(1)
    for x, d in ((1.0, False), (np.nan, False), (4.0, True)):
        s = m.update(s, jnp.asarray([x], jnp.float32), jnp.asarray([d]))
    host = m.to_host(m.compute(s))
    assert host["Episode_Metrics/r"] == 1.0 + 0.25 * 4.0
    assert host["Episode_Metrics/r/nonfinite"] == 1


def test_running_episodes_report_their_discounted_return_so_far():
    m = jm.Metrics(terms={"r": jm.Term(lambda x: x, reduce=jm.discounted(0.5))})
    s = m.update(m.init(2), jnp.asarray([2.0, 4.0]), jnp.asarray([False, True]))
    s = m.update(s, jnp.asarray([2.0, 8.0]), jnp.asarray([False, False]))
    # env 0: 2 + 0.5 * 2 = 3 (its episode runs on); env 1 restarted: 8.
    assert m.to_host(m.compute(s, include_running=True))["Episode_Metrics/r/running"] == 5.5


def _one_episode_each(xs: np.ndarray, dones: np.ndarray, gamma: float) -> np.ndarray:
    """The discounted returns `Metrics` reports for `xs`/`dones` `[steps, envs]`, folded under
    `jit` + `lax.scan`, in report order."""
    envs = xs.shape[1]
    m = jm.Metrics(
        terms={"r": jm.Term(lambda x: x, reduce=jm.discounted(gamma), stats=(jm.window(envs),))}
    )

    @jax.jit
    def go(xs, dones):
        body = lambda s, a: (m.update(s, *a), None)  # noqa: E731
        return m.compute(jax.lax.scan(body, m.init(envs), (xs, dones))[0])

    return m.to_host(go(jnp.asarray(xs), jnp.asarray(dones)))["Episode_Metrics/r/window_values"]


@pytest.mark.parametrize("gamma", [0.99, 0.999, 0.9999, 1.0])
def test_10k_step_float32_episodes_within_1e6_of_float64(gamma):
    steps, envs = 10_000, 4
    rng = np.random.default_rng(0)
    xs = (100.0 + rng.standard_normal((steps, envs))).astype(np.float32)
    dones = np.zeros((steps, envs), bool)
    dones[-1] = True
    want = np.asarray(discounted_returns(xs, dones, gamma), np.float64)
    np.testing.assert_allclose(_one_episode_each(xs, dones, gamma), want, rtol=1e-6)
    if gamma in (0.999, 0.9999):
        # A running float32 factor (gamma^t as a product of float32 gammas) drifts past the
        # bound (measured: 1.3e-5 and 6.9e-5 relative).
        factor = np.float32(1.0)
        total = np.zeros(envs, np.float64)
        for t in range(steps):
            total += np.float64(factor) * xs[t]
            factor = np.float32(factor * np.float32(gamma))
        assert np.max(np.abs(total - want) / np.abs(want)) > 1e-6


def test_merge_and_sharding_concatenate_running_episodes_along_the_env_axis():
    m = jm.Metrics(
        terms={"r": jm.Term(lambda x: x, reduce=jm.discounted(0.9), stats=(jm.window(64),))}
    )
    rng = np.random.default_rng(1)
    xs = jnp.asarray(rng.normal(size=(10, 8)).astype(np.float32))
    dones = jnp.asarray(rng.random((10, 8)) < 0.3)
    update = jax.jit(m.update)

    def feed(state, xs, dones):
        for x, d in zip(xs, dones):
            state = update(state, x, d)
        return state

    whole = feed(m.init(8), xs, dones)
    # Two workers of 4 envs each, merged mid-episode, then run on as one.
    a = feed(m.init(4), xs[:5, :4], dones[:5, :4])
    b = feed(m.init(4), xs[:5, 4:], dones[:5, 4:])
    merged = feed(m.merge(a, b), xs[5:], dones[5:])
    mesh = jax.make_mesh((4,), ("env",), axis_types=(AxisType.Auto,), devices=jax.devices()[:4])
    sharding = NamedSharding(mesh, P("env"))
    on_mesh = jax.device_put((xs, dones), NamedSharding(mesh, P(None, "env")))
    sharded = feed(m.init(8, sharding=sharding), *on_mesh)
    want = m.to_host(m.compute(whole, include_running=True))
    for state in (sharded, merged):
        got = m.to_host(m.compute(state, include_running=True))
        np.testing.assert_allclose(
            got["Episode_Metrics/r/running"], want["Episode_Metrics/r/running"], rtol=1e-6
        )
        got_w, want_w = (np.sort(r["Episode_Metrics/r/window_values"]) for r in (got, want))
        np.testing.assert_allclose(got_w, want_w, rtol=1e-6)


def test_the_discount_is_part_of_the_spec_identity():
    def make(g):
        return jm.Metrics(terms={"r": jm.Term(lambda x: x, reduce=jm.discounted(g))})

    assert make(0.9).init(2).spec == make(0.9).init(2).spec
    with pytest.raises(ValueError, match="built by a different Metrics spec"):
        make(0.99).compute(make(0.9).init(2))


@pytest.mark.parametrize(
    "gamma, match",
    [
        (0.0, r"term 'ret': discounted\(gamma\) needs gamma in \(0, 1\], got 0.0"),
        (1.5, "got 1.5. Use e.g. reduce=jaxmetrics.discounted"),
        (-0.1, "got -0.1"),
        (float("nan"), "got nan"),
        ("0.99", "got '0.99'"),
        (True, "got True"),
    ],
)
def test_bad_gamma_names_the_term_and_the_fix(gamma, match):
    with pytest.raises(ValueError, match=match):
        jm.Metrics(terms={"ret": jm.Term(lambda x: x, reduce=jm.discounted(gamma))})


def test_discounted_needs_its_parameter_and_names_the_output():
    with pytest.raises(ValueError, match=r"term 'ret': the 'discounted' reduction takes a param"):
        jm.Metrics(terms={"ret": jm.Term(lambda x: x, reduce="discounted")})
    with pytest.raises(ValueError, match=r"jaxmetrics.discounted\(gamma\) \(the discounted"):
        jm.Metrics(terms={"ret": jm.Term(lambda x: x, reduce="discount")})
    two = jm.Term(lambda x: {"a": x, "b": x}, outputs=("a", "b"), reduce={"b": jm.discounted(2.0)})
    with pytest.raises(ValueError, match="term 'two': discounted"):
        jm.Metrics(terms={"two": two})
    ok = jm.Term(lambda x: {"a": x, "b": x}, outputs=("a", "b"), reduce={"b": jm.discounted(0.5)})
    m = jm.Metrics(terms={"two": ok})
    s = m.update(m.init(1), jnp.ones(1), jnp.zeros(1, bool))
    s = m.update(s, jnp.ones(1), jnp.ones(1, bool))
    host = m.to_host(m.compute(s))
    assert (host["Episode_Metrics/two/a"], host["Episode_Metrics/two/b"]) == (1.0, 1.5)


@pytest.mark.parametrize(
    "gamma, length", [(0.995, 10_000), (0.995, 7_000), (0.999, 10_000), (0.9, 800)]
)
def test_a_sparse_terminal_reward_is_discounted_within_1e6_of_float64(gamma, length):
    # One reward at the last step: gamma^t alone decides the return, at large |t ln gamma|.
    # exp(float32(t) * float32(ln gamma)) was off by up to 2.6e-6 here.
    envs = 2
    xs = np.zeros((length, envs), np.float32)
    xs[-1] = (1.0, 3.0)
    dones = np.zeros((length, envs), bool)
    dones[-1] = True
    want = np.asarray(discounted_returns(xs, dones, gamma), np.float64)
    np.testing.assert_allclose(_one_episode_each(xs, dones, gamma), want, rtol=1e-6)
