"""Contract of the pure functions under jit, scan, cond, vmap and sharding."""

import chex
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.sharding import Mesh, NamedSharding, PartitionSpec
from reference import SIMPLE_STATS

import jaxmetrics as jm

E = 4
STATS = (
    *SIMPLE_STATS,
    jm.ema(0.1),
    jm.window(5, (50,)),
    jm.histogram(4, (0.0, 1.0)),
)


def make(dtype=jnp.float32):
    return jm.Metrics(
        terms={
            "x": jm.Term(lambda s: s["x"], reduce="mean", stats=STATS),
            "y": jm.Term(
                lambda s: {"a": s["x"] * 2, "b": s["x"] > 0.5},
                outputs=("a", "b"),
                reduce={"a": "std", "b": "last"},
                stats=STATS,
            ),
        },
        logged={"loss": jm.Logged(stats=STATS)},
        counters=("updates",),
        dtype=dtype,
    )


def data(key, steps, num_envs=E):
    kx, kd = jax.random.split(key)
    xs = jax.random.uniform(kx, (steps, num_envs))
    dones = jax.random.uniform(kd, (steps, num_envs)) < 0.3
    return xs, dones


def rollout(metrics, xs, dones):
    def body(state, inp):
        x, d = inp
        state = metrics.update(state, {"x": x}, d)
        state = metrics.log(state, {"loss": jnp.mean(x)})
        state = metrics.increment(state, "updates")
        return state, None

    return jax.lax.scan(body, metrics.init(xs.shape[1]), (xs, dones))[0]


def python_loop(metrics, xs, dones):
    state = metrics.init(xs.shape[1])
    for x, d in zip(xs, dones):
        state = metrics.update(state, {"x": x}, d)
        state = metrics.log(state, {"loss": jnp.mean(x)})
        state = metrics.increment(state, "updates")
    return state


def assert_host_reports_close(got, want, rtol, skip=()):
    assert got.keys() == want.keys()
    for k in want:
        if k.startswith(skip):
            continue
        np.testing.assert_allclose(
            np.asarray(got[k], np.float64),
            np.asarray(want[k], np.float64),
            rtol=rtol,
            atol=1e-6,
            equal_nan=True,
            err_msg=k,
        )


def assert_reports_equal(m, a, b, rtol=1e-6):
    assert_host_reports_close(m.to_host(m.compute(a)), m.to_host(m.compute(b)), rtol)


def test_scan_under_jit_equals_eager_python_loop():
    m = make()
    xs, dones = data(jax.random.key(0), 12)
    assert_reports_equal(
        m, jax.jit(lambda a, b: rollout(m, a, b))(xs, dones), python_loop(m, xs, dones), rtol=1e-5
    )


def test_cond_branches_keep_state_types():
    m = make()
    xs, dones = data(jax.random.key(1), 6)
    s = rollout(m, xs, dones)

    @jax.jit
    def maybe_reset(state, flag):
        return jax.lax.cond(flag, m.reset_period, lambda t: t, state)

    kept, reset = maybe_reset(s, False), maybe_reset(s, True)
    assert jax.tree.structure(kept) == jax.tree.structure(s)
    chex.assert_trees_all_equal_dtypes(kept, s)
    chex.assert_trees_all_equal(kept, s)
    assert m.to_host(m.compute(reset))["Episode_Metrics/x/count"] == 0


def test_state_shapes_and_dtypes_stable_through_scan():
    # float32 only: narrower state dtypes are refused (test_core_errors).
    dtype = jnp.float32
    m = make(dtype)
    xs, dones = data(jax.random.key(2), 5)
    init = m.init(E)
    out = jax.jit(lambda a, b: rollout(m, a, b))(xs, dones)
    chex.assert_trees_all_equal_shapes_and_dtypes(out, init)
    floats = [x for x in jax.tree.leaves(out) if jnp.issubdtype(x.dtype, jnp.floating)]
    assert floats and all(x.dtype == jnp.dtype(dtype) for x in floats)


def test_no_retrace_on_second_call():
    m = make()

    @jax.jit
    @chex.assert_max_traces(n=1)
    def step(state, x, d):
        state = m.update(state, {"x": x}, d)
        return m.reset_period(m.log(state, {"loss": x[0]}))

    chex.clear_trace_counter()
    s = m.init(E)
    for k in range(3):
        xs, dones = data(jax.random.key(k), 1)
        s = step(s, xs[0], dones[0])
    report = jax.jit(chex.assert_max_traces(m.compute, n=1))
    report(s)
    report(s)


def test_vmap_over_seeds_equals_each_seed_alone():
    m = make()
    keys = jax.random.split(jax.random.key(3), 3)
    xs, dones = jax.vmap(lambda k: data(k, 8))(keys)
    batched = jax.jit(jax.vmap(lambda a, b: rollout(m, a, b)))(xs, dones)
    reports = jax.jit(jax.vmap(m.compute))(batched)
    for i in range(3):
        alone = rollout(m, xs[i], dones[i])
        want = m.to_host(m.compute(alone))
        got = m.to_host(jax.tree.map(lambda a, i=i: a[i], reports))
        assert_host_reports_close(got, want, rtol=1e-6)


def test_envs_sharded_over_devices_equal_single_device():
    devices = np.asarray(jax.devices()[:2])
    mesh = Mesh(devices, ("env",))
    m = make()
    xs, dones = data(jax.random.key(4), 10, num_envs=8)
    env_sharded = NamedSharding(mesh, PartitionSpec(None, "env"))
    xs_s, dones_s = jax.device_put(xs, env_sharded), jax.device_put(dones, env_sharded)
    sharded = jax.jit(lambda a, b: rollout(m, a, b))(xs_s, dones_s)
    assert sharded.running.steps.sharding.spec == PartitionSpec(None, "env") or (
        len(sharded.running.steps.sharding.device_set) == 2
    )
    single = jax.jit(lambda a, b: rollout(m, a, b))(xs, dones)
    assert_reports_equal(m, sharded, single, rtol=1e-5)


def test_explicit_sharding_mesh_equals_single_device():
    # jax.make_mesh defaults to Explicit axes, where layouts are known at trace time: a
    # state made for the env sharding updates shard-locally and reports what one device
    # does; a state made without it is refused with the fix, never resharded per step.
    mesh = jax.make_mesh(
        (2,), ("env",), axis_types=(jax.sharding.AxisType.Explicit,), devices=jax.devices()[:2]
    )
    m = make()
    xs, dones = data(jax.random.key(5), 10, num_envs=8)
    single = jax.jit(lambda a, b: rollout(m, a, b))(xs, dones)

    def sharded_rollout(xs, dones, sharding):
        def body(state, inp):
            x, d = inp
            state = m.update(state, {"x": x}, d)
            return m.log(state, {"loss": jnp.mean(x)}), None

        return jax.lax.scan(body, m.init(xs.shape[1], sharding=sharding), (xs, dones))[0]

    with jax.set_mesh(mesh):
        spec = NamedSharding(mesh, PartitionSpec(None, "env"))
        args = jax.device_put(xs, spec), jax.device_put(dones, spec)
        out = jax.jit(sharded_rollout, static_argnums=2)(
            *args, NamedSharding(mesh, PartitionSpec("env"))
        )
        assert jax.typeof(out.running.steps).sharding.spec == PartitionSpec(None, "env")
        with pytest.raises(ValueError, match=r"init\(num_envs, sharding=<the env batch"):
            jax.jit(sharded_rollout, static_argnums=2)(*args, None)
    got, want = m.to_host(m.compute(out)), m.to_host(m.compute(single))
    # this rollout does not increment "updates"; everything else must match
    assert_host_reports_close(got, want, rtol=1e-5, skip=("Counters/updates",))


def test_empty_spec_has_no_state_and_update_is_identity():
    m = jm.Metrics()
    s = m.init(1024)
    assert jax.tree.leaves(s) == []
    assert m.update(s, {"anything": jnp.zeros(3)}, jnp.zeros(1024, bool)) is s
    jaxpr = jax.make_jaxpr(lambda st, d: m.update(st, None, d))(s, jnp.zeros(1024, bool))
    assert len(jaxpr.eqns) == 0
    assert m.compute(s) == {}
