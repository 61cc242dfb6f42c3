"""Scenario "sharded": the Brax rollout with its envs split over devices.

Weak scaling: `per_device` envs on each of 1, 2, ... local devices (a 1-D mesh "env",
the env batch `P("env")`), bare vs the full 10-term spec vs the same terms with simple
statistics, all with the state made by `init(num_envs, sharding=...)`; and, for
reference, the full spec with a state made without `sharding=` (one shard: every step
then reduces across devices). Each row also counts the cross-device collectives left in
the compiled step loop. A second table times the flush (in-graph compute and pack, then
the copy to the host) and its bytes per device count; `distributed` runs the isolated
update in several processes under `jax.distributed` (see `_distributed.py`).
"""

import json
import os
import socket
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator
from typing import Any

import jax
from jax.sharding import AxisType, NamedSharding
from jax.sharding import PartitionSpec as P

import jaxmetrics as jm

from . import _workload as wl
from ._hlo import collectives, loop_body_ops
from ._report import Table
from ._rollout import Rollout, _bare, _with_metrics
from ._timing import Variant, blocking, compile_jit, measure

SPECS = {
    "full": "jaxmetrics, 10 terms, every statistic",
    "simple": "jaxmetrics, 10 terms, simple statistics",
    "unsharded": "jaxmetrics, 10 terms, every statistic, state made without sharding=",
}


def env_sharding(devices: list[Any]) -> NamedSharding:
    mesh = jax.make_mesh((len(devices),), ("env",), axis_types=(AxisType.Auto,), devices=devices)
    return NamedSharding(mesh, P("env"))


def variants(
    ro: Rollout, steps: int, sharding: NamedSharding, which: tuple[str, ...]
) -> tuple[list[Variant], dict[str, int], dict[str, Any]]:
    """Timed variants of one rollout set-up, their loop collectives and metrics states."""
    out, coll, states = [], {}, {}
    rollout = ro.scan(steps, _bare)
    compiled, compile_s = compile_jit(rollout, ro.state0, None)
    coll["bare"] = sum(collectives(loop_body_ops(compiled.as_text())).values())
    out.append(Variant("bare", blocking(compiled, ro.state0, None), compile_s))
    for name in which:
        spec = wl.rollout_spec(features="simple" if name == "simple" else "full")
        ms = spec.init(ro.num_envs, sharding=None if name == "unsharded" else sharding)
        rollout = ro.scan(steps, _with_metrics(spec))
        compiled, compile_s = compile_jit(rollout, ro.state0, ms)
        coll[name] = sum(collectives(loop_body_ops(compiled.as_text())).values())
        out.append(Variant(name, blocking(compiled, ro.state0, ms), compile_s))
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
        f"Weak scaling, {env_name} ({backend}), {per_device} envs per device, {steps}-step scan",
        ["devices", "variant", "ms/step", "overhead %", "collectives in step loop", "compile s"],
    )
    f = Table(
        "sharded_flush",
        "Flush of the full spec's state per device count",
        ["devices", "envs", "bytes to host", "compute + copy ms", "Logger.flush ms"],
    )
    for d in counts:
        sharding = env_sharding(local[:d])
        ro = Rollout(env_name, backend, per_device * d, sharding=sharding)
        which = ("full", "simple") + (("unsharded",) if d > 1 else ())
        vs, coll, states = variants(ro, steps, sharding, which)
        timings, _ = measure(vs, repeats)
        bare = timings["bare"].median_s
        for v in vs:
            ms = timings[v.name].median_s / steps * 1e3
            over = (timings[v.name].median_s / bare - 1) * 100
            label = "bare rollout" if v.name == "bare" else SPECS[v.name]
            t.add(d, label, ms, None if v.name == "bare" else over, coll[v.name], v.compile_s)
        spec, ms0, compiled = states["full"]
        _, state, _ = compiled(ro.state0, ms0)
        f.add(d, per_device * d, *_flush_cost(spec, state, repeats))
    t.notes.append(
        "Overhead: median time of the variant over the bare rollout's, same devices, same run. "
        "Target: the overhead on several devices within 0.5 percentage points of one device's."
    )
    t.notes.append(
        "collectives: all-reduce/all-gather/all-to-all/collective-permute/reduce-scatter ops "
        "left in the body of the compiled scan (0 = the step is shard-local)."
    )
    f.notes.append(
        "bytes to host: the packed report a Logger.flush copies (O(metrics), whatever the envs); "
        "compute + copy: jitted compute, then device_get of every leaf, median."
    )
    yield t
    yield f
    if processes:
        yield distributed(per_device, steps, repeats, processes)


def _flush_cost(spec: jm.Metrics, state: Any, repeats: int) -> list[Any]:
    compute = jax.jit(spec.compute)
    jax.device_get(compute(state))
    samples = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.device_get(compute(state))
        samples.append(time.perf_counter() - t0)
    with jm.Logger(spec, [jm.MemoryWriter()]) as logger:
        logger.flush(state, 0)
        logger.wait()
        flush_s = []
        for i in range(repeats):
            t0 = time.perf_counter()
            logger.flush(state, i + 1)
            flush_s.append(time.perf_counter() - t0)
        nbytes = logger.report_nbytes
    return [nbytes, statistics.median(samples) * 1e3, statistics.median(flush_s) * 1e3]


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


def _process_env(i: int) -> dict[str, str]:
    env = dict(os.environ)
    # `benchmarks` is no installed package: the worker finds it where this one was found.
    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    env["PYTHONPATH"] = os.pathsep.join(filter(None, (root, env.get("PYTHONPATH"))))
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
