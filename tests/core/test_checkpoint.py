"""A MetricsState saved mid-run (orbax-checkpoint, flax.serialization) and restored into a
fresh process's spec continues exactly as the uninterrupted run: windows, EMA, histograms,
quantile sketches, counters and running episodes (discounted returns included) carry over
bit for bit, sharded or not. Restored into another number of devices, it continues equal to
a float64 reference; into another number of envs, or cut to another layout by orbax's
strict=False, it is refused naming both layouts."""

import functools
import os
import subprocess
import sys

import flax.serialization
import jax
import jax.numpy as jnp
import numpy as np
import orbax.checkpoint as ocp
import pytest
from jax.sharding import AxisType, NamedSharding
from jax.sharding import PartitionSpec as P

import jaxmetrics as jm

# One xdist worker runs the file (--dist loadgroup): its op-by-op updates of restored
# states compile each op once per process for each layout, which the tests share.
pytestmark = pytest.mark.xdist_group("test_checkpoint")

E, STEPS, SPLIT = 8, 24, 12


def spec():
    # Built anew for every use, as a resumed process would.
    return jm.Metrics(
        terms={
            "r": jm.Term(
                lambda x: x,
                reduce="sum",
                stats=("mean", "std", "min", "max", "count", jm.ema(0.1), jm.window(5, (50,))),
            ),
            "h": jm.Term(lambda x: x, stats=(jm.histogram(4, (0.0, 4.0)),)),
            "d": jm.Term(lambda x: x, reduce=jm.discounted(0.9), stats=(jm.quantiles((50, 90)),)),
        },
        logged=["loss"],
        counters=["updates"],
    )


def data():
    rng = np.random.default_rng(0)
    xs = rng.uniform(0, 4, (STEPS, E)).astype(np.float32)
    dones = rng.random((STEPS, E)) < 0.3
    return jnp.asarray(xs), jnp.asarray(dones)


@functools.cache
def programs(m):
    """`m`'s rollout, period reset and report, jitted once per spec object."""

    def body(s, a):
        s = m.update(s, a[0], a[1])
        s = m.increment(m.log(s, {"loss": a[0][0]}), "updates")
        return s, None

    rollout = jax.jit(lambda s, a: jax.lax.scan(body, s, a)[0])
    return rollout, jax.jit(m.reset_period), jax.jit(m.compute)


def run(m, state, xs, dones):
    return programs(m)[0](state, (xs, dones))


def report(m, state):
    return m.to_host(programs(m)[2](state))


def save_restore(kind, state, tmp_path, target):
    m = spec()
    if kind == "flax":
        restored = flax.serialization.from_bytes(target, flax.serialization.to_bytes(state))
        return m.from_checkpoint(restored, target)
    # orbax refuses zero-size arrays (statistics the spec does not keep): to_checkpoint.
    with ocp.StandardCheckpointer() as ckpt:
        ckpt.save(tmp_path / "ckpt", m.to_checkpoint(state))
        ckpt.wait_until_finished()
        return m.from_checkpoint(ckpt.restore(tmp_path / "ckpt", m.to_checkpoint(target)), target)


# flax.serialization restores host arrays: the sharded layout is orbax's part.
@pytest.mark.parametrize("kind, sharded", [("orbax", False), ("flax", False), ("orbax", True)])
def test_restored_state_continues_exactly_as_the_uninterrupted_run(kind, sharded, tmp_path):
    xs, dones = data()
    sharding = None
    if sharded:
        mesh = jax.make_mesh((4,), ("env",), axis_types=(AxisType.Auto,), devices=jax.devices()[:4])
        sharding = NamedSharding(mesh, P("env"))
        xs, dones = jax.device_put((xs, dones), NamedSharding(mesh, P(None, "env")))
    m = spec()
    whole = run(m, m.init(E, sharding), xs, dones)
    # Checkpointed at a period end, as a Logger's flush returns it.
    first = programs(m)[1](run(m, m.init(E, sharding), xs[:SPLIT], dones[:SPLIT]))

    fresh = spec()  # the resumed process's spec: same configuration, another object
    restored = save_restore(kind, first, tmp_path, fresh.init(E, sharding))
    chex_equal(restored, first)
    if sharded:
        layout = fresh.state_sharding(sharding)  # restored onto the target's devices
        assert restored.finished.count.hi.sharding == layout.finished.count.hi
    resumed = run(fresh, restored, xs[SPLIT:], dones[SPLIT:])
    ref = run(m, first, xs[SPLIT:], dones[SPLIT:])  # the uninterrupted run goes on
    got, want = report(fresh, resumed), report(m, ref)
    assert got.keys() == want.keys()
    for tag in want:
        np.testing.assert_array_equal(np.asarray(got[tag]), np.asarray(want[tag]), err_msg=tag)
    assert got["Counters/updates"] == STEPS == report(m, whole)["Counters/updates"]


def chex_equal(a, b):
    assert jax.tree.structure(a) == jax.tree.structure(b)
    for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b)):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))


def test_restoring_into_another_spec_of_the_same_shapes_is_refused(tmp_path):
    # Same shapes, other tag: restored as is, it would have been relabelled.
    a = jm.Metrics(terms={"r": lambda x: x})
    b = jm.Metrics(terms={"s": lambda x: x})
    saved = flax.serialization.to_bytes(a.init(E))
    with pytest.raises(ValueError, match=r"field names .* do not match"):
        flax.serialization.from_bytes(b.init(E), saved)
    with ocp.StandardCheckpointer() as ckpt:
        ckpt.save(tmp_path / "ckpt", a.to_checkpoint(a.init(E)))
        ckpt.wait_until_finished()
        with pytest.raises(ValueError, match=r"tree structures do not match"):
            ckpt.restore(tmp_path / "ckpt", b.to_checkpoint(b.init(E)))


def test_the_spec_identity_is_the_same_in_every_process():
    # Sets of statistics iterate in an order salted per process (PYTHONHASHSEED): a
    # checkpoint written by one process was refused by the next one's identical spec.
    script = (
        "import jaxmetrics as jm\n"
        "m = jm.Metrics(terms={'r': jm.Term(lambda x: x, stats=('mean', 'std', 'min', 'max',"
        " 'sum', 'count', jm.ema(0.1)))}, logged={'l': jm.Logged(stats=('max', 'mean'))})\n"
        "print(m.init(2).spec._fields[0])\n"
    )
    seen = set()
    for seed in ("1", "2", "3", "4"):
        env = dict(os.environ, PYTHONHASHSEED=seed, JAX_PLATFORMS="cpu")
        out = subprocess.run(
            [sys.executable, "-c", script], capture_output=True, text=True, env=env, check=True
        )
        seen.add(out.stdout.strip().splitlines()[-1])
    assert len(seen) == 1, seen


def test_a_restore_without_target_or_of_another_shape_is_refused_at_once(tmp_path):
    # orbax's restore without a target gives plain dicts; from_checkpoint reordered their
    # leaves and failed later with TypeError, IndexError or StopIteration.
    m = spec()
    xs, dones = data()
    state = run(m, m.init(E), xs, dones)
    with ocp.StandardCheckpointer() as ckpt:
        ckpt.save(tmp_path / "ckpt", m.to_checkpoint(state))
        ckpt.wait_until_finished()
        targetless = ckpt.restore(tmp_path / "ckpt")
    with pytest.raises(ValueError, match=r"\(dict\) is not the MetricsCheckpoint.*with its target"):
        m.from_checkpoint(targetless, m.init(E))
    # Saved with 8 envs, restored into a target of 4.
    with pytest.raises(
        ValueError, match=r"is of 8 envs in 1 env shard, but the target is of 4 envs in 1 env"
    ):
        m.from_checkpoint(m.to_checkpoint(state), m.init(E // 2))
    restored = m.from_checkpoint(m.to_checkpoint(state), m.init(E))
    assert jax.tree.all(jax.tree.map(lambda a, b: bool(jnp.array_equal(a, b)), restored, state))


C, W = 0.1, 5


def plain_spec():
    """What `reference` computes: the episode sums' statistics, EMA and window."""
    stats = ("mean", "std", "min", "max", "count", jm.ema(C), jm.window(W))
    return jm.Metrics(
        terms={"r": jm.Term(lambda x: x, reduce="sum", stats=stats)},
        logged=["loss"],
        counters=["updates"],
    )


def reference(xs: np.ndarray, dones: np.ndarray) -> dict[str, float]:
    """In float64, over the whole run: the statistics of the returns of the episodes that
    ended, in order of step, then env index."""
    acc, ended = np.zeros(xs.shape[1]), []
    for t in range(xs.shape[0]):
        acc += xs[t].astype(np.float64)
        for e in np.flatnonzero(dones[t]):
            ended.append(acc[e])
            acc[e] = 0.0
    x = np.asarray(ended)
    ema = x[0]
    for v in x[1:]:
        ema = C * v + (1 - C) * ema
    return {
        "": x.mean(),
        "/std": x.std(),
        "/min": x.min(),
        "/max": x.max(),
        "/count": len(x),
        "/ema": ema,
        "/window_mean": x[-W:].mean(),
    }


def env_sharding(devices: int) -> NamedSharding | None:
    if devices == 1:
        return None
    mesh = jax.make_mesh(
        (devices,), ("env",), axis_types=(AxisType.Auto,), devices=jax.devices()[:devices]
    )
    return NamedSharding(mesh, P("env"))


@pytest.mark.parametrize(
    "kind, saved, restored", [("flax", 1, 4), ("flax", 4, 1), ("orbax", 4, 1), ("orbax", 2, 4)]
)
def test_a_checkpoint_continues_exactly_on_another_number_of_devices(
    kind, saved, restored, tmp_path
):
    xs, dones = data()
    m = plain_spec()
    state = run(m, m.init(E, env_sharding(saved)), xs[:SPLIT], dones[:SPLIT])
    fresh = plain_spec()
    target = fresh.init(E, env_sharding(restored))
    if kind == "flax":
        raw = flax.serialization.from_bytes(target, flax.serialization.to_bytes(state))
        # flax restores numpy arrays, which have no `.at`: an eager update used to fail.
        fresh.update(raw, xs[SPLIT], dones[SPLIT])
        back = fresh.from_checkpoint(raw, target)
    else:
        with ocp.StandardCheckpointer() as ckpt:
            ckpt.save(tmp_path / "ckpt", m.to_checkpoint(state))
            ckpt.wait_until_finished()
            restored_tree = ckpt.restore(tmp_path / "ckpt", fresh.checkpoint_target(E, saved))
        back = fresh.from_checkpoint(restored_tree, target)
    # JAX arrays, laid out like the target: each device folds its own envs.
    for got, want in zip(jax.tree.leaves(back), jax.tree.leaves(target)):
        assert isinstance(got, jax.Array)
        assert got.sharding.is_equivalent_to(want.sharding, got.ndim)
    back = fresh.update(back, xs[SPLIT], dones[SPLIT])  # eagerly, then jitted
    resumed = run(fresh, back, xs[SPLIT + 1 :], dones[SPLIT + 1 :])
    got = report(fresh, resumed)
    for suffix, want in reference(np.asarray(xs), np.asarray(dones)).items():
        assert got[f"Episode_Metrics/r{suffix}"] == pytest.approx(want, rel=1e-5), suffix
    assert got["Counters/env_steps"] == E * STEPS
    assert got["Counters/updates"] == STEPS - 1  # the eager update logs nothing


def test_a_restore_into_another_layout_is_refused_naming_both(tmp_path):
    xs, dones = data()
    m = plain_spec()
    four = run(m, m.init(E, env_sharding(4)), xs[:SPLIT], dones[:SPLIT])
    one = run(m, m.init(E), xs[:SPLIT], dones[:SPLIT])
    with ocp.StandardCheckpointer() as ckpt:
        for name, state in (("four", four), ("one", one)):
            ckpt.save(tmp_path / name, m.to_checkpoint(state))
        ckpt.wait_until_finished()
        # strict=False cuts the 4 shards to the target's 1, shard 0's statistics alone.
        cut = ckpt.restore(tmp_path / "four", m.to_checkpoint(m.init(E)), strict=False)
        padded = ckpt.restore(tmp_path / "one", m.to_checkpoint(m.init(2 * E)), strict=False)
    with pytest.raises(
        ValueError,
        match=r"holds a state of 8 envs in 4 env shards, but its arrays came back as 8 envs "
        r"in 1 env shard.*checkpoint_target\(8, shards=4\)",
    ):
        m.from_checkpoint(cut, m.init(E))
    # Another number of envs, by either path: refused at restore, naming both.
    flax_restored = flax.serialization.from_bytes(m.init(2 * E), flax.serialization.to_bytes(one))
    for restored in (padded, flax_restored):
        with pytest.raises(
            ValueError, match=r"is of 8 envs in 1 env shard, but the target is of 16 envs in 1"
        ):
            m.from_checkpoint(restored, m.init(2 * E))
