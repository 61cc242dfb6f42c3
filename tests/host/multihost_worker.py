"""One process of the 2-process jax.distributed test (run by test_multihost.py, not pytest).

Usage: python multihost_worker.py PROCESS_ID PORT OUT_DIR

Each process owns 2 CPU devices of a 4-device global mesh over the env axis. Every process
feeds the same global rollout, writes its report to OUT_DIR/report<id>.json, and runs a
Logger whose writers (a factory) only process 0 may create, under OUT_DIR/logs<id>/.
"""

import json
import os
import sys

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import NamedSharding
from jax.sharding import PartitionSpec as P

import jaxmetrics as jm

sys.path.insert(0, os.path.dirname(__file__))
from multihost_spec import METRICS, NUM_ENVS, rollout_data  # noqa: E402


def main(pid: int, port: int, out: str) -> None:
    # Set before JAX starts its backend; only when run as a worker (pytest's doctest
    # collection imports this module too and must not change the suite's devices).
    jax.config.update("jax_num_cpu_devices", 2)
    jax.config.update("jax_cpu_collectives_implementation", "gloo")
    jax.distributed.initialize(f"localhost:{port}", num_processes=2, process_id=pid)
    assert jax.device_count() == 4 and jax.local_device_count() == 2
    mesh = jax.make_mesh((4,), ("env",), axis_types=(jax.sharding.AxisType.Auto,))
    xs, dones, losses = rollout_data()

    def global_array(a, spec):
        sharding = NamedSharding(mesh, spec)
        return jax.make_array_from_callback(a.shape, sharding, lambda idx: a[idx])

    gx = global_array(xs, P(None, None, "env"))
    gd = global_array(dones, P(None, "env"))
    gl = global_array(losses, P())
    env_sharding = NamedSharding(mesh, P("env"))

    @jax.jit
    def rollout(xs, dones, losses):
        def body(state, inp):
            x, d, loss = inp
            state = METRICS.update(state, x, d)
            return METRICS.log(state, {"loss": loss}), None

        state = METRICS.init(NUM_ENVS, sharding=env_sharding)
        return jax.lax.scan(body, state, (xs, dones, losses))[0]

    state = rollout(gx, gd, gl)
    report = METRICS.to_host(METRICS.compute(state))

    logdir = os.path.join(out, f"logs{pid}")
    logger = jm.Logger(
        METRICS,
        lambda run: [
            jm.JsonlWriter(os.path.join(logdir, "metrics.jsonl")),
            jm.TensorBoardWriter(os.path.join(logdir, "tb")),
        ],
    )
    state = logger.flush(state, step=1)
    flush_bytes = logger.report_nbytes
    emit = jax.jit(lambda s: logger.emit(s, jnp.int32(2), jnp.bool_(True)))
    state = emit(rollout(gx, gd, gl))
    logger.close()

    def plain(v):
        return v.tolist() if isinstance(v, np.ndarray) else v

    with open(os.path.join(out, f"report{pid}.json"), "w") as f:
        json.dump(
            {
                "report": {k: plain(v) for k, v in report.items()},
                "flush_bytes": flush_bytes,
                "writes": logger.writes,
                "shards": int(state.shard_counts.hi.shape[0]),
            },
            f,
        )
    jax.distributed.shutdown()


if __name__ == "__main__":
    main(int(sys.argv[1]), int(sys.argv[2]), sys.argv[3])
