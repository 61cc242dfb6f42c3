"""One process of the `distributed` bench table (started by `_sharded.distributed`).

`python -m benchmarks._distributed ID PER_DEVICE STEPS REPEATS PROCESSES PORT OUT` (a
worker process, started by the sharded scenario, not a command of its own):
joins `jax.distributed` on localhost and runs the isolated update (10 random terms per
step, no physics) over one global env batch of `PER_DEVICE` envs per device on every
process's devices: the hand-written floor vs the full spec with a sharded state. It
flushes once through a `Logger` (only process 0 writes), and process 0 writes the rows
to `OUT/result.json`.

Brax envs are not used here: building one after `jax.distributed.initialize` (brax 0.14,
CPU, 2 processes) captured a non-process-local array in `reset` and failed to lower.
"""

import json
import os
import sys

import jax
import numpy as np


def main(argv: list[str]) -> None:
    pid = int(argv[0])
    per_device, steps, repeats, processes, port = (int(a) for a in argv[1:6])
    out = argv[6]
    if os.environ.get("JAX_PLATFORMS") == "cpu":  # CPU processes talk through gloo
        jax.config.update("jax_cpu_collectives_implementation", "gloo")
    jax.distributed.initialize(f"localhost:{port}", num_processes=processes, process_id=pid)

    import jaxmetrics as jm

    from . import _workload as wl
    from ._hlo import collectives, loop_body_ops
    from ._isolated import DONE_PROB, _floor_scan, _metrics_scan
    from ._sharded import env_sharding
    from ._timing import Variant, blocking, compile_jit, measure

    sharding = env_sharding(jax.devices())
    mesh = sharding.mesh
    num_envs = per_device * jax.device_count()
    rng = np.random.default_rng(0)  # the same global inputs in every process
    xs = rng.random((steps, 10, num_envs), np.float32)
    dones = rng.random((steps, num_envs)) < DONE_PROB

    def global_array(a: np.ndarray, spec: jax.sharding.PartitionSpec) -> jax.Array:
        s = jax.sharding.NamedSharding(mesh, spec)
        return jax.make_array_from_callback(a.shape, s, lambda idx: a[idx])

    P = jax.sharding.PartitionSpec
    gx, gd = global_array(xs, P(None, None, "env")), global_array(dones, P(None, "env"))
    spec = wl.random_spec(10, features="full")
    ms = spec.init(num_envs, sharding=sharding)
    floor = jax.jit(
        lambda: wl.floor_init(10, num_envs), out_shardings=wl.FloorState(P(None, "env"), P(), P())
    )
    with jax.set_mesh(mesh):
        fs = floor()
    variants, texts = [], {}
    for name, fn, state in (("floor", _floor_scan(10), fs), ("full", _metrics_scan(spec), ms)):
        compiled, compile_s = compile_jit(fn, state, gx, gd)
        texts[name] = compiled.as_text()
        variants.append(Variant(name, blocking(compiled, state, gx, gd), compile_s))
    timings, last = measure(variants, repeats)
    with jm.Logger(spec, lambda run: [jm.MemoryWriter()]) as logger:
        logger.flush(last["full"], 1)
        nbytes = logger.report_nbytes
    rows = []
    floor_s = timings["floor"].median_s
    for name, label in (("floor", "hand-written floor"), ("full", "jaxmetrics, full 10-term spec")):
        sec = timings[name].median_s
        coll = sum(collectives(loop_body_ops(texts[name])).values())
        rows.append(
            [label, sec / steps * 1e6, sec / floor_s, coll, nbytes if name == "full" else None]
        )
    if pid == 0:
        with open(os.path.join(out, "result.json"), "w") as f:
            json.dump({"rows": rows, "devices": jax.device_count()}, f)
    jax.distributed.shutdown()


if __name__ == "__main__":
    main(sys.argv[1:])
