"""Timing: compile apart, warm up, block until ready, median of interleaved repeats.

Repeats are interleaved across the variants of one table (round r times every variant
once before round r + 1 starts), so that slow drift of the machine (clocks, other
processes) lands on every variant alike rather than on whichever ran last. Each round
starts one variant later than the one before, so that no variant always runs first or
always follows the same one (with a fixed order an H100 once read two identical rollout
programs 0.67% apart, about the overhead being measured).
"""

import dataclasses
import statistics
import time
from collections.abc import Callable, Sequence
from typing import Any

import jax


@dataclasses.dataclass(frozen=True)
class Timing:
    """Seconds per call: median and spread of the timed repeats (warm-up excluded)."""

    median_s: float
    min_s: float
    max_s: float
    repeats: int
    samples: tuple[float, ...] = ()  # every timed call, in the order they ran


@dataclasses.dataclass(frozen=True)
class Variant:
    """One timed thing: `run()` does one whole call and returns only once it has finished."""

    name: str
    run: Callable[[], Any]
    compile_s: float | None = None


def compile_jit(fn: Callable[..., Any], *args: Any, donate_argnums: tuple[int, ...] = ()):
    """Compiles `fn` for `args`; returns the executable and the seconds that took."""
    t0 = time.perf_counter()
    compiled = jax.jit(fn, donate_argnums=donate_argnums).lower(*args).compile()
    return compiled, time.perf_counter() - t0


def blocking(compiled: Callable[..., Any], *args: Any) -> Callable[[], Any]:
    """A `run` for `Variant`: call and block until every output (and callback) is done."""

    def run():
        out = jax.block_until_ready(compiled(*args))
        jax.effects_barrier()
        return out

    return run


def measure(
    variants: Sequence[Variant], repeats: int, warmup: int = 1
) -> tuple[dict[str, Timing], dict[str, Any]]:
    """Times every variant; returns name -> `Timing` and name -> output of its last call."""
    last: dict[str, Any] = {}
    for v in variants:
        for _ in range(warmup):
            last[v.name] = v.run()
    samples: dict[str, list[float]] = {v.name: [] for v in variants}
    for r in range(repeats):
        for v in rotated(variants, r):
            t0 = time.perf_counter()
            last[v.name] = v.run()
            samples[v.name].append(time.perf_counter() - t0)
    timings = {
        name: Timing(statistics.median(s), min(s), max(s), len(s), tuple(s))
        for name, s in samples.items()
    }
    return timings, last


def rotated(items: Sequence[Any], r: int) -> list[Any]:
    """`items` in round `r`'s order: starting at item `r` (mod their number), wrapping."""
    k = r % len(items) if items else 0
    return [*items[k:], *items[:k]]


def tree_bytes(tree: Any) -> int:
    """Bytes held by the arrays of a pytree."""
    return int(sum(x.nbytes for x in jax.tree.leaves(tree)))
