"""The `Logger`'s checks of what its callers pass: each error names the argument and the fix.

They run before a call acts, so that a call that raises has done nothing.
"""

from typing import Any

import jax
import jax.core  # jax.core.Tracer: imported by jax, named here for the type checker
import jax.numpy as jnp

from .._core._metrics_state import MetricsState
from .._core._spec import check_name
from .._core._validate import is_int, is_number


def check_settings(runs: Any, max_pending: Any, timeout: Any, timer_prefix: Any) -> None:
    """Checks `Logger(...)`'s settings.

    Raises:
      ValueError: a setting out of range, or an invalid timer prefix.
    """
    if not is_int(runs) or runs < 1:
        raise ValueError(f"Logger: runs must be an int >= 1, got {runs!r}.")
    if not is_int(max_pending) or max_pending < 1:
        raise ValueError(f"Logger: max_pending must be an int >= 1, got {max_pending!r}.")
    if timeout is not None and (not is_number(timeout) or not timeout > 0):
        raise ValueError(f"Logger: timeout must be seconds > 0 or None, got {timeout!r}.")
    check_name(timer_prefix, "Logger(timer_prefix=...)")


def is_traced(tree: Any) -> bool:
    """Whether `tree` holds a tracer: the caller runs inside `jit`, `vmap` or `scan`."""
    return any(isinstance(x, jax.core.Tracer) for x in jax.tree.leaves(tree))


def check_state(state: Any, runs: int) -> None:
    """Raises unless `state` is a `MetricsState` with the leading axes of `runs` runs.

    Raises:
      TypeError: not a `MetricsState`.
      ValueError: other leading axes, with the fix.
    """
    if not isinstance(state, MetricsState):
        raise TypeError(f"Logger.flush: expected a MetricsState, got {type(state).__name__}.")
    # A leaf and its own axes (counters [C], logged [R], finished [shards, R]).
    leaves = (
        (None if state.counters is None else state.counters.lo, 1),
        (None if state.logged is None else state.logged.mean, 1),
        (None if state.finished is None else state.finished.mean, 2),
    )
    found = next(((x, own) for x, own in leaves if x is not None), None)
    if found is None:
        return
    leaf, own = found
    lead = tuple(leaf.shape[:-own])
    want = () if runs == 1 else (runs,)
    if lead != want:
        hint = (
            f"for {lead[0]} vmapped seeds create Logger(..., runs={lead[0]})"
            if runs == 1 and len(lead) == 1
            else f"pass the states of all {runs} runs stacked on a leading axis"
        )
        raise ValueError(
            f"Logger(runs={runs}).flush: the state has leading axes {lead}, "
            f"expected {want}; {hint}."
        )


def check_step(step: Any, runs: int, last: int | None) -> None:
    """Raises unless `step` is a valid step of a flush after the host-int step `last`.

    Raises:
      TypeError: not an int (or an int array of shape () or [runs]).
      ValueError: a host int outside [0, 2^63), or below `last`.
    """
    ok = is_int(step)
    if not ok and hasattr(step, "dtype") and hasattr(step, "shape"):
        ok = jnp.issubdtype(step.dtype, jnp.integer) and tuple(step.shape) in ((), (runs,))
    if not ok:
        raise TypeError(
            f"Logger.flush: step must be an int (or an int array of shape () or "
            f"({runs},)), got {step!r}."
        )
    if not is_int(step):
        return  # a device array: checked on the writer thread
    if not 0 <= step < 2**63:
        raise ValueError(
            f"Logger.flush: step must be in [0, 2^63) (TensorBoard stores int64), got {step}."
        )
    if last is not None and step < last:
        raise ValueError(
            f"Logger.flush: step {step} after step {last}; steps must not decrease (charts "
            "would draw back over themselves). To resume a run from an earlier step, "
            "create a new Logger whose writers have purge_step=<step>."
        )


def scalar_args(where: str, **args: Any) -> tuple[jax.Array, ...]:
    """The in-graph arguments as scalar arrays: `when` a bool, the others ints.

    Raises:
      TypeError: an argument of another dtype or shape.
    """
    out = []
    for name, v in args.items():
        v = jnp.asarray(v)
        ok = v.dtype == jnp.bool_ if name == "when" else jnp.issubdtype(v.dtype, jnp.integer)
        if not ok or v.shape != ():
            kind = "a bool" if name == "when" else "an int"
            raise TypeError(f"{where}: {name} must be {kind} scalar, got {v.dtype}{list(v.shape)}.")
        out.append(v)
    return tuple(out)
