"""Scenario 4: what a flush moves device -> host and how long it takes, against num_envs.

A flush is `compute` + `reset_period` (jitted, the state donated) and the copy of the
report to the host. Neither touches the per-env episode accumulators, so the cost
should not depend on num_envs.
"""

import time
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

import jaxmetrics as jm

from . import _workload as wl
from ._isolated import _metrics_scan, inputs
from ._report import Table
from ._timing import tree_bytes

FILL_STEPS = 20


def _flush_fn(metrics: jm.Metrics):
    def flush(state):
        return metrics.compute(state), metrics.reset_period(state)

    return flush


def _packed_flush_fn(metrics: jm.Metrics):
    # The same report as two flat buffers (floats, uint32 counts): two transfers, not one
    # per report entry.
    def flush(state):
        leaves = jax.tree.leaves(metrics.compute(state))
        floats = [x.reshape(-1) for x in leaves if jnp.issubdtype(x.dtype, jnp.floating)]
        ints = [x.reshape(-1) for x in leaves if not jnp.issubdtype(x.dtype, jnp.floating)]
        return (jnp.concatenate(floats), jnp.concatenate(ints)), metrics.reset_period(state)

    return flush


def _time(fn, state, repeats: int, host: Any) -> tuple[float, Any]:
    """Median seconds of `host(fn(state))`, threading the donated state through."""
    samples = []
    for i in range(repeats + 1):
        t0 = time.perf_counter()
        report, state = fn(state)
        out = host(report)
        if i:  # the first call is the warm-up
            samples.append(time.perf_counter() - t0)
    return float(np.median(samples)), (out, state)


def time_logger(spec: jm.Metrics, state: Any, repeats: int) -> tuple[float, float, Any, int]:
    """`jm.Logger.flush` into a `MemoryWriter`: the call alone (what the training loop
    waits for: dispatch + the start of an asynchronous copy), and flush + `wait()` (until
    the record is written); then the state and the bytes a flush copies."""
    calls, waits = [], []
    with jm.Logger(spec, [jm.MemoryWriter()]) as logger:
        for i in range(repeats + 1):
            jax.block_until_ready(state)
            t0 = time.perf_counter()
            state = logger.flush(state, step=i)
            t1 = time.perf_counter()
            logger.wait()
            t2 = time.perf_counter()
            if i:
                calls.append(t1 - t0)
                waits.append(t2 - t0)
        nbytes = logger.report_nbytes
    return float(np.median(calls)), float(np.median(waits)), state, nbytes


def flush(env_list: list[int], repeats: int) -> Table:
    t = Table(
        "flush",
        "Flush: device -> host bytes and wall time per flush (10 terms)",
        [
            "num_envs",
            "report entries",
            "bytes to host",
            "state bytes",
            "compute+reset ms",
            "device_get ms",
            "to_host ms",
            "packed ms",
            "Logger.flush ms",
            "Logger flush+wait ms",
        ],
    )
    spec = wl.random_spec(10)
    fill = jax.jit(_metrics_scan(spec))
    for n in env_list:
        xs, dones = inputs(n, FILL_STEPS, seed=1)
        state = jax.block_until_ready(fill(spec.init(n), xs, dones))
        del xs, dones
        flush_jit = jax.jit(_flush_fn(spec), donate_argnums=0)
        packed_jit = jax.jit(_packed_flush_fn(spec), donate_argnums=0)
        report, state = flush_jit(state)
        nbytes, entries = tree_bytes(report), len(report)
        dev_s, (_, state) = _time(flush_jit, state, repeats, jax.block_until_ready)
        get_s, (_, state) = _time(flush_jit, state, repeats, jax.device_get)
        host_s, (_, state) = _time(flush_jit, state, repeats, spec.to_host)
        pk_s, (out, state) = _time(packed_jit, state, repeats, jax.device_get)
        call_s, wait_s, state, _ = time_logger(spec, state, repeats)
        t.add(
            n,
            entries,
            nbytes,
            tree_bytes(state),
            dev_s * 1e3,
            get_s * 1e3,
            host_s * 1e3,
            pk_s * 1e3,
            call_s * 1e3,
            wait_s * 1e3,
        )
        t.data[str(n)] = {"packed_bytes": int(sum(a.nbytes for a in out))}
    t.notes += [
        "compute+reset: the jitted `compute` + `reset_period` (state donated), blocked on; "
        "device_get: that plus `jax.device_get` of the report (one copy per column: per "
        "statistic, not per tag); "
        "to_host: that plus `Metrics.to_host` (floats, exact ints, numpy arrays); packed: "
        "the same report concatenated in-graph into one float and one uint32 buffer, "
        "then `device_get` (two copies); Logger.flush: `jm.Logger(spec, [MemoryWriter()])"
        ".flush(state, step)`, the call alone (asynchronous copy and writer thread) and "
        "with `wait()` until the record is written. Each a median over "
        f"{repeats} flushes after a warm-up; the state was filled by {FILL_STEPS} random steps.",
    ]
    return t


def _period_end_programs(spec: jm.Metrics, logger: jm.Logger, every: int, capacity: int):
    """The jitted rollouts of one seed: (inputs, base step) -> ..., a period end every
    `every` steps: reset only, `Logger.emit`, `Logger.record` into a history."""

    def scan(state, xs, dones, carry, end):
        def body(c, inp):
            s, extra = c
            s = spec.update(s, inp[0], inp[1])
            when = inp[2] % every == every - 1
            return end(s, extra, inp[2], when), None

        steps = jnp.arange(xs.shape[0], dtype=jnp.int32)
        return jax.lax.scan(body, (state, carry), (xs, dones, steps))[0]

    def reset_only(state, xs, dones, base):
        def end(s, extra, i, when):
            return jax.lax.cond(when, spec.reset_period, lambda s: s, s), extra

        return scan(state, xs, dones, base, end)[0]

    def emit(state, xs, dones, base):
        def end(s, extra, i, when):
            return logger.emit(s, extra + i, when), extra

        return scan(state, xs, dones, base, end)[0]

    def history(state, xs, dones, base):
        def end(s, h, i, when):
            return logger.record(s, h, base + i, when)

        return scan(state, xs, dones, logger.history_init(capacity), end)

    return {"reset only": reset_only, "emit": emit, "history": history}


def period_ends(num_envs: int, periods: int, every: int, repeats: int) -> Table:
    """What a period end costs: `Logger.emit` (an ordered host callback per period end)
    against `Logger.record` into an in-graph history written after the call."""
    t = Table(
        "period_ends",
        f"Period ends in one jit: emit vs report history ({num_envs} envs, 10 terms, "
        f"{periods} period ends of {every} steps)",
        [
            "variant",
            "jitted call ms",
            "host write ms",
            "us per period end above reset only",
            "compile s",
            "history bytes per record",
        ],
    )
    spec = wl.random_spec(10)
    steps = periods * every
    xs, dones = inputs(num_envs, steps, seed=2)
    memory = jm.MemoryWriter()
    timed: dict[str, list[tuple[float, float]]] = {}
    with jm.Logger(spec, [memory]) as logger:
        programs = _period_end_programs(spec, logger, every, periods)
        compiled, compile_s = {}, {}
        state = spec.init(num_envs)
        for name, fn in programs.items():
            t0 = time.perf_counter()
            compiled[name] = jax.jit(fn).lower(state, xs, dones, jnp.int32(0)).compile()
            compile_s[name] = time.perf_counter() - t0
        base = 0
        for i in range(repeats + 1):  # interleaved; the first round is the warm-up
            for name, fn in compiled.items():
                t0 = time.perf_counter()
                out = fn(state, xs, dones, jnp.int32(base))
                jax.block_until_ready(out)
                jax.effects_barrier()
                t1 = time.perf_counter()
                if name == "history":
                    logger.write_history(out[1])
                logger.wait()
                t2 = time.perf_counter()
                base += steps
                if i:
                    timed.setdefault(name, []).append((t1 - t0, t2 - t1))
        h = logger.history_init(periods)
        record_bytes = sum(x.nbytes for x in (h.floats, h.counts, *h.steps)) // periods
    med = {
        n: (float(np.median([a for a, _ in v])), float(np.median([b for _, b in v])))
        for n, v in timed.items()
    }
    floor = med["reset only"][0]
    for name, (call, write) in med.items():
        above = None if name == "reset only" else (call + write - floor) / periods * 1e6
        t.add(
            name,
            call * 1e3,
            write * 1e3,
            above,
            compile_s[name],
            record_bytes if name == "history" else None,
        )
    t.data["records_written"] = len(memory.records)
    t.notes += [
        "One jitted lax.scan of the 10-term spec's update over random inputs, a period end "
        f"every {every} steps: `reset only` resets the period in a lax.cond (no report); "
        "`emit` is `Logger.emit` (ordered io_callback under lax.cond) into a MemoryWriter; "
        "`history` is `Logger.record` into `history_init(periods)`, returned with the "
        "state. jitted call: until the result is ready (and emit's callbacks have run); "
        "host write: `write_history` + `wait()` for the history, `wait()` for emit. "
        "us per period end: (call + write - reset only's call) / period ends. Medians of "
        f"{repeats} interleaved repeats after a warm-up.",
    ]
    return t
