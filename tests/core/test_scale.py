"""Envs sharded over devices: shard-local updates, and reports equal to one device.

conftest gives 8 CPU devices; meshes of 2, 4 and 8 devices, one and two axes, Auto and
Explicit axis types. Every statistic is compared with the float64 Python reference, after
every step; the compiled step loop is checked for cross-device collectives.
"""

import jax
import jax.extend
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from jax.sharding import AxisType, NamedSharding
from jax.sharding import PartitionSpec as P
from reference import SIMPLE_STATS, RefEpisodes
from test_core_reductions import EMA_C, HIST, PCTS, WINDOW, assert_reports_follow_reference

import jaxmetrics as jm
from benchmarks._hlo import collectives, loop_body_ops, program_ops
from jaxmetrics._core._sharding import whole

E, T = 8, 10  # 8 envs finishing at once overflow the window (and any shard's share)
REDUCTIONS = ("mean", "sum", "max", "std")
STATS = (*SIMPLE_STATS, jm.ema(EMA_C), jm.window(WINDOW, PCTS), jm.histogram(HIST[0], HIST[1:]))
METRICS = jm.Metrics(
    terms={
        f"r_{red}": jm.Term(lambda x, k: x[k], reduce=red, stats=STATS, params={"k": k})
        for k, red in enumerate(REDUCTIONS)
    },
    logged=["loss"],
)

# (mesh shape, axis names, env axes of the batch): 1-D and 2-D meshes, and a batch split
# over only one axis of a 2-D mesh (the other replicates it).
LAYOUTS = {
    "8": ((8,), ("env",), "env"),
    "4": ((4,), ("env",), "env"),
    "2x4": ((2, 4), ("host", "device"), ("host", "device")),
    "2x4-device": ((2, 4), ("host", "device"), "device"),
    "2x2": ((2, 2), ("host", "device"), ("host", "device")),
    # Auto axes of equal sizes: the trace cannot tell which splits the envs, and the
    # shards fold as one batch (`_sharding.shard_axes`).
    "2x2-device": ((2, 2), ("host", "device"), "device"),
}


def mesh_of(layout, axis_type=AxisType.Auto):
    shape, names, env = LAYOUTS[layout]
    devices = jax.devices()[: int(np.prod(shape))]
    mesh = jax.make_mesh(shape, names, axis_types=(axis_type,) * len(shape), devices=devices)
    return mesh, env


def place_of(mesh, env):
    """The layouts of one step's values `[R, E]` and dones `[E]`, envs split over `env`."""
    return NamedSharding(mesh, P(None, env)), NamedSharding(mesh, P(env))


def place(mesh, env, xs, dones):
    return (
        jax.device_put(xs, NamedSharding(mesh, P(None, None, env))),
        jax.device_put(dones, NamedSharding(mesh, P(None, env))),
    )


def rollout(metrics, sharding, xs, dones, flushes):
    """Reports after every step of a scanned rollout, flushing where `flushes`."""

    def body(state, inp):
        x, d, flush = inp
        state = metrics.update(state, x, d)
        report = metrics.compute(state)
        state = jax.lax.cond(flush, metrics.reset_period, lambda s: s, state)
        return state, report

    state = metrics.init(dones.shape[1], sharding=sharding)
    return jax.lax.scan(body, state, (xs, dones, flushes))[1]


_JITTED = {}


def sharded_reports(layout, xs, dones, flushes):
    mesh, env = mesh_of(layout)
    key = layout
    if key not in _JITTED:
        sharding = NamedSharding(mesh, P(env))
        _JITTED[key] = jax.jit(lambda a, b, c: rollout(METRICS, sharding, a, b, c))
    return jax.device_get(_JITTED[key](*place(mesh, env, xs, dones), jnp.asarray(flushes)))


grid = st.integers(-300, 300).map(lambda k: k / 8 + 1 / 16)  # never on a histogram edge


@st.composite
def rollouts(draw):
    n = T * len(REDUCTIONS) * E
    xs = np.asarray(draw(st.lists(grid, min_size=n, max_size=n)), np.float32)
    xs = xs.reshape(T, len(REDUCTIONS), E)
    nan_at = draw(st.lists(st.integers(0, n - 1), max_size=4))
    xs.reshape(-1)[nan_at] = np.nan
    pattern = draw(st.sampled_from(["random", "all", "sparse", "last_shard"]))
    if pattern == "random":
        dones = np.asarray(draw(st.lists(st.booleans(), min_size=T * E, max_size=T * E)))
    elif pattern == "all":
        dones = np.ones(T * E, bool)
    elif pattern == "last_shard":  # only the highest env finishes, often
        dones = np.tile(np.arange(E) == E - 1, T)
    else:
        dones = np.asarray(draw(st.lists(st.integers(0, 5), min_size=T * E, max_size=T * E))) == 0
    flushes = np.asarray(draw(st.lists(st.booleans(), min_size=T, max_size=T)))
    return xs, dones.reshape(T, E), flushes


@pytest.mark.parametrize("layout", ["8", "2x2-device", "2x4-device"])
@settings(max_examples=12, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(data=rollouts())
def test_sharded_reports_match_the_float64_reference_after_every_step(layout, data):
    xs, dones, flushes = data
    reports = sharded_reports(layout, xs, dones, flushes)
    assert_reports_follow_reference(METRICS, reports, xs, dones, flushes, REDUCTIONS)


def long_rollout(seed, steps, num_envs, p_done):
    rng = np.random.default_rng(seed)
    xs = rng.normal(50.0, 10.0, (steps, len(REDUCTIONS), num_envs)).astype(np.float32)
    return xs, rng.random((steps, num_envs)) < p_done


@pytest.mark.parametrize("layout", ["4", "2x2"])
def test_ema_across_shards_past_its_exact_history(layout):
    # EMA(0.3) keeps the newest 63 values per shard for merging; 16 envs finishing half the
    # time give ~400 episodes per shard, so the merged EMA leans on its tail estimate.
    # Its error bound is (1-c)^63 ~ 2^-32 of the values' range: float32 equality.
    xs, dones = long_rollout(1, 200, 16, 0.5)
    mesh, env = mesh_of(layout)
    sharding = NamedSharding(mesh, P(env))
    flushes = np.zeros(len(xs), bool)
    run = jax.jit(lambda a, b, c: rollout(METRICS, sharding, a, b, c))
    got = jax.device_get(run(*place(mesh, env, xs, dones), jnp.asarray(flushes)))
    one = jax.device_get(
        jax.jit(lambda a, b, c: rollout(METRICS, None, a, b, c))(xs, dones, flushes)
    )
    ref = RefEpisodes(16, {f"r_{r}": r for r in REDUCTIONS}, ema_coeff=EMA_C, window=WINDOW)
    for t in range(len(xs)):
        ref.step({f"r_{r}": xs[t, k] for k, r in enumerate(REDUCTIONS)}, dones[t])
    for r in REDUCTIONS:
        tag = f"Episode_Metrics/r_{r}/ema"
        want = ref.streams[f"r_{r}"].report()["ema"]
        np.testing.assert_allclose(got[tag][-1], want, rtol=2e-6, err_msg=tag)
        np.testing.assert_allclose(got[tag], one[tag], rtol=2e-6, err_msg=tag)
        wv = f"Episode_Metrics/r_{r}/window_values"
        np.testing.assert_array_equal(got[wv][-1], one[wv][-1], err_msg=wv)


def scan_of_updates(metrics, sharding, num_envs):
    def run(xs, dones):
        state = metrics.init(num_envs, sharding=sharding)
        return jax.lax.scan(lambda s, a: (metrics.update(s, *a), None), state, (xs, dones))[0]

    return jax.jit(run)


@pytest.mark.parametrize("axis_type", [AxisType.Auto, AxisType.Explicit])
@pytest.mark.parametrize("layout", list(LAYOUTS))
def test_step_loop_has_no_cross_device_collectives(layout, axis_type):
    mesh, env = mesh_of(layout, axis_type)
    xs, dones = long_rollout(2, 4, 16, 0.3)
    with jax.set_mesh(mesh):
        args = place(mesh, env, xs, dones)
        sharded = scan_of_updates(METRICS, NamedSharding(mesh, P(env)), 16)
        ops = loop_body_ops(sharded.lower(*args).compile().as_text())
        assert ops, "no loop found in the compiled rollout"
        assert collectives(ops) == {}, f"{layout}: the step loop holds {collectives(ops)}"
        state = sharded(*args)
    shards = state.shard_counts.hi.shape[0]
    assert shards == {"8": 8, "2x4": 8, "2x2-device": 2}.get(layout, 4)
    assert state.finished.count.hi.sharding.spec[0] == env


@pytest.mark.parametrize("axis_type", [AxisType.Auto, AxisType.Explicit])
@pytest.mark.parametrize("layout", ["4", "2x4", "2x4-device"])
def test_compute_moves_the_shards_in_one_collective(layout, axis_type):
    # Left to XLA, each of the state's per-shard leaves (about thirty) crossed devices in
    # a collective of its own, each a launch and a synchronization on GPUs.
    mesh, env = mesh_of(layout, axis_type)
    xs, dones = long_rollout(2, 4, 16, 0.3)
    with jax.set_mesh(mesh):
        state = scan_of_updates(METRICS, NamedSharding(mesh, P(env)), 16)(
            *place(mesh, env, xs, dones)
        )
    # No mesh set: compute traces under the state's own.
    ops = collectives(program_ops(jax.jit(METRICS.compute).lower(state).compile().as_text()))
    assert sum(ops.values()) == 1, ops


@pytest.mark.parametrize("axis_type", [AxisType.Auto, AxisType.Explicit])
def test_whole_moves_every_dtype_bit_for_bit(axis_type):
    mesh, env = mesh_of("4", axis_type)
    rng = np.random.default_rng(0)
    bits = rng.integers(0, 2**32, size=(4, 3, 5), dtype=np.uint64).astype(np.uint32)
    tree = {
        "f32": bits.view(np.float32),  # NaNs and infinities among them, by their bits
        "u32": bits,
        "i32": bits.view(np.int32)[:, 0],
        "f16": bits.view(np.float16),
        "bf16": bits.astype(np.uint16).view(jnp.bfloat16),
        "u8": bits.astype(np.uint8),
        "bool": bits % 2 == 0,
    }
    placed = jax.device_put(tree, NamedSharding(mesh, P(env)))
    with jax.set_mesh(mesh):
        moved = jax.jit(whole)(placed)
        ops = collectives(program_ops(jax.jit(whole).lower(placed).compile().as_text()))
    assert sum(ops.values()) == 1, ops
    for k, want in tree.items():
        got = np.asarray(moved[k])
        assert got.dtype == want.dtype and got.shape == want.shape, k
        np.testing.assert_array_equal(got.view(np.uint8), np.asarray(want).view(np.uint8), k)


def test_the_collective_check_can_fail_a_state_made_for_one_device():
    # The same rollout with a state laid out for one device (Auto axes, no sharding given)
    # reduces over a split env axis every step: the check above must see it.
    mesh, env = mesh_of("4")
    xs, dones = long_rollout(3, 4, 16, 0.3)
    ops = loop_body_ops(
        scan_of_updates(METRICS, None, 16).lower(*place(mesh, env, xs, dones)).compile().as_text()
    )
    assert collectives(ops), ops


def test_vmapped_seeds_over_an_env_sharded_batch():
    mesh, env = mesh_of("4")
    sharding = NamedSharding(mesh, P(env))
    seeds = [long_rollout(10 + s, 12, 8, 0.3) for s in range(3)]
    xs = np.stack([x for x, _ in seeds])
    dones = np.stack([d for _, d in seeds])
    flushes = np.zeros(12, bool)
    run = jax.jit(jax.vmap(lambda a, b: rollout(METRICS, sharding, a, b, jnp.asarray(flushes))))
    got = jax.device_get(
        run(
            jax.device_put(xs, NamedSharding(mesh, P(None, None, None, env))),
            jax.device_put(dones, NamedSharding(mesh, P(None, None, env))),
        )
    )
    alone = jax.jit(lambda a, b: rollout(METRICS, None, a, b, jnp.asarray(flushes)))
    for s in range(3):
        want = jax.device_get(alone(xs[s], dones[s]))
        for tag, v in want.items():
            g = jax.tree.map(lambda a, s=s: a[s], got[tag])
            np.testing.assert_allclose(
                np.asarray(g, np.float64),
                np.asarray(v, np.float64),
                rtol=2e-6,
                equal_nan=True,
                err_msg=tag,
            )


def test_merge_of_lockstep_workers_equals_one_run_over_both_env_sets():
    # Two hosts of 8 envs each, 4 shards each: merged, they are one run over 16 envs.
    xs, dones = long_rollout(4, 30, 16, 0.4)
    mesh, env = mesh_of("4")
    sharding = NamedSharding(mesh, P(env))
    run = scan_of_updates(METRICS, sharding, 8)
    a = run(*place(mesh, env, xs[..., :8], dones[:, :8]))
    b = run(*place(mesh, env, xs[..., 8:], dones[:, 8:]))
    merged = jax.jit(METRICS.merge)(a, b)
    assert merged.shard_counts.hi.shape[0] == 8  # per shard: env steps, episodes
    whole = scan_of_updates(METRICS, None, 16)(xs, dones)
    compute = jax.jit(METRICS.compute)
    got = METRICS.to_host(compute(merged))
    want = METRICS.to_host(compute(whole))
    for tag in want:
        np.testing.assert_allclose(
            np.asarray(got[tag], np.float64),
            np.asarray(want[tag], np.float64),
            rtol=2e-6,
            equal_nan=True,
            err_msg=tag,
        )


def test_bad_layouts_are_refused_with_the_fix():
    mesh, env = mesh_of("4")
    with pytest.raises(ValueError, match=r"6 envs do not split evenly over the 4 shards"):
        METRICS.init(6, sharding=NamedSharding(mesh, P(env)))
    with pytest.raises(TypeError, match=r"init\(sharding=...\) takes the env batch's"):
        METRICS.init(8, sharding="env")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match=r"this state has no envs: .* Use init\(num_envs\)"):
        METRICS.update(METRICS.empty(), jnp.zeros((4, 0)), jnp.zeros(0, bool))
    b = METRICS.init(4, sharding=NamedSharding(mesh, P(env)))
    # 2 envs in one shard and 1 env per shard do not form one env axis: one shard.
    m = jax.jit(METRICS.merge)(METRICS.init(2, sharding=NamedSharding(mesh, P())), b)
    assert m.shard_counts.hi.shape[0] == 1 and m.running.steps.shape == (4, 6)
    m = jax.jit(METRICS.update)(m, jnp.ones((4, 6)), jnp.ones(6, bool))
    assert METRICS.to_host(jax.jit(METRICS.compute)(m))["Counters/episodes"] == 6
    with pytest.raises(
        ValueError, match=r"done must be a bool array of shape \(num_envs,\)=\(4,\)"
    ):
        METRICS.update(b, jnp.zeros((4, 6)), jnp.zeros(6, bool))


def test_float64_state_keeps_window_and_ema_history_to_the_last_bit():
    # A float64 value takes two words of a ring slot: values 1e-9 apart (below float32's
    # resolution at 1e4) must come back whole from the windows, and from the EMA history
    # that the shards' merge folds.
    with jax.enable_x64(True):
        metrics = jm.Metrics(
            terms={"x": jm.Term(lambda x: x[0], reduce="max", stats=(jm.ema(0.5), jm.window(6)))},
            dtype=jnp.float64,
        )
        mesh, env = mesh_of("4")
        rng = np.random.default_rng(3)
        xs = 1e4 + rng.integers(0, 1000, (12, 1, 16)) * 1e-9
        dones = rng.random((12, 16)) < 0.4
        sharding = NamedSharding(mesh, P(env))
        got = jax.device_get(
            jax.jit(lambda a, b, c: rollout(metrics, sharding, a, b, c))(
                *place(mesh, env, jnp.asarray(xs), jnp.asarray(dones)),
                jnp.zeros(12, bool),
            )
        )
    ref = RefEpisodes(16, {"x": "max"}, ema_coeff=0.5, window=6)
    for t in range(12):
        ref.step({"x": xs[t, 0]}, dones[t])
        want = ref.streams["x"].report()
        wv = got["Episode_Metrics/x/window_values"][t]
        np.testing.assert_array_equal(wv[~np.isnan(wv)], want["window_values"], err_msg=str(t))
        np.testing.assert_allclose(got["Episode_Metrics/x/ema"][t], want["ema"], rtol=1e-15)


def fold_paths(jaxpr, path=()):
    """The enclosing primitives of every arrival rank of the fold (`population_count`, which
    only `_stream.arrivals_after` uses) in a jaxpr, recursively."""
    for eqn in jaxpr.eqns:
        name = eqn.primitive.name
        if name == "population_count":
            yield path
        for value in eqn.params.values():
            for v in value if isinstance(value, (tuple, list)) else (value,):
                if isinstance(v, (jax.extend.core.ClosedJaxpr, jax.extend.core.Jaxpr)):
                    yield from fold_paths(getattr(v, "jaxpr", v), (*path, name))


@pytest.mark.parametrize("axis_type", [AxisType.Auto, AxisType.Explicit])
def test_each_shard_folded_on_its_device_follows_the_float64_reference(axis_type):
    # Each device folding its shard inside the shard_map, 4 shards of 64 envs: every
    # statistic after every step against the float64 reference, as one device's.
    mesh, env = mesh_of("4", axis_type)
    xs, dones = long_rollout(5, 6, 256, 0.3)
    xs[2, 0, :3] = np.nan
    flushes = np.arange(6) == 3
    sharding = NamedSharding(mesh, P(env))
    run = jax.jit(lambda a, b, c: rollout(METRICS, sharding, a, b, c))
    args = (*place(mesh, env, xs, dones), jnp.asarray(flushes))
    paths = list(fold_paths(jax.make_jaxpr(run)(*args).jaxpr))
    assert paths and all("shard_map" in p for p in paths), paths
    reports = jax.device_get(run(*args))
    assert_reports_follow_reference(METRICS, reports, xs, dones, flushes, REDUCTIONS)


def with_mesh(mesh, fn, *args):
    with jax.set_mesh(mesh):
        return fn(*args)


@pytest.mark.parametrize("axis_type", [AxisType.Auto, AxisType.Explicit])
def test_each_device_folds_its_shard_where_the_trace_knows_the_axes(axis_type):
    # Where the trace knows the devices' axes of the shards, each device folds its own
    # shard inside a shard_map (no collective by construction); one device folds its
    # batch as it is; where the trace cannot tell the axes (Auto axes of equal sizes), the
    # shards are folded as one batch, outside any shard_map.
    def traced(num_envs, sharding=None):
        xs, dones = long_rollout(3, 1, num_envs, 0.3)
        x, done = xs[0], dones[0]
        if sharding is not None:
            mesh, env = sharding.mesh, sharding.spec[0]
            x, done = (jax.device_put(a, s) for a, s in zip((x, done), place_of(mesh, env)))
        step = lambda x, done: METRICS.update(METRICS.init(num_envs, sharding=sharding), x, done)  # noqa: E731
        return list(fold_paths(jax.make_jaxpr(step)(x, done).jaxpr))

    one = traced(256)
    assert one and not any("shard_map" in p for p in one), one
    for layout in ("4", "2x4", "2x4-device"):
        mesh, env = mesh_of(layout, axis_type)
        sharding = NamedSharding(mesh, P(env))
        # The mesh is read from the state's type, or from the one set.
        for paths in (traced(1024, sharding), with_mesh(mesh, traced, 1024, sharding)):
            assert paths and all("shard_map" in p for p in paths), (layout, paths)
    # A 2 x 2 mesh, envs split over "device" only: under Auto axes the types do not say
    # which of the two axes of size 2 splits them.
    mesh = jax.make_mesh((2, 2), ("host", "device"), axis_types=(axis_type,) * 2)
    paths = traced(1024, NamedSharding(mesh, P("device")))
    assert paths
    if axis_type == AxisType.Auto:
        assert not any("shard_map" in p for p in paths), paths
    else:
        assert all("shard_map" in p for p in paths), paths
