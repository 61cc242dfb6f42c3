"""A MetricsState saved mid-run (orbax-checkpoint, flax.serialization) and restored into a
fresh process's spec continues exactly as the uninterrupted run: windows, EMA, histograms,
quantile sketches, counters and running episodes (discounted returns included) carry over
bit for bit, sharded or not."""

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
    if kind == "flax":
        return flax.serialization.from_bytes(target, flax.serialization.to_bytes(state))
    # orbax refuses zero-size arrays (statistics the spec does not keep): to_checkpoint.
    m = spec()
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
    with pytest.raises(ValueError, match=r"\(dict\) is not the MetricsState.*with its target"):
        m.from_checkpoint(targetless, m.init(E))
    # Saved with 8 envs, restored into a target of 4.
    with pytest.raises(
        ValueError, match=r"\.running\.\w+ is \w+\[\d+, 8\], but the target has \w+\[\d+, 4\]"
    ):
        m.from_checkpoint(m.to_checkpoint(state), m.init(E // 2))
    restored = m.from_checkpoint(m.to_checkpoint(state), m.init(E))
    assert jax.tree.all(jax.tree.map(lambda a, b: bool(jnp.array_equal(a, b)), restored, state))
