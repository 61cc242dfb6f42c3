"""Where a MetricsState lives when the env batch is split over devices.

A sharded state keeps its finished-episode statistics per env shard: shard `i` folds the
`i`-th contiguous block of envs, on the devices that hold those envs, so a step needs no
communication; shards meet only when a report is computed.
"""

import contextlib
import itertools
import math
from collections.abc import Iterator
from typing import Any

import jax
import jax.core  # jax.core.Tracer: imported by jax, named here for the type checker
import jax.numpy as jnp
import numpy as np


def gathered(x: jax.Array) -> jax.Array:
    """`x` unsharded, where it is sharded over explicit mesh axes (a no-op otherwise).

    Under explicit sharding JAX asks for an axis to be whole before it is scanned in
    order or indexed; this is the one place such a gather happens (at compute time).
    """
    sharding = jax.typeof(x).sharding
    spec = getattr(sharding, "spec", None)
    if spec is None or all(p is None for p in spec):
        return x
    return jax.sharding.reshard(
        x, jax.sharding.NamedSharding(sharding.mesh, jax.sharding.PartitionSpec())
    )


def whole(tree: Any) -> Any:
    """In-graph: `tree`, whose leaves hold one entry per env shard on a leading axis split
    over devices, whole on every device of the mesh traced under, moved in one collective.

    Left to XLA, every leaf that `compute` reads across shards is moved by a collective of
    its own (a sharded state has about thirty leaves), and on GPUs each collective is a
    launch and a synchronization of the devices. The leaves travel as the uint32 words of
    one `[shards, words]` array instead, bit for bit, and are read back from it."""
    mesh = jax.sharding.get_abstract_mesh()
    leaves, treedef = jax.tree.flatten(tree)
    if mesh.empty or jax.sharding.AxisType.Manual in mesh.axis_types:
        return tree  # under `shard_map` the caller decides what moves between devices
    if not any(isinstance(x, jax.core.Tracer) for x in leaves):
        # Run op by op (an eager `compute`), each leaf moves on its own anyway, and ops
        # on concrete arrays under an abstract mesh are refused.
        return tree
    words = [_as_words(x) for x in leaves]
    packed = jnp.concatenate(words, axis=1)
    everywhere = jax.sharding.PartitionSpec()
    if all(t == jax.sharding.AxisType.Explicit for t in mesh.axis_types):
        packed = jax.sharding.reshard(packed, everywhere)
    else:
        packed = jax.lax.with_sharding_constraint(packed, everywhere)
    out, start = [], 0
    for x, w in zip(leaves, words):
        out.append(_from_words(packed[:, start : start + w.shape[1]], x))
        start += w.shape[1]
    return jax.tree.unflatten(treedef, out)


def _as_words(x: jax.Array) -> jax.Array:
    """`x[S, ...]` as `uint32[S, k]`, bit for bit (narrower types widened, wider split)."""
    if x.dtype == jnp.bool_ or x.dtype.itemsize < 4:
        bits = x if x.dtype == jnp.bool_ else jax.lax.bitcast_convert_type(x, _uint(x.dtype))
        w = bits.astype(jnp.uint32)
    else:
        w = jax.lax.bitcast_convert_type(x, jnp.uint32)
    return w.reshape(x.shape[0], -1)


def _from_words(w: jax.Array, like: jax.Array) -> jax.Array:
    """`_as_words`' inverse, for an array shaped and typed as `like`."""
    if like.dtype == jnp.bool_:
        return w.reshape(like.shape) != 0
    if like.dtype.itemsize < 4:
        narrow = w.reshape(like.shape).astype(_uint(like.dtype))
        return jax.lax.bitcast_convert_type(narrow, like.dtype)
    split = like.dtype.itemsize // 4
    shape = like.shape + ((split,) if split > 1 else ())
    return jax.lax.bitcast_convert_type(w.reshape(shape), like.dtype)


def _uint(dt: Any) -> Any:
    return np.dtype(f"uint{8 * np.dtype(dt).itemsize}")


def mesh_of(tree: Any) -> jax.sharding.Mesh | None:
    """Host side: the mesh of a concrete state's sharded leaves (None on one device)."""
    for leaf in jax.tree.leaves(tree):
        sharding = getattr(leaf, "sharding", None)
        if isinstance(sharding, jax.sharding.NamedSharding) and sharding.mesh.size > 1:
            assert isinstance(sharding.mesh, jax.sharding.Mesh)  # a concrete array's
            return sharding.mesh
    return None


def env_axis_names(spec: Any) -> tuple[str, ...]:
    """The mesh axes that a `PartitionSpec` (or its tuple) splits its first (env) axis over."""
    first = spec[0] if spec else None
    if first is None:
        return ()
    return (first,) if isinstance(first, str) else tuple(first)


def shard_axes(leaf: jax.Array, shards: int) -> tuple[str, ...] | None:
    """In-graph: the mesh axes over which each device holds one of a state's `shards` env
    shards (`leaf`: one of its per-shard leaves, `[S, ...]`), where the trace knows them;
    None where it does not (one shard, or no mesh to read them from).

    Under Explicit axes the leaf's type says (`update` traces under the state's mesh).
    Under Auto axes the types carry no layout: the axes are read from the mesh `update`
    traces under (the state's own, which a state made by `init(sharding=...)` carries in
    its type, or the one the caller set with `jax.set_mesh`), as the one set of its axes
    whose devices number `shards`; where two sets would do (a 2 x 2 mesh and 2 shards), none is
    guessed. The state's shards are then folded per device (`jax.shard_map`); without axes
    they are folded as one batch of shards, which XLA keeps local to each device too.
    """
    if shards < 2:
        return None
    mesh = jax.sharding.get_abstract_mesh()
    if mesh.empty:
        return None
    spec = getattr(jax.typeof(leaf).sharding, "spec", None)
    names = env_axis_names(spec)
    if names:
        candidates = [names]
    else:
        auto = [
            n for n, t in zip(mesh.axis_names, mesh.axis_types) if t == jax.sharding.AxisType.Auto
        ]
        candidates = [
            c
            for k in range(1, len(auto) + 1)
            for c in itertools.combinations(auto, k)
            if math.prod(mesh.shape[n] for n in c) == shards
        ]
    if len(candidates) != 1 or math.prod(mesh.shape[n] for n in candidates[0]) != shards:
        return None
    return tuple(str(n) for n in candidates[0])


def placed(tree: Any, sharding: Any) -> Any:
    """In-graph: `tree` laid out by `sharding` (one `NamedSharding`, or a tree of them
    matching `tree`): a reshard on Explicit mesh axes, where a sharding constraint would
    only assert, and a sharding constraint on Auto ones."""
    if isinstance(sharding, jax.sharding.NamedSharding):
        sharding = jax.tree.map(lambda _: sharding, tree)

    def one(x: jax.Array, s: jax.sharding.NamedSharding) -> jax.Array:
        if all(t == jax.sharding.AxisType.Explicit for t in s.mesh.axis_types):
            return jax.sharding.reshard(x, s)
        return jax.lax.with_sharding_constraint(x, s)

    return jax.tree.map(one, tree, sharding)


def replicated(tree: Any, mesh: jax.sharding.Mesh | None) -> Any:
    """In-graph: `tree` whole on every device of `mesh` (every process can read it)."""
    if mesh is None:
        return tree
    return placed(tree, jax.sharding.NamedSharding(mesh, jax.sharding.PartitionSpec()))


def like(x: jax.Array, ref: jax.Array, what: str) -> jax.Array:
    """`x`, checked to be laid out like the state's `ref` over an explicit mesh.

    Under explicit sharding the layouts are known at trace time; an input split
    differently from the state would need a cross-device copy on every step, so it is an
    error rather than a silent reshard (under Auto axes XLA decides; see docs/devices.md).
    """
    want = getattr(jax.typeof(ref).sharding, "spec", None)
    have = getattr(jax.typeof(x).sharding, "spec", None)
    if want is None or have is None:
        return x
    want = tuple(want) + (None,) * (x.ndim - len(want))
    have = tuple(have) + (None,) * (x.ndim - len(have))
    if want == have:
        return x
    raise ValueError(
        f"update: {what} are laid out as {jax.sharding.PartitionSpec(*have)} but the "
        f"MetricsState expects {jax.sharding.PartitionSpec(*want)} (env axis last). "
        "Build the state with metrics.init(num_envs, sharding=<the env batch's "
        "sharding>) so that each device folds its own envs, or reshard the inputs."
    )


def shard_count(sharding: Any, num_envs: int) -> int:
    """The number of env shards for `Metrics.init(sharding=...)`, checked."""
    if sharding is None or isinstance(sharding, jax.sharding.SingleDeviceSharding):
        return 1
    if not isinstance(sharding, jax.sharding.NamedSharding):
        raise TypeError(
            f"init(sharding=...) takes the env batch's jax.sharding.NamedSharding (e.g. "
            f"NamedSharding(mesh, P('env')), or env_state.done.sharding), got "
            f"{type(sharding).__name__}."
        )
    spec = tuple(sharding.spec)
    names = env_axis_names(spec)
    shards = math.prod(sharding.mesh.shape[n] for n in names)
    if num_envs % shards:
        raise ValueError(
            f"init: {num_envs} envs do not split evenly over the {shards} shards of "
            f"{sharding.spec} on mesh {dict(sharding.mesh.shape)}; use a multiple of {shards}."
        )
    return shards


@contextlib.contextmanager
def state_mesh(tree: Any) -> Iterator[None]:
    """Traces under the mesh of `tree`'s explicitly sharded leaves, where no mesh is set.

    Under Explicit mesh axes (what `jax.make_mesh` makes by default) JAX resolves the
    sharding of a traced scatter or `arange` against the current mesh, and without
    `jax.set_mesh` there is none ("Resource axis: env ... is not found in mesh: ()"). The
    state's own leaves say which mesh it lives on; a mesh the caller set is kept.
    """
    if not jax.sharding.get_abstract_mesh().empty:
        yield
        return
    for leaf in jax.tree.leaves(tree):
        mesh = getattr(jax.typeof(leaf).sharding, "mesh", None)
        if isinstance(mesh, jax.sharding.AbstractMesh) and not mesh.empty:
            with jax.sharding.use_abstract_mesh(mesh):
                yield
            return
    yield
