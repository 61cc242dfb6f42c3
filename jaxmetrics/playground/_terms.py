"""Terms that read Playground's `State.data` (the `mjx.Data`)."""

from collections.abc import Sequence
from typing import Any

from .._core._spec import DEFAULT_STATS, Stat, Term
from ..brax._terms import norm


def joint_velocity(
    indices: Any = None,
    *,
    ord: float = 2,  # noqa: A002
    reduce: str = "mean",
    stats: Sequence[Stat] = DEFAULT_STATS,
) -> Term:
    """The norm of the generalized velocity `state.data.qvel` or a slice of it.

    Reduction "mean" by default. For a free-floating base the first 6 entries are the
    base's: `joint_velocity(slice(6, None))` for the joints only.

    Examples:
      >>> import jaxmetrics.playground as jmp
      >>> jmp.joint_velocity(slice(6, None)).reduce
      'mean'
    """
    # A Playground State (with `data`) in the Transition typed for Brax's.
    return norm(lambda t: t.state.data.qvel, indices, ord=ord, reduce=reduce, stats=stats)  # pyright: ignore[reportAttributeAccessIssue]
