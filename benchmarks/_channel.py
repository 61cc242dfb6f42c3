"""`python -m benchmarks channel`: the report channels side by side in a jitted loop, records
and time per step.

A scanned step of `--kernels` small dependent kernels (each its own kernel) over `--envs`
floats (a cheap env step, where a host round trip per step shows), logging one value per
step, emitting a report every `--period` steps through `Logger.emit` with `report_channel`
"ring" and "io_callback", the same loop with no emit (`none`), and with a pure `lax.cond`
of the same period in place of the emit (`cond_pure`). Each variant runs `--repeats` times
after a warm-up; the records of both channels are checked equal to each other and
to a float64 reference of the period means.

`python -m benchmarks channel --out F.json`
"""

import argparse
import json
import platform
import statistics
import time
from collections.abc import Sequence
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

import jaxmetrics as jm


def _loop(
    metrics: jm.Metrics, logger: jm.Logger | None, cond: bool, args: argparse.Namespace
) -> Any:
    def body(carry: Any, i: jax.Array) -> Any:
        state, x, acc = carry
        for _ in range(args.kernels):
            # The barriers keep each operation a kernel of its own, as a launch-bound env is.
            x = jax.lax.optimization_barrier(jnp.sin(x) * jnp.float32(1.0001) + jnp.float32(1e-3))
        state = metrics.log(state, {"x": x[0] + i.astype(jnp.float32)})
        when = i % args.period == args.period - 1
        if logger is not None:
            state = logger.emit(state, i, when)
        elif cond:  # a pure conditional of the same period: the floor of any report
            acc = jax.lax.cond(when, lambda: acc + jnp.sum(x), lambda: acc)
        return (state, x, acc), None

    @jax.jit
    def run(x: jax.Array) -> Any:
        carry = (metrics.init(1), x, jnp.float32(0))
        return jax.lax.scan(body, carry, jnp.arange(args.steps))[0]

    return run


def _time(run: Any, x: jax.Array, repeats: int) -> list[float]:
    jax.block_until_ready(run(x))
    out = []
    for _ in range(repeats):
        t = time.perf_counter()
        jax.block_until_ready(run(x))
        out.append(1e6 * (time.perf_counter() - t))
    return out


def main(argv: Sequence[str] | None = None) -> None:
    p = argparse.ArgumentParser(
        prog="python -m benchmarks channel",
        description="The report channels side by side in a jitted loop: records and time per step.",
    )
    p.add_argument("--envs", type=int, default=2048)
    p.add_argument("--kernels", type=int, default=100)
    p.add_argument("--steps", type=int, default=1000)
    p.add_argument("--period", type=int, default=100)
    p.add_argument("--repeats", type=int, default=5)
    p.add_argument("--out", default=None)
    args = p.parse_args(argv)
    metrics = jm.Metrics(logged=["x"])
    x = jnp.linspace(0.0, 1.0, args.envs, dtype=jnp.float32)
    rows: dict[str, Any] = {}
    records: dict[str, list[tuple[int, float]]] = {}
    for variant in ("none", "cond_pure", "io_callback", "ring", "cond_pure_again"):
        memory = jm.MemoryWriter()
        logger = None
        if variant in ("io_callback", "ring"):
            logger = jm.Logger(metrics, [memory], report_channel=variant)
        run = _loop(metrics, logger, variant.startswith("cond"), args)
        times = _time(run, x, args.repeats)
        row: dict[str, Any] = {"us_per_step": statistics.median(times) / args.steps}
        if logger is not None:
            logger.close()
            row["channel"] = logger.report_channel._asdict()
            row["records"] = len(memory.records)
            records[variant] = [(r.step, r.scalars["Train/x"]) for r in memory.records]
        rows[variant] = row
        print(variant, json.dumps(row), flush=True)
    # float64 reference of one call's period means
    xs = np.asarray(jnp.linspace(0.0, 1.0, args.envs, dtype=jnp.float32), np.float64)
    firsts = []
    for i in range(args.steps):
        for _ in range(args.kernels):
            xs = np.sin(xs.astype(np.float32)).astype(np.float32) * np.float32(1.0001)
            xs = (xs + np.float32(1e-3)).astype(np.float32)
        firsts.append(float(xs[0]) + i)
    ref = [float(np.mean(firsts[k : k + args.period])) for k in range(0, args.steps, args.period)]
    calls = 1 + args.repeats
    same = records["ring"] == records["io_callback"]
    got = [v for _, v in records["ring"]][: len(ref)]
    err = float(np.max(np.abs(np.asarray(got) - np.asarray(ref)) / np.maximum(1, np.abs(ref))))
    summary = {
        "ring_equals_io_callback": same,
        "records_expected": calls * len(ref),
        "records": {k: len(v) for k, v in records.items()},
        "ring_vs_float64_max_rel_err": err,
    }
    print(json.dumps(summary), flush=True)
    if args.out:
        doc = {
            "device": jax.devices()[0].device_kind,
            "jax": jax.__version__,
            "host": platform.node(),
            "args": vars(args),
            "rows": rows,
            "summary": summary,
        }
        with open(args.out, "w") as f:
            json.dump(doc, f, indent=1)
