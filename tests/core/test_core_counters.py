"""Lifetime counters stay exact past 2^31 (and 2^32) without jax_enable_x64."""

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import jaxmetrics as jm
from jaxmetrics._core import _count

OPTIMIZED = {"xla_backend_optimization_level": 3, "xla_llvm_disable_expensive_passes": False}


@settings(max_examples=50, deadline=None)
@given(st.lists(st.integers(0, 2**32 - 1), min_size=1, max_size=20))
def test_count_add_is_exact_against_python_ints(incs):
    add = jax.jit(_count.add)
    c = _count.zeros(())
    for i in incs:
        c = add(c, jnp.asarray(i, jnp.uint32))
    assert _count.to_int(c) == sum(incs)


@settings(max_examples=30, deadline=None)
@given(st.integers(0, 2**40), st.integers(0, 2**40))
def test_count_merge_is_exact(a, b):
    def make(v):
        return _count.Count(
            jnp.asarray(v >> 32, jnp.uint32), jnp.asarray(v & 0xFFFFFFFF, jnp.uint32)
        )

    assert _count.to_int(jax.jit(_count.merge)(make(a), make(b))) == a + b


COUNTER_U = jm.Metrics(counters=["u"])
# Jitted once for every hypothesis example (a bound method jitted anew retraces).
INCREMENT_U = jax.jit(COUNTER_U.increment, static_argnums=1)


@settings(max_examples=40, deadline=None)
@given(
    st.lists(
        st.one_of(st.integers(-(2**31), 2**31 - 1), st.integers(0, 2**32 - 1).map(str)),
        min_size=1,
        max_size=12,
    )
)
def test_increment_signed_and_unsigned_is_exact_against_python_ints(incs):
    # int32 increments (negative ones subtract) and uint32 ones (given here as strings),
    # traced, against Python's integers: -1 once made the counter 4294967295.
    m, inc = COUNTER_U, INCREMENT_U
    s, want = m.init(0), 0
    for i in incs:
        v = jnp.asarray(int(i), jnp.uint32) if isinstance(i, str) else jnp.asarray(i, jnp.int32)
        s, want = inc(s, "u", v), want + int(i)
    assert m.to_host(m.compute(s))["Counters/u"] == want
    # Python ints take the same path, below zero and past int32's range.
    s = m.increment(m.increment(m.init(0), "u", -5), "u", 2**32 - 1)
    assert m.to_host(m.compute(s))["Counters/u"] == 2**32 - 6


def test_env_steps_exact_past_2_pow_31():
    # 4096 envs x 600k steps = 2.46e9 env steps: an int32 counter would have wrapped.
    n_env, steps = 4096, 600_000
    m = jm.Metrics(terms={"x": lambda s: s}, counters=["updates"])

    # The one test whose time is run time, not compile time: it compiles with the
    # optimizations that conftest.py turns off for the suite's compile-bound rest.
    @functools.partial(jax.jit, compiler_options=OPTIMIZED)
    def run(state):
        def body(s, _):
            s = m.update(s, jnp.zeros(n_env), jnp.zeros(n_env, bool))
            return s, None

        return jax.lax.scan(body, state, None, length=steps // 1000)[0]

    # Run 1000 scans of 600 steps; each adds 600*4096 env steps.
    state = m.init(n_env)
    for _ in range(1000):
        state = run(state)
    host = m.to_host(m.compute(state))
    assert host["Counters/env_steps"] == n_env * steps
    assert host["Counters/env_steps"] > 2**31
    # A user counter incremented by large amounts passes 2^32 exactly.
    inc = jax.jit(m.increment, static_argnums=1)
    for _ in range(3):
        state = inc(state, "updates", jnp.asarray(2**31 + 7, jnp.uint32))
    state = m.increment(state, "updates", 2**32 - 1)  # a Python int above int32's range
    assert m.to_host(m.compute(state))["Counters/updates"] == 3 * (2**31 + 7) + 2**32 - 1
    assert isinstance(host["Counters/env_steps"], int)


@pytest.mark.parametrize(
    "terms, groups",
    [(1, 0), (1, 1), (4, 2)],
    ids=["fewer-rows-than-counters", "grouped-fewer-rows", "more-rows-than-counters"],
)
def test_builtin_counts_match_a_python_loop_whatever_the_number_of_rows(terms, groups):
    # The per-shard counts are padded to whole multiples of the episode rows; with fewer
    # rows than counters they take several of them.
    n_env, steps = 7, 40
    rng = np.random.default_rng(terms * 10 + groups)
    dones = rng.random((steps, n_env)) < 0.3
    group = rng.integers(-1, groups + 1, (steps, n_env))  # some out of range
    names = tuple(f"g{i}" for i in range(groups))
    m = jm.Metrics(
        terms={f"x{i}": (lambda s: s[0]) for i in range(terms)},
        groups=jm.groups(lambda s: s[1].astype(jnp.int32), names) if groups else None,
    )

    @jax.jit
    def run(state, xs, ds):
        return jax.lax.scan(lambda s, x: (m.update(s, x[0], x[1]), None), state, (xs, ds))[0]

    xs = np.stack([np.ones((steps, n_env)), group], axis=1).astype(np.float32)
    host = m.to_host(m.compute(run(m.init(n_env), jnp.asarray(xs), jnp.asarray(dones))))
    assert host["Counters/env_steps"] == steps * n_env
    assert host["Counters/episodes"] == int(dones.sum())
    if groups:
        out = dones & ((group < 0) | (group >= groups))
        assert host["Counters/ungrouped"] == int(out.sum()) > 0
