"""Scenario "sharded": the Brax rollout with its envs split over devices, set up the way
users shard it.

Weak scaling: `per_device` envs on each of 1, 2, ... local devices. As a user does: an
Auto mesh "env" set with `jax.set_mesh`, the env state and the actions `device_put` with
`NamedSharding(mesh, P("env"))`, the metrics state made by `init(num_envs, sharding=...)`.
The step loop (`update` in a scanned rollout) is timed apart from `compute` and
`Logger.flush`: bare vs the full 10-term spec vs the same terms with simple statistics.
A device count whose bare rollout is more than `WEAK_SCALING` slower than one device's does
not weak-scale, and its overheads are no measure of what the metrics cost there (the
targets mark it invalid). Each row counts the cross-device collectives left in the compiled
step loop, and the flush table those of `compute`; `distributed` runs the isolated update
in several processes under `jax.distributed` (see `_distributed.py`).
"""

import json
import os
import socket
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Iterator
from typing import Any

import jax
import jax.numpy as jnp
from jax.sharding import AxisType, NamedSharding
from jax.sharding import PartitionSpec as P

import jaxmetrics as jm

from . import _workload as wl
from ._flush_cost import time_logger
from ._hlo import collectives, loop_body_ops, program_ops
from ._report import Table
from ._rollout import _brax_promotion
from ._timing import Variant, blocking, compile_jit, measure

SPECS = {
    "full": "jaxmetrics, 10 terms, every statistic",
    "simple": "jaxmetrics, 10 terms, simple statistics",
}
BARE = "bare rollout"

WEAK_SCALING = 1.02
"""The most a device count's bare rollout may take, in multiples of one device's, for its
overheads to be judged (a baseline that does not weak-scale hides what metrics cost)."""


def env_sharding(devices: list[Any]) -> NamedSharding:
    """The env batch split over `devices` on an Auto mesh "env" (what users make)."""
    mesh = jax.make_mesh((len(devices),), ("env",), axis_types=(AxisType.Auto,), devices=devices)
    return NamedSharding(mesh, P("env"))


class ShardedRollout:
    """A Brax env batch split over `devices`, as a user lays it out (module docstring)."""

    def __init__(self, env_name: str, backend: str, devices: list[Any], per_device: int):
        from brax import envs  # isort: skip
        from brax.envs.wrappers import training  # isort: skip

        self.sharding = env_sharding(devices)
        assert isinstance(self.sharding.mesh, jax.sharding.Mesh)  # a concrete mesh, made here
        self.mesh = self.sharding.mesh
        self.num_envs = per_device * len(devices)
        with _brax_promotion():  # outside the mesh: the model's arrays load on one device
            base = envs.get_environment(env_name, backend=backend)
            self.env = training.wrap(base, episode_length=1000)
        with jax.set_mesh(self.mesh), _brax_promotion():
            keys = jax.random.split(jax.random.PRNGKey(0), self.num_envs)
            state = jax.jit(self.env.reset)(jax.device_put(keys, self.sharding))
            self.state0 = jax.block_until_ready(jax.device_put(state, self.sharding))
            shape = (self.num_envs, self.env.action_size)
            actions = jax.random.uniform(jax.random.PRNGKey(1), shape, jnp.float32, -1.0, 1.0)
            self.actions = jax.device_put(actions, self.sharding)

    def scan(self, steps: int, metrics: jm.Metrics | None) -> Callable[..., Any]:
        """`rollout(env_state, metrics_state, actions) -> (env_state, metrics_state)`."""

        def rollout(env_state, ms, actions):
            def body(c, t):
                s, ms = c
                # A new action per step, elementwise, so laid out as the envs are.
                a = jnp.sin(actions * (t + 1).astype(jnp.float32))
                with _brax_promotion():
                    s = self.env.step(s, a)
                if metrics is not None:
                    ms = metrics.update(ms, s, s.done.astype(bool))
                return (s, ms), None

            ts = jnp.arange(steps, dtype=jnp.int32)
            return jax.lax.scan(body, (env_state, ms), ts)[0]

        return rollout


def variants(
    ro: ShardedRollout, steps: int
) -> tuple[list[Variant], dict[str, int], dict[str, Any]]:
    """Timed step loops of one rollout set-up, their loop collectives and their metrics
    states (spec, state, compiled loop)."""
    out, coll, states = [], {}, {}
    with jax.set_mesh(ro.mesh):
        for name in ("bare", *SPECS):
            spec = None if name == "bare" else wl.rollout_spec(features=name)
            ms = None if spec is None else spec.init(ro.num_envs, sharding=ro.sharding)
            compiled, compile_s = compile_jit(ro.scan(steps, spec), ro.state0, ms, ro.actions)
            coll[name] = sum(collectives(loop_body_ops(compiled.as_text())).values())
            out.append(Variant(name, blocking(compiled, ro.state0, ms, ro.actions), compile_s))
            states[name] = (spec, ms, compiled)
    return out, coll, states


def sharded(
    env_name: str,
    backend: str,
    per_device: int,
    steps: int,
    repeats: int,
    device_counts: tuple[int, ...],
    processes: int = 0,
) -> Iterator[Table]:
    """The weak-scaling and flush tables (and, with `processes`, the distributed one),
    each as soon as it is measured: a distributed run that fails keeps the others."""
    local = jax.local_devices()
    counts = tuple(d for d in device_counts if d <= len(local))
    t = Table(
        "sharded",
        f"Weak scaling, {env_name} ({backend}), {per_device} envs per device, {steps}-step "
        "scan of the step loop",
        [
            "devices",
            "variant",
            "ms/step",
            "overhead %",
            "x 1-device bare",
            "collectives in step loop",
            "compile s",
        ],
    )
    f = Table(
        "sharded_flush",
        "Compute and flush of the full spec's sharded state per device count",
        [
            "devices",
            "envs",
            "bytes to host",
            "collectives in compute",
            "compute + copy ms",
            "Logger.flush ms",
            "Logger flush+wait ms",
        ],
    )
    one_bare = None
    for d in counts:
        r = _in_own_process(env_name, backend, per_device, steps, repeats, d)
        med = r["median_s"]
        one_bare = med["bare"] if one_bare is None else one_bare
        for name in ("bare", *SPECS):
            ms = med[name] / steps * 1e3
            if name == "bare":
                t.add(d, BARE, ms, None, med[name] / one_bare, r["collectives"][name],
                      r["compile_s"][name])  # fmt: skip
            else:
                over = (med[name] / med["bare"] - 1) * 100
                t.add(d, SPECS[name], ms, over, None, r["collectives"][name], r["compile_s"][name])
        f.add(d, r["envs"], *r["flush"])
    t.notes.append(
        "Each device count is measured in a process of its own (in one process, after the "
        "1-device programs, the 2-device bare rollout once ran 1.156x one device's on 2 "
        "H200s; in a fresh process 1.012x)."
    )
    t.notes.append(
        "Step loop: the scanned rollout with update only, compute and flush timed apart "
        "(below). Overhead: median time of the variant over the bare rollout's, same "
        "devices, same run. x 1-device bare: the bare rollout's time over one device's; a "
        f"device count above {WEAK_SCALING} does not weak-scale and its overheads are not "
        "judged. Target: the overhead on several devices within 0.5 percentage points of "
        "one device's."
    )
    t.notes.append(
        "collectives: all-reduce/all-gather/all-to-all/collective-permute/reduce-scatter ops "
        "left in the body of the compiled scan (0 = the step is shard-local)."
    )
    f.notes.append(
        "bytes to host: the packed report a Logger.flush copies (O(metrics), whatever the envs); "
        "collectives in compute: those of the jitted compute (the shards meet once); "
        "compute + copy: jitted compute, then device_get of every leaf, median; "
        "Logger.flush: the call alone, the previous flush written (what a training loop "
        "waits for; the copy completes on the writer thread), and flush + wait(), median."
    )
    yield t
    yield f
    if processes:
        yield distributed(per_device, steps, repeats, processes)


def measure_count(
    env_name: str, backend: str, per_device: int, steps: int, repeats: int, d: int
) -> dict[str, Any]:
    """One device count's step loops, collectives and flush, measured in this process."""
    local = jax.local_devices()
    if len(local) < d:
        raise RuntimeError(f"{d} devices asked for, this process has {len(local)}")
    ro = ShardedRollout(env_name, backend, local[:d], per_device)
    vs, coll, states = variants(ro, steps)
    timings, _ = measure(vs, repeats)
    spec, ms0, compiled = states["full"]
    _, state = compiled(ro.state0, ms0, ro.actions)
    return {
        "median_s": {v.name: timings[v.name].median_s for v in vs},
        "collectives": coll,
        "compile_s": {v.name: v.compile_s for v in vs},
        "envs": ro.num_envs,
        "flush": _flush_cost(spec, state, repeats),
    }


def _in_own_process(*args: Any) -> dict[str, Any]:
    """`measure_count(*args)` in a fresh Python process: in a process that had run one
    device count's programs, the next count's once ran slower (see the table's notes)."""
    with tempfile.TemporaryDirectory() as out:
        path = os.path.join(out, "count.json")
        cmd = [sys.executable, "-m", "benchmarks._sharded", path, *map(str, args)]
        env = _with_root(dict(os.environ))
        if jax.default_backend() == "cpu":  # the CPU devices this process was given
            env["JAX_NUM_CPU_DEVICES"] = str(jax.local_device_count())
        else:
            # This process may hold 75% of each GPU already (JAX preallocates at its first
            # operation, e.g. an earlier scenario's); the worker's allocator grows instead.
            env["XLA_PYTHON_CLIENT_PREALLOCATE"] = "false"
        subprocess.run(cmd, env=env, check=True, timeout=1800)
        with open(path) as fh:
            return json.load(fh)


def _flush_cost(spec: jm.Metrics, state: Any, repeats: int) -> list[Any]:
    compute = jax.jit(spec.compute)
    moved = sum(collectives(program_ops(compute.lower(state).compile().as_text())).values())
    jax.device_get(compute(state))
    samples = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.device_get(compute(state))
        samples.append(time.perf_counter() - t0)
    call_s, wait_s, _, nbytes = time_logger(spec, state, repeats)
    return [nbytes, moved, statistics.median(samples) * 1e3, call_s * 1e3, wait_s * 1e3]


def distributed(per_device: int, steps: int, repeats: int, processes: int) -> Table:
    """`processes` processes x 1 device under `jax.distributed` on this machine, running
    the isolated update (see `_distributed.py`)."""
    t = Table(
        "distributed",
        f"{processes} processes x 1 device under jax.distributed: isolated update, 10 terms, "
        f"{per_device} envs per device, {steps}-step scan",
        ["variant", "us/step", "x floor", "collectives in step loop", "bytes to host"],
    )
    with socket.socket() as s:
        s.bind(("localhost", 0))
        port = s.getsockname()[1]
    with tempfile.TemporaryDirectory() as out:
        args = [per_device, steps, repeats, processes, port, out]
        procs = [
            subprocess.Popen(
                [sys.executable, "-m", "benchmarks._distributed", str(i), *map(str, args)],
                env=_process_env(i),
            )
            for i in range(processes)
        ]
        codes = [p.wait(timeout=1800) for p in procs]
        if any(codes):
            raise RuntimeError(f"distributed bench processes exited with {codes}")
        with open(os.path.join(out, "result.json")) as fh:
            result = json.load(fh)
    for row in result["rows"]:
        t.add(*row)
    t.notes.append(
        "Each process owns one device; one global env batch split over all; the state made "
        "by init(sharding=...); only process 0 writes; bytes to host: one flush's packed report."
    )
    return t


def _with_root(env: dict[str, str]) -> dict[str, str]:
    # `benchmarks` is no installed package: a worker finds it where this one was found.
    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    env["PYTHONPATH"] = os.pathsep.join(filter(None, (root, env.get("PYTHONPATH"))))
    return env


def _process_env(i: int) -> dict[str, str]:
    env = _with_root(dict(os.environ))
    if jax.default_backend() == "gpu":
        env["CUDA_VISIBLE_DEVICES"] = str(i)
        # This process already holds most of each GPU's memory (JAX preallocates 75%): a
        # worker that preallocated too failed NCCL's set-up on 80 GB cards.
        env["XLA_PYTHON_CLIENT_PREALLOCATE"] = "false"
    else:
        env["JAX_PLATFORMS"] = "cpu"
        env.pop("JAX_NUM_CPU_DEVICES", None)
        # One CPU device per process; the caller's other flags stay (the test suite's
        # fast-compile flags among them).
        flags = env.get("XLA_FLAGS", "").split()
        env["XLA_FLAGS"] = " ".join(
            f for f in flags if not f.startswith("--xla_force_host_platform_device_count")
        )
    return env


if __name__ == "__main__":
    _path, _env, _backend, *_ints = sys.argv[1:]
    with open(_path, "w") as _fh:
        json.dump(measure_count(_env, _backend, *map(int, _ints)), _fh)
