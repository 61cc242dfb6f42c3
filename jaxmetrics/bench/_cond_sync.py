"""What a per-step `lax.cond` costs a loop whose step is many small kernels.

The reporting wrappers (`jmb.wrap(logger=...)` and the others) decide on every env step
whether a period ends, with a `lax.cond` whose true branch makes the report's ordered
`io_callback`. On a GPU, XLA reads a conditional's predicate back to the host each time the
conditional runs, so the host waits for the device on every step and cannot queue the next
step's kernels ahead of it. A step of a few large kernels (Brax `ant` on MJX) hides that; a
step of many small ones (MJX's Warp physics, a cheap env) does not. This bench measures a
scanned step of `--kernels` small kernels over `--envs` floats:

- `bare`: the step alone;
- `cond_pure`: plus a `lax.cond` that is true once per `--period` steps, with a pure branch;
- `cond_callback`: the same, with an ordered `io_callback` in the branch (what the
  wrappers do);
- `cond_unordered`: the same with an unordered `io_callback`;
- `where`: the pure branch's result selected with `jnp.where` instead (no conditional).

Each variant runs in a fresh process per `--xla-flags` setting (XLA reads its flags once).

`python -m jaxmetrics.bench._cond_sync --xla-flags=--xla_gpu_enable_command_buffer=`
"""

import argparse
import json
import platform
import sys
import time

from ._timing import in_fresh_process

VARIANTS = ("bare", "cond_pure", "cond_callback", "cond_unordered", "where")


def measure(kernels: int, envs: int, steps: int, period: int, repeats: int) -> dict[str, float]:
    """Median microseconds per step of each variant, in this process."""
    import jax
    import jax.numpy as jnp
    import numpy as np

    def step(x: jax.Array) -> jax.Array:
        # The barriers keep each operation a kernel of its own, as a launch-bound env is.
        for i in range(kernels):
            x = jax.lax.optimization_barrier(jnp.sin(x) * jnp.float32(0.999) + jnp.float32(i))
        return x

    def report(x: jax.Array) -> jax.Array:
        return jnp.sum(x, dtype=jnp.float32)[None]

    def io(x: jax.Array, ordered: bool) -> jax.Array:
        spec = jax.ShapeDtypeStruct((1,), jnp.float32)
        return jax.experimental.io_callback(lambda v: np.asarray(v), spec, x, ordered=ordered)

    def body(variant: str):
        def f(carry, _):
            x, t, acc = carry
            x = step(x)
            t = t + 1
            when = t % period == 0
            if variant == "cond_pure":
                acc = jax.lax.cond(when, lambda: acc + report(x), lambda: acc)
            elif variant in ("cond_callback", "cond_unordered"):
                ordered = variant == "cond_callback"
                acc = jax.lax.cond(when, lambda: acc + io(report(x), ordered), lambda: acc)
            elif variant == "where":
                acc = jnp.where(when, acc + report(x), acc)
            return (x, t, acc), None

        return f

    out = {}
    for variant in VARIANTS:
        run = jax.jit(lambda c, v=variant: jax.lax.scan(body(v), c, None, length=steps)[0])
        carry = (jnp.ones((envs,), jnp.float32), jnp.int32(0), jnp.zeros((1,), jnp.float32))
        jax.block_until_ready(run(carry))
        times = []
        for _ in range(repeats):
            t0 = time.perf_counter()
            jax.block_until_ready(run(carry))
            times.append(time.perf_counter() - t0)
        out[variant] = float(np.median(times)) / steps * 1e6
    return out


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--kernels", type=int, default=100)
    p.add_argument("--envs", type=int, default=2048)
    p.add_argument("--steps", type=int, default=2000)
    p.add_argument("--period", type=int, default=1000)
    p.add_argument("--repeats", type=int, default=5)
    p.add_argument(
        "--xla-flags",
        action="append",
        help="XLA_FLAGS to add, one process per use (write --xla-flags=--xla_...); the "
        "default flags always run first",
    )
    p.add_argument("--out", help="write the results here as JSON")
    p.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    a = p.parse_args(argv)
    sizes = (a.kernels, a.envs, a.steps, a.period, a.repeats)
    if a.child:
        print(json.dumps(measure(*sizes)))
        return 0
    rows = []
    for flags in ["", *(a.xla_flags or ())]:
        args = [
            f"--{k}={v}" for k, v in zip(("kernels", "envs", "steps", "period", "repeats"), sizes)
        ]
        us = in_fresh_process("jaxmetrics.bench._cond_sync", args, flags)
        rows.append({"xla_flags": flags, "us_per_step": us})
        cells = " ".join(f"{v}={us[v]:.1f}" for v in VARIANTS)
        print(f"{flags or '(default flags)'}: {cells} us/step", flush=True)
    if a.out:
        import jax

        doc = {
            "benchmark": "cond_sync",
            "device": str(jax.devices()[0].device_kind),
            "jax": jax.__version__,
            "host": platform.node(),
            "sizes": dict(zip(("kernels", "envs", "steps", "period", "repeats"), sizes)),
            "rows": rows,
        }
        with open(a.out, "w") as f:
            json.dump(doc, f, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
