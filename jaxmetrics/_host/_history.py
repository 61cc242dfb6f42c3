"""Report history: a fixed-capacity in-graph buffer of packed reports, no host callback.

`Logger.emit` reaches the host through an ordered `io_callback`; a program holding one
stays out of JAX's persistent compilation cache, and vmapping it needs a `custom_vmap`
rule. Here each period end writes the packed report (`_transfer`) and its step into
slot `ends` of a `History` carried with the training state; after the jitted call `fetch`
brings it to the host, its records in writing order (`Logger.write_history`). Everything
in-graph is plain `lax.switch` and `.at[].set`, so `vmap` and sharding need no rule of
their own.
"""

import collections
import functools
import heapq
from collections.abc import Callable
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from .._core._count import Count, to_int
from .._core._validate import is_int
from ._transfer import Packer

_INT32_MAX = 2**31 - 1


class History(NamedTuple):
    """The period ends of one run (a leading axis per vmapped seed), in order.

    Attributes:
      floats: `[capacity, F]` each record's packed float statistics.
      counts: uint32 `[capacity, 2, K]` each record's packed exact counts.
      steps: `Count` of shape `[capacity]`: each record's step, exact to 64 bits.
      ends: int32 `()`: period ends so far; past `capacity` the history overflowed, and
        the records of the period ends past it were not kept.
      layout: the report layout's identity (spec and `include_running`), in the tree
        structure only, like `MetricsState.spec`.
    """

    floats: jax.Array
    counts: jax.Array
    steps: Count
    ends: jax.Array
    layout: tuple


@functools.cache
def layout_id(spec_field: str, include_running: bool) -> tuple:
    """The identity of the report layout of the spec whose `MetricsState.spec` field is
    `spec_field`, with or without running episodes: a leafless namedtuple."""
    kind = "running" if include_running else "finished"
    return collections.namedtuple("ReportLayout", [f"{spec_field}_{kind}"])(None)


def init(packer: Packer, capacity: int, layout: tuple) -> History:
    """An empty history of `capacity` records.

    Raises:
      ValueError: for a capacity that is not an int >= 1.
    """
    if not is_int(capacity) or capacity < 1:
        raise ValueError(
            f"Logger.history_init: capacity must be an int >= 1 (the period ends the "
            f"jitted call records), got {capacity!r}."
        )
    capacity = int(capacity)
    return History(
        jnp.zeros((capacity, packer.num_floats), packer.dtype),
        jnp.zeros((capacity, 2, packer.num_counts), jnp.uint32),
        Count(jnp.zeros((capacity,), jnp.uint32), jnp.zeros((capacity,), jnp.uint32)),
        jnp.zeros((), jnp.int32),
        layout,
    )


def step_words(step: jax.Array) -> tuple[jax.Array, jax.Array]:
    """An integer step as (hi, lo) uint32 words of its 64-bit two's complement."""
    lo = step.astype(jnp.uint32)
    if step.dtype.itemsize == 8:
        return (step >> 32).astype(jnp.uint32), lo
    if jnp.issubdtype(step.dtype, jnp.signedinteger):
        return jnp.where(step < 0, jnp.uint32(0xFFFFFFFF), jnp.uint32(0)), lo
    return jnp.zeros((), jnp.uint32), lo


def record(
    compute: Callable[[Any], tuple[jax.Array, jax.Array]],
    reset: Callable[[Any], Any],
    state: Any,
    history: History,
    step: jax.Array,
    when: jax.Array,
) -> tuple[Any, History]:
    """Where `when`: the packed report of `state` goes into the next free slot and the
    period resets. A full history keeps the period (nothing is reset, so the state's next
    report still covers it) and only counts the period end."""
    capacity = history.floats.shape[0]

    def keep(args):
        state, h = args
        floats, counts = compute(state)
        i = h.ends
        hi, lo = step_words(step)
        h = h._replace(
            floats=h.floats.at[i].set(floats),
            counts=h.counts.at[i].set(counts),
            steps=Count(h.steps.hi.at[i].set(hi), h.steps.lo.at[i].set(lo)),
            ends=h.ends + 1,
        )
        return reset(state), h

    def overflow(args):
        state, h = args
        return state, h._replace(ends=h.ends + (h.ends < _INT32_MAX).astype(jnp.int32))

    branch = jnp.where(when, jnp.where(history.ends < capacity, 1, 2), 0)
    return jax.lax.switch(branch, (lambda args: args, keep, overflow), (state, history))


def check(history: Any, layout: tuple, packer: Packer, lead: tuple[int, ...], who: str) -> None:
    """Raises unless `history` is a `History` of this layout with leading axes `lead`.

    Raises:
      TypeError: not a `History`.
      ValueError: a history of another spec or `include_running` setting, or of other
        shapes.
    """
    if not isinstance(history, History):
        raise TypeError(
            f"{who}: expected the History of logger.history_init(capacity), got "
            f"{type(history).__name__}."
        )
    if type(history.layout) is not type(layout):
        raise ValueError(
            f"{who}: this history was made by history_init of a Logger of another Metrics "
            "spec (or include_running setting); make it with this logger's history_init."
        )
    shape = tuple(history.floats.shape)
    n = len(lead)
    want = (packer.num_floats,)
    ok = (
        len(shape) == n + 2
        and shape[:n] == lead
        and shape[n + 1 :] == want
        and tuple(history.counts.shape) == (*shape[: n + 1], 2, packer.num_counts)
        and tuple(history.steps.hi.shape) == shape[: n + 1]
        and tuple(history.ends.shape) == lead
    )
    if not ok:
        raise ValueError(
            f"{who}: the history's floats have shape {shape}, expected "
            f"{(*lead, 'capacity', *want)}: one history per run, stacked on a leading "
            "[runs] axis for Logger(runs > 1) (vmapped seeds)."
        )


class FetchedHistory(NamedTuple):
    """A history on the host, its records in the order they are written.

    Attributes:
      floats: `[runs, capacity, F]` packed float statistics.
      counts: uint32 `[runs, capacity, 2, K]` packed exact counts.
      order: `(step, run, slot)` per record kept: each run's records in the order its
        periods ended, the runs interleaved by step.
      kept: `[runs]` records kept per run.
      ends: `[runs]` period ends per run (more than `capacity`: it overflowed).
    """

    floats: np.ndarray
    counts: np.ndarray
    order: list[tuple[int, int, int]]
    kept: np.ndarray
    ends: np.ndarray


def fetch(history: History, runs: int) -> FetchedHistory:
    """Copies a (checked) history of `runs` runs to the host."""
    floats, counts, hi, lo, ends = jax.device_get(
        (history.floats, history.counts, history.steps.hi, history.steps.lo, history.ends)
    )
    capacity = history.floats.shape[-2]
    steps = np.reshape(to_int(Count(hi, lo)), (runs, capacity))
    ends = np.reshape(ends, (runs,))
    kept = np.minimum(ends, capacity)
    order = heapq.merge(
        *[[(int(steps[r, k]), r, k) for k in range(int(kept[r]))] for r in range(runs)]
    )
    return FetchedHistory(
        np.reshape(floats, (runs, capacity, -1)),
        np.reshape(counts, (runs, capacity, 2, -1)),
        list(order),
        kept,
        ends,
    )


def check_overflow(history: FetchedHistory) -> None:
    """Raises if the history had more period ends than its capacity.

    Raises:
      ValueError: naming how many period ends were not kept and the capacity that holds
        them all.
    """
    capacity = history.floats.shape[1]
    over = [(r, int(n)) for r, n in enumerate(history.ends) if n > capacity]
    if over:
        shown = ", ".join(f"run {r}: {n} period ends" for r, n in over)
        raise ValueError(
            f"Logger.write_history: the history overflowed ({shown}; capacity "
            f"{capacity}): the {capacity} records it holds per run are written, the "
            "period ends past them were not kept (the state returned with it still "
            "holds those periods: flush it to report them). Create the history with "
            f"logger.history_init({max(n for _, n in over)}) or more."
        )
