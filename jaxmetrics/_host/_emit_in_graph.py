"""In-graph emit: a report sent to the host under `lax.cond`, at period ends only.

The report leaves through the Logger's report channel (`_channel`: a ring in host memory
written by the device, or an ordered `io_callback`). JAX can vmap neither the callback
nor a `cond` whose branches have its effects. So the emit is a `custom_vmap` function:
unbatched, it is `cond(when, write, identity)`; under `vmap` its rule moves the batch
axis to the front and calls the same construction one level up, which computes every
batch element's report with an inner `vmap` (effect-free) and sends *one* report
carrying all of them, together with each element's run index, step and `when`. The host
splits them. Nested `vmap`s stack further leading axes the same way.

A wrapper that reports by itself has no run index to pass: built with `runs_by_position`,
the batch element at position `i` of a (single) vmapped axis is run `i`.

Under `jax.grad` or `jvp` the report is a side effect of the forward pass: it carries the
state's primal values, and the state leaves the emit without a tangent, as from
`Metrics.update` and `Metrics.log`.
"""

from collections.abc import Callable
from typing import Any

import jax
import jax.numpy as jnp
from jax import custom_batching

from .._core._count import Count

_NEEDS_RUN = (
    "emit under vmap sends each batch element to its own run, so `run` must be batched "
    "along the same axis as the state: create Logger(..., runs=N) and call "
    "logger.emit(state, step, when, run=seed_index) with seed_index vmapped alongside "
    "(e.g. jax.vmap(train)(keys, jnp.arange(N)))."
)


def _expand(mask: jax.Array, ndim: int) -> jax.Array:
    return mask.reshape(mask.shape + (1,) * (ndim - mask.ndim))


class InGraphEmit:
    """`emit(state, step, when, run) -> state`, pure and jittable.

    Args:
      compute: state -> report (in-graph).
      reset: state -> state at the start of a new period.
      send: in-graph, sends `(report, step, when, run)` to the host (`Channel.send`);
        every argument has the same leading batch axes (none when not vmapped).
      runs_by_position: the logger's number of runs, for an emit whose `run` is not
        batched: under one `vmap` of that size, element `i` is run `i`. None: `run` must be
        batched alongside the state.
    """

    def __init__(
        self,
        compute: Callable[[Any], Any],
        reset: Callable[[Any], Any],
        send: Callable[..., None],
        runs_by_position: int | None = None,
    ):
        self._compute, self._reset, self._send = compute, reset, send
        self._runs_by_position = runs_by_position
        self._levels: dict[int, Callable[..., Any]] = {}

    def __call__(self, state: Any, step: jax.Array | Count, when: jax.Array, run: jax.Array) -> Any:
        # A host callback has no derivative (JAX refuses to differentiate an io_callback),
        # so a state that carries tangents (a carry differentiated as a whole) is sent as
        # its primal values.
        return self._level(0)(jax.lax.stop_gradient(state), step, when, run)

    def _level(self, nd: int) -> Callable[..., Any]:
        if nd not in self._levels:
            self._levels[nd] = self._build(nd)
        return self._levels[nd]

    def _build(self, nd: int) -> Callable[..., Any]:
        compute, reset, send = self._compute, self._reset, self._send
        for _ in range(nd):
            compute, reset = jax.vmap(compute), jax.vmap(reset)

        @custom_batching.custom_vmap
        def emit(state, step, when, run):
            def fire() -> None:
                send(compute(state), step, when, run)

            # Only the report goes through the conditional, which has no outputs: a branch
            # that passed the state through would copy every array of it on every step
            # (in a CUDA graph, a copy node each). The reset is a select, fused with the
            # step's other elementwise work.
            jax.lax.cond(jnp.any(when), fire, lambda: None)
            new = reset(state)
            return jax.tree.map(lambda n, o: jnp.where(_expand(when, n.ndim), n, o), new, state)

        @emit.def_vmap
        def rule(axis_size, in_batched, state, step, when, run):
            if not in_batched[3]:
                run = self._run_by_position(nd, axis_size)
                in_batched = (*in_batched[:3], True)
            args = jax.tree.map(
                lambda x, b: x if b else jnp.broadcast_to(x, (axis_size, *jnp.shape(x))),
                (state, step, when, run),
                tuple(in_batched),
            )
            out = self._level(nd + 1)(*args)
            return out, jax.tree.map(lambda _: True, out)

        return emit

    def _run_by_position(self, nd: int, axis_size: int) -> jax.Array:
        runs = self._runs_by_position
        if runs is None:
            raise ValueError(_NEEDS_RUN)
        if nd > 0:
            raise ValueError(
                "a reporting wrapper under nested vmaps: its runs are the positions along "
                "one vmapped axis of seeds; vmap over a single (flattened) seed axis."
            )
        if axis_size != runs:
            nested = (
                f", or, if {axis_size} is the inner of nested vmaps over {runs} seeds in all, "
                f"vmap over one flattened axis of {runs} seeds"
                if runs % axis_size == 0 and runs > axis_size
                else ""
            )
            raise ValueError(
                f"a reporting wrapper is vmapped over {axis_size} seeds, but its Logger has "
                f"runs={runs}: create the Logger with runs={axis_size} (seed i of the vmapped "
                f"axis reports to run i){nested}."
            )
        return jnp.arange(axis_size, dtype=jnp.int32)
